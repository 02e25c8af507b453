//! The NI raster's frame stream on the fake bench (`libfakebench.so`: a Nano-Drive whose x/y
//! external inputs follow the PCI-6120's ao0/ao1 through a first-order lag, the board's ai0–ai3
//! recording the QPD and the x sensor monitor on the AO clock), through the real drivers and
//! the scan engine (`run_raster` → `strategy::stream`):
//!
//! - a 256 × 256 raster at 10 µs per pixel (8 samples at 800 kS/s), with the fake's stage lag
//!   τ = 2 ms (settle 10 ms: ramps, margins and turnarounds of 5 τ) and τ = 0.2 ms (settle 1 ms);
//!   the target: wall time ≤ 1.2 × (pixel time + turnarounds), the frame's duration;
//! - a 60 s continuous stream of 4 channels at 800 kS/s (256 × 256 at 0.8 ms per pixel): no
//!   overflow, how far the reader fell behind the clock against the buffer, and the share of one
//!   core that converting and binning the samples took.
//!
//! `cargo bench --features bench --bench ni_stream` prints a Markdown table for docs/performance.md.

#[path = "../support/fakebench.rs"]
mod fakebench;

use bfpscope::acquire::raster::RasterOptions;
use bfpscope::acquire::run_raster;
use bfpscope::acquire::{Axis, Plan, ScanEnv, Sweep};
use bfpscope::config::connect::connect;
use bfpscope::config::Config;
use bfpscope::instrument::Instrument;
use std::ffi::CString;
use std::os::raw::{c_char, c_int};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

const CENTRE: [f64; 3] = [37.5, 37.5, 25.0];

struct Case {
    what: &'static str,
    tau_ms: &'static str,
    settle_s: f64,
    n: i64,
    pitch_um: f64,
    dwell_s: f64,
}

fn main() {
    let lib = fakebench::library();
    let l = unsafe { libloading::Library::new(&lib) }.expect("load the fake");
    let set: libloading::Symbol<unsafe extern "C" fn(*const c_char, *const c_char) -> c_int> =
        unsafe { l.get(b"fakebench_set\0") }.expect("fakebench_set");
    // the config `bfpscope emulate nidaq` prints for the fake
    let text = bfpscope::config::bench::fake_bench_config(&lib);
    let cfg = Config::from_toml_str(&text, "bench.toml").unwrap();
    let cases = [
        Case {
            what: "256 × 256 at 10 µs per pixel, stage lag τ = 2 ms (settle 10 ms)",
            tau_ms: "2",
            settle_s: 0.01,
            n: 256,
            pitch_um: 0.01,
            dwell_s: 10e-6,
        },
        Case {
            what: "256 × 256 at 10 µs per pixel, stage lag τ = 0.2 ms (settle 1 ms)",
            tau_ms: "0.2",
            settle_s: 0.001,
            n: 256,
            pitch_um: 0.01,
            dwell_s: 10e-6,
        },
        Case {
            what: "60 s stream: 256 × 256 at 0.8 ms per pixel, τ = 2 ms (settle 10 ms)",
            tau_ms: "2",
            settle_s: 0.01,
            n: 256,
            pitch_um: 0.01,
            dwell_s: 0.8e-3,
        },
    ];
    println!("| case | pixel time | turnarounds | frame (pixels + turnarounds) | wall time | wall / frame | target | samples streamed | most behind the clock / buffer | converting + binning, share of one core | status |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for c in &cases {
        let (k, v) = (
            CString::new("tau_ms").unwrap(),
            CString::new(c.tau_ms).unwrap(),
        );
        assert_eq!(
            unsafe { set(k.as_ptr(), v.as_ptr()) },
            0,
            "fakebench_set tau_ms"
        );
        let mut conn = connect(&cfg, |_: &Config| -> anyhow::Result<Instrument> {
            anyhow::bail!("no simulator here")
        })
        .unwrap_or_else(|e| panic!("{e}"));
        conn.instrument.settle_s = c.settle_s;
        conn.instrument.stage.move_to(CENTRE).unwrap();
        let half = c.pitch_um * (c.n - 1) as f64 / 2.0;
        let plan = Plan::grid(
            "scan_xy",
            Sweep::new(
                "scan_xy",
                Axis::X,
                CENTRE[0] - half,
                CENTRE[0] + half,
                c.n,
                "nx",
            )
            .unwrap(),
            Sweep::new(
                "scan_xy",
                Axis::Y,
                CENTRE[1] - half,
                CENTRE[1] + half,
                c.n,
                "ny",
            )
            .unwrap(),
            vec![(Axis::Z, CENTRE[2])],
            c.dwell_s,
            false,
            false,
        )
        .unwrap();
        let abort = AtomicBool::new(false);
        let log = |_: &str| {};
        let save = |_: &bfpscope::data::Scan| -> Result<std::path::PathBuf, String> {
            Ok(std::path::PathBuf::from("memory"))
        };
        let limits = conn.limits;
        let env = ScanEnv::plain(&limits, &abort, &log, &save);
        let t0 = Instant::now();
        let r = run_raster(&mut conn.instrument, &plan, &RasterOptions::default(), &env)
            .unwrap_or_else(|e| panic!("{e}"));
        let wall = t0.elapsed().as_secs_f64();
        let m = &r.scan.meta["raster"];
        let s = &m["stream"];
        let frame = s["frame_s"].as_f64().unwrap_or(f64::NAN);
        let pixels = (c.n * c.n) as f64 * c.dwell_s;
        let status = match &r.ended {
            bfpscope::acquire::Ended::Complete => "complete".to_string(),
            other => format!("{other:?}"),
        };
        println!(
            "| {} | {:.3} s | {:.3} s | {:.3} s | {:.3} s | {:.3} | ≤ 1.2 {} | {} × 4 channels | {} / {} samples ({:.0} ms / {:.0} ms) | {:.2} s of {:.2} s: {:.1} % | {} |",
            c.what,
            pixels,
            frame - pixels,
            frame,
            wall,
            wall / frame,
            if wall / frame <= 1.2 { "✓" } else { "✗" },
            s["frame_samples"],
            s["max_behind_samples"],
            s["buffer_samples"],
            s["max_behind_samples"].as_f64().unwrap_or(0.0) / 800.0,
            s["buffer_samples"].as_f64().unwrap_or(0.0) / 800.0,
            s["binning_cpu_s"].as_f64().unwrap_or(f64::NAN),
            s["stream_s"].as_f64().unwrap_or(f64::NAN),
            100.0 * s["binning_cpu_share"].as_f64().unwrap_or(f64::NAN),
            status,
        );
        eprintln!("{}: time.lines {}", c.what, r.scan.meta["time"]["lines"]);
    }
}
