//! The information limit of filament measurements: the Cramér–Rao bounds attached to the
//! per-row method's measurement (Sec. 4.2 steps 4–5) and the whole-image bead-model fit, on
//! scenes made by the simulator (an independent path: its own renderer of the scene's
//! filament, its own noise).

use crate::analysis_support::*;
use bfpscope::analysis::orientation::{
    measure_filament, AngleCurve, AngleCurveOptions, MeasureOptions,
};
use bfpscope::analysis::quantities;
use bfpscope::instrument::sim::scene::{Scene, PAPER_DETECTOR_SIGMA_SAMPLE};
use bfpscope::optics::rayleigh::DetectorModel;
use bfpscope::optics::Optics;

const H: f64 = 0.05;

/// A 13-protofilament microtubule (protein cylinder, n = 1.587, in n_s = 1.335) along y with a
/// 2° tilt through (1.6, 1.6), detector noise at `samples` per pixel.
fn microtubule_scan(o: &Optics, samples: usize, seed: u64) -> bfpscope::data::Scan {
    let mut sc = Scene::default();
    sc.add_filament(sim_straight(
        [1.6, 1.6],
        2.0,
        8.0,
        mt_d_nm(),
        quantities::PROTEIN_N,
    ))
    .unwrap();
    simulate(
        o,
        &noisy(sc, PAPER_DETECTOR_SIGMA_SAMPLE, seed),
        64,
        H,
        samples,
    )
}

fn mt_d_nm() -> f64 {
    let mu = 13.0 * quantities::PROTOFILAMENT_MDA_PER_UM;
    let da_per_nm3 = quantities::PROTEIN_DENSITY_G_CM3 * 1e-21 * quantities::DA_PER_G;
    (4.0 * mu * 1e3 / da_per_nm3 / std::f64::consts::PI).sqrt()
}

fn mt_optics() -> Optics {
    Optics {
        n_medium: 1.335,
        ..Optics::default()
    }
}

/// The per-row measurement carries the bound of the data it read: the pixel noise it states is
/// the simulator's (σ_s/√n), and the method's own 1σ of the angle and of the mean corrected
/// sensitivity sit above their bounds (the parabola maxima use a 0.4 µm window of each row).
#[test]
fn per_row_measurement_states_its_cramer_rao_bounds() {
    let o = mt_optics();
    let tpl = model_template(&o, &DetectorModel::default());
    let curve = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    let samples = 1000; // 10 ms per pixel
    let s = microtubule_scan(&o, samples, 5);
    let m = measure_filament(&s.sx, &s.sy, &curve, &MeasureOptions::default()).unwrap();
    let c = m
        .crlb
        .expect("a noisy scan measured with a computed curve has a bound");
    let sig = PAPER_DETECTOR_SIGMA_SAMPLE / (samples as f64).sqrt();
    for k in 0..2 {
        assert!(
            (c.sigma[k] / sig - 1.0).abs() < 0.1,
            "σ {:?} vs {sig}",
            c.sigma
        );
    }
    println!(
        "per-row: angle {:.3} ± {:.3}° (CRLB {:.3}°), mean_corr {:.4} ± {:.4} (CRLB {:.4}; {:.2} %)",
        m.angle_deg,
        m.angle_err_deg,
        c.angle_deg,
        m.mean_corr,
        m.sem_corr,
        c.mean_corr,
        100.0 * c.lin_dens_rel
    );
    assert!(c.angle_deg > 0.0 && c.angle_deg < m.angle_err_deg);
    assert!(c.mean_corr > 0.0 && c.mean_corr < m.sem_corr);
    assert!((c.diameter_rel - 0.5 * c.lin_dens_rel).abs() < 1e-15);
    // a curve loaded from a file carries no template: no bound, and the measurement is the same
    let loaded: AngleCurve = serde_json::from_str(&serde_json::to_string(&curve).unwrap()).unwrap();
    assert!(loaded.template.is_none());
    let m2 = measure_filament(&s.sx, &s.sy, &loaded, &MeasureOptions::default()).unwrap();
    assert!(m2.crlb.is_none());
    assert_eq!(m2.mean_corr, m.mean_corr);
}

fn sd(v: &[f64]) -> (f64, f64) {
    let m = v.iter().sum::<f64>() / v.len() as f64;
    let s = (v.iter().map(|a| (a - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt();
    (m, s)
}

/// Scatter over `n_seeds` noise draws of the whole-image fit (each from its own matched-filter
/// search) of the microtubule at `samples` per pixel: (mean λ, sd λ, mean CRLB λ, mean angle,
/// sd angle, mean CRLB angle).
fn seed_study(samples: usize, n_seeds: u64, seed0: u64) -> (f64, f64, f64, f64, f64, f64) {
    use bfpscope::analysis::filament_fit::{fit_line_filament, LineFitOptions};
    let o = mt_optics();
    let tpl = model_template(&o, &DetectorModel::default());
    let (mut lam, mut ang, mut crlb_l, mut crlb_a) = (vec![], vec![], vec![], vec![]);
    for seed in 0..n_seeds {
        let s = microtubule_scan(&o, samples, seed0 + seed);
        let r = fit_line_filament(&s.sx, &s.sy, &tpl, None, &LineFitOptions::default()).unwrap();
        assert!(r.warnings.is_empty(), "seed {seed}: {:?}", r.warnings);
        lam.push(r.filament.lambda);
        ang.push(r.filament.angle_deg);
        crlb_l.push(r.crlb.lambda);
        crlb_a.push(r.crlb.angle_deg);
        assert!(
            (r.err.lambda / r.crlb.lambda - 1.0).abs() < 0.05,
            "{:?}",
            r.err
        );
    }
    let (ml, sl) = sd(&lam);
    let (ma, sa) = sd(&ang);
    let n = n_seeds as f64;
    (
        ml,
        sl,
        crlb_l.iter().sum::<f64>() / n,
        ma,
        sa,
        crlb_a.iter().sum::<f64>() / n,
    )
}

/// The whole-image fit of the bead-model filament reaches the Cramér–Rao bound without bias on
/// simulated microtubules at 10 ms per pixel (the accuracy report's default dwell): over 60
/// noise seeds the scatter of λ and of the angle is within 1.2× of the bound and the means are
/// within 0.5σ of the truth. (The standard deviation over N seeds has a statistical error of
/// 1/√(2(N−1)): 9 % at 60 seeds; 20 seeds, 16 %, once gave 1.33 for λ. Over 200 seeds:
/// scatter/CRLB 1.01 for λ, bias 0.06σ — `whole_image_fit_seed_study`. The angle over 400 seeds
/// per dwell through the scan engine, each fit from its own search: 0.96 ± 0.03 at 1 ms,
/// 1.07 ± 0.04 at 10 ms, 1.05 ± 0.04 at 30 ms, 1.00 ± 0.04 at 300 ms; 1.02 ± 0.02 pooled.)
#[test]
fn whole_image_fit_reaches_the_bound_without_bias() {
    use bfpscope::analysis::filament_fit::lambda_of_diameter;
    let o = mt_optics();
    let tpl = model_template(&o, &DetectorModel::default());
    let truth = lambda_of_diameter(&tpl, mt_d_nm(), quantities::PROTEIN_N).unwrap();
    let (ml, sl, bl, ma, sa, ba) = seed_study(1000, 60, 100);
    println!(
        "whole-image fit, 10 ms, 60 seeds: λ {ml:.4} (true {truth:.4}) scatter {sl:.5} CRLB {bl:.5} (×{:.2}; bias {:.2}σ); angle {ma:.3}° scatter {sa:.4}° CRLB {ba:.4}° (×{:.2}; bias {:.2}σ)",
        sl / bl,
        (ml - truth) / sl,
        sa / ba,
        (ma - 2.0) / sa
    );
    assert!(sl / bl < 1.2, "λ scatter {sl} vs CRLB {bl}");
    assert!(sl / bl > 0.8, "λ scatter {sl} below the bound {bl}");
    assert!(sa / ba < 1.2, "angle scatter {sa} vs CRLB {ba}");
    assert!(
        ((ml - truth) / sl).abs() < 0.5,
        "λ bias {} σ",
        (ml - truth) / sl
    );
    assert!(
        ((ma - 2.0) / sa).abs() < 0.5,
        "angle bias {} σ",
        (ma - 2.0) / sa
    );
}

/// At 3 ms per pixel, where the per-row maxima lose the filament in some seeds and are biased
/// (docs/accuracy.md: −1.5 % in its report of 2026-11-26), the
/// whole-image fit's mean λ over 30 seeds is within 0.5σ of the truth (a relative bias under
/// 0.6 %) and its scatter within 1.2× of the bound... with the 13 % statistical error of 30
/// seeds, asserted below 1.35×.
#[test]
fn whole_image_fit_is_unbiased_where_the_row_maxima_are_biased() {
    use bfpscope::analysis::filament_fit::lambda_of_diameter;
    let o = mt_optics();
    let tpl = model_template(&o, &DetectorModel::default());
    let truth = lambda_of_diameter(&tpl, mt_d_nm(), quantities::PROTEIN_N).unwrap();
    let (ml, sl, bl, ..) = seed_study(300, 30, 500);
    println!(
        "whole-image fit, 3 ms, 30 seeds: λ {ml:.4} (true {truth:.4}, {:+.2} %) scatter {sl:.5} CRLB {bl:.5} (×{:.2}; bias {:.2}σ)",
        100.0 * (ml / truth - 1.0),
        sl / bl,
        (ml - truth) / sl
    );
    assert!(
        ((ml - truth) / sl).abs() < 0.5,
        "λ bias {} σ",
        (ml - truth) / sl
    );
    assert!((ml / truth - 1.0).abs() < 0.006);
    assert!(sl / bl < 1.35, "λ scatter {sl} vs CRLB {bl}");
}

/// At 1 ms per pixel the per-row maxima do not find the microtubule (docs/accuracy.md: not found
/// at ≤ 1 ms); the whole-image fit does, within 4 of its bounds of the truth.
#[test]
fn whole_image_fit_finds_the_filament_where_row_maxima_give_up() {
    use bfpscope::analysis::filament_fit::{fit_line_filament, lambda_of_diameter, LineFitOptions};
    let o = mt_optics();
    let tpl = model_template(&o, &DetectorModel::default());
    let curve = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    let truth = lambda_of_diameter(&tpl, mt_d_nm(), quantities::PROTEIN_N).unwrap();
    let mut per_row_failed = 0;
    for seed in 0..4 {
        let s = microtubule_scan(&o, 100, 300 + seed);
        if measure_filament(&s.sx, &s.sy, &curve, &MeasureOptions::default()).is_err() {
            per_row_failed += 1;
        }
        let r = fit_line_filament(&s.sx, &s.sy, &tpl, None, &LineFitOptions::default()).unwrap();
        let f = r.filament;
        println!(
            "1 ms seed {seed}: λ {:.4} ± {:.4} (true {truth:.4}), angle {:.2} ± {:.2}°, offset {:.4} µm",
            f.lambda, r.crlb.lambda, f.angle_deg, r.crlb.angle_deg, f.offset_um
        );
        assert!((f.lambda - truth).abs() < 4.0 * r.crlb.lambda);
        assert!((f.angle_deg - 2.0).abs() < 4.0 * r.crlb.angle_deg);
    }
    assert!(
        per_row_failed >= 3,
        "per-row failed in {per_row_failed} of 4"
    );
}

/// The seed study behind the numbers in docs (not run by default; SEEDS, SAMPLES, SEED0, SEARCH,
/// ENGINE in the environment): the whole-image fit over many seeds started at the noise-free fit,
/// its noise estimate against the simulator's, the fit to the noise-free scan (model mismatch:
/// none), and the scatter of λ and of the angle over their bounds with the statistical error of
/// a standard deviation of N seeds, 1/√(2(N−1)). SEARCH: each seed also fitted from its own
/// search (printed beside); ENGINE: the scans taken through the scan engine on the simulated
/// instrument and fitted from their own search, as the accuracy report does (its seeds of the
/// i-th dwell, from i = 0 at 100 µs, are SEED0 = 20000 + 100·i with SEEDS=16: `ENGINE=1 SEEDS=16
/// SEED0=20500 SAMPLES=3000` reproduces its 30 ms row, angle scatter/CRLB 1.42).
/// `SEEDS=200 cargo test --release --test physics whole_image_fit_seed_study -- --ignored --nocapture`
#[test]
#[ignore]
fn whole_image_fit_seed_study() {
    use bfpscope::analysis::filament_fit::{fit_line_filament, lambda_of_diameter, LineFitOptions};
    let o = mt_optics();
    let tpl = model_template(&o, &DetectorModel::default());
    let truth = lambda_of_diameter(&tpl, mt_d_nm(), quantities::PROTEIN_N).unwrap();
    let n_seeds: u64 = std::env::var("SEEDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(20);
    let samples: usize = std::env::var("SAMPLES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1000);
    let sig = PAPER_DETECTOR_SIGMA_SAMPLE / (samples as f64).sqrt();
    // noise-free
    let mut sc = Scene::default();
    sc.add_filament(sim_straight(
        [1.6, 1.6],
        2.0,
        8.0,
        mt_d_nm(),
        quantities::PROTEIN_N,
    ))
    .unwrap();
    let clean = simulate(&o, &sc, 64, H, samples);
    let opts = LineFitOptions {
        sigma: Some(sig),
        ..LineFitOptions::default()
    };
    let r0 = fit_line_filament(&clean.sx, &clean.sy, &tpl, None, &opts).unwrap();
    println!(
        "noise-free: λ {:.5} (true {truth:.5}) angle {:.4} offset {:.5} bg {:?} rms resid/σ {:.3} crlb λ {:.5}",
        r0.filament.lambda, r0.filament.angle_deg, r0.filament.offset_um, r0.filament.background,
        (r0.rss / r0.n_residuals as f64).sqrt() / sig, r0.crlb.lambda
    );
    let t = std::time::Instant::now();
    let (mut lam, mut ang, mut sest, mut cl, mut ca) = (vec![], vec![], vec![], vec![], vec![]);
    // ENGINE: the scans through the scan engine on the simulated instrument and each fit from its
    // own search, as the accuracy report takes and fits them
    let engine = std::env::var("ENGINE").is_ok();
    let seed0: u64 = std::env::var("SEED0")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(100);
    for seed in 0..n_seeds {
        let s = if engine {
            let sc = noisy(sc.clone(), PAPER_DETECTOR_SIGMA_SAMPLE, seed0 + seed);
            let dwell =
                samples as f64 / bfpscope::instrument::sim::SimConfig::default().sample_rate;
            bfpscope::accuracy::instrument::engine_scan(&o, &sc, dwell)
                .unwrap()
                .0
        } else {
            microtubule_scan(&o, samples, seed0 + seed)
        };
        let r = fit_line_filament(
            &s.sx,
            &s.sy,
            &tpl,
            (!engine).then_some(&r0.filament),
            &LineFitOptions::default(),
        )
        .unwrap();
        if std::env::var("SEARCH").is_ok() {
            let q =
                fit_line_filament(&s.sx, &s.sy, &tpl, None, &LineFitOptions::default()).unwrap();
            println!(
                "seed {seed}: from truth λ {:.5} angle {:.4} rss {:.6e} | from search λ {:.5} angle {:.4} rss {:.6e} start {:?} {:?} {}",
                r.filament.lambda, r.filament.angle_deg, r.rss, q.filament.lambda, q.filament.angle_deg, q.rss, q.start, q.status, q.iterations
            );
        }
        lam.push(r.filament.lambda);
        ang.push(r.filament.angle_deg);
        sest.push(r.sigma / sig);
        cl.push(r.crlb.lambda * sig / r.sigma);
        ca.push(r.crlb.angle_deg * sig / r.sigma);
    }
    let (ml, sl) = sd(&lam);
    let (ma, sa) = sd(&ang);
    let (ms, _) = sd(&sest);
    let bl = cl.iter().sum::<f64>() / cl.len() as f64;
    let ba = ca.iter().sum::<f64>() / ca.len() as f64;
    // the standard deviation of N draws has a relative statistical error of 1/√(2(N−1))
    let stat = 1.0 / (2.0 * (n_seeds as f64 - 1.0)).sqrt();
    println!(
        "{n_seeds} seeds, {samples} samples ({:.1} s): λ mean {ml:.5} sd {sl:.5} CRLB(true σ) {bl:.5} ratio {:.3} ± {:.3} bias {:.2}σ; angle {ma:.4}° sd {sa:.5}° CRLB(true σ) {ba:.5}° ratio {:.3} ± {:.3} bias {:.2}σ; σ_est/σ {ms:.4}",
        t.elapsed().as_secs_f64(),
        sl / bl,
        stat * sl / bl,
        (ml - truth) / sl,
        sa / ba,
        stat * sa / ba,
        (ma - 2.0) / sa
    );
}
