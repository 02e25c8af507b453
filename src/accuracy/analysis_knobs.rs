//! Accuracy knobs of the analysis and of the physics-model choice: fit
//! tolerance and evaluation budget, derivative stencil, Mie term count, and the scattering model
//! (point dipole vs finite-size sphere rule vs focused-beam Mie) for a given bead size.
//!
//! Every knob measures its error against a high-accuracy reference computed in the same run and
//! the median wall time of repeats ([`super::time_median`]).

use super::{time_median, Knob, Point};
use crate::analysis::fit::{detect_beads, fit_beads, BeadInit, FitOptions, FitResult};
use crate::analysis::peaks::{point_peak, PeakOptions};
use crate::analysis::sensitivity::{sensitivity, Axis, Stencil};
use crate::analysis::template::{RefBead, Template};
use crate::data::Scan;
use crate::instrument::sim::scene::{Bead, DetectorNoise, Scene, PAPER_DETECTOR_SIGMA_SAMPLE};
use crate::instrument::sim::{render_xy, Renderer};
use crate::optics::finite_size::DEFAULT_N_R;
use crate::optics::mie::{default_terms, mie_s1s2_terms, Complex64};
use crate::optics::mie_beam::{
    max_sensitivity_in_beam, Amplitudes, MieBeam, MieBeamSpec, SphereModel,
};
use crate::optics::params::{Optics, REF_BEAD_N};
use crate::optics::rayleigh::{alpha_um3, DetectorModel};
use crate::optics::template::TemplateSpec;
use crate::optics::ValidOptics;

/// Pixel size of the simulated analysis scans, µm (the paper's scans: 50 nm pixels).
pub const PIXEL_UM: f64 = 0.05;
/// Samples per pixel of the project's "paper noise" (0.1 s at 100 kHz, docs/physics.md §7).
pub const PAPER_SAMPLES: usize = 10_000;

/// Model template of the 110 nm polystyrene reference bead (default optics, 20 nm grid).
pub fn reference_template() -> Template {
    Template::from_optics(
        &Optics::default(),
        &DetectorModel::default(),
        RefBead::default(),
        0.02,
        0.0,
    )
    .expect("default optics and reference bead are valid")
}

fn axis(n: usize) -> Vec<f64> {
    (0..n).map(|i| i as f64 * PIXEL_UM).collect()
}

/// An n×n scan of 50 nm pixels from (0, 0) of polystyrene beads `(x, y, d_nm)`, with the
/// paper's detector noise (seeded) when `noise`.
pub fn bead_scan(beads: &[(f64, f64, f64)], n: usize, noise: bool, seed: u64) -> Scan {
    let mut s = Scene::default();
    for &(x, y, d) in beads {
        s.add_bead(Bead {
            pos: [x, y, 0.0],
            d_nm: d,
            n: REF_BEAD_N,
        })
        .expect("valid bead");
    }
    if noise {
        s.effects.detector_noise = Some(DetectorNoise {
            sigma_sample: PAPER_DETECTOR_SIGMA_SAMPLE,
        });
        s.seed = seed;
    }
    let r =
        Renderer::checked(&Optics::default(), &s, TemplateSpec::default()).expect("valid scene");
    let ax = axis(n);
    render_xy(&r, &ax, &ax, 0.0, PAPER_SAMPLES)
}

/// Largest deviation of a fit from the reference fit of the same data, in units of the
/// reference's own 1σ uncertainties (positions and weights; beads matched by nearest position).
fn deviation_in_sigma(fit: &FitResult, reference: &FitResult) -> f64 {
    let mut worst: f64 = 0.0;
    if fit.beads.len() != reference.beads.len() {
        return f64::INFINITY;
    }
    for r in &reference.beads {
        let b = fit
            .beads
            .iter()
            .min_by(|a, b| {
                (a.x - r.x)
                    .hypot(a.y - r.y)
                    .total_cmp(&(b.x - r.x).hypot(b.y - r.y))
            })
            .expect("same number of beads");
        for (d, e) in [
            (b.x - r.x, r.x_err),
            (b.y - r.y, r.y_err),
            (b.weight - r.weight, r.weight_err),
        ] {
            let e = e.unwrap_or(f64::NAN);
            worst = worst.max((d / e).abs());
        }
    }
    if worst.is_finite() {
        worst
    } else {
        f64::INFINITY
    }
}

/// The three overlapping 170 nm beads of the analysis tests and the fit benchmark, 64×64 (quick:
/// 48×48) pixels of 50 nm, paper noise; initial guesses from `detect_beads`, moved 80 nm and
/// halved in weight.
fn fit_case(quick: bool) -> (Scan, Template, Vec<BeadInit>) {
    let tpl = reference_template();
    let n = if quick { 48 } else { 64 };
    let c = n as f64 * PIXEL_UM / 2.0;
    let scan = bead_scan(
        &[
            (c - 0.2, c - 0.1, 170.0),
            (c + 0.15, c, 170.0),
            (c - 0.05, c + 0.3, 170.0),
        ],
        n,
        true,
        11,
    );
    let init = detect_beads(
        &scan.sx,
        &scan.sy,
        &tpl,
        Default::default(),
        3,
        FitOptions::default().detect_stencil,
    )
    .expect("detection on a valid scan")
    .into_iter()
    // a poor start (80 nm off, half the weight) so that the evaluation budget matters
    .map(|b| BeadInit {
        x: b.x + 0.08,
        y: b.y - 0.04,
        weight: 0.5 * b.weight,
    })
    .collect();
    (scan, tpl, init)
}

fn fit_sweep(
    quick: bool,
    id: &str,
    title: &str,
    settings: &[(String, f64, FitOptions, bool)],
) -> Knob {
    let (scan, tpl, init) = fit_case(quick);
    let base = FitOptions {
        init: Some(init),
        ..FitOptions::default()
    };
    let reference = fit_beads(
        &scan.sx,
        &scan.sy,
        &tpl,
        &FitOptions {
            ftol: 1e-15,
            xtol: 1e-15,
            gtol: 1e-15,
            patience: 10_000,
            ..base.clone()
        },
    )
    .expect("reference fit");
    let reps = if quick { 3 } else { 7 };
    let points = settings
        .iter()
        .map(|(setting, value, o, is_default)| {
            let opts = FitOptions {
                init: base.init.clone(),
                ..o.clone()
            };
            let r = fit_beads(&scan.sx, &scan.sy, &tpl, &opts);
            let err = match &r {
                Ok(f) => deviation_in_sigma(f, &reference),
                Err(_) => f64::INFINITY,
            };
            let secs = time_median(reps, || fit_beads(&scan.sx, &scan.sy, &tpl, &opts));
            let evals = r.as_ref().map(|f| f.evaluations).unwrap_or(0);
            Point {
                setting: format!("{setting} ({evals} evaluations)"),
                value: *value,
                error: err.clamp(1e-16, 1e300),
                seconds: secs,
                is_default: *is_default,
            }
        })
        .collect();
    let n = scan.sx.cols();
    Knob {
        id: id.into(),
        title: title.into(),
        metric: format!(
            "largest deviation of a bead's x, y or weight from the reference fit of the same data, in units of that fit's 1σ (3 overlapping 170 nm beads, {n}×{n} × 50 nm, paper noise)"
        ),
        timed: "fit_beads from the same initial guesses (detected, then moved 80 nm, weights halved)".into(),
        reference: "ftol = xtol = gtol = 1e-15, patience 10 000".into(),
        points,
    }
}

/// Fit tolerance (ftol = xtol = gtol swept together).
pub fn knob_fit_tolerance(quick: bool) -> Knob {
    let d = FitOptions::default();
    let tols: &[f64] = if quick {
        &[1e-2, 1e-4, 1e-6, 1e-10]
    } else {
        &[1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-8, 1e-10, 1e-12]
    };
    let settings: Vec<_> = tols
        .iter()
        .map(|&t| {
            (
                format!("tol = {t:.0e}"),
                t,
                FitOptions {
                    ftol: t,
                    xtol: t,
                    gtol: t,
                    ..d.clone()
                },
                t == d.ftol && t == d.xtol && t == d.gtol,
            )
        })
        .collect();
    fit_sweep(
        quick,
        "fit_tolerance",
        "Fit tolerance (ftol = xtol = gtol)",
        &settings,
    )
}

/// Fit evaluation budget (`patience`: residual evaluations allowed = patience × (3n + 1)).
pub fn knob_fit_patience(quick: bool) -> Knob {
    let d = FitOptions::default();
    let ps: &[usize] = if quick {
        &[1, 2, 4, 100]
    } else {
        &[1, 2, 3, 4, 6, 10, 100, 1000]
    };
    let settings: Vec<_> = ps
        .iter()
        .map(|&p| {
            (
                format!("patience = {p}"),
                p as f64,
                FitOptions {
                    patience: p,
                    ..d.clone()
                },
                p == d.patience,
            )
        })
        .collect();
    fit_sweep(
        quick,
        "fit_patience",
        "Fit evaluation budget (patience; max evaluations = patience × (3n+1))",
        &settings,
    )
}

/// Derivative stencil for the maximum sensitivity (∂Sx/∂x)max of a 110 nm bead: RMS relative
/// error over noise seeds (paper noise, 50 nm pixels) of the parabola-refined maximum
/// (`point_peak`) against the exact model value; time: sensitivity image + peak of a 64×64 scan.
pub fn knob_stencil(quick: bool) -> Knob {
    let n = 64;
    let c = n as f64 * PIXEL_UM / 2.0;
    // ∂Sx/∂x of the bead at zero displacement (the maximum, paper Fig. 2c), signal units per µm,
    // in the beam the scans are rendered in (the default vector beam: the 110 nm bead is a point
    // dipole there, `Amplitudes::Dipole`, whose response already carries the bead's α)
    let o = ValidOptics::default();
    let truth = MieBeam::new(
        &o,
        110.0,
        Complex64::new(REF_BEAD_N, 0.0),
        MieBeamSpec {
            amplitudes: Amplitudes::Dipole,
            ..MieBeamSpec::of_beam(&o)
        },
    )
    .and_then(|m| m.response_grad(0.0, 0.0, 0.0))
    .expect("default optics")
    .1[0];
    let seeds = if quick { 8 } else { 48 };
    let scans: Vec<Scan> = (0..seeds)
        .map(|s| bead_scan(&[(c, c, 110.0)], n, true, 100 + s as u64))
        .collect();
    let clean = bead_scan(&[(c, c, 110.0)], n, false, 0);
    let stencils: Vec<(String, Stencil)> = {
        let mut v = vec![
            ("Central2".to_string(), Stencil::Central2),
            ("Central5".to_string(), Stencil::Central5),
        ];
        for m in [1usize, 2, 3, 4] {
            if quick && m != 2 {
                continue;
            }
            v.push((
                format!("SG{} (Savitzky–Golay)", 2 * m + 1),
                Stencil::SavitzkyGolay { half_width: m },
            ));
        }
        v
    };
    let peak = |img: &crate::data::Image, st: Stencil| -> f64 {
        sensitivity(img, Axis::X, st)
            .and_then(|s| point_peak(&s, &PeakOptions::default()))
            .map(|p| p.value)
            .unwrap_or(f64::NAN)
    };
    let points = stencils
        .into_iter()
        .map(|(name, st)| {
            // the pipeline's own noise-free value: what every calibration in the crate divides by
            let cal = peak(&clean.sx, st);
            let bias = (cal - truth) / truth;
            let (mut ms_cal, mut ms_raw) = (0.0, 0.0);
            for s in &scans {
                let v = peak(&s.sx, st);
                ms_cal += (v / cal - 1.0).powi(2) / seeds as f64;
                ms_raw += (v / truth - 1.0).powi(2) / seeds as f64;
            }
            let secs = time_median(if quick { 5 } else { 21 }, || peak(&scans[0].sx, st));
            Point {
                setting: format!(
                    "{name} (uncalibrated: bias {:+.1} %, RMS {:.1} %)",
                    100.0 * bias,
                    100.0 * ms_raw.sqrt()
                ),
                value: st.noise_gain(),
                error: if ms_cal.is_finite() {
                    ms_cal.sqrt().max(1e-16)
                } else {
                    f64::INFINITY
                },
                seconds: secs,
                is_default: st == Stencil::default(),
            }
        })
        .collect();
    Knob {
        id: "stencil".into(),
        title: "Derivative stencil for (∂Sx/∂x)max, 110 nm bead at paper noise".into(),
        metric: format!(
            "RMS relative error over {seeds} noise seeds of the parabola-refined (∂Sx/∂x)max, calibrated by the same pipeline's noise-free value (as every calibration in the crate does), 64×64 × 50 nm"
        ),
        timed: "sensitivity image + point_peak of one 64×64 scan".into(),
        reference: "noise-free scan through the same stencil (calibrated); exact model ∂Sx/∂x at zero displacement (uncalibrated columns)".into(),
        points,
    }
}

/// Mie term count: worst error of the amplitude functions S1, S2 (relative to max |S|) at 91
/// angles for the 500 nm polystyrene bead in water at 1064 nm, against default + 40 terms.
pub fn knob_mie_terms(quick: bool) -> Knob {
    let o = Optics::default();
    let x = std::f64::consts::PI * 500.0 * o.n_medium / o.wavelength_nm;
    let m = Complex64::new(REF_BEAD_N / o.n_medium, 0.0);
    let mu: Vec<f64> = (0..91)
        .map(|i| (i as f64 * 2.0).to_radians().cos())
        .collect();
    let nd = default_terms(x, m);
    let reference = mie_s1s2_terms(x, m, &mu, Some(nd + 40)).expect("valid Mie input");
    let scale = reference
        .iter()
        .fold(0.0f64, |a, (s1, s2)| a.max(s1.norm()).max(s2.norm()));
    let mut ns: Vec<usize> = if quick {
        vec![2, 4, 6, nd]
    } else {
        vec![1, 2, 3, 4, 5, 6, 8, nd, nd + 10]
    };
    ns.sort_unstable();
    ns.dedup();
    let points = ns
        .into_iter()
        .map(|n| {
            let v = mie_s1s2_terms(x, m, &mu, Some(n)).expect("valid Mie input");
            let err = v
                .iter()
                .zip(&reference)
                .map(|((a1, a2), (b1, b2))| ((a1 - b1).norm()).max((a2 - b2).norm()))
                .fold(0.0f64, f64::max)
                / scale;
            let secs = time_median(if quick { 5 } else { 21 }, || {
                mie_s1s2_terms(x, m, &mu, Some(n))
            });
            Point {
                setting: format!("{n} terms"),
                value: n as f64,
                error: err.max(1e-16),
                seconds: secs,
                is_default: n == nd,
            }
        })
        .collect();
    Knob {
        id: "mie_terms".into(),
        title: format!("Mie term count, 500 nm polystyrene bead (x = {x:.2})"),
        metric: "worst |ΔS1|, |ΔS2| at 91 angles 0–180°, relative to max |S|".into(),
        timed: "amplitude functions at 91 angles".into(),
        reference: format!("{} terms (default + 40)", nd + 40),
        points,
    }
}

/// Scattering model for a polystyrene bead of diameter `d_nm` in the default (vector) beam: the
/// paper's normalised maximum sensitivity (∂Sx/∂x)max(d)/(∂Sx/∂x)max(110 nm) (Fig. 3c) from the
/// point dipole (Rayleigh, what the simulator renders inside the point dipole's domain), the
/// finite-size sphere rule (suppl. S6) and the focused-beam Mie tier, each in the vector beam
/// (`mie_beam::max_sensitivity_in_beam`), against the Mie tier on a finer incident grid. Time:
/// one maximum-sensitivity evaluation for the bead (focus search included; Mie includes
/// building its pair matrix).
pub fn knob_model(quick: bool, d_nm: f64) -> Knob {
    let o = ValidOptics::default();
    let ms = |d: f64, model: SphereModel| -> f64 {
        max_sensitivity_in_beam(&o, d, REF_BEAD_N, model)
            .expect("valid bead")
            .0
    };
    let fine = MieBeamSpec {
        n_theta_in: 24,
        n_phi_in: 12,
        ..MieBeamSpec::of_beam(&o)
    };
    let mie_fine = |d: f64| -> f64 {
        let alpha = alpha_um3(d, REF_BEAD_N, o.n_medium);
        MieBeam::new(&o, d, Complex64::new(REF_BEAD_N, 0.0), fine)
            .expect("valid Mie bead")
            .extreme_sensitivity_x(alpha)
            .0
    };
    let reference = mie_fine(d_nm) / mie_fine(110.0);
    let reps = if quick { 1 } else { 3 };
    let cube = (d_nm / 110.0).powi(3);
    let mut points = vec![];
    // point dipoles: the normalised sensitivity is the volume ratio exactly
    let secs = time_median(reps * 5, || ms(d_nm, SphereModel::Dipole));
    points.push(Point {
        setting: format!("Rayleigh point dipole (ratio {cube:.3}, Mie {reference:.3})"),
        value: 1.0,
        error: ((cube - reference) / reference).abs().max(1e-16),
        seconds: secs,
        is_default: true,
    });
    let orders: &[usize] = if quick {
        &[DEFAULT_N_R]
    } else {
        &[2, DEFAULT_N_R, 6]
    };
    for &nr in orders {
        let m = SphereModel::FiniteSize { n_r: nr };
        let v = ms(d_nm, m) / ms(110.0, m);
        let secs = time_median(reps, || ms(d_nm, m));
        points.push(Point {
            setting: format!("finite-size sphere rule, n_r = {nr} (ratio {v:.3})"),
            value: (2 * nr * nr * nr) as f64,
            error: ((v - reference) / reference).abs().max(1e-16),
            seconds: secs,
            is_default: false,
        });
    }
    let spec = MieBeamSpec::of_beam(&o);
    let v = ms(d_nm, SphereModel::Mie) / ms(110.0, SphereModel::Mie);
    let secs = time_median(reps, || ms(d_nm, SphereModel::Mie));
    points.push(Point {
        setting: format!(
            "Mie tier, default grid ({}, {}) (ratio {v:.3})",
            spec.n_theta_in, spec.n_phi_in
        ),
        value: (4 * spec.n_theta_in * spec.n_phi_in) as f64,
        error: ((v - reference) / reference).abs().max(1e-16),
        seconds: secs,
        is_default: false,
    });
    Knob {
        id: format!("model_{d_nm:.0}"),
        title: format!("Scattering model, {d_nm:.0} nm polystyrene bead, vector beam"),
        metric: "relative error of (∂Sx/∂x)max(d)/(∂Sx/∂x)max(110 nm) (paper Fig. 3c)".into(),
        timed:
            "one maximum-sensitivity evaluation incl. focus search (Mie: incl. building the tier)"
                .into(),
        reference: "focused-beam Mie tier in the vector beam, incident grid (24, 12)".into(),
        points,
    }
}

/// Where the point dipole holds: for beads of index `n` and diameter d, the point dipole's
/// relative error in the paper's normalised sensitivity (∂Sx/∂x)max(d, n)/(∂Sx/∂x)max(110 nm PS)
/// (Fig. 3c; the reference bead is the paper's polystyrene one), against the focused-beam Mie
/// tier in one beam (`mie_beam::point_dipole_error`).
#[derive(Debug, Clone)]
pub struct Validity {
    /// Bead index (real).
    pub n: f64,
    /// (diameter nm, relative error) pairs, increasing d.
    pub points: Vec<(f64, f64)>,
    /// Largest diameter of the sweep below which every point is within 1 %, linearly
    /// interpolated to the first crossing; None when the smallest diameter already fails or no
    /// point does (then `points` says which).
    pub d_1pct: Option<f64>,
}

/// The validity sweep for polystyrene (n = 1.572), silica (1.45) and a high-index bead (2.0);
/// quick: polystyrene only, three diameters.
pub fn model_validity(quick: bool) -> Vec<Validity> {
    let o = Optics::default();
    let (indices, ds): (&[f64], &[f64]) = if quick {
        (&[REF_BEAD_N], &[170.0, 250.0, 350.0])
    } else {
        (
            &[1.45, REF_BEAD_N, 2.0],
            &[60.0, 110.0, 170.0, 210.0, 250.0, 300.0, 350.0, 500.0],
        )
    };
    indices
        .iter()
        .map(|&n| {
            let points: Vec<(f64, f64)> = ds
                .iter()
                .map(|&d| {
                    let e = crate::optics::mie_beam::point_dipole_error(&o, d, n)
                        .expect("valid Mie bead");
                    (d, e)
                })
                .collect();
            Validity {
                n,
                d_1pct: first_crossing(&points, 0.01),
                points,
            }
        })
        .collect()
}

/// Linear interpolation of the first d where |err| reaches `tol` (None if the first point is
/// already beyond it or none is).
fn first_crossing(points: &[(f64, f64)], tol: f64) -> Option<f64> {
    if points.first().is_none_or(|p| p.1.abs() > tol) {
        return None;
    }
    points.windows(2).find_map(|w| {
        let ((d0, e0), (d1, e1)) = (w[0], w[1]);
        (e1.abs() > tol).then(|| d0 + (d1 - d0) * (tol - e0.abs()) / (e1.abs() - e0.abs()))
    })
}

#[cfg(test)]
mod validity_tests {
    use super::first_crossing;

    #[test]
    fn first_crossing_interpolates_and_refuses_the_impossible() {
        let p = [
            (100.0, 0.002),
            (200.0, -0.006),
            (300.0, 0.014),
            (400.0, 0.5),
        ];
        // |e| goes 0.006 → 0.014 between 200 and 300 nm: 1 % at 250 nm
        assert!((first_crossing(&p, 0.01).unwrap() - 250.0).abs() < 1e-9);
        assert_eq!(first_crossing(&p, 1.0), None);
        assert_eq!(first_crossing(&[(60.0, 0.02), (110.0, 0.03)], 0.01), None);
    }
}
