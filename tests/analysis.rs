//! Analysis accuracy tests on synthetic scenes with known ground truth (seeded noise; the noise
//! level is stated in each test). Sections refer to the paper (seed/000_a01c3b91f68df4b7.txt).
//! The paper's numbers are reproduced in the paper's paraxial beam (`paper_optics()`); the
//! tests marked "vector beam" repeat a recovery in the default aplanatic vector focus, whose
//! values differ (docs/paper-figures.md, "Vector beam").

use crate::analysis_support;

use analysis_support::*;
use bfpscope::analysis::bead_model::{filament_beads, BeadModelOptions, Filament};
use bfpscope::analysis::fit::{fit_beads, BeadInit, Channels, FitOptions};
use bfpscope::analysis::focus::{focus_search, FocusOptions};
use bfpscope::analysis::orientation::{
    measure_filament, measure_filament_along, AngleCurve, AngleCurveOptions, Channel,
    MeasureOptions,
};
use bfpscope::analysis::peaks::{peak_2d, point_peak, row_peaks, PeakOptions};
use bfpscope::analysis::quantities::{self, DiameterCalib, LinDensCalib};
use bfpscope::analysis::sbr::{sbr, SbrOptions};
use bfpscope::analysis::sensitivity::{sensitivity, Axis, Stencil};
use bfpscope::analysis::stats;
use bfpscope::analysis::template::{FromScansOptions, RefBead, Template};
use bfpscope::analysis::{background, profile};
use bfpscope::data::{Image, Scan};
use bfpscope::optics::grid::Interp;

const H: f64 = 0.05; // pixel, µm

#[test]
fn sensitivity_of_a_bead_peaks_at_its_centre_with_unit_value() {
    // Noise-free. Stand-in bead at a sub-pixel position; Central2 has bias −h²/w² at the peak.
    let tpl = standin();
    let s = scene(&tpl, &[(1.013, 1.207, 1.0)], &[], 49, H, 0.0, 0);
    let sens = sensitivity(&s.sx, Axis::X, Stencil::Central2).unwrap();
    let p = peak_2d(&sens, 0.4, None).unwrap();
    assert!(
        (p.x - 1.013).abs() < 0.003 && (p.y - 1.207).abs() < 0.003,
        "{p:?}"
    );
    // 1 − h²/w² = 0.984 from the stencil, minus the quadratic-window bias (a few %).
    assert!(p.value > 0.9 && p.value < 1.0, "{}", p.value);
    let c5 = peak_2d(
        &sensitivity(&s.sx, Axis::X, Stencil::Central5).unwrap(),
        0.4,
        None,
    )
    .unwrap();
    assert!(
        c5.value > p.value,
        "5-point stencil has less truncation bias"
    );
    // ∂Sy/∂y peaks at the same place with the same value (stand-in is isotropic).
    let py = peak_2d(
        &sensitivity(&s.sy, Axis::Y, Stencil::Central2).unwrap(),
        0.4,
        None,
    )
    .unwrap();
    assert!((py.value - p.value).abs() < 1e-3 && (py.x - p.x).abs() < 1e-3);
    // Row-parabola maximum (Sec. 5 method): the pipeline value of the template (averaged over
    // sub-pixel positions) agrees with this bead's.
    let pp = point_peak(&sens, &PeakOptions::default()).unwrap();
    assert!(
        (pp.x - 1.013).abs() < 0.003 && (pp.y - 1.207).abs() < 0.01,
        "{pp:?}"
    );
    let pipe = tpl.pipeline_max_sens(H, Stencil::Central2, 0.4).unwrap();
    assert!((pipe - pp.value).abs() < 0.003, "{pipe} vs {}", pp.value);
    assert!(pipe > 0.95 && pipe < 0.984, "{pipe}");
}

#[test]
fn row_maxima_follow_a_filament_with_uncertainties() {
    // Filament along y at x = 1.23 µm; pixel noise σ = 2 % of the reference bead's Sx peak.
    let tpl = standin();
    let sigma = 0.02 * sx_peak(&tpl);
    let f = Filament::straight([1.23, 1.6], 0.0, 6.0, 110.0, tpl.reference.n);
    let s = scene(&tpl, &[], &[f], 64, H, sigma, 11);
    let sens = sensitivity(&s.sx, Axis::X, Stencil::Central2).unwrap();
    let rows = row_peaks(&sens, &PeakOptions::default()).unwrap();
    let pos: Vec<f64> = rows
        .iter()
        .filter_map(|r| r.peak().map(|p| p.pos))
        .collect();
    assert!(pos.len() > 60);
    let m = stats::summary(&pos).unwrap();
    assert!((m.mean - 1.23).abs() < 0.003, "{m:?}");
    // The reported (residual-based) position uncertainty is conservative: it includes the
    // parabola's misfit of the non-parabolic peak, so it exceeds the actual scatter, by less
    // than 3×.
    let errs: Vec<f64> = rows
        .iter()
        .filter_map(|r| r.peak().and_then(|p| p.pos_err))
        .collect();
    let mean_err = errs.iter().sum::<f64>() / errs.len() as f64;
    assert!(
        mean_err / m.std > 0.8 && mean_err / m.std < 3.0,
        "reported {mean_err} vs scatter {}",
        m.std
    );
}

#[test]
fn template_from_noisy_reference_scans_matches_truth() {
    // 6 scans of one reference bead each at random sub-pixel positions; pixel noise σ = 3 % of
    // the Sx peak per scan. The averaged template must match the stand-in to ≲ σ/√6 and be
    // centred within 10 nm.
    let truth = standin();
    let sigma = 0.03 * sx_peak(&truth);
    let mut scans: Vec<Scan> = Vec::new();
    let offs = [
        (1.51, 1.49),
        (1.473, 1.534),
        (1.522, 1.507),
        (1.488, 1.466),
        (1.507, 1.521),
        (1.532, 1.479),
    ];
    for (k, &(x, y)) in offs.iter().enumerate() {
        // Gain varies by ±5 % between scans (bead size spread), as in the paper's averaging.
        let w = 1.0 + 0.05 * ((k as f64) - 2.5) / 2.5;
        scans.push(scene(
            &truth,
            &[(x, y, w)],
            &[],
            61,
            H,
            sigma,
            100 + k as u64,
        ));
    }
    let refs: Vec<&Scan> = scans.iter().collect();
    let t = Template::from_scans(
        &refs,
        RefBead::default(),
        &FromScansOptions {
            half_width_um: 1.2,
            ..Default::default()
        },
    )
    .unwrap();
    match &t.source {
        bfpscope::analysis::TemplateSource::Scans {
            n_beads,
            rms_misfit,
            ..
        } => {
            assert_eq!(*n_beads, 6);
            assert!(
                (rms_misfit / sigma - 1.0).abs() < 0.3,
                "misfit {rms_misfit} vs σ {sigma}"
            );
        }
        s => panic!("{s:?}"),
    }
    // Compare shapes: after normalisation both have max ∂Sx/∂x = 1.
    let mut maxdev: f64 = 0.0;
    for j in -16..=16 {
        for i in -16..=16 {
            let (u, v) = (i as f64 * 0.05, j as f64 * 0.05);
            let a = t.eval(u, v);
            let b = truth.eval(u, v);
            maxdev = maxdev.max((a[0] - b[0]).abs()).max((a[1] - b[1]).abs());
        }
    }
    assert!(maxdev < 0.05 * sx_peak(&truth), "max deviation {maxdev}");
    // Centring: the zero crossings of Sx(u, 0) and Sy(0, v) (antisymmetric responses) lie within
    // 10 nm of the origin (the maximum of the noisy derivative, `sens_peak`, is a poorer
    // locator).
    let zero = |f: &dyn Fn(f64) -> f64| {
        let (mut a, mut b) = (-0.1, 0.1);
        for _ in 0..50 {
            let m = 0.5 * (a + b);
            if f(a) * f(m) <= 0.0 {
                b = m
            } else {
                a = m
            }
        }
        0.5 * (a + b)
    };
    let ux = zero(&|u| t.eval(u, 0.0)[0]);
    let vy = zero(&|v| t.eval(0.0, v)[1]);
    assert!(ux.abs() < 0.01 && vy.abs() < 0.01, "{ux} {vy}");
    // Save / load round trip.
    let back = Template::from_json(&t.to_json()).unwrap();
    assert!(back.approx_eq(&t, 1e-14));
}

#[test]
fn three_overlapping_170nm_beads_at_paper_noise() {
    // Accuracy target: 3 overlapping 170 nm beads, positions within 20 nm and weights within 5 %
    // at the paper's noise level (σ derived from its 950 kDa mass resolution, see
    // analysis_support::paper_noise). 10 noise seeds.
    let tpl = standin();
    let sigma = paper_noise(&tpl, H);
    let w = ps_weight(170.0);
    let truth = [(1.40, 1.50, w), (1.78, 1.62, w), (1.55, 1.92, w)];
    let mut worst_pos: f64 = 0.0;
    let mut worst_w: f64 = 0.0;
    for seed in 0..10 {
        let s = scene(&tpl, &truth, &[], 64, H, sigma, seed);
        let r = fit_beads(
            &s.sx,
            &s.sy,
            &tpl,
            &FitOptions {
                n_beads: Some(3),
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(r.beads.len(), 3);
        assert!(!r.is_degenerate(), "{:?}", r.degeneracies);
        assert!(r.iterations < 50);
        for t in &truth {
            let b = r
                .beads
                .iter()
                .min_by(|a, b| {
                    (a.x - t.0)
                        .hypot(a.y - t.1)
                        .total_cmp(&(b.x - t.0).hypot(b.y - t.1))
                })
                .unwrap();
            worst_pos = worst_pos.max((b.x - t.0).hypot(b.y - t.1));
            worst_w = worst_w.max((b.weight / t.2 - 1.0).abs());
            // Reported uncertainties are consistent with the actual error (< 5σ).
            assert!((b.x - t.0).abs() < 5.0 * b.x_err.unwrap() + 1e-4);
        }
        assert!(
            (r.sigma / sigma - 1.0).abs() < 0.05,
            "σ estimate {}",
            r.sigma
        );
    }
    println!(
        "3 beads: worst position error {:.2} nm, worst weight error {:.2} %",
        worst_pos * 1e3,
        worst_w * 100.0
    );
    assert!(worst_pos < 0.020, "{worst_pos}");
    assert!(worst_w < 0.05, "{worst_w}");
}

#[test]
fn growing_the_model_finds_the_bead_count() {
    // 4 beads of different sizes, σ = paper noise. Starting from one bead, beads are added at the
    // largest residual while the BIC decreases: it must stop at 4.
    let tpl = standin();
    let sigma = paper_noise(&tpl, H);
    let truth = [
        (1.0, 1.0, 1.0),
        (2.0, 1.3, 2.5),
        (1.4, 2.2, 0.5),
        (2.3, 2.4, 3.7),
    ];
    let s = scene(&tpl, &truth, &[], 64, H, sigma, 5);
    let r = fit_beads(
        &s.sx,
        &s.sy,
        &tpl,
        &FitOptions {
            grow: true,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(r.beads.len(), 4, "{:?}", r.history);
    assert!(r.history.last().map(|h| !h.accepted).unwrap_or(false));
    let tw: f64 = truth.iter().map(|t| t.2).sum();
    assert!((r.total_weight() / tw - 1.0).abs() < 0.01);
}

#[test]
fn eleven_beads_on_128x128() {
    // Suppl. S7-like field: 11 beads (170 nm, some touching), σ = paper noise.
    let tpl = standin();
    let sigma = paper_noise(&tpl, H);
    let w = ps_weight(170.0);
    let pos = [
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
    ];
    let truth: Vec<(f64, f64, f64)> = pos.iter().map(|&(x, y)| (x, y, w)).collect();
    let s = scene(&tpl, &truth, &[], 128, H, sigma, 3);
    let r = fit_beads(
        &s.sx,
        &s.sy,
        &tpl,
        &FitOptions {
            n_beads: Some(11),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(r.beads.len(), 11);
    for t in &truth {
        let d = r
            .beads
            .iter()
            .map(|b| (b.x - t.0).hypot(b.y - t.1))
            .fold(f64::INFINITY, f64::min);
        assert!(d < 0.02, "bead at {t:?}: nearest fit {d}");
    }
    assert!((r.chi2 / r.dof as f64 - 1.0).abs() < 0.05);
}

#[test]
fn angle_curve_symmetries_for_an_isotropic_template() {
    // Noise-free. For the stand-in (Sy(u,v) = Sx(v,u)), the S_y curve is the S_x curve shifted by
    // 90°, S_x is even in the angle, maximal at 0° and minimal at 90°.
    let tpl = standin();
    let c = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    assert_eq!(c.angles_deg.len(), 18);
    assert!((c.eval(0.0).0 - 1.0).abs() < 1e-12);
    for a in [10.0, 30.0, 45.0, 60.0, 80.0] {
        let (sx_p, sy_p) = c.eval(a);
        let (sx_m, _) = c.eval(-a);
        assert!((sx_p - sx_m).abs() < 0.01, "{a}: {sx_p} vs {sx_m}");
        assert!((sy_p - c.eval(a - 90.0).0).abs() < 0.02, "{a}: {sy_p}");
    }
    assert!(c.eval(90.0).0 < 0.1 && c.eval(0.0).1 < 0.1);
    // Periodicity.
    assert!((c.eval(25.0).0 - c.eval(205.0).0).abs() < 1e-12);
    // The bead-model cylinder of the reference's diameter: weight per µm 1.5·1000/110 = 13.6,
    // × ∫ exp(−y²/w²) dy = w√π = 0.709 µm → ≈ 9.7 (less the pipeline's few-% bias).
    assert!(c.sx0 > 9.0 && c.sx0 < 9.8, "{}", c.sx0);
}

#[test]
fn fibril_diameters_any_angle() {
    // Accuracy target (stand-in template until the physics templates land): collagen fibrils
    // (n = 1.414) of 20–150 nm at angles −80…90°, ideal scenes (no noise): diameter within 3 nm.
    let tpl = standin();
    let n_col = 1.414;
    let curve = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    let m = MeasureOptions::default();
    let cal = DiameterCalib::from_template(
        &tpl,
        n_col,
        110.0,
        tpl.reference.n,
        H,
        &m,
        &BeadModelOptions::default(),
    )
    .unwrap();
    println!(
        "A = {:.2} nm (paper's instrument: 58.6 nm), sens_bm = {:.3}, n_corr = {:.4}",
        cal.a_nm, cal.sens_bm, cal.n_corr
    );
    let mut worst: f64 = 0.0;
    for (k, &angle) in [0.0, 15.0, -30.0, 45.0, 60.0, -80.0, 90.0]
        .iter()
        .enumerate()
    {
        for &d in &[20.0, 60.0, 150.0] {
            let f = Filament::straight([1.6, 1.6], angle, 8.0, d, n_col);
            let s = scene(&tpl, &[], &[f], 64, H, 0.0, k as u64);
            let meas = measure_filament(&s.sx, &s.sy, &curve, &m).unwrap();
            assert!(
                (meas.angle_deg - angle).abs() < 0.5 || (meas.angle_deg - angle).abs() > 179.5,
                "angle {angle}: {}",
                meas.angle_deg
            );
            let exp_ch = if angle.abs() <= 45.0 {
                Channel::SxRows
            } else {
                Channel::SyCols
            };
            if angle.abs() != 45.0 {
                assert_eq!(meas.channel, exp_ch, "angle {angle}");
            }
            let dm = cal.diameter_nm(meas.mean_corr).unwrap();
            worst = worst.max((dm - d).abs());
            assert!(
                (dm - d).abs() < 3.0,
                "angle {angle}, d {d}: measured {dm:.2} nm"
            );
        }
    }
    println!("fibril diameters: worst error {worst:.2} nm");
}

#[test]
fn microtubule_linear_density_and_protofilaments() {
    // Accuracy target (stand-in): microtubules of 11–14 protofilaments modelled as protein
    // cylinders (n = 1.587, ρ = 1/0.745 g/cm³) of the same linear density, along y, in buffer
    // n_s = 1.335; pixel noise σ = 1 % of the reference Sx peak. μ within 3 %, N_pf exact.
    let mut tpl = standin();
    tpl.reference.n_medium = 1.335;
    let curve = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    let m = MeasureOptions::default();
    let cal = LinDensCalib::from_template(
        &tpl,
        quantities::PROTEIN_N,
        quantities::PROTEIN_DENSITY_G_CM3,
        H,
        &m,
        &BeadModelOptions::default(),
    )
    .unwrap();
    let sigma = 0.01 * sx_peak(&tpl);
    for npf in 11..=14u32 {
        let mu = npf as f64 * quantities::PROTOFILAMENT_MDA_PER_UM;
        // Solid protein cylinder of linear density μ: area = μ/ρ.
        let da_per_nm3 = quantities::PROTEIN_DENSITY_G_CM3 * 1e-21 * quantities::DA_PER_G;
        let area_nm2 = mu * 1e6 / 1000.0 / da_per_nm3;
        let d = (4.0 * area_nm2 / std::f64::consts::PI).sqrt();
        let f = Filament::straight([1.6, 1.6], 3.0, 8.0, d, quantities::PROTEIN_N);
        let s = scene(&tpl, &[], &[f], 64, H, sigma, npf as u64);
        let meas = measure_filament(&s.sx, &s.sy, &curve, &m).unwrap();
        let got = cal.linear_density(meas.mean_corr).unwrap();
        let (_, n) = quantities::protofilaments(got).unwrap();
        println!("{npf} pf: μ = {got:.1} MDa/µm (true {mu:.1}), N = {n}");
        assert!((got / mu - 1.0).abs() < 0.03, "{npf}: {got} vs {mu}");
        assert_eq!(n, npf);
    }
}

#[test]
fn background_removal_improves_sbr_threefold() {
    // Fig.-6-like scene (stand-in): a microtubule-like filament along y with 14 point-like
    // aggregates of 0.3–1.5 reference-bead weights around it; pixel noise σ = 0.5 % of the
    // reference Sx peak. SBR (method a) after removal must be ≥ 3× the SBR before.
    let tpl = standin();
    let sigma = 0.005 * sx_peak(&tpl);
    let f = Filament::straight([3.2, 3.2], 0.0, 5.4, 17.0, quantities::PROTEIN_N);
    let aggs = [
        (1.2, 1.0, 0.8),
        (2.0, 2.2, 1.5),
        (4.3, 1.4, 0.6),
        (5.1, 2.6, 1.2),
        (2.4, 4.1, 0.9),
        (4.6, 4.4, 1.4),
        (1.4, 5.4, 0.4),
        (5.3, 5.5, 1.0),
        (3.9, 0.8, 0.7),
        (2.6, 0.6, 0.5),
        (5.6, 3.9, 0.3),
        (1.0, 3.3, 1.1),
        (2.2, 5.8, 0.6),
        (4.2, 5.9, 0.8),
    ];
    let s = scene(&tpl, &aggs, &[f], 128, H, sigma, 21);
    let curve = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    let m = MeasureOptions::default();
    let bg = background::remove_point_background(&s.sx, &s.sy, &tpl, &Default::default()).unwrap();
    let fit = bg.fit.as_ref().unwrap();
    let after = measure_filament(&bg.sx, &bg.sy, &curve, &m).unwrap();
    assert_eq!(after.channel, Channel::SxRows);
    assert!(after.angle_deg.abs() < 0.5, "{}", after.angle_deg);
    let sa = sbr(&after, &SbrOptions::default()).unwrap();
    // The same filament line measured in the raw image (as the paper compares before/after).
    let before =
        measure_filament_along(&s.sx, &s.sy, &curve, after.channel, after.line, &m).unwrap();
    let sb = sbr(&before, &SbrOptions::default()).unwrap();
    // Even in the raw image the robust line search finds the filament.
    let raw = measure_filament(&s.sx, &s.sy, &curve, &m).unwrap();
    assert_eq!(raw.channel, Channel::SxRows);
    assert!(
        (raw.angle_deg - after.angle_deg).abs() < 1.0,
        "{}",
        raw.angle_deg
    );
    println!(
        "SBR (a) before {:.2} after {:.2}; (b) before {:.2} after {:.2}; {} objects fitted",
        sb.sbr_background,
        sa.sbr_background,
        sb.sbr_uniformity,
        sa.sbr_uniformity,
        fit.beads.len()
    );
    assert!(sa.sbr_background >= 3.0 * sb.sbr_background);
    assert!(fit.beads.len() >= 14);
}

#[test]
fn focus_search_on_a_synthetic_xz_scan() {
    // Noise-free XZ scan whose amplitude falls as 1/(1 + ((z − z0)/zR)²) and whose width grows
    // as w(z) = w0√(1 + ((z − z0)/zR)²): max sensitivity(z) = 1/(1 + ((z − z0)/zR)²), so the best z
    // is z0 and the 98 % range is z0 ± zR·√(1/0.98 − 1).
    let (z0, zr, w0) = (0.137, 1.4, 0.4);
    let x: Vec<f64> = (0..61).map(|i| -1.5 + i as f64 * H).collect();
    let z: Vec<f64> = (0..41).map(|i| -1.0 + i as f64 * 0.05).collect();
    let data = ndarray::Array2::from_shape_fn((z.len(), x.len()), |(r, c)| {
        let q = 1.0 + ((z[r] - z0) / zr).powi(2);
        let w = w0 * q.sqrt();
        (x[c] - 0.02) * (-(x[c] - 0.02).powi(2) / (w * w)).exp() / q
    });
    let img = Image::new(data, x, z).with_axis_names("x", "z");
    let f = focus_search(&img, &FocusOptions::default()).unwrap();
    assert!((f.z_best - z0).abs() < 0.005, "{f:?}");
    let half = zr * (1.0 / 0.98 - 1.0f64).sqrt();
    assert!(
        (f.z_lo.unwrap() - (z0 - half)).abs() < 0.02
            && (f.z_hi.unwrap() - (z0 + half)).abs() < 0.02,
        "{:?} {:?}",
        f.z_lo,
        f.z_hi
    );
}

#[test]
fn loglog_slope_of_bead_sensitivities() {
    // Fig. 3c / Sec. 3.2: between 110 and 160 nm the paper measures (∂Sx/∂x)max ∝ d^(3.02±0.04),
    // and both its models give slope 3, within 1 % of volume scaling below 240 nm. Here the
    // scenes come from an independent path: every bead rendered by the focused-beam Lorenz–Mie
    // tier (`mie` effect), not by the point dipole whose weight is linear in d³. The pipeline
    // (sensitivity, peak) measures each scan. The Mie tier's finite-size departure from d³ is
    // below 1 % up to 240 nm, i.e. a slope within ln(1.01)/ln(240/110) ≈ 0.013 of 3.
    let o = paper_optics();
    let measure = |d: f64| -> f64 {
        let mut sc = Scene::default();
        sc.add_bead(sim_bead(0.8, 0.8, d, 1.572)).unwrap();
        sc.effects.enable("mie").unwrap();
        let s = simulate(&o, &sc, 33, 0.05, 1);
        peak_2d(
            &sensitivity(&s.sx, Axis::X, Stencil::Central2).unwrap(),
            0.4,
            None,
        )
        .unwrap()
        .value
    };
    let ds = [110.0, 125.0, 140.0, 160.0];
    let sens: Vec<f64> = ds.iter().map(|&d| measure(d)).collect();
    let f = stats::loglog_fit(&ds, &sens, None).unwrap();
    assert!((f.slope - 3.0).abs() < 0.013, "slope {f:?}"); // measured 3.005
                                                           // volume scaling holds within 1 % up to 240 nm (paper), relative to 110 nm
    let s240 = measure(240.0);
    let ratio = s240 / sens[0] / (240.0f64 / 110.0).powi(3);
    // measured 0.9943: a 240 nm sphere samples a weaker field than its centre's (w0 ≈ 400 nm),
    // so it stays below volume scaling; a point dipole would give exactly 1
    assert!(
        ratio > 0.99 && ratio < 0.999,
        "240 nm / 110 nm vs volume: {ratio}"
    );
}

#[test]
fn mass_of_a_170nm_bead_from_the_fit_weight() {
    // σ = paper noise; the fitted weight of one 170 nm bead gives its mass (ρ = 1.05) within 3σ.
    let tpl = standin();
    let sigma = paper_noise(&tpl, H);
    let s = scene(&tpl, &[(1.5, 1.5, ps_weight(170.0))], &[], 60, H, sigma, 9);
    let r = fit_beads(
        &s.sx,
        &s.sy,
        &tpl,
        &FitOptions {
            n_beads: Some(1),
            ..Default::default()
        },
    )
    .unwrap();
    let b = r.beads[0];
    let rb = tpl.reference;
    let po =
        quantities::point_object(b.weight, b.weight_err, 1.0, rb.n, rb.density_g_cm3, &rb).unwrap();
    let true_mass = quantities::mass_kda(std::f64::consts::PI / 6.0 * 170f64.powi(3), 1.05);
    let err = po.mass_err_kda.unwrap();
    println!(
        "mass {:.0} ± {:.0} kDa (true {:.0}); resolution {:.0} kDa",
        po.mass_kda, err, true_mass, err
    );
    assert!((po.mass_kda - true_mass).abs() < 3.0 * err);
    // The noise level was set from the paper's 950 kDa resolution: the fit reproduces it.
    assert!((err / 950.0 - 1.0).abs() < 0.15, "{err}");
    assert!((po.sphere_d_nm - 170.0).abs() < 1.0);
}

#[test]
fn profile_along_the_fibril_axis() {
    // The line profile along a straight filament's axis is flat (ideal, uniform filament) and
    // its ∂Sx/∂x value equals the row maxima (up to the parabola's bias).
    let tpl = standin();
    let f = Filament::straight([1.6, 1.6], 0.0, 8.0, 110.0, tpl.reference.n);
    let s = scene(&tpl, &[], &[f], 64, H, 0.0, 0);
    let sens = sensitivity(&s.sx, Axis::X, Stencil::Central2).unwrap();
    let p =
        profile::profile_polyline(&sens, &[[1.6, 0.5], [1.6, 2.7]], 0.02, Interp::Cubic).unwrap();
    let st = stats::summary(&p.v).unwrap();
    assert!(st.std / st.mean < 1e-3, "{st:?}");
    let rows = row_peaks(&sens, &PeakOptions::default()).unwrap();
    let v = rows[32].peak().unwrap().value;
    assert!((v / st.mean - 1.0).abs() < 0.05);
}

#[test]
fn bead_model_beads_reproduce_a_single_bead_at_short_length() {
    // A filament section as short as one spacing has the weight of one section: 3h/(2d)·(d/d_ref)³.
    let tpl = standin();
    let f = Filament {
        points: vec![[0.0, 0.0], [0.0, 0.05]],
        d_nm: vec![110.0],
        n: tpl.reference.n,
    };
    let b = filament_beads(&tpl, &f, &BeadModelOptions::default()).unwrap();
    assert_eq!(b.len(), 1);
    assert!((b[0].2 - 1.5 * 50.0 / 110.0).abs() < 1e-12);
}

#[test]
fn single_channel_fit_recovers_beads() {
    // Background-removal building block: fit only S_y, predict S_x. σ = paper noise.
    let tpl = standin();
    let sigma = paper_noise(&tpl, H);
    let truth = [(1.2, 1.4, 1.0), (2.0, 1.9, 2.0)];
    let s = scene(&tpl, &truth, &[], 64, H, sigma, 4);
    let init = vec![
        BeadInit {
            x: 1.25,
            y: 1.35,
            weight: 0.8,
        },
        BeadInit {
            x: 1.95,
            y: 1.95,
            weight: 2.2,
        },
    ];
    let r = fit_beads(
        &s.sx,
        &s.sy,
        &tpl,
        &FitOptions {
            channels: Channels::Sy,
            init: Some(init),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(r.n_residuals, 64 * 64);
    for (b, t) in r.beads.iter().zip(&truth) {
        assert!((b.x - t.0).hypot(b.y - t.1) < 0.02 && (b.weight / t.2 - 1.0).abs() < 0.05);
    }
    // Subtracting the predicted Sx leaves only noise in Sx.
    let res = &s.sx.data - &r.model_sx.data;
    let rms = (res.iter().map(|v| v * v).sum::<f64>() / res.len() as f64).sqrt();
    assert!(rms < 1.2 * sigma, "{rms} vs {sigma}");
}

// ------------------------------------------------------------------------------------------
// With the physics model (optics::template via Template::from_optics) and the simulator
// (instrument::sim): the analysis library's accuracy targets on simulated scenes.
// ------------------------------------------------------------------------------------------

use bfpscope::instrument::sim::scene::{
    Aggregates, DiameterProfile, Scene, PAPER_DETECTOR_SIGMA_SAMPLE,
};
use bfpscope::optics::rayleigh::{DetectorModel, Misalignment};
use bfpscope::optics::Optics;

#[test]
fn model_three_overlapping_170nm_beads() {
    // Accuracy target: 3 overlapping 170 nm polystyrene beads, simulated with the Rayleigh model;
    // detector noise at the paper's level (σ = 2e-5 of the beam power per pixel = 0.84 % of the
    // reference bead's peak Sx, docs/physics.md §7) and at 4× that (≈ the level implied by the
    // paper's 950 kDa mass resolution at 50 nm pixels). 4 seeds each. Positions within 20 nm,
    // weights within 5 % of (170/110)³.
    let o = paper_optics();
    let tpl = model_template(&o, &DetectorModel::default());
    let pos = [(1.40, 1.50), (1.78, 1.62), (1.55, 1.92)];
    let w = ps_weight(170.0);
    for (factor, label) in [(1.0, "paper noise"), (4.0, "4× paper noise")] {
        let (mut wp, mut ww): (f64, f64) = (0.0, 0.0);
        for seed in 0..4 {
            let mut sc = Scene::default();
            for &(x, y) in &pos {
                sc.add_bead(sim_bead(x, y, 170.0, 1.572)).unwrap();
            }
            let s = simulate(
                &o,
                &noisy(sc, factor * PAPER_DETECTOR_SIGMA_SAMPLE, seed),
                64,
                H,
                PAPER_SAMPLES,
            );
            let r = fit_beads(
                &s.sx,
                &s.sy,
                &tpl,
                &FitOptions {
                    n_beads: Some(3),
                    ..Default::default()
                },
            )
            .unwrap();
            assert_eq!(r.beads.len(), 3, "{:?}", r.degeneracies);
            for &(x, y) in &pos {
                let b = r
                    .beads
                    .iter()
                    .min_by(|a, b| {
                        (a.x - x)
                            .hypot(a.y - y)
                            .total_cmp(&(b.x - x).hypot(b.y - y))
                    })
                    .unwrap();
                wp = wp.max((b.x - x).hypot(b.y - y));
                ww = ww.max((b.weight / w - 1.0).abs());
            }
            assert!(
                (r.sigma / (factor * paper_sigma_pixel()) - 1.0).abs() < 0.05,
                "σ {}",
                r.sigma
            );
        }
        println!("model, 3 × 170 nm beads, {label}: worst position error {:.2} nm, worst weight error {:.2} %", wp * 1e3, ww * 100.0);
        assert!(wp < 0.020 && ww < 0.05, "{label}: {wp} µm, {ww}");
    }
}

#[test]
fn model_fibril_diameters_any_angle() {
    // Accuracy target: collagen fibrils (n = 1.414) of 20–150 nm on ideal simulated scenes (no
    // noise) at 7 angles: diameter d = A·√(sens_corr) within 3 nm. A is computed from the model
    // template's bead model of a 110 nm polystyrene (n = 1.57) cylinder — the paper's recipe —
    // and compared with the paper's 58.6 nm for its instrument.
    model_fibril_diameters(paper_optics(), Some(69.38));
}

/// Vector beam: the same recovery in the default aplanatic focus (Sy/Sx = 1.65, so the angle
/// curve is asymmetric and the Sx/Sy channel choice matters), with the vector beam's own model
/// template, angle curve and A (77.67 nm). Its −13 % overshoot puts a parallel line of weak
/// maxima beside the filament; before the line search broke ties by summed sensitivity, it
/// took that line at ±75° and read 20 nm as 5.2 nm.
#[test]
fn model_fibril_diameters_any_angle_in_the_vector_beam() {
    model_fibril_diameters(Optics::default(), None);
}

fn model_fibril_diameters(o: Optics, a_pin: Option<f64>) {
    let tpl = model_template(&o, &DetectorModel::default());
    let curve = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    let m = MeasureOptions::default();
    let cal = DiameterCalib::from_template(
        &tpl,
        1.414,
        110.0,
        1.57,
        H,
        &m,
        &BeadModelOptions::default(),
    )
    .unwrap();
    println!(
        "A = {:.2} nm for λ = 1064 nm, w0 = 400 nm, NA 1.2, n_s = 1.333, n_cf = 1.414, d_bm = 110 nm PS (paper: 58.6 nm); sens_bm = {:.3}, n_corr = {:.4}",
        cal.a_nm, cal.sens_bm, cal.n_corr
    );
    // Regression pin: the noise-free model gives A = 69.38 nm for these optics (deterministic;
    // the paper's 58.6 nm is its own instrument's, "determined independently by scanning a
    // reference object"). Whether A is right is tested below: diameters recovered with it.
    if let Some(a) = a_pin {
        assert!((cal.a_nm - a).abs() < 0.05, "A = {} nm", cal.a_nm);
    }
    let mut worst: f64 = 0.0;
    for (k, &angle) in [0.0, 20.0, -35.0, 45.0, 60.0, -75.0, 90.0]
        .iter()
        .enumerate()
    {
        for &d in &[20.0, 50.0, 100.0, 150.0] {
            let mut sc = Scene::default();
            sc.add_filament(sim_straight([1.6, 1.6], angle, 8.0, d, 1.414))
                .unwrap();
            sc.seed = k as u64;
            let s = simulate(&o, &sc, 64, H, 1);
            let meas = measure_filament(&s.sx, &s.sy, &curve, &m).unwrap();
            let dm = cal.diameter_nm(meas.mean_corr).unwrap();
            worst = worst.max((dm - d).abs());
            assert!(
                (dm - d).abs() < 3.0,
                "angle {angle}°, d = {d} nm: measured {dm:.2} nm (angle {:.2}°, {:?})",
                meas.angle_deg,
                meas.channel
            );
        }
    }
    println!("model fibril diameters 20–150 nm at 7 angles: worst error {worst:.2} nm");
}

/// Diameter of a solid protein cylinder with the linear density of `npf` protofilaments.
fn mt_equivalent_d_nm(npf: u32) -> f64 {
    let mu = npf as f64 * quantities::PROTOFILAMENT_MDA_PER_UM;
    let da_per_nm3 = quantities::PROTEIN_DENSITY_G_CM3 * 1e-21 * quantities::DA_PER_G;
    let area_nm2 = mu * 1e6 / 1000.0 / da_per_nm3;
    (4.0 * area_nm2 / std::f64::consts::PI).sqrt()
}

#[test]
fn model_microtubule_linear_density() {
    // Accuracy target: microtubules of 11–14 protofilaments (modelled as protein cylinders,
    // n = 1.587, ρ = 1/0.745 g/cm³, of the same linear density) in buffer n_s = 1.335, along the
    // y-axis (2° tilt), simulated with the paper's detector noise (σ = 2e-5 per pixel).
    // Linear density (eq. mtLinDens) within 3 %, protofilament number exact.
    let o = Optics {
        n_medium: 1.335,
        ..paper_optics()
    };
    let tpl = model_template(&o, &DetectorModel::default());
    let curve = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    let m = MeasureOptions::default();
    let cal = LinDensCalib::from_template(
        &tpl,
        quantities::PROTEIN_N,
        quantities::PROTEIN_DENSITY_G_CM3,
        H,
        &m,
        &BeadModelOptions::default(),
    )
    .unwrap();
    for npf in 11..=14u32 {
        let mu = npf as f64 * quantities::PROTOFILAMENT_MDA_PER_UM;
        let mut sc = Scene::default();
        sc.add_filament(sim_straight(
            [1.6, 1.6],
            2.0,
            8.0,
            mt_equivalent_d_nm(npf),
            quantities::PROTEIN_N,
        ))
        .unwrap();
        let s = simulate(
            &o,
            &noisy(sc, PAPER_DETECTOR_SIGMA_SAMPLE, npf as u64),
            64,
            H,
            PAPER_SAMPLES,
        );
        let meas = measure_filament(&s.sx, &s.sy, &curve, &m).unwrap();
        let got = cal.linear_density(meas.mean_corr).unwrap();
        let (_, n) = quantities::protofilaments(got).unwrap();
        println!(
            "model MT {npf} pf: μ = {got:.1} ± {:.1} MDa/µm (true {mu:.1}), N = {n}",
            cal.linear_density(meas.sem_corr).unwrap()
        );
        assert!((got / mu - 1.0).abs() < 0.03, "{npf}: {got} vs {mu}");
        assert_eq!(n, npf);
    }
}

#[test]
fn model_fig6_background_removal_sbr() {
    // Accuracy target: a Fig.-6-like scene — a 13-protofilament microtubule along the y-axis
    // (protein cylinder, n = 1.587) among 16 protein aggregates of 40–100 nm (n = 1.587) in
    // buffer n_s = 1.335, paper detector noise (σ = 2e-5 per pixel), 128×128 pixels of 50 nm.
    // SBR (method a) after removing the aggregates fitted in S_y must be ≥ 3× the SBR before.
    let o = Optics {
        n_medium: 1.335,
        ..paper_optics()
    };
    let tpl = model_template(&o, &DetectorModel::default());
    let mut sc = Scene::default();
    sc.add_filament(sim_straight(
        [3.2, 3.2],
        0.0,
        5.0,
        mt_equivalent_d_nm(13),
        quantities::PROTEIN_N,
    ))
    .unwrap();
    sc.add_aggregates(Aggregates {
        count: 16,
        d_nm: [40.0, 100.0],
        n: quantities::PROTEIN_N,
        region: [[0.2, 6.2], [0.2, 6.2]],
        z: 0.0,
        seed: 6,
    })
    .unwrap();
    let s = simulate(
        &o,
        &noisy(sc, PAPER_DETECTOR_SIGMA_SAMPLE, 6),
        128,
        H,
        PAPER_SAMPLES,
    );
    let curve = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    let m = MeasureOptions::default();
    let bg = background::remove_point_background(&s.sx, &s.sy, &tpl, &Default::default()).unwrap();
    let after = measure_filament(&bg.sx, &bg.sy, &curve, &m).unwrap();
    assert!(after.angle_deg.abs() < 1.0, "{}", after.angle_deg);
    let before =
        measure_filament_along(&s.sx, &s.sy, &curve, after.channel, after.line, &m).unwrap();
    let (sb, sa) = (
        sbr(&before, &SbrOptions::default()).unwrap(),
        sbr(&after, &SbrOptions::default()).unwrap(),
    );
    let cal = LinDensCalib::from_template(
        &tpl,
        quantities::PROTEIN_N,
        quantities::PROTEIN_DENSITY_G_CM3,
        H,
        &m,
        &BeadModelOptions::default(),
    )
    .unwrap();
    println!(
        "model Fig. 6: SBR (a) {:.2} → {:.2} ({:.1}×), (b) {:.2} → {:.2}; {} objects fitted; μ = {:.0} MDa/µm in the uniform region (13 pf: {:.0})",
        sb.sbr_background,
        sa.sbr_background,
        sa.sbr_background / sb.sbr_background,
        sb.sbr_uniformity,
        sa.sbr_uniformity,
        bg.fit.as_ref().map(|f| f.beads.len()).unwrap_or(0),
        cal.linear_density(sa.mean_corr).unwrap(),
        13.0 * quantities::PROTOFILAMENT_MDA_PER_UM
    );
    assert!(sa.sbr_background >= 3.0 * sb.sbr_background);
    // The linear density from the uniform region after removal: right protofilament number.
    assert_eq!(
        quantities::protofilaments(cal.linear_density(sa.mean_corr).unwrap())
            .unwrap()
            .1,
        13
    );
}

#[test]
fn model_template_from_simulated_reference_scans() {
    // Five simulated scans of one 110 nm polystyrene bead each (paper detector noise) at
    // sub-pixel offsets: the averaged template matches the model template within 3 % of its
    // peak Sx everywhere, and the normalisation factors agree within 3.5 % (a template built on
    // the scans' 50 nm pixels differentiates like a central difference over 100 nm: its peak
    // ∂Sx/∂x reads ≈ 1.6 % lower than the 20 nm model grid's, plus −0.6 % from the smoothed
    // maximum search and the noise).
    let o = paper_optics();
    let model = model_template(&o, &DetectorModel::default());
    let offs = [
        (1.51, 1.49),
        (1.473, 1.534),
        (1.522, 1.507),
        (1.488, 1.466),
        (1.507, 1.521),
    ];
    let scans: Vec<Scan> = offs
        .iter()
        .enumerate()
        .map(|(k, &(x, y))| {
            let mut sc = Scene::default();
            sc.add_bead(sim_bead(x, y, 110.0, 1.572)).unwrap();
            simulate(
                &o,
                &noisy(sc, PAPER_DETECTOR_SIGMA_SAMPLE, 40 + k as u64),
                61,
                H,
                PAPER_SAMPLES,
            )
        })
        .collect();
    let refs: Vec<&Scan> = scans.iter().collect();
    let t = Template::from_scans(
        &refs,
        RefBead::default(),
        &FromScansOptions {
            half_width_um: 1.2,
            ..Default::default()
        },
    )
    .unwrap();
    assert!(
        (t.norm_factor / model.norm_factor - 1.0).abs() < 0.035,
        "{} vs {}",
        t.norm_factor,
        model.norm_factor
    );
    let peak = sx_peak(&model);
    // Shape: after the best common scale (the normalisation is checked above).
    let nodes: Vec<([f64; 3], [f64; 3])> = (-20..=20)
        .flat_map(|j| (-20..=20).map(move |i| (i as f64 * 0.05, j as f64 * 0.05)))
        .map(|(u, v)| (t.eval(u, v), model.eval(u, v)))
        .collect();
    let (sab, saa) = nodes.iter().fold((0.0, 0.0), |(ab, aa), (a, b)| {
        (
            ab + a[0] * b[0] + a[1] * b[1],
            aa + a[0] * a[0] + a[1] * a[1],
        )
    });
    let scale = sab / saa;
    let dev = nodes
        .iter()
        .map(|(a, b)| (scale * a[0] - b[0]).abs().max((scale * a[1] - b[1]).abs()))
        .fold(0.0, f64::max);
    println!("template from 5 simulated scans: shape deviation {:.2} % of peak Sx (scale {scale:.4}), norm {:.3} vs model {:.3}", 100.0 * dev / peak, t.norm_factor, model.norm_factor);
    assert!(dev < 0.02 * peak);
}

#[test]
fn model_focus_search_on_a_simulated_xz_scan() {
    // XZ scan of a 110 nm bead at z = 0 (ideal, no noise): the best focus is z = 0 and the
    // maximum sensitivity stays within 2 % over z = ±105 nm (the point-dipole model's value,
    // docs/physics.md; the paper reports ±200 nm for its instrument).
    use bfpscope::instrument::sim::{render_xy, Renderer};
    use bfpscope::optics::template::TemplateSpec;
    let o = paper_optics();
    let mut sc = Scene::default();
    sc.add_bead(sim_bead(0.0, 0.0, 110.0, 1.572)).unwrap();
    let r = Renderer::checked(&o, &sc, TemplateSpec::default()).unwrap();
    let xs: Vec<f64> = (0..61).map(|i| -1.5 + i as f64 * H).collect();
    let zs: Vec<f64> = (0..49).map(|i| -0.6 + i as f64 * 0.025).collect();
    let mut data = ndarray::Array2::zeros((zs.len(), xs.len()));
    for (iz, &z) in zs.iter().enumerate() {
        let row = render_xy(&r, &xs, &[0.0], z, 1);
        data.row_mut(iz).assign(&row.sx.data.row(0));
    }
    let img = Image::new(data, xs, zs).with_axis_names("x", "z");
    let f = focus_search(&img, &FocusOptions::default()).unwrap();
    println!(
        "model focus: z_best = {:.1} nm, 2 % range [{:.0}, {:.0}] nm",
        f.z_best * 1e3,
        f.z_lo.unwrap() * 1e3,
        f.z_hi.unwrap() * 1e3
    );
    assert!(f.z_best.abs() < 0.005, "{}", f.z_best);
    assert!((f.z_hi.unwrap() - 0.105).abs() < 0.02 && (f.z_lo.unwrap() + 0.105).abs() < 0.02);
}

#[test]
fn model_misaligned_qpd_angle_series() {
    // Fig. 4d with the misalignment effect (Sy ~30 % weaker): the bead-model curve from the
    // misaligned template has S_y(90°) ≈ 0.7·S_x(0°); a simulated 80 nm collagen fibril scanned
    // at 7 angles (the rotation series), each corrected with the curve (step 5), gives the same
    // corrected sensitivity within 2 %. Paper detector noise.
    let o = paper_optics();
    let det = DetectorModel {
        polarization: false,
        misalignment: Some(Misalignment::default()),
    };
    let tpl = model_template(&o, &det);
    let curve = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    let sy90 = curve.eval(90.0).1;
    println!("misaligned QPD: S_y(90°)/S_x(0°) = {sy90:.3}");
    let m = MeasureOptions::default();
    let mut vals = Vec::new();
    for (k, &angle) in [-80.0, -50.0, -20.0, 0.0, 30.0, 60.0, 90.0]
        .iter()
        .enumerate()
    {
        let mut sc = Scene::default();
        sc.add_filament(sim_straight([1.6, 1.6], angle, 8.0, 80.0, 1.414))
            .unwrap();
        sc.effects.misalignment = Some(Misalignment::default());
        let s = simulate(
            &o,
            &noisy(sc, PAPER_DETECTOR_SIGMA_SAMPLE, k as u64),
            64,
            H,
            PAPER_SAMPLES,
        );
        let meas = measure_filament(&s.sx, &s.sy, &curve, &m).unwrap();
        vals.push(meas.mean_corr);
    }
    let st = stats::summary(&vals).unwrap();
    println!("rotation series corrected sensitivities: {vals:?}");
    assert!((st.max - st.min) / st.mean < 0.02, "{st:?}");
    let _ = DiameterProfile::Constant { d_nm: 1.0 };
}

#[test]
fn model_alpha_tip_diameter_profile() {
    // Sec. 5: a collagen α-tip (parabola of revolution: d(s) = 150 nm·√(s/3 µm), so d² grows
    // linearly) at 15° to the y-axis, ideal simulated scene. The diameter profile from the
    // per-row corrected maxima follows the truth within 3 nm wherever the beam sees a linear d²
    // (0.6 µm from the apex up to 0.6 µm before the end of the taper) and on the uniform part.
    let o = paper_optics();
    let tpl = model_template(&o, &DetectorModel::default());
    let curve = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    let m = MeasureOptions::default();
    let cal = DiameterCalib::from_template(
        &tpl,
        1.414,
        110.0,
        1.57,
        H,
        &m,
        &BeadModelOptions::default(),
    )
    .unwrap();
    let angle: f64 = 15.0;
    let (s0, len) = ([1.0, 0.4], 6.0);
    let t = angle.to_radians();
    let end = [s0[0] + len * t.sin(), s0[1] + len * t.cos()];
    let mut sc = Scene::default();
    sc.add_filament(sim_filament(
        vec![s0, end],
        DiameterProfile::AlphaTip {
            d_nm: 150.0,
            tip_um: 3.0,
        },
        1.414,
    ))
    .unwrap();
    let s = simulate(&o, &sc, 80, H, 1);
    let meas = measure_filament(&s.sx, &s.sy, &curve, &m).unwrap();
    println!("α-tip: fitted angle {:.2}° (true {angle}°)", meas.angle_deg);
    // The d² gradient along the taper tilts each row's profile and shifts its maximum a little:
    // the fitted angle is off by up to ~1° (0.5 % in sensitivity at 15°).
    assert!((meas.angle_deg - angle).abs() < 1.5);
    let mut checked = 0;
    let mut worst: f64 = 0.0;
    for p in &meas.points {
        // Arc position from the apex along the filament.
        let sa = (p.x - s0[0]) * t.sin() + (p.y - s0[1]) * t.cos();
        let truth = if sa < 3.0 {
            150.0 * (sa.max(0.0) / 3.0).sqrt()
        } else {
            150.0
        };
        let inside = (0.6..=2.4).contains(&sa) || (3.6..=len - 0.8).contains(&sa);
        if inside && p.y < 3.9 {
            let d = cal.diameter_nm(p.sens_corr).unwrap();
            worst = worst.max((d - truth).abs());
            checked += 1;
        }
    }
    println!("α-tip profile: {checked} rows checked, worst diameter error {worst:.2} nm");
    assert!(checked > 30 && worst < 3.0, "{worst}");
}

#[test]
fn model_point_object_mass_from_max_sensitivity() {
    // Sec. 3.2: the volume and mass of a point-like object from its maximum sensitivity, with
    // the reference bead measured through the same pipeline (`pipeline_max_sens`). A 150 nm
    // protein-like sphere (n = 1.587, ρ = 1/0.745) in an ideal simulated scan: mass within 2 %.
    let o = paper_optics();
    let tpl = model_template(&o, &DetectorModel::default());
    let mut sc = Scene::default();
    sc.add_bead(sim_bead(1.513, 1.487, 150.0, quantities::PROTEIN_N))
        .unwrap();
    let s = simulate(&o, &sc, 60, H, 1);
    let sens = sensitivity(&s.sx, Axis::X, Stencil::Central2).unwrap();
    let p = point_peak(&sens, &PeakOptions::default()).unwrap();
    let sens_rb = tpl.pipeline_max_sens(H, Stencil::Central2, 0.4).unwrap();
    let po = quantities::point_object(
        p.value * tpl.norm_factor,
        None,
        sens_rb,
        quantities::PROTEIN_N,
        quantities::PROTEIN_DENSITY_G_CM3,
        &tpl.reference,
    )
    .unwrap();
    let truth = quantities::mass_kda(
        std::f64::consts::PI / 6.0 * 150f64.powi(3),
        quantities::PROTEIN_DENSITY_G_CM3,
    );
    println!(
        "point object: {:.0} kDa (true {:.0}), sphere-equivalent d = {:.1} nm",
        po.mass_kda, truth, po.sphere_d_nm
    );
    assert!((po.mass_kda / truth - 1.0).abs() < 0.02);
    // And from the template fit weight (pipeline-independent).
    let r = fit_beads(
        &s.sx,
        &s.sy,
        &tpl,
        &FitOptions {
            n_beads: Some(1),
            ..Default::default()
        },
    )
    .unwrap();
    let pf = quantities::point_object(
        r.beads[0].weight,
        None,
        1.0,
        quantities::PROTEIN_N,
        quantities::PROTEIN_DENSITY_G_CM3,
        &tpl.reference,
    )
    .unwrap();
    assert!((pf.mass_kda / truth - 1.0).abs() < 0.005, "{}", pf.mass_kda);
}

#[test]
fn background_removal_for_a_filament_along_x() {
    // Sec. 6 with the roles swapped: a filament along the QPD x-axis is invisible in S_x, so the
    // point objects are fitted in S_x and subtracted from S_y; the filament is then measured in
    // S_y per column. Stand-in template, 8 aggregates, σ = 0.5 % of the reference Sx peak.
    let tpl = standin();
    let sigma = 0.005 * sx_peak(&tpl);
    let f = Filament::straight([3.2, 3.2], 90.0, 9.0, 17.0, quantities::PROTEIN_N);
    let aggs = [
        (1.1, 1.4, 0.8),
        (2.3, 2.2, 1.2),
        (4.4, 1.2, 0.6),
        (5.2, 4.6, 1.0),
        (2.0, 4.3, 0.9),
        (4.0, 4.1, 1.3),
        (1.2, 5.4, 0.5),
        (5.5, 2.3, 0.7),
    ];
    let s = scene(&tpl, &aggs, &[f], 128, H, sigma, 31);
    let curve = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    let m = MeasureOptions::default();
    let opts = background::BackgroundOptions {
        axis: background::FilamentAxis::X,
        ..Default::default()
    };
    let bg = background::remove_point_background(&s.sx, &s.sy, &tpl, &opts).unwrap();
    let fit = bg.fit.as_ref().unwrap();
    assert_eq!(fit.n_residuals, 128 * 128, "fitted in one channel");
    let after = measure_filament(&bg.sx, &bg.sy, &curve, &m).unwrap();
    assert_eq!(after.channel, Channel::SyCols);
    assert!(
        (after.angle_deg.abs() - 90.0).abs() < 0.5,
        "{}",
        after.angle_deg
    );
    let before =
        measure_filament_along(&s.sx, &s.sy, &curve, after.channel, after.line, &m).unwrap();
    let (sb, sa) = (
        sbr(&before, &SbrOptions::default()).unwrap(),
        sbr(&after, &SbrOptions::default()).unwrap(),
    );
    println!(
        "filament along x: SBR (a) {:.2} → {:.2}; {} objects",
        sb.sbr_background,
        sa.sbr_background,
        fit.beads.len()
    );
    assert!(sa.sbr_background >= 3.0 * sb.sbr_background);
    // Every aggregate was found (within 30 nm).
    for a in &aggs {
        assert!(
            fit.beads
                .iter()
                .any(|b| (b.x - a.0).hypot(b.y - a.1) < 0.03),
            "{a:?}"
        );
    }
}

#[test]
fn focus_range_is_bracketing_and_stable_with_noisy_rows() {
    // Noise of 1 % of the peak on every pixel: the row maxima scatter by about as much as the
    // 2 % band itself. The range comes from the parabola over z, so it must bracket z_best and
    // stay near the noise-free half-width zR·√(1/0.98 − 1) (within 30 %).
    let (z0, zr, w0) = (0.05, 1.0, 0.4);
    let x: Vec<f64> = (0..61).map(|i| -1.5 + i as f64 * H).collect();
    let z: Vec<f64> = (0..41).map(|i| -1.0 + i as f64 * 0.05).collect();
    let mut state: u64 = 7;
    let mut noise = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * 3f64.sqrt() * 0.01 * 0.26
    };
    let data = ndarray::Array2::from_shape_fn((z.len(), x.len()), |(r, c)| {
        let q = 1.0 + ((z[r] - z0) / zr).powi(2);
        let w = w0 * q.sqrt();
        x[c] * (-(x[c] * x[c]) / (w * w)).exp() / q + noise()
    });
    let img = Image::new(data, x, z).with_axis_names("x", "z");
    let f = focus_search(&img, &FocusOptions::default()).unwrap();
    let (lo, hi) = (f.z_lo.unwrap(), f.z_hi.unwrap());
    assert!(lo < f.z_best && f.z_best < hi, "{lo} {} {hi}", f.z_best);
    let half = zr * (1.0 / 0.98 - 1.0f64).sqrt();
    assert!(
        ((hi - lo) / 2.0 - half).abs() < 0.3 * half,
        "{lo} {hi} vs ±{half}"
    );
}

#[test]
fn mie_rendered_beads_recovered_by_a_template_from_mie_reference_scans() {
    // Recovery from an independent path: every scene is rendered by the focused-beam
    // Lorenz–Mie tier (`mie` effect), not by optics::rayleigh, and the template is made as in the
    // paper (suppl. S5) from scans of the 110 nm reference bead, here Mie-rendered too. Three
    // separated polystyrene beads of 110, 150 and 200 nm, noise-free, 50 nm pixels. The Mie
    // tier's sensitivity is within 1 % of volume scaling below 240 nm (paper Sec. 3.2; measured
    // 0.9943 at 240 nm in loglog_slope_of_bead_sensitivities), so each fitted weight gives
    // d = 110 nm · w^(1/3) within 0.4 % (1 %/3 with margin), and the position within 2 nm.
    // (The paraxial point-dipole template against these scenes is 2 % low in diameter: the two
    // beams differ, the subject of the one-beam work.)
    let o = paper_optics();
    let mie_scan = |beads: &[(f64, f64, f64)]| {
        let mut sc = Scene::default();
        for &(x, y, d) in beads {
            sc.add_bead(sim_bead(x, y, d, 1.572)).unwrap();
        }
        sc.effects.enable("mie").unwrap();
        simulate(&o, &sc, 64, H, 1)
    };
    let refs = [
        mie_scan(&[(1.6, 1.6, 110.0)]),
        mie_scan(&[(1.55, 1.62, 110.0)]),
    ];
    let tpl = Template::from_scans(
        &refs.iter().collect::<Vec<_>>(),
        RefBead::default(),
        &FromScansOptions {
            half_width_um: 1.2,
            ..Default::default()
        },
    )
    .unwrap();
    let truth = [(1.0, 1.0, 110.0), (2.2, 1.1, 150.0), (1.6, 2.3, 200.0)];
    let s = mie_scan(&truth);
    let r = fit_beads(
        &s.sx,
        &s.sy,
        &tpl,
        &FitOptions {
            // start 30 nm off each bead with weight 1 (a 110 nm bead's): the 110 nm bead is 6×
            // weaker than the 200 nm one, too weak for the automatic guesses beside it
            init: Some(
                truth
                    .iter()
                    .map(|&(x, y, _)| BeadInit {
                        x: x + 0.03,
                        y: y - 0.02,
                        weight: 1.0,
                    })
                    .collect(),
            ),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(r.beads.len(), 3, "{:?}", r.degeneracies);
    for &(x, y, d) in &truth {
        let b = r
            .beads
            .iter()
            .min_by(|a, b| {
                ((a.x - x).hypot(a.y - y))
                    .partial_cmp(&(b.x - x).hypot(b.y - y))
                    .unwrap()
            })
            .unwrap();
        let d_fit = 110.0 * b.weight.cbrt();
        assert!(
            (b.x - x).hypot(b.y - y) < 0.002, // measured ≤ 1 nm
            "{d} nm bead at ({x}, {y}) found at ({}, {})",
            b.x,
            b.y
        );
        assert!(
            ((d_fit - d) / d).abs() < 0.004, // measured −0.08, +0.15, +0.29 %
            "{d} nm bead: fitted diameter {d_fit:.2} nm"
        );
    }
}
