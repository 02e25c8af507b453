//! The physics of BFP detection (pure functions, no I/O, no Rhai). Each formula cites the
//! section or equation of the paper (`docs/physics.md` lists the conventions).

pub mod grid;
pub mod params;

pub use params::{Optics, OpticsError};
pub mod calc;
pub mod finite_size;
pub mod quad;
pub mod rayleigh;
pub mod template;
