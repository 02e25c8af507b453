//! The physics of BFP detection (pure functions, no I/O, no Rhai).
pub mod mie;
