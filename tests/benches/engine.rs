//! Engine benchmarks (criterion):
//! - `binding_call`: a native binding called from a Rhai loop through the registry
//!   (target ≥ 3 M calls/s in a release build);
//! - `scan_128x128`: a 128×128 scan end to end from a script on the mock instrument, including
//!   pre-flight, metadata and the autosave (target ≤ 100 ms wall), reporting the instrument
//!   time the same scan would take.
//!
//! `cargo bench --features bench --bench engine`

use bfpscope::script::{Settings, Workbench};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use std::time::{Duration, Instant};

const CALLS: i64 = 200_000;

fn workbench(tag: &str) -> Workbench {
    let dir = std::env::temp_dir().join(format!("bfpscope-bench-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (s, _) = Settings::captured(dir);
    let mut w = Workbench::new(s);
    let _ = w.eval_line("connect(#{backend: \"mock\"});").unwrap();
    w
}

fn binding_call(c: &mut Criterion) {
    let mut w = workbench("calls");
    let script = format!("let t = 0.0; for i in 0..{CALLS} {{ t = clock(); }} t");
    // one measured run for the headline number
    let t0 = Instant::now();
    let _ = w.eval_line(&script).unwrap();
    let rate = CALLS as f64 / t0.elapsed().as_secs_f64();
    let empty = format!("let t = 0.0; for i in 0..{CALLS} {{ t = 1.0; }} t");
    let t0 = Instant::now();
    let _ = w.eval_line(&empty).unwrap();
    let loop_rate = CALLS as f64 / t0.elapsed().as_secs_f64();
    eprintln!("binding_call: {:.2} M calls/s of clock() through the registry (empty loop: {:.2} M iterations/s)", rate / 1e6, loop_rate / 1e6);

    let mut g = c.benchmark_group("engine");
    g.throughput(Throughput::Elements(CALLS as u64));
    g.sample_size(10).measurement_time(Duration::from_secs(5));
    g.bench_function("binding_call", |b| b.iter(|| w.eval_line(&script).unwrap()));
    g.finish();
}

fn scan_128(c: &mut Criterion) {
    let mut w = workbench("scan");
    let script = "scan_xy(#{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 128, ny: 128, dwell: 0.001}).meta.time.instrument_s";
    let t0 = Instant::now();
    let t_inst = w.eval_line(script).unwrap().as_float().unwrap();
    eprintln!(
        "scan_128x128: {:.1} ms wall end to end (incl. autosave); the instrument would take {:.1} s",
        t0.elapsed().as_secs_f64() * 1e3,
        t_inst
    );
    let mut g = c.benchmark_group("engine");
    g.sample_size(10).measurement_time(Duration::from_secs(5));
    g.bench_function("scan_128x128", |b| b.iter(|| w.eval_line(script).unwrap()));
    g.finish();
}

criterion_group!(benches, binding_call, scan_128);
criterion_main!(benches);
