//! `bfpscope emulate stage|qpd|both`: start emulators, print their pseudo-terminal paths and
//! a config snippet, serve until Ctrl-C (or end of input on a terminal).

use super::{
    shared_position, standin_bead, start_qpd_emulator, start_stage_emulator, Emulator,
    QpdEmulatorConfig, SignalSource, StageEmulatorConfig,
};
use std::io::{IsTerminal, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// Where the CLI's stand-in bead sits (µm): the middle of the emulated travel range.
pub const BEAD: [f64; 3] = [50.0, 50.0, 10.0];

/// Start the emulators named by `kind` (`stage`, `qpd`, or `both`: a stage and a QPD sharing
/// the stage position) with the analytic stand-in bead at [`BEAD`] as the QPD's signal, print where they
/// are and serve until Ctrl-C, or end of input when stdin is a terminal (Ctrl-D).
pub fn run_emulator_cli(kind: &str) -> anyhow::Result<()> {
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        // Another handler may already be installed (e.g. by the REPL); then Ctrl-C ends the
        // process as usual, which also stops the emulators.
        let _ = ctrlc::set_handler(move || stop.store(true, Ordering::SeqCst));
    }
    let stdin = std::io::stdin();
    if stdin.is_terminal() {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let mut sink = String::new();
            while std::io::stdin()
                .read_line(&mut sink)
                .map(|n| n > 0)
                .unwrap_or(false)
            {
                sink.clear();
            }
            stop.store(true, Ordering::SeqCst);
        });
    }
    // The stand-in bead sits in the middle of the emulated travel range.
    let source = |p: [f64; 3]| standin_bead([p[0] - BEAD[0], p[1] - BEAD[1], p[2] - BEAD[2]]);
    run_emulator_cli_with(kind, source, &mut std::io::stdout(), stop)
}

/// As [`run_emulator_cli`], with the QPD signal from `source` (plug the simulator in here),
/// printing to `out` and serving until `stop` is set.
pub fn run_emulator_cli_with(
    kind: &str,
    source: impl SignalSource,
    out: &mut dyn Write,
    stop: Arc<AtomicBool>,
) -> anyhow::Result<()> {
    let stage_cfg = StageEmulatorConfig {
        start: [45.0, 45.0, 10.0],
        ..StageEmulatorConfig::default()
    };
    let pos = shared_position(stage_cfg.start);
    let mut emus: Vec<Emulator> = Vec::new();
    match kind {
        "stage" => emus.push(start_stage_emulator(stage_cfg, pos)?),
        "qpd" => emus.push(start_qpd_emulator(
            QpdEmulatorConfig::default(),
            pos,
            source,
        )?),
        "both" | "pair" | "all" => {
            emus.push(start_stage_emulator(stage_cfg, pos.clone())?);
            emus.push(start_qpd_emulator(
                QpdEmulatorConfig::default(),
                pos,
                source,
            )?);
        }
        other => {
            anyhow::bail!("emulate: unknown device `{other}` (expected `stage`, `qpd` or `both`)")
        }
    }
    for e in &emus {
        let what = match e.kind() {
            "stage" => "PI GCS 2.0 stage (axes A B C, travel 0–100 × 0–100 × 0–20 µm, servo off)",
            _ => "SCPI QPD digitiser (100 kHz, 1 V per signal unit)",
        };
        writeln!(out, "{}: {what} on {}", e.kind(), e.path())?;
    }
    if kind == "qpd" {
        writeln!(
            out,
            "(the QPD alone sees a stage parked at (45, 45, 10) µm; use `both` to scan)"
        )?;
    }
    writeln!(out, "\n# bfpscope.toml for these emulators:")?;
    for e in &emus {
        match e.kind() {
            "stage" => writeln!(
                out,
                "[stage]\nbackend = \"gcs\"\nport = \"{}\"\naxes = {{ x = \"A\", y = \"B\", z = \"C\" }}\n",
                e.path()
            )?,
            _ => writeln!(out, "[qpd]\nbackend = \"scpi\"\nport = \"{}\"\n", e.path())?,
        }
    }
    writeln!(out, "Serving until Ctrl-C.")?;
    out.flush()?;
    while !stop.load(Ordering::SeqCst) {
        if emus.iter().all(|e| !e.is_running()) {
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    drop(emus);
    Ok(())
}
