//! The physics of BFP detection (pure functions, no I/O, no Rhai). Each formula cites the
//! section or equation of the paper (`docs/physics.md` lists the conventions).

pub mod beam;
pub mod calc;
pub mod finite_size;
pub mod grid;
pub mod mie;
pub mod mie_beam;
pub mod mie_template;
pub mod params;
pub mod quad;
pub mod rayleigh;
pub mod template;

pub use beam::{DipoleTier, OpticsArg, ResolvedBeam, ValidOptics};
pub use params::{Beam, Optics, OpticsError};
