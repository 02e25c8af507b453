//! Speed of the Mie tier: efficiencies vs size parameter, vs term count, and
//! amplitude functions vs number of angles.
//!
//! `cargo bench --features bench --bench mie` runs the criterion benchmarks.
//! `MIE_COMPARE_JSON=1 cargo bench --features bench --bench mie` instead prints one JSON object per line
//! (values and ns per call on the comparison grid) for `scripts/py/mie_compare.py`, which
//! times miepython on the same grid in the same run and reports ratios and agreement.
//! `MIE_TERMS_TABLE=1 cargo bench --features bench --bench mie` prints the accuracy-vs-term-count table used in
//! `docs/mie.md` (error against N + 400 terms, and time per call).

use bfpscope::optics::mie::{
    default_terms, mie_q, mie_q_terms, mie_s1s2, wiscombe_terms, Complex64, MieResult,
};
use criterion::{BenchmarkId, Criterion};
use std::hint::black_box;
use std::time::{Duration, Instant};

/// Size parameters of the comparison grid (the Mie tier's target range: x = 0.1 … 1000).
const XS: [f64; 5] = [0.1, 1.0, 10.0, 100.0, 1000.0];

fn indices() -> [(&'static str, Complex64); 3] {
    [
        ("m=1.5", Complex64::new(1.5, 0.0)),
        ("m=1.5+0.1i", Complex64::new(1.5, 0.1)),
        ("m=1.2+1i", Complex64::new(1.2, 1.0)),
    ]
}

/// miepython's own truncation, int(x + 4.05 x^0.33333 + 2) (its `wiscombe_terms`), so that the
/// comparison can also be made term-for-term.
fn miepython_terms(x: f64) -> usize {
    (x + 4.05 * x.powf(0.33333) + 2.0) as usize
}

/// Median ns per call of `f` over `rounds` rounds of at least `min_round` each.
fn time_ns<F: FnMut()>(mut f: F, rounds: usize, min_round: Duration) -> f64 {
    let mut per_call = Vec::with_capacity(rounds);
    for _ in 0..rounds {
        let mut n = 0u64;
        let t = Instant::now();
        while t.elapsed() < min_round {
            f();
            n += 1;
        }
        per_call.push(t.elapsed().as_nanos() as f64 / n as f64);
    }
    per_call.sort_by(|a, b| a.partial_cmp(b).unwrap());
    per_call[rounds / 2]
}

fn json_line(x: f64, m: Complex64, tag: &str, r: &MieResult, ns: f64) -> String {
    format!(
        "{{\"tag\":\"{tag}\",\"x\":{x:e},\"m_re\":{:e},\"m_im\":{:e},\"qext\":{:.17e},\"qsca\":{:.17e},\"qback\":{:.17e},\"g\":{:.17e},\"n_terms\":{},\"ns_per_call\":{ns:.1}}}",
        m.re, m.im, r.qext, r.qsca, r.qback, r.g, r.n_terms
    )
}

/// The array sweeps of the comparison: 1000 size parameters evenly spaced over (0.1, x_max].
const SWEEP_MAX: [f64; 2] = [10.0, 1000.0];
const SWEEP_N: usize = 1000;

fn sweep(x_max: f64) -> Vec<f64> {
    (0..SWEEP_N)
        .map(|k| 0.1 + (x_max - 0.1) * (k + 1) as f64 / SWEEP_N as f64)
        .collect()
}

/// JSON dump for scripts/py/mie_compare.py.
fn compare_dump() {
    for &x_max in &SWEEP_MAX {
        let xs = sweep(x_max);
        for (_, m) in indices() {
            let ns = time_ns(
                || {
                    for &x in &xs {
                        drop(black_box(mie_q(black_box(x), black_box(m))));
                    }
                },
                5,
                Duration::from_millis(100),
            );
            println!(
                "{{\"tag\":\"sweep\",\"x_max\":{x_max:e},\"n\":{SWEEP_N},\"m_re\":{:e},\"m_im\":{:e},\"ns_per_sphere\":{:.1}}}",
                m.re,
                m.im,
                ns / SWEEP_N as f64
            );
        }
    }
    for &x in &XS {
        for (_, m) in indices() {
            let r = mie_q(x, m).unwrap();
            let ns = time_ns(
                || drop(black_box(mie_q(black_box(x), black_box(m)))),
                5,
                Duration::from_millis(60),
            );
            println!("{}", json_line(x, m, "default", &r, ns));
            let n = miepython_terms(x);
            let r = mie_q_terms(x, m, Some(n)).unwrap();
            let ns = time_ns(
                || drop(black_box(mie_q_terms(black_box(x), black_box(m), Some(n)))),
                5,
                Duration::from_millis(60),
            );
            println!("{}", json_line(x, m, "miepython_terms", &r, ns));
        }
    }
}

/// Accuracy vs term count (relative error against N + 400 terms) and time, for docs/mie.md.
fn terms_table() {
    let rel = |a: f64, b: f64| {
        if b == 0.0 {
            a.abs()
        } else {
            ((a - b) / b).abs()
        }
    };
    println!(
        "| x | m | N | N − N_default | max rel. err Q_ext,Q_sca,g | rel. err Q_back | µs/call |"
    );
    println!("|---|---|---|---|---|---|---|");
    for &x in &[1.0, 10.0, 100.0, 1000.0] {
        for (label, m) in indices() {
            let nd = default_terms(x, m);
            let nw = wiscombe_terms(x);
            let r_ref = mie_q_terms(x, m, Some(nd + 400)).unwrap();
            let mut ns_list: Vec<usize> =
                vec![nw.saturating_sub(4).max(1), nw, nd, nd + 10, nd + 40];
            ns_list.dedup();
            for n in ns_list {
                let r = mie_q_terms(x, m, Some(n)).unwrap();
                let e = rel(r.qext, r_ref.qext)
                    .max(rel(r.qsca, r_ref.qsca))
                    .max((r.g - r_ref.g).abs());
                let eb = rel(r.qback, r_ref.qback);
                let ns = time_ns(
                    || drop(black_box(mie_q_terms(black_box(x), black_box(m), Some(n)))),
                    3,
                    Duration::from_millis(40),
                );
                let tag = if n == nw {
                    " (Wiscombe)"
                } else if n == nd {
                    " (default)"
                } else {
                    ""
                };
                println!(
                    "| {x} | {label} | {n}{tag} | {:+} | {e:.1e} | {eb:.1e} | {:.2} |",
                    n as i64 - nd as i64,
                    ns / 1000.0
                );
            }
        }
    }
}

fn bench_vs_x(c: &mut Criterion) {
    let mut g = c.benchmark_group("mie_q_vs_x");
    for (label, m) in indices() {
        for &x in &XS {
            g.bench_with_input(BenchmarkId::new(label, x), &x, |b, &x| {
                b.iter(|| mie_q(black_box(x), black_box(m)).unwrap())
            });
        }
    }
    g.finish();
}

fn bench_vs_terms(c: &mut Criterion) {
    let mut g = c.benchmark_group("mie_q_vs_terms_x100");
    let m = Complex64::new(1.5, 0.1);
    let x = 100.0;
    for n in [60, 100, wiscombe_terms(x), default_terms(x, m), 200, 400] {
        g.bench_with_input(BenchmarkId::from_parameter(n), &n, |b, &n| {
            b.iter(|| mie_q_terms(black_box(x), black_box(m), Some(n)).unwrap())
        });
    }
    g.finish();
}

fn bench_s1s2(c: &mut Criterion) {
    let mut g = c.benchmark_group("mie_s1s2_x10");
    let m = Complex64::new(1.5, 0.1);
    for n_ang in [1usize, 19, 181] {
        let mus: Vec<f64> = (0..n_ang)
            .map(|k| (std::f64::consts::PI * k as f64 / (n_ang.max(2) - 1) as f64).cos())
            .collect();
        g.bench_with_input(BenchmarkId::from_parameter(n_ang), &mus, |b, mus| {
            b.iter(|| mie_s1s2(black_box(10.0), black_box(m), black_box(mus)).unwrap())
        });
    }
    g.finish();
}

fn main() {
    if std::env::var_os("MIE_COMPARE_JSON").is_some() {
        compare_dump();
        return;
    }
    if std::env::var_os("MIE_TERMS_TABLE").is_some() {
        terms_table();
        return;
    }
    let mut c = Criterion::default()
        .warm_up_time(Duration::from_millis(300))
        .measurement_time(Duration::from_secs(1))
        .configure_from_args();
    bench_vs_x(&mut c);
    bench_vs_terms(&mut c);
    bench_s1s2(&mut c);
    c.final_summary();
}
