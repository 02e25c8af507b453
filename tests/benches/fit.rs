//! Multi-bead template fit benchmarks: a 3-bead fit on 64×64 pixels and an 11-bead fit
//! on 128×128 (50 nm pixels, 170 nm polystyrene beads simulated with the Rayleigh model by
//! `instrument::sim`, the paper's detector noise σ = 2e-5 per pixel, docs/physics.md §7), fitted
//! with the model template of the 110 nm reference bead (`Template::from_optics`, 20 nm grid). Besides criterion's statistics, the bench writes the scenes, the template and
//! the initial guesses as .npy files plus its own timings to `target/fit_bench/` so that
//! `scripts/py/fit_compare.py` can run the same fits with scipy.optimize.least_squares and
//! report the speed ratio and accuracies.
//!
//! Run: `cargo bench --features bench --bench fit` then `python3 scripts/py/fit_compare.py`
//! (or `python3 scripts/py/fit_compare.py --run-bench` to do both).

use bfpscope::analysis::fit::{detect_beads, fit_beads, BeadInit, Channels, FitOptions, FitResult};
use bfpscope::analysis::sensitivity::Stencil;
use bfpscope::analysis::template::{RefBead, Template};
use bfpscope::data::Scan;
use bfpscope::instrument::sim::scene::{
    Bead as SimBead, DetectorNoise, Scene, PAPER_DETECTOR_SIGMA_SAMPLE,
};
use bfpscope::instrument::sim::{render_xy, Renderer};
use bfpscope::optics::rayleigh::DetectorModel;
use bfpscope::optics::template::TemplateSpec;
use bfpscope::optics::Optics;
use criterion::{criterion_group, criterion_main, Criterion};
use ndarray::{Array1, Array2};
use ndarray_npy::write_npy;
use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::time::Instant;

const H: f64 = 0.05;

struct Case {
    name: &'static str,
    tpl: Template,
    scan: Scan,
    truth: Vec<(f64, f64, f64)>,
    init: Vec<BeadInit>,
    sigma: f64,
}

/// The template used by the benchmark: the physics model of the 110 nm reference bead.
fn template() -> Template {
    Template::from_optics(
        &Optics::default(),
        &DetectorModel::default(),
        RefBead::default(),
        0.02,
        0.0,
    )
    .unwrap()
}

fn make_case(name: &'static str, n_px: usize, pos: &[(f64, f64)], seed: u64) -> Case {
    let tpl = template();
    let w = (170.0f64 / 110.0).powi(3);
    let truth: Vec<(f64, f64, f64)> = pos.iter().map(|&(x, y)| (x, y, w)).collect();
    let ax: Vec<f64> = (0..n_px).map(|i| i as f64 * H).collect();
    let mut scene = Scene::default();
    for &(x, y) in pos {
        scene
            .add_bead(SimBead {
                pos: [x, y, 0.0],
                d_nm: 170.0,
                n: 1.572,
            })
            .unwrap();
    }
    scene.effects.detector_noise = Some(DetectorNoise {
        sigma_sample: PAPER_DETECTOR_SIGMA_SAMPLE,
    });
    scene.seed = seed;
    let r = Renderer::checked(&Optics::default(), &scene, TemplateSpec::default()).unwrap();
    let scan = render_xy(&r, &ax, &ax, 0.0, 10_000);
    let sigma = PAPER_DETECTOR_SIGMA_SAMPLE / 100.0;
    let init = detect_beads(
        &scan.sx,
        &scan.sy,
        &tpl,
        Channels::Both,
        truth.len(),
        Stencil::SavitzkyGolay { half_width: 2 },
    )
    .unwrap();
    Case {
        name,
        tpl,
        scan,
        truth,
        init,
        sigma,
    }
}

/// Positions of `n` beads in a square field `[lo, hi]²` µm, no two closer than `min_sep` µm,
/// drawn from a fixed 64-bit LCG (Knuth's MMIX constants) so the scene is the same on every
/// machine and run.
fn spread(n: usize, lo: f64, hi: f64, min_sep: f64, seed: u64) -> Vec<(f64, f64)> {
    let mut s = seed;
    let mut next = move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut out: Vec<(f64, f64)> = Vec::with_capacity(n);
    while out.len() < n {
        let p = (lo + (hi - lo) * next(), lo + (hi - lo) * next());
        if out.iter().all(|q| (p.0 - q.0).hypot(p.1 - q.1) >= min_sep) {
            out.push(p);
        }
    }
    out
}

/// Which cases to run: all, or those named in `FIT_BENCH_CASES` (comma-separated).
fn selected(name: &str) -> bool {
    match std::env::var("FIT_BENCH_CASES") {
        Ok(v) if !v.trim().is_empty() => v.split(',').any(|c| c.trim() == name),
        _ => true,
    }
}

/// A case: name, pixels per side, bead positions (µm), noise seed.
type CaseSpec = (&'static str, usize, Vec<(f64, f64)>, u64);

fn cases() -> Vec<Case> {
    let all: Vec<CaseSpec> = vec![
        (
            "3beads_64",
            64,
            vec![(1.40, 1.50), (1.78, 1.62), (1.55, 1.92)],
            1,
        ),
        (
            "11beads_128",
            128,
            vec![
                (1.0, 1.2),
                (1.35, 1.3),
                (2.5, 1.0),
                (3.6, 1.8),
                (4.8, 1.1),
                (1.6, 3.3),
                (2.9, 3.0),
                (3.2, 3.4),
                (5.2, 3.6),
                (2.0, 5.0),
                (4.4, 5.2),
            ],
            2,
        ),
        // A field of the size of the paper's microtubule scenes with aggregates (Sec. 6): 40
        // point-like objects over 12.75 µm × 12.75 µm, at least 0.5 µm (1.25 w0) apart.
        ("40beads_256", 256, spread(40, 0.8, 12.0, 0.5, 40), 3),
    ];
    all.into_iter()
        .filter(|c| selected(c.0))
        .map(|(name, n, pos, seed)| make_case(name, n, &pos, seed))
        .collect()
}

fn run(c: &Case) -> FitResult {
    fit_beads(
        &c.scan.sx,
        &c.scan.sy,
        &c.tpl,
        &FitOptions {
            init: Some(c.init.clone()),
            ..Default::default()
        },
    )
    .unwrap()
}

fn errors(c: &Case, r: &FitResult) -> (f64, f64) {
    let mut ep: f64 = 0.0;
    let mut ew: f64 = 0.0;
    for t in &c.truth {
        let b = r
            .beads
            .iter()
            .min_by(|a, b| {
                (a.x - t.0)
                    .hypot(a.y - t.1)
                    .total_cmp(&(b.x - t.0).hypot(b.y - t.1))
            })
            .unwrap();
        ep = ep.max((b.x - t.0).hypot(b.y - t.1));
        ew = ew.max((b.weight / t.2 - 1.0).abs());
    }
    (ep, ew)
}

fn export(c: &Case, dir: &Path, ms: f64, r: &FitResult) {
    let d = dir.join(c.name);
    std::fs::create_dir_all(&d).unwrap();
    write_npy(d.join("sx.npy"), &c.scan.sx.data).unwrap();
    write_npy(d.join("sy.npy"), &c.scan.sy.data).unwrap();
    write_npy(d.join("x.npy"), &Array1::from(c.scan.sx.x.clone())).unwrap();
    write_npy(d.join("y.npy"), &Array1::from(c.scan.sx.y.clone())).unwrap();
    let g = &c.tpl.grid;
    let tx = Array2::from_shape_fn((g.nv, g.nu), |(j, i)| g.data[j * g.nu + i][0]);
    let ty = Array2::from_shape_fn((g.nv, g.nu), |(j, i)| g.data[j * g.nu + i][1]);
    write_npy(d.join("tpl_sx.npy"), &tx).unwrap();
    write_npy(d.join("tpl_sy.npy"), &ty).unwrap();
    let tu = Array1::from((0..g.nu).map(|i| g.u0 + i as f64 * g.h).collect::<Vec<_>>());
    let tv = Array1::from((0..g.nv).map(|j| g.v0 + j as f64 * g.h).collect::<Vec<_>>());
    write_npy(d.join("tpl_u.npy"), &tu).unwrap();
    write_npy(d.join("tpl_v.npy"), &tv).unwrap();
    let init = Array2::from_shape_fn((c.init.len(), 3), |(i, k)| {
        [c.init[i].weight, c.init[i].x, c.init[i].y][k]
    });
    write_npy(d.join("init.npy"), &init).unwrap();
    let truth = Array2::from_shape_fn((c.truth.len(), 3), |(i, k)| {
        [c.truth[i].2, c.truth[i].0, c.truth[i].1][k]
    });
    write_npy(d.join("truth.npy"), &truth).unwrap();
    let fit = Array2::from_shape_fn((r.beads.len(), 3), |(i, k)| {
        [r.beads[i].weight, r.beads[i].x, r.beads[i].y][k]
    });
    write_npy(d.join("fit.npy"), &fit).unwrap();
    let (ep, ew) = errors(c, r);
    let json = serde_json::json!({
        "name": c.name, "pixels": c.scan.sx.data.dim(), "beads": c.truth.len(), "sigma": c.sigma,
        "rust_ms": ms, "iterations": r.iterations, "evaluations": r.evaluations,
        "max_pos_err_nm": ep * 1e3, "max_weight_err_pct": ew * 100.0, "rss": r.rss, "status": format!("{:?}", r.status),
        "template": "Rayleigh model of the 110 nm PS reference bead (default optics), 20 nm grid, Keys cubic",
        "norm_factor": c.tpl.norm_factor,
    });
    std::fs::write(
        d.join("rust.json"),
        serde_json::to_string_pretty(&json).unwrap(),
    )
    .unwrap();
}

/// Where the scenes are exchanged with `scripts/py/fit_compare.py`: `$FIT_BENCH_DIR`, else
/// `<repository>/target/fit_bench` (the same rule as the script's; it does not follow
/// `CARGO_TARGET_DIR`, so the script finds the scenes whatever target directory cargo used).
fn exchange_dir() -> PathBuf {
    match std::env::var_os("FIT_BENCH_DIR") {
        Some(d) if !d.is_empty() => PathBuf::from(d),
        _ => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/fit_bench"),
    }
}

/// `FIT_BENCH_FITS=N`: only the own timing, over N fits per case, and no criterion run (for
/// A/B comparisons of two builds under `perf stat`, where a fixed amount of work is wanted).
fn fits_only() -> Option<usize> {
    std::env::var("FIT_BENCH_FITS").ok()?.trim().parse().ok()
}

fn bench(cr: &mut Criterion) {
    let dir = exchange_dir();
    for c in cases() {
        // Own timing (median of repeated runs) for the comparison report.
        let r = run(&c);
        let n = fits_only().unwrap_or(15).max(1);
        let mut t = Vec::new();
        for _ in 0..n {
            let s = Instant::now();
            black_box(run(&c));
            t.push(s.elapsed().as_secs_f64() * 1e3);
        }
        t.sort_by(|a, b| a.total_cmp(b));
        let ms = t[t.len() / 2];
        let (ep, ew) = errors(&c, &r);
        println!(
            "{}: {:.2} ms (median of {n}), {} iterations, {} evaluations, max position error {:.1} nm, max weight error {:.2} %",
            c.name, ms, r.iterations, r.evaluations, ep * 1e3, ew * 100.0
        );
        if fits_only().is_some() {
            continue;
        }
        export(&c, &dir, ms, &r);
        cr.bench_function(c.name, |b| b.iter(|| black_box(run(&c))));
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = bench
}
criterion_main!(benches);
