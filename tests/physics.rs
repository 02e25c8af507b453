//! The physics and analysis suite: optics, Mie and vector beams, the simulator, the fits and
//! the paper's analyses, the accuracy report, hard cases and point objects. Pure computation:
//! no device, no wall clock.
//!
//! Each module is one file of `tests/`; run one with `cargo test --test physics <module>::`.

mod analysis_support;
mod support;

mod accuracy_report;
mod analysis;
mod analysis_hard;
mod beam_fit;
mod filament_fit;
mod fit_oracle;
mod hard_cases;
mod mie;
mod mie_beam;
mod optics;
mod point_objects;
mod sim;
mod truth_sweep;
mod vector_beam;
mod vector_scene;
