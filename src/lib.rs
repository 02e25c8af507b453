//! bfpscope: back-focal-plane (BFP) interferometric microscopy workbench.
//!
//! Layout (see `docs/guide.md`): `optics` is the physics (pure functions), `instrument` the
//! device traits with the simulated and serial backends, `acquire` the scan engine and every
//! safety rule, `data` scans/images/files, `analysis` the quantitative steps of the paper,
//! `config` the one parse of `bfpscope.toml` and connecting what it names, `plot` figures,
//! `script` the Rhai engine and binding registry, `repl` the interactive prompt.

// Index loops over small fixed channel arrays read more clearly than iterator chains in numeric code.
#![allow(clippy::needless_range_loop)]

pub mod accuracy;
pub mod acquire;
pub mod analysis;
pub mod config;
pub mod data;
pub mod instrument;
pub mod optics;
pub mod plot;
pub mod repl;
pub mod script;
