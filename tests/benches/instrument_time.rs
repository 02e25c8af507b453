//! Instrument time per point on `bfpscope emulate pair`: a 20 × 20 scan
//! through the real GCS and SCPI drivers, dwell 10 ms and 1 ms, settle 5 ms, on a modelled
//! 115200-baud link with 1 ms reply latency and at the pseudo-terminal's full speed; "before"
//! is the protocol of the drivers before the speed work reproduced by their options (`ONT?` polled
//! every 5 ms, `MEAS:QPD:STAT?` and `SYST:ERR?` after every measurement), "after" the new
//! defaults with a 1 ms polling interval (`stage.poll_ms = 1`, the GCS default since the device-truth work) (`#5`, its `ERR?` once the motion has ended, `MEAS:QPD?` for the means the
//! scan stores, no `SYST:ERR?` after a well-formed reading).
//! The device-truth work split "after" in two, interleaved in the same run: "#5 alone" (the move ends when
//! `#5` answers 0) and "#5 + ONT?" (then one `ONT?` of the moved axis confirms on target): the
//! per-point cost of the confirmation.
//! Prints a Markdown table (ms per point against settle + dwell, and the per-phase split from
//! `meta.time.phases`) for docs/performance.md.
//!
//! `cargo bench --features bench --bench instrument_time`

#[path = "../support/emulate.rs"]
mod emulate;

use bfpscope::acquire::{run_plan, Axis, Plan, ScanEnv, SoftLimits, Sweep};
use bfpscope::instrument::gcs::{GcsOptions, GcsStage};
use bfpscope::instrument::scpi::{ScpiOptions, ScpiQpd};
use bfpscope::instrument::{DeviceError, Instrument, Qpd, QpdReading, WallClock};
use emulate::Emulator;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

const SETTLE_S: f64 = 0.005;
const N: i64 = 20;

/// Start `bfpscope emulate pair` with these link flags; returns the emulator (stopped with
/// Ctrl-C when dropped) and the stage and QPD paths it printed.
fn emulate(link: &[&str]) -> (Emulator, String, String) {
    let e = Emulator::start(&[&["pair"], link].concat());
    let (stage, qpd) = (e.path_of("stage:"), e.path_of("qpd:"));
    (e, stage, qpd)
}

/// The QPD as the engine read it before the speed work: the full `read` (`MEAS:QPD:STAT?`) per point.
struct Legacy(ScpiQpd);

impl Qpd for Legacy {
    fn name(&self) -> String {
        self.0.name()
    }
    fn sample_rate(&self) -> f64 {
        self.0.sample_rate()
    }
    fn read(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        self.0.read(n)
    }
    fn link_costs(&mut self) -> bfpscope::instrument::link::LinkCosts {
        self.0.link_costs()
    }
}

struct Row {
    link: &'static str,
    dwell_ms: f64,
    version: &'static str,
    phases: serde_json::Value,
}

/// The drivers' protocol: "before" the speed work, "#5 alone" (from the speed work until the device-truth work: the move
/// ends when `#5` answers 0), "#5 + ONT?" (since the device-truth work: then `ONT?` of the moved axis).
const VERSIONS: [&str; 3] = ["before", "#5 alone", "#5 + ONT?"];

fn scan(stage: &str, qpd: &str, dwell_s: f64, version: &str) -> serde_json::Value {
    let before = version == "before";
    let gcs = GcsOptions {
        motion_status: !before,
        confirm_on_target: version != "#5 alone",
        poll_interval: Duration::from_millis(if before { 5 } else { 1 }),
        ..GcsOptions::default()
    };
    let scpi = ScpiOptions {
        check_error_each_read: before,
        ..ScpiOptions::default()
    };
    let q = ScpiQpd::open(qpd, 115_200, scpi).expect("qpd");
    let q: Box<dyn Qpd> = if before {
        Box::new(Legacy(q))
    } else {
        Box::new(q)
    };
    let mut inst = Instrument {
        stage: Box::new(GcsStage::open(stage, 115_200, gcs).expect("stage")),
        qpd: q,
        clock: Arc::new(WallClock::default()),
        settle_s: SETTLE_S,
        description: serde_json::json!({}),
    };
    // park at the scan's start so the first point is a step like the others
    inst.stage.move_to([-0.5, -0.5, 0.0]).expect("park");
    let plan = Plan::grid(
        "scan_xy",
        Sweep::new("scan_xy", Axis::X, -0.5, 0.5, N, "nx").expect("x"),
        Sweep::new("scan_xy", Axis::Y, -0.5, 0.5, N, "ny").expect("y"),
        vec![(Axis::Z, 0.0)],
        dwell_s,
        false,
        true,
    )
    .expect("plan");
    let limits = SoftLimits::default();
    let abort = AtomicBool::new(false);
    let log = |s: &str| eprintln!("  {s}");
    let save = |_: &bfpscope::data::Scan| Ok(std::path::PathBuf::from("memory"));
    let env = ScanEnv::plain(&limits, &abort, &log, &save);
    let run = run_plan(&mut inst, &plan, &env).expect("scan");
    run.scan.meta["time"]["phases"].clone()
}

fn main() {
    // `cargo test --benches` runs benches with --bench absent: skip the slow work there
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let links: [(&'static str, [&str; 4]); 2] = [
        (
            "115200 baud, 1 ms latency",
            ["--baud", "115200", "--latency-ms", "1"],
        ),
        ("pty full speed", ["--baud", "max", "--latency-ms", "0"]),
    ];
    let mut rows = Vec::new();
    for (name, flags) in links {
        let (emulator, stage, qpd) = emulate(&flags);
        for dwell_s in [0.010, 0.001] {
            for version in VERSIONS {
                eprintln!("{name}, dwell {} ms, {version}:", dwell_s * 1e3);
                let phases = scan(&stage, &qpd, dwell_s, version);
                rows.push(Row {
                    link: name,
                    dwell_ms: dwell_s * 1e3,
                    version,
                    phases,
                });
            }
        }
        drop(emulator);
    }
    println!("| link | dwell | drivers | ms per point | settle + dwell | ratio | move | settle | QPD (dwell) | other | link bytes per point | their wire time at 115200 baud |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for r in &rows {
        let p = &r.phases;
        let f = |k: &str| p[k].as_f64().unwrap_or(f64::NAN);
        let floor = SETTLE_S * 1e3 + r.dwell_ms;
        let bytes = f("link_bytes_per_point");
        println!(
            "| {} | {} ms | {} | {:.2} | {:.1} | {:.2}× | {:.2} | {:.2} | {:.2} ({:.2}) | {:.2} | {:.0} | {:.2} ms |",
            r.link,
            r.dwell_ms,
            r.version,
            f("per_point_ms"),
            floor,
            f("per_point_ms") / floor,
            f("move_ms"),
            f("settle_ms"),
            f("qpd_ms"),
            f("dwell_ms"),
            f("other_ms"),
            bytes,
            bytes * 10.0 / 115_200.0 * 1e3
        );
    }
    println!();
    println!("The on-target confirmation: `#5 + ONT?` against `#5 alone`, same link, same dwell, same run:");
    println!();
    println!("| link | dwell | ms per point, #5 alone | ms per point, #5 + ONT? | difference | ratio | `ONT?` per point (count, bytes, ms) |");
    println!("|---|---|---|---|---|---|---|");
    for pair in rows.chunks(VERSIONS.len()) {
        let (a, b) = (&pair[1], &pair[2]);
        let pa = a.phases["per_point_ms"].as_f64().unwrap_or(f64::NAN);
        let pb = b.phases["per_point_ms"].as_f64().unwrap_or(f64::NAN);
        let o = &b.phases["stage_link"]["ONT?"];
        let g = |k: &str| o[k].as_f64().unwrap_or(f64::NAN);
        println!(
            "| {} | {} ms | {:.2} | {:.2} | {:+.2} ms | {:.3}× | {:.2}, {:.0} B, {:.2} ms |",
            a.link,
            a.dwell_ms,
            pa,
            pb,
            pb - pa,
            pb / pa,
            g("per_point"),
            g("bytes_per_point"),
            g("write_ms") + g("reply_ms")
        );
    }
    println!();
    println!("Per command, ms per point (write + reply) and count per point:");
    for r in &rows {
        let p = &r.phases;
        let cmds = |k: &str| {
            p[k].as_object()
                .map(|m| {
                    m.iter()
                        .map(|(w, c)| {
                            format!(
                                "`{w}` {:.2}× {:.0} B {:.2} ms",
                                c["per_point"].as_f64().unwrap_or(0.0),
                                c["bytes_per_point"].as_f64().unwrap_or(0.0),
                                c["write_ms"].as_f64().unwrap_or(0.0)
                                    + c["reply_ms"].as_f64().unwrap_or(0.0)
                            )
                        })
                        .collect::<Vec<_>>()
                        .join(", ")
                })
                .unwrap_or_default()
        };
        println!(
            "- {}, dwell {} ms, {}: stage {}; QPD {}",
            r.link,
            r.dwell_ms,
            r.version,
            cmds("stage_link"),
            cmds("qpd_link")
        );
    }
}
