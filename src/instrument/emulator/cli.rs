//! `bfpscope emulate stage|gcs|qpd|pair|redpitaya`: start emulators, print their pseudo-terminal paths
//! (or the stage's `tcp://` address with `--tcp`) and a config snippet, serve until Ctrl-C (or
//! end of input on a terminal).

use super::{
    shared_position, sim_signal_source, standin_bead, start_qpd_emulator, start_stage_emulator,
    start_stage_emulator_tcp, Emulator, LinkModel, QpdEmulatorConfig, SignalSource,
    StageEmulatorConfig,
};
use crate::instrument::sim::{Renderer, SimConfig};
use std::io::{IsTerminal, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// Where the stand-in bead of [`run_emulator_cli`] sits (µm): the middle of the default
/// emulated travel range.
pub const BEAD: [f64; 3] = [50.0, 50.0, 10.0];

/// How `bfpscope emulate` serves the stage.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EmulateOptions {
    /// Serve the GCS stage on this TCP address (`127.0.0.1:0`: a free loopback port) instead
    /// of a pseudo-terminal, as a PI controller's GCS port 50000.
    pub tcp: Option<String>,
    /// The stage answers a query naming several axes for the first one only.
    pub one_axis_per_query: bool,
    /// `redpitaya`: serve the board's SCPI server on this loopback port (None: a free port;
    /// a real board listens on 5000).
    pub port: Option<u16>,
    /// `redpitaya`: fast inputs, 2 (STEMlab 125-14, the default when 0) or 4 (4-input model,
    /// Sz on IN3).
    pub inputs: usize,
    /// The serial link both emulators model (`--baud`, `--latency-ms`; the command line's
    /// default is [`LinkModel::USB_SERIAL_115200`], this struct's the pty's full speed).
    pub link: LinkModel,
    /// `redpitaya`: the signal at a path's nodes in one call (the simulator's), see
    /// [`RedPitayaEmulatorConfig::along`](super::RedPitayaEmulatorConfig::along).
    pub along: Option<Along>,
}

/// A [`PathSource`](super::PathSource) in [`EmulateOptions`] (equal when it is the same one).
#[derive(Clone)]
pub struct Along(pub super::PathSource);

impl std::fmt::Debug for Along {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Along(…)")
    }
}

impl PartialEq for Along {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

/// `--baud` and `--latency-ms` of `bfpscope emulate` → a [`LinkModel`]: `baud` a rate in
/// 300–12 000 000 bit/s, or `max` / `0` for the pseudo-terminal's full speed; `latency_ms`
/// 0–1000.
pub fn parse_link(baud: &str, latency_ms: f64) -> Result<LinkModel, String> {
    let b = baud.trim();
    let rate = if b.eq_ignore_ascii_case("max") || b == "0" {
        None
    } else {
        match b.parse::<u32>() {
            Ok(r) if (300..=12_000_000).contains(&r) => Some(r),
            _ => {
                return Err(format!(
                    "emulate: --baud {b}: allowed are 300–12000000 (bit/s; PI controllers: 115200) or `max` (the pseudo-terminal's full speed)"
                ))
            }
        }
    };
    if !(latency_ms.is_finite() && (0.0..=1000.0).contains(&latency_ms)) {
        return Err(format!(
            "emulate: --latency-ms {latency_ms}: allowed are 0–1000 (ms from the end of a command to the start of its reply)"
        ));
    }
    Ok(LinkModel {
        baud: rate,
        latency: Duration::from_secs_f64(latency_ms / 1e3),
    })
}

/// A stop flag raised by Ctrl-C, or by end of input when stdin is a terminal (Ctrl-D).
fn stop_on_ctrlc_or_eof() -> Arc<AtomicBool> {
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        // Another handler may already be installed (e.g. by the REPL); then Ctrl-C ends the
        // process as usual, which also stops the emulators.
        let _ = ctrlc::set_handler(move || stop.store(true, Ordering::SeqCst));
    }
    if std::io::stdin().is_terminal() {
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
    stop
}

/// Start the emulators named by `kind` (`stage`, `qpd`, or `pair` (alias `both`): a stage and a QPD sharing
/// the stage position) with an analytic stand-in bead at [`BEAD`] as the QPD's signal, print
/// where they are and serve until Ctrl-C, or end of input when stdin is a terminal (Ctrl-D).
pub fn run_emulator_cli(kind: &str) -> anyhow::Result<()> {
    let stop = stop_on_ctrlc_or_eof();
    let source = |p: [f64; 3]| standin_bead([p[0] - BEAD[0], p[1] - BEAD[1], p[2] - BEAD[2]]);
    run_emulator_cli_with(kind, source, &mut std::io::stdout(), stop)
}

/// As [`run_emulator_cli`], with the simulator's signal: the QPD answers with the ideal signal
/// of `renderer`'s scene (plus the emulator's detector noise) at the emulated stage position;
/// the stage has the simulator's travel range and move time.
pub fn run_emulator_cli_sim(
    kind: &str,
    renderer: Arc<Renderer>,
    sim: &SimConfig,
    opts: &EmulateOptions,
) -> anyhow::Result<()> {
    let stop = stop_on_ctrlc_or_eof();
    let qpd = QpdEmulatorConfig {
        sample_rate_hz: sim.sample_rate,
        ..QpdEmulatorConfig::default()
    };
    serve_emulators(
        kind,
        StageEmulatorConfig::like_sim(sim),
        qpd,
        sim_signal_source(renderer.clone()),
        &mut std::io::stdout(),
        stop,
        &EmulateOptions {
            along: Some(Along(super::sim_signal_along(renderer))),
            ..opts.clone()
        },
    )
}

/// As [`run_emulator_cli`], with the QPD signal from `source` (stage coordinates, default
/// emulated travel 0–100 × 0–100 × 0–20 µm, parked at (45, 45, 10) µm), printing to `out` and
/// serving until `stop` is set.
pub fn run_emulator_cli_with(
    kind: &str,
    source: impl SignalSource,
    out: &mut dyn Write,
    stop: Arc<AtomicBool>,
) -> anyhow::Result<()> {
    let stage = StageEmulatorConfig {
        start: [45.0, 45.0, 10.0],
        ..StageEmulatorConfig::default()
    };
    serve_emulators(
        kind,
        stage,
        QpdEmulatorConfig::default(),
        source,
        out,
        stop,
        &EmulateOptions::default(),
    )
}

fn range(t: (f64, f64)) -> String {
    format!("{}–{}", t.0, t.1)
}

/// Start the emulators named by `kind` (`stage` or its alias `gcs`, `qpd`, `pair`) with these
/// settings, print their paths and a `bfpscope.toml` snippet to `out`, and serve until `stop`
/// is set or every emulator has stopped (unplug fault).
pub fn serve_emulators(
    kind: &str,
    mut stage_cfg: StageEmulatorConfig,
    qpd_cfg: QpdEmulatorConfig,
    source: impl SignalSource,
    out: &mut dyn Write,
    stop: Arc<AtomicBool>,
    opts: &EmulateOptions,
) -> anyhow::Result<()> {
    if kind == "redpitaya" {
        return serve_redpitaya(stage_cfg, source, out, stop, opts);
    }
    if opts.port.is_some() || opts.inputs != 0 {
        anyhow::bail!("emulate: --port and --inputs are for `emulate redpitaya`");
    }
    if matches!(kind, "kpa101" | "kpz101" | "thorlabs") {
        if opts.tcp.is_some() {
            anyhow::bail!(
                "emulate: --tcp serves the GCS stage; Thorlabs cubes are serial (USB) devices"
            );
        }
        return serve_apt(kind, source, out, stop, opts.link);
    }
    stage_link_options(&mut stage_cfg, opts);
    let mut qpd_cfg = qpd_cfg;
    qpd_cfg.link = opts.link;
    let stage_desc = format!(
        "PI GCS 2.0 stage (axes {}, travel {} × {} × {} µm, servo off{}, {})",
        stage_cfg.axes.join(" "),
        range(stage_cfg.travel[0]),
        range(stage_cfg.travel[1]),
        range(stage_cfg.travel[2]),
        if stage_cfg.one_axis_per_query {
            ", one axis per query"
        } else {
            ""
        },
        stage_cfg.link.describe()
    );
    let qpd_desc = format!(
        "SCPI QPD digitiser ({} Hz, {:?} V per signal unit, {})",
        qpd_cfg.sample_rate_hz,
        qpd_cfg.volts_per_unit,
        opts.link.describe()
    );
    let axes = stage_cfg.axes.clone();
    let start = stage_cfg.start;
    let pos = shared_position(start);
    let start_stage = |cfg, pos| match &opts.tcp {
        Some(addr) => start_stage_emulator_tcp(cfg, pos, addr)
            .map_err(|e| anyhow::anyhow!("emulate: --tcp {addr}: {e}")),
        None => start_stage_emulator(cfg, pos).map_err(anyhow::Error::from),
    };
    let mut emus: Vec<Emulator> = Vec::new();
    match kind {
        "stage" | "gcs" => emus.push(start_stage(stage_cfg, pos)?),
        "qpd" if opts.tcp.is_some() => {
            anyhow::bail!(
                "emulate: --tcp serves the GCS stage; `emulate qpd` has none (use `gcs` or `pair`)"
            )
        }
        "qpd" => emus.push(start_qpd_emulator(qpd_cfg, pos, source)?),
        "both" | "pair" | "all" => {
            emus.push(start_stage(stage_cfg, pos.clone())?);
            emus.push(start_qpd_emulator(qpd_cfg, pos, source)?);
        }
        other => {
            anyhow::bail!(
                "emulate: unknown device `{other}` (expected `stage` (alias `gcs`), `qpd`, `pair`, \
                 `kpa101`, `kpz101`, `thorlabs` or `redpitaya`)"
            )
        }
    }
    for e in &emus {
        let what = if e.kind() == "stage" {
            &stage_desc
        } else {
            &qpd_desc
        };
        writeln!(out, "{}: {what} on {}", e.kind(), e.path())?;
    }
    if kind == "qpd" {
        writeln!(
            out,
            "(the QPD alone sees a stage parked at {start:?} µm; use `pair` to scan)"
        )?;
    }
    writeln!(out, "\n# bfpscope.toml for these emulators:")?;
    for e in &emus {
        if e.kind() == "stage" {
            writeln!(
                out,
                "[stage]\nbackend = \"gcs\"\nport = \"{}\"\naxes = {{ x = \"{}\", y = \"{}\", z = \"{}\" }}\n",
                e.path(),
                axes[0],
                axes[1],
                axes[2]
            )?;
        } else {
            writeln!(out, "[qpd]\nbackend = \"scpi\"\nport = \"{}\"\n", e.path())?;
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

/// The GCS stage's link as the options model it: its serial link (TCP has no baud rate: only
/// the latency stays), and `--one-axis-per-query`.
fn stage_link_options(stage_cfg: &mut StageEmulatorConfig, opts: &EmulateOptions) {
    stage_cfg.one_axis_per_query |= opts.one_axis_per_query;
    stage_cfg.link = if opts.tcp.is_some() {
        LinkModel {
            baud: None,
            ..opts.link
        }
    } else {
        opts.link
    };
}

/// `redpitaya`: a GCS stage (pseudo-terminal, or TCP with `--tcp`) and a Red Pitaya board on
/// a loopback TCP port sharing the stage position, the board's inputs carrying `source`
/// (Sx → IN1, Sy → IN2, Sz → IN3 on the 4-input model), 1 V per signal unit, 1 mV rms noise.
fn serve_redpitaya(
    mut stage_cfg: StageEmulatorConfig,
    source: impl SignalSource,
    out: &mut dyn Write,
    stop: Arc<AtomicBool>,
    opts: &EmulateOptions,
) -> anyhow::Result<()> {
    use super::{start_redpitaya_emulator, RedPitayaEmulatorConfig};
    let rp_cfg = match opts.inputs {
        0 | 2 => RedPitayaEmulatorConfig::default(),
        4 => RedPitayaEmulatorConfig::four_inputs(),
        n => anyhow::bail!(
            "emulate: --inputs {n}: a STEMlab 125-14 has 2 fast inputs, its 4-input model 4"
        ),
    };
    let four = rp_cfg.inputs == 4;
    // the board is on TCP at full speed
    stage_link_options(&mut stage_cfg, opts);
    let axes = stage_cfg.axes.clone();
    let link_desc = stage_cfg.link.describe();
    let pos = shared_position(stage_cfg.start);
    // the stage's OUT1 drives the board's external trigger; the board follows the wave's path
    let path = super::StagePath::new();
    let rp_cfg = RedPitayaEmulatorConfig {
        path: Some(path.clone()),
        along: opts.along.as_ref().map(|a| a.0.clone()),
        ..rp_cfg
    };
    let addr = format!("127.0.0.1:{}", opts.port.unwrap_or(0));
    let (rp, ext) = start_redpitaya_emulator(rp_cfg, pos.clone(), source, &addr)
        .map_err(|e| anyhow::anyhow!("emulate: redpitaya on {addr}: {e}"))?;
    stage_cfg.wave.trigger_out[0] = Some(ext);
    stage_cfg.wave.path = Some(path);
    let stage = match &opts.tcp {
        Some(addr) => start_stage_emulator_tcp(stage_cfg, pos.clone(), addr)
            .map_err(|e| anyhow::anyhow!("emulate: --tcp {addr}: {e}"))?,
        None => start_stage_emulator(stage_cfg, pos)?,
    };
    let hostport = rp.path().trim_start_matches("tcp://").to_string();
    let (host, port) = hostport.rsplit_once(':').unwrap_or((&hostport, "5000"));
    writeln!(
        out,
        "stage: PI GCS 2.0 stage (axes {}, {}) on {}",
        axes.join(" "),
        link_desc,
        stage.path()
    )?;
    writeln!(
        out,
        "redpitaya: Red Pitaya STEMlab 125-14{} SCPI server (16384-sample buffers, 125 MS/s / decimation; external trigger DIO0_P wired to the stage's OUT1) on {}",
        if four { " 4-input" } else { "" },
        rp.path()
    )?;
    writeln!(out, "\n# bfpscope.toml for these emulators:")?;
    writeln!(
        out,
        "[stage]\nbackend = \"gcs\"\nport = \"{}\"\naxes = {{ x = \"{}\", y = \"{}\", z = \"{}\" }}\ntrigger_line = 1\n",
        stage.path(),
        axes[0],
        axes[1],
        axes[2]
    )?;
    writeln!(
        out,
        "[qpd]\nbackend = \"redpitaya\"\nhost = \"{host}\"\nport = {port}\nchannels = {}\n",
        if four {
            "{ sx = 1, sy = 2, sz = 3 }"
        } else {
            "{ sx = 1, sy = 2 }"
        }
    )?;
    writeln!(out, "Serving until Ctrl-C.")?;
    out.flush()?;
    while !stop.load(Ordering::SeqCst) {
        if !stage.is_running() && !rp.is_running() {
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    Ok(())
}

/// Middle of the emulated KPZ101 cubes' 0–20 µm travel: the scene's origin sits here.
pub const APT_CENTRE: [f64; 3] = [10.0, 10.0, 10.0];

/// `kpa101` (the aligner alone, stage parked at the centre), `kpz101` (three cubes, x y z) or
/// `thorlabs` (both, sharing the stage position): the scene's origin at [`APT_CENTRE`].
fn serve_apt(
    kind: &str,
    source: impl SignalSource,
    out: &mut dyn Write,
    stop: Arc<AtomicBool>,
    link: LinkModel,
) -> anyhow::Result<()> {
    use super::{start_kpa101_emulator, start_kpz101_stage_on, KpaEmulatorConfig};
    let pos = shared_position(APT_CENTRE);
    let shifted = move |p: [f64; 3]| {
        source([
            p[0] - APT_CENTRE[0],
            p[1] - APT_CENTRE[1],
            p[2] - APT_CENTRE[2],
        ])
    };
    let mut cubes: Vec<Emulator> = Vec::new();
    let mut kpa: Option<Emulator> = None;
    if kind != "kpa101" {
        cubes.extend(start_kpz101_stage_on([20.0; 3], pos.clone(), link)?);
    }
    if kind != "kpz101" {
        kpa = Some(start_kpa101_emulator(
            KpaEmulatorConfig {
                link,
                ..KpaEmulatorConfig::default()
            },
            pos,
            shifted,
        )?);
    }
    for (e, ax) in cubes.iter().zip(["x", "y", "z"]) {
        writeln!(
            out,
            "kpz101 {ax}: Thorlabs KPZ101 piezo cube (travel 0–20 µm, open loop, channel disabled, {}) on {}",
            link.describe(),
            e.path()
        )?;
    }
    if let Some(q) = &kpa {
        writeln!(
            out,
            "kpa101: Thorlabs KPA101 position aligner (Sum 5 V with no sample; scene origin at {APT_CENTRE:?} µm; {}) on {}",
            link.describe(),
            q.path()
        )?;
    }
    writeln!(out, "\n# bfpscope.toml for these emulators:")?;
    if !cubes.is_empty() {
        writeln!(
            out,
            "[stage]\nbackend = \"kpz101\"\nports = {{ x = \"{}\", y = \"{}\", z = \"{}\" }}\n",
            cubes[0].path(),
            cubes[1].path(),
            cubes[2].path()
        )?;
    }
    if let Some(q) = &kpa {
        writeln!(
            out,
            "[qpd]\nbackend = \"kpa101\"\nport = \"{}\"\ncalibration = {{ gain = [1.0, 1.0, 0.2], offset_v = [0.0, 0.0, 5.0] }}   # Sz = (Sum - 5 V) / 5 V\n",
            q.path()
        )?;
    }
    if kind != "thorlabs" {
        writeln!(
            out,
            "(the other device must be hardware too: `bfpscope emulate thorlabs` serves both)"
        )?;
    }
    writeln!(out, "Serving until Ctrl-C.")?;
    out.flush()?;
    while !stop.load(Ordering::SeqCst) {
        if cubes.iter().chain(kpa.iter()).all(|e| !e.is_running()) {
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    Ok(())
}
