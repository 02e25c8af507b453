//! Hardware-timed raster against point-by-point: a 64 × 64 image at
//! 1 ms per pixel on `bfpscope emulate redpitaya` (a PI GCS stage whose trigger output OUT1 is
//! wired to a Red Pitaya 4-input board, loopback TCP), through the real drivers and the
//! engines: `run_raster` (wave generator, triggered buffer, recorder) and `run_plan` (move,
//! settle 5 ms, read) over the same field. The stage on a pseudo-terminal modelling a
//! 115200-baud USB-serial link with 1 ms reply latency, at the pseudo-terminal's full speed,
//! and on a loopback TCP port (a controller's GCS port 50000, 1 ms latency, no baud limit).
//! The target: raster wall time ≤ 1.2 × (4096 × 1 ms + turnarounds) = 1.2 × 64 × line
//! duration. Prints a Markdown table and the per-line phases for docs/performance.md.
//!
//! `cargo bench --features bench --bench raster_time`

#[path = "../support/emulate.rs"]
mod emulate;

use bfpscope::acquire::raster::RasterOptions;
use bfpscope::acquire::run_raster;
use bfpscope::acquire::{run_plan, Axis, Plan, ScanEnv, SoftLimits, Sweep};
use bfpscope::instrument::gcs::{GcsOptions, GcsStage, LineSweep};
use bfpscope::instrument::redpitaya::{ChannelMap, RedPitaya, RedPitayaOptions};
use bfpscope::instrument::{Instrument, LineScan, Stage, WallClock};
use emulate::Emulator;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

const SETTLE_S: f64 = 0.005;
const N: i64 = 64;
const DWELL_S: f64 = 1e-3;

/// Start `bfpscope emulate redpitaya --inputs 4` with these flags; the emulator (stopped with
/// Ctrl-C when dropped), the stage path and the board's `host:port`.
fn emulate(flags: &[&str]) -> (Emulator, String, String) {
    let e = Emulator::start(&[&["redpitaya", "--inputs", "4"], flags].concat());
    let stage = e.path_of("stage:");
    let board = e
        .path_of("redpitaya:")
        .trim_start_matches("tcp://")
        .to_string();
    (e, stage, board)
}

fn instrument(stage: &str, board: &str) -> Instrument {
    let gcs = GcsOptions {
        poll_interval: Duration::from_millis(1),
        trigger_line: Some(1),
        ..GcsOptions::default()
    };
    let (h, p) = board.rsplit_once(':').expect("host:port");
    let rp = RedPitaya::open(
        h,
        p.parse().expect("port"),
        RedPitayaOptions {
            channels: ChannelMap {
                sx: 1,
                sy: 2,
                sz: Some(3),
            },
            ..RedPitayaOptions::default()
        },
    )
    .expect("board");
    Instrument {
        stage: Box::new(GcsStage::open(stage, 115_200, gcs).expect("stage")),
        qpd: Box::new(rp),
        clock: Arc::new(WallClock::default()),
        settle_s: SETTLE_S,
        description: serde_json::json!({}),
    }
}

fn plan() -> Plan {
    Plan::grid(
        "scan_xy",
        Sweep::new("scan_xy", Axis::X, -0.5, 0.5, N, "nx").expect("x"),
        Sweep::new("scan_xy", Axis::Y, -0.5, 0.5, N, "ny").expect("y"),
        vec![(Axis::Z, 0.0)],
        DWELL_S,
        false,
        false,
    )
    .expect("plan")
}

/// One scan; its metadata.
fn scan(inst: &mut Instrument, raster: bool) -> serde_json::Value {
    inst.stage.move_to([-0.5, -0.5, 0.0]).expect("park");
    let limits = SoftLimits::default();
    let abort = AtomicBool::new(false);
    let log = |s: &str| eprintln!("  {s}");
    let save = |_: &bfpscope::data::Scan| Ok(std::path::PathBuf::from("memory"));
    let env = ScanEnv::plain(&limits, &abort, &log, &save);
    let run = if raster {
        run_raster(inst, &plan(), &RasterOptions::default(), &env).expect("raster")
    } else {
        run_plan(inst, &plan(), &env).expect("points")
    };
    assert_eq!(run.ended, bfpscope::acquire::Ended::Complete);
    run.scan.meta
}

/// Snake rasters: the wall time of configuring one line whose direction alternates,
/// every line configured in full (`forget_waves` first: the driver before the device-truth work) against
/// two wave tables switched with `WSL`, in alternating blocks of 8 lines on one connection.
/// Returns (ms per line before, ms per line with two tables).
fn configure_cost(stage: &str) -> (f64, f64) {
    let gcs = GcsOptions {
        poll_interval: Duration::from_millis(1),
        trigger_line: Some(1),
        ..GcsOptions::default()
    };
    let mut s = GcsStage::open(stage, 115_200, gcs).expect("stage");
    let t = LineScan::line_timing(&mut s)
        .expect("line timing")
        .expect("a wave generator");
    // a 64-pixel line at 1 ms: 64 ms of wave at 50 µs, ramps of 100 points
    let sweep = |from: f64, to: f64| LineSweep {
        axis: 0,
        from_um: from,
        to_um: to,
        points: 1480,
        speedupdown: 100,
        rate: 1,
        record_rate: 5,
        trigger_line: Some(1),
        table: 1,
        servo_cycle_s: t.servo_cycle_s,
    };
    let lines = [sweep(-0.55, 0.55), sweep(0.55, -0.55)];
    let (mut full, mut two) = (0.0, 0.0);
    let (mut n_full, mut n_two) = (0usize, 0usize);
    for _block in 0..4 {
        for l in lines.iter().cycle().take(8) {
            s.forget_waves();
            let t0 = std::time::Instant::now();
            s.wave_configure(l).expect("configure");
            full += t0.elapsed().as_secs_f64();
            n_full += 1;
        }
        // load both tables (not timed), then 8 alternating lines
        s.forget_waves();
        s.wave_configure(&lines[0]).expect("configure");
        s.wave_configure(&lines[1]).expect("configure");
        for l in lines.iter().cycle().take(8) {
            let t0 = std::time::Instant::now();
            s.wave_configure(l).expect("configure");
            two += t0.elapsed().as_secs_f64();
            n_two += 1;
        }
    }
    (full / n_full as f64 * 1e3, two / n_two as f64 * 1e3)
}

fn main() {
    // `cargo test --benches` runs benches with --bench absent: skip the slow work there
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let links: [(&str, &[&str], bool); 3] = [
        (
            "pty, 115200 baud, 1 ms latency",
            &["--baud", "115200", "--latency-ms", "1"],
            true,
        ),
        (
            "pty full speed",
            &["--baud", "max", "--latency-ms", "0"],
            true,
        ),
        (
            "TCP, 1 ms latency",
            &["--tcp", "127.0.0.1:0", "--latency-ms", "1"],
            false,
        ),
    ];
    // snake rasters' line configuration first (printed at once: the rasters below take minutes)
    let mut snake = Vec::new();
    for (name, flags, _) in links {
        let (emulator, stage, _) = emulate(flags);
        eprintln!("{name}: configure, snake lines");
        let (full, two) = configure_cost(&stage);
        snake.push(format!(
            "| {name} | {full:.2} ms | {two:.2} ms | {:.2} ms | {:.1}× |",
            full - two,
            full / two
        ));
        drop(emulator);
    }
    println!("Snake rasters, configuring a line whose direction alternates (32 lines per column, alternating blocks of 8 on one connection):");
    println!();
    println!("| stage link | every line configured (WAV, WSL, WGC, WTR, CTO, TWC, TWS, DRC, RTR + ERR? each) | two wave tables, `WSL` + `ERR?` | saving per line | ratio |");
    println!("|---|---|---|---|---|");
    for r in &snake {
        println!("{r}");
    }
    println!();
    let mut table = Vec::new();
    let mut phases = Vec::new();
    for (name, flags, points_too) in links {
        let (emulator, stage, board) = emulate(flags);
        let mut inst = instrument(&stage, &board);
        eprintln!("{name}: raster");
        let m = scan(&mut inst, true);
        let r = &m["raster"];
        let line_s = r["line_s"].as_f64().unwrap_or(f64::NAN);
        let wall = m["time"]["wall_s"].as_f64().unwrap_or(f64::NAN);
        let target = 1.2 * N as f64 * line_s;
        let points = if points_too {
            eprintln!("{name}: point by point");
            let p = scan(&mut inst, false);
            p["time"]["wall_s"].as_f64()
        } else {
            None
        };
        table.push(format!(
            "| {name} | {:.2} s | {:.1} ms ({:.1} ms turnaround) | {:.2} s | {:.2}× | {} | {} |",
            wall,
            line_s * 1e3,
            r["turnaround_s"].as_f64().unwrap_or(f64::NAN) * 1e3,
            target,
            wall / target,
            points.map_or("—".into(), |p| format!("{p:.1} s")),
            points.map_or("—".into(), |p| format!("{:.1}×", p / wall)),
        ));
        let l = &m["time"]["lines"];
        let f = |k: &str| l[k].as_f64().unwrap_or(f64::NAN);
        phases.push(format!(
            "| {name} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {} | {} |",
            wall / N as f64 * 1e3,
            f("move_ms"),
            f("configure_arm_ms"),
            f("wave_ms"),
            f("qpd_read_ms"),
            f("record_read_ms"),
            r["samples_per_pixel_mean"]
                .as_f64()
                .map_or("—".into(), |v| format!("{v:.1}")),
            r["record_rate"],
        ));
        drop(inst);
        drop(emulator);
    }
    println!("| stage link | raster wall time | line (64 px + turnaround) | target 1.2 × 64 lines | raster / target | point by point (settle 5 ms) | points / raster |");
    println!("|---|---|---|---|---|---|---|");
    for r in &table {
        println!("{r}");
    }
    println!();
    println!("Per line, ms (`meta.time.lines`):");
    println!();
    println!("| stage link | wall per line | move to the line start | configure + arm | wave | board read | recorder read (`DRR?`) | samples per pixel | record rate (cycles) |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for r in &phases {
        println!("{r}");
    }
}
