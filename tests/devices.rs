//! The devices suite: the drivers against emulators and fake vendor libraries written from the
//! vendors' documents (PI GCS, Thorlabs APT, Red Pitaya, the Mad City Labs + NI bench), the
//! targeted protocols on them, the scan engine's rasters, ETAs, faults and stop rule.
//!
//! Each module is one file of `tests/`; run one with `cargo test --test devices <module>::`.

mod support;

mod apt;
mod bench_drivers;
mod device_truth;
mod eta;
mod family_toy;
mod hardware;
mod raster;
mod raster_faults;
mod raster_hw;
mod raster_sim;
mod redpitaya;
mod stop_rule;
mod targeted_hw;
