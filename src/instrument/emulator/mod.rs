//! The emulated instrument: the family emulators (a PI GCS 2.0 stage, `gcs/emulator.rs`; a SCPI
//! QPD, `scpi/emulator.rs`; a Red Pitaya, `redpitaya/emulator.rs`; Thorlabs APT cubes,
//! `thorlabs/emulator.rs`) started together on pseudo-terminals or TCP ports, imaging the
//! simulator's scene at the emulated stage position, for `connect(#{backend: "emulated"})` and
//! `bfpscope emulate` (`cli.rs`). The serving machinery they share is `instrument/emulation.rs`.

mod cli;

pub use super::emulation::*;
pub use super::gcs::emulator::{
    start_stage_emulator, start_stage_emulator_tcp, StageEmulatorConfig, WaveConfig,
};
pub use super::redpitaya::emulator::{
    start_redpitaya_emulator, Generator, PathSource, RedPitayaEmulatorConfig,
};
pub use super::scpi::emulator::{start_qpd_emulator, QpdEmulatorConfig};
pub use super::thorlabs::emulator::{
    start_kpa101_emulator, start_kpz101_emulator, start_kpz101_stage, start_kpz101_stage_on,
    KpaEmulatorConfig, KpzEmulatorConfig, UNKNOWN_ID,
};
pub use cli::{
    parse_link, run_emulator_cli, run_emulator_cli_sim, run_emulator_cli_with, serve_emulators,
    EmulateOptions,
};

use super::Pos;

/// The simulator as a signal source: the ideal (noise-free) signal of `renderer`'s scene at
/// the stage position, evaluated like a one-pixel `render_grid_ideal`. The emulator adds its own
/// detector noise (`QpdEmulatorConfig::noise_v`); instrument effects of the scene (drift,
/// pointing noise, …) are not applied.
pub fn sim_signal_source(
    renderer: std::sync::Arc<crate::instrument::sim::Renderer>,
) -> impl SignalSource {
    move |p: Pos| {
        let g = renderer.render_grid_ideal(&[p[0]], &[p[1]], p[2]);
        [g[0][0], g[1][0], g[2][0]]
    }
}

/// As [`sim_signal_source`] at many positions in one call: positions along x (y and z fixed)
/// or along y (x and z fixed) are rendered as one row or column of `render_grid_ideal`,
/// anything else position by position. The same values as the one-position source.
pub fn sim_signal_along(renderer: std::sync::Arc<crate::instrument::sim::Renderer>) -> PathSource {
    std::sync::Arc::new(move |ps: &[Pos]| {
        let Some(&[x0, y0, z0]) = ps.first() else {
            return Vec::new();
        };
        let row = |g: [Vec<f64>; 3]| -> Vec<[f64; 3]> {
            (0..g[0].len())
                .map(|i| [g[0][i], g[1][i], g[2][i]])
                .collect()
        };
        if ps.iter().all(|p| p[1] == y0 && p[2] == z0) {
            let xs: Vec<f64> = ps.iter().map(|p| p[0]).collect();
            row(renderer.render_grid_ideal(&xs, &[y0], z0))
        } else if ps.iter().all(|p| p[0] == x0 && p[2] == z0) {
            let ys: Vec<f64> = ps.iter().map(|p| p[1]).collect();
            row(renderer.render_grid_ideal(&[x0], &ys, z0))
        } else {
            ps.iter()
                .map(|p| {
                    let g = renderer.render_grid_ideal(&[p[0]], &[p[1]], p[2]);
                    [g[0][0], g[1][0], g[2][0]]
                })
                .collect()
        }
    })
}

/// Start a stage and a QPD emulator sharing one stage position: a scan through the real
/// drivers images `source`.
pub fn start_pair(
    stage: StageEmulatorConfig,
    qpd: QpdEmulatorConfig,
    source: impl SignalSource,
) -> std::io::Result<(Emulator, Emulator)> {
    let pos = shared_position(stage.start);
    let s = start_stage_emulator(stage, pos.clone())?;
    let q = start_qpd_emulator(qpd, pos, source)?;
    Ok((s, q))
}

/// The family emulators started together, connected through the real drivers. (listed in `instrument::registry`).
pub const FAMILY: crate::instrument::family::Family = crate::instrument::family::Family {
    keys: &["scene", "noise_v", "qpd"],
    help: crate::instrument::family::ConnectHelp {
        backend: "\"emulated\" (the serial drivers talking to in-process emulators)",
        about: "\"emulated\": starts a GCS stage emulator and a SCPI QPD emulator on pseudo-terminals in this process \
             and connects the real drivers to them; the QPD answers with the simulator's signal of the scene at the \
             emulated stage position, so scans go through the whole hardware path without hardware (real time); \
             with qpd: \"redpitaya\" the QPD is a Red Pitaya board emulator over loopback TCP whose external \
             trigger is wired to the stage's trigger output OUT1, for hardware-timed rasters (mode: \"raster\").",
    },
    ..crate::instrument::family::Family::new(
        "emulator",
        "emulated",
        crate::instrument::family::Open::Emulated,
    )
};
