//! The focus family of the truth sweep (`focus_search.z_best`, `focus_search.max_sens`,
//! `focus_search.detection`): an XZ scan through one polystyrene bead at a random focus offset
//! (or an empty field), searched for the best focus as `focus_search` does (suppl. S5).
//!
//! Truth, by a path apart from the analysis: the noise-free renderer's largest lateral slope
//! ∂Sx/∂x near the bead (central differences on a 1 nm grid), over z in 2 nm steps; its
//! maximum gives the best focus relative to the bead (`z_peak`, µm) and the reference bead's
//! maximum sensitivity (`s_peak`, µm⁻¹). A bead of diameter d scales the slope by its weight
//! (d / 110 nm)³ (point dipoles, eq. alpha; a bead the simulator renders by the Mie tier, which saturates below d³, gets its own curve: [`FocusTruth::of_bead`]).
//!
//! A maximum sensitivity read off pixels depends on the pixel size, the stencil and the
//! parabola window (Sec. 3.2; the central difference and the parabola read a peak low, by 1 %
//! at 30 nm pixels and 7 % at 100 nm): what `max_sens` estimates is that pipeline's reading,
//! which masses divide by the reference bead's read the same way
//! ([`Template::pipeline_max_sens`]). Its truth is the peak above times that reading of a bead
//! of peak 1, at the scene's pixel size.

use crate::analysis::focus::{focus_search, FocusOptions};
use crate::analysis::template::Template;
use crate::data::Image;
use crate::instrument::sim::domain::{is_suspect, DomainCheck};
use crate::instrument::sim::scene::{
    Bead, DetectorNoise, Scene, PAPER_DETECTOR_SIGMA_SAMPLE, PAPER_SAMPLES_PER_PIXEL,
};
use crate::instrument::sim::Renderer;
use crate::optics::beam::OpticsArg;
use crate::optics::params::{Optics, REF_BEAD_N};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

/// Half the lateral extent (µm) and half the z range (µm) of the focus scenes' XZ scan.
const X_HALF: f64 = 1.5;
const Z_HALF: f64 = 2.0;

/// The diameter of the reference bead, nm (the weight unit).
const REF_D_NM: f64 = 110.0;

/// One focus scene: the bead `[x µm, z µm, d nm]` (None: an empty field), the paper's noise ×
/// `noise`, lateral pixels of `pixel_nm`, z rows every `z_step_nm`, the noise's `seed`.
#[derive(Debug, Clone, Serialize, serde::Deserialize, PartialEq)]
pub struct FocusCase {
    pub bead: Option<[f64; 3]>,
    pub noise: f64,
    pub pixel_nm: u32,
    pub z_step_nm: u32,
    pub seed: u64,
}

impl FocusCase {
    /// One field in eight empty; otherwise a 40–200 nm bead (log-uniform) within ±0.8 µm of
    /// the scan's middle and ±3 µm of its focus (the scan reaches ±2 µm).
    pub(super) fn draw(rng: &mut ChaCha8Rng) -> FocusCase {
        let empty = rng.random_range(0..8) == 0;
        let x = rng.random_range(-0.8..0.8);
        let z = rng.random_range(-3.0..3.0);
        let d = (40f64.ln() + rng.random::<f64>() * (200f64 / 40.0).ln()).exp();
        let noise = rng.random_range(0.0..10.0);
        let pixel_nm = PIXELS_NM[rng.random_range(0..5)];
        let z_step_nm = [25u32, 50, 100][rng.random_range(0..3)];
        let seed = rng.random::<u64>();
        FocusCase {
            bead: (!empty).then_some([x, z, d]),
            noise,
            pixel_nm,
            z_step_nm,
            seed,
        }
    }

    pub(super) fn describe(&self) -> String {
        format!(
            "focus: {}, noise ×{:.4}, pixel {} nm, z step {} nm on ±{X_HALF} × ±{Z_HALF} µm, seed {}",
            match self.bead {
                Some([x, z, d]) => format!("bead d {d:.1} nm at x {x:.3} µm, z {z:.3} µm"),
                None => "empty field".into(),
            },
            self.noise,
            self.pixel_nm,
            self.z_step_nm,
            self.seed
        )
    }
}

/// The best focus of the reference bead relative to it (µm) and its maximum sensitivity
/// (µm⁻¹), from the noise-free renderer (see the module docs).
#[derive(Debug, Clone, Copy)]
pub(super) struct FocusTruth {
    z_peak: f64,
    s_peak: f64,
    /// The pipeline's reading of a bead of peak sensitivity 1, by lateral pixel size (nm).
    pipeline: [(u32, f64); 5],
}

/// The focus scenes' lateral pixel sizes, nm.
const PIXELS_NM: [u32; 5] = [20, 30, 50, 75, 100];

impl FocusTruth {
    pub(super) fn compute(optics: &Optics, tpl: &Template) -> Result<FocusTruth, String> {
        let opts = FocusOptions::default();
        let mut pipeline = [(0, 0.0); 5];
        for (p, &nm) in pipeline.iter_mut().zip(&PIXELS_NM) {
            let f = tpl
                .pipeline_max_sens_by(
                    nm as f64 / 1000.0,
                    opts.stencil,
                    opts.window_um,
                    crate::analysis::peaks::point_peak_3row,
                )
                .map_err(|e| e.to_string())?;
            *p = (nm, f);
        }
        let (z_peak, s_peak) = bead_focus(optics, REF_D_NM)?;
        Ok(FocusTruth {
            z_peak,
            s_peak,
            pipeline,
        })
    }

    /// The best focus relative to a polystyrene bead of `d_nm` (µm) and its maximum
    /// sensitivity (µm⁻¹, before the pipeline's reading): the reference bead's scaled by the
    /// weight (d / 110 nm)³ where the simulator renders the bead as a point dipole; the bead's
    /// own noise-free focus curve where it may not (the domain check can give it to the Mie
    /// tier, whose sensitivity saturates below d³ and whose best focus moves:
    /// docs/accuracy.md#model_500).
    fn of_bead(&self, optics: &Optics, d_nm: f64) -> Result<(f64, f64), String> {
        if renders_by_mie(optics, d_nm)? {
            bead_focus(optics, d_nm)
        } else {
            Ok((self.z_peak, self.s_peak * (d_nm / REF_D_NM).powi(3)))
        }
    }
}

/// A scene holding one polystyrene bead of `d_nm` at the origin, nothing else.
fn lone_bead(d_nm: f64) -> Result<Scene, String> {
    let mut sc = Scene::default();
    sc.add_bead(Bead {
        pos: [0.0; 3],
        d_nm,
        n: REF_BEAD_N,
    })
    .map_err(|e| e.to_string())?;
    Ok(sc)
}

/// Whether the simulator renders a polystyrene bead of `d_nm` by the Mie tier: the domain
/// check's verdict (the point dipole more than 1 % off, docs/accuracy.md#model_500), which
/// the renderer reads the same way.
fn renders_by_mie(optics: &Optics, d_nm: f64) -> Result<bool, String> {
    if !is_suspect(d_nm, REF_BEAD_N) {
        return Ok(false);
    }
    let valid = optics.valid().map_err(|e| e.to_string())?;
    Ok(DomainCheck::run_shared(&valid, &lone_bead(d_nm)?)
        .outside(d_nm, REF_BEAD_N)
        .is_some())
}

/// A polystyrene bead's best focus relative to it (µm) and its maximum lateral slope ∂Sx/∂x
/// (µm⁻¹), from the noise-free renderer of a scene holding that bead alone (the renderer's
/// own tier: point dipole, or Mie where the domain check says so).
fn bead_focus(optics: &Optics, d_nm: f64) -> Result<(f64, f64), String> {
    let r = Renderer::checked(optics, &lone_bead(d_nm)?, Default::default())
        .map_err(|e| e.to_string())?;
    // the largest slope along x at each z: central differences of Sx every 1 nm over
    // ±0.15 µm, the maximum refined by the parabola through its neighbours (the lateral
    // maximum need not sit on the bead's centre)
    let h = 1e-3;
    let xs: Vec<f64> = (0..=300).map(|i| -0.15 + h * i as f64).collect();
    let slope = |z: f64| {
        let s = r.render_grid_ideal(&xs, &[0.0], z);
        let d: Vec<f64> = (1..xs.len() - 1)
            .map(|i| (s[0][i + 1] - s[0][i - 1]) / (2.0 * h))
            .collect();
        sampled_max(&d).map_or(f64::NAN, |(_, _, v)| v)
    };
    // the maximum on a 2 nm grid over ±0.5 µm, refined the same way: found on a 20 nm grid
    // first, then on the 2 nm grid within ±30 nm of it (the curve is smooth and has one
    // maximum there; a Mie bead's slope costs ~40 ms)
    let coarse: Vec<f64> = (0..=50).map(|i| -0.5 + 0.02 * i as f64).collect();
    let vc: Vec<f64> = coarse.iter().map(|&z| slope(z)).collect();
    let Some((ic, _, _)) = sampled_max(&vc) else {
        return Err(format!(
            "the {d_nm} nm bead's focus curve could not be sampled"
        ));
    };
    let zs: Vec<f64> = (-15..=15).map(|i| coarse[ic] + 0.002 * i as f64).collect();
    let v: Vec<f64> = zs.iter().map(|&z| slope(z)).collect();
    let Some((i, t, s_peak)) = sampled_max(&v).filter(|m| m.1.is_finite()) else {
        return Err(format!(
            "the {d_nm} nm bead's focus curve has no maximum within ±0.5 µm"
        ));
    };
    Ok((zs[i] + t * 0.002, s_peak))
}

/// The largest interior sample of `v`, refined by the parabola through it and its two
/// neighbours: (index, vertex offset in samples, vertex value). The offset is NaN (and the value
/// the sample's) where the three are not concave; None for fewer than three samples.
fn sampled_max(v: &[f64]) -> Option<(usize, f64, f64)> {
    let i = (1..v.len().checked_sub(1)?).max_by(|&a, &b| v[a].total_cmp(&v[b]))?;
    let (a, b, c) = (v[i - 1], v[i], v[i + 1]);
    let den = a - 2.0 * b + c;
    if den < 0.0 {
        let t = 0.5 * (a - c) / den;
        Some((i, t, b - 0.25 * (a - c) * t))
    } else {
        Some((i, f64::NAN, b))
    }
}

/// The XZ scan of the scene: rows are z (the focus's height), columns x; Sx through the
/// simulator's reading of each point (the detector noise effect of the paper × `noise`).
fn render_xz(optics: &Optics, case: &FocusCase) -> Option<Image> {
    let mut sc = Scene::default();
    if let Some([x, z, d]) = case.bead {
        sc.add_bead(Bead {
            pos: [x, 0.0, z],
            d_nm: d,
            n: REF_BEAD_N,
        })
        .ok()?;
    }
    sc.effects.detector_noise = Some(DetectorNoise {
        sigma_sample: case.noise * PAPER_DETECTOR_SIGMA_SAMPLE,
    });
    let r = Renderer::checked(optics, &sc, Default::default()).ok()?;
    let axis = |half: f64, step_nm: u32| -> Vec<f64> {
        let n = (2.0 * half / (step_nm as f64 / 1000.0)).round() as usize + 1;
        (0..n)
            .map(|i| -half + 2.0 * half * i as f64 / (n - 1) as f64)
            .collect()
    };
    let xs = axis(X_HALF, case.pixel_nm);
    let zs = axis(Z_HALF, case.z_step_nm);
    let mut rng = ChaCha8Rng::seed_from_u64(case.seed);
    let data = ndarray::Array2::from_shape_fn((zs.len(), xs.len()), |(iz, ix)| {
        let (v, _) = r.render_point([xs[ix], 0.0, zs[iz]], PAPER_SAMPLES_PER_PIXEL, &mut rng);
        v[0]
    });
    Some(Image::new(data, xs, zs).with_axis_names("x", "z"))
}

/// One estimator's outcome on one scene, as the sweep tallies it.
#[derive(Debug, Clone)]
pub enum Outcome {
    /// The scene could not be rendered.
    Refused,
    /// A warning or a refusal, in words.
    Flagged(Vec<String>),
    /// An answer inside its domain: `value` against `truth`, its 1σ, the relative error beyond
    /// which it is an outlier whatever its σ (counts), and the case in words.
    Answer {
        value: f64,
        truth: f64,
        sigma: Option<f64>,
        rel_limit: Option<f64>,
        what: String,
    },
}

/// The focus family: one XZ scene searched for the best focus; z_best and max_sens against
/// the truth, an empty field against "no object". Returns each estimator's outcome and the
/// search's answer (for `--replay`).
pub(super) fn focus_case(
    case: &FocusCase,
    optics: &Optics,
    truth: &FocusTruth,
) -> (
    Vec<(&'static str, Outcome)>,
    Option<crate::analysis::focus::FocusResult>,
) {
    let keys = [
        "focus_search.z_best",
        "focus_search.max_sens",
        "focus_search.detection",
    ];
    let Some(img) = render_xz(optics, case) else {
        return (keys.map(|k| (k, Outcome::Refused)).to_vec(), None);
    };
    let r = focus_search(&img, &FocusOptions::default());
    let why: Vec<String> = match &r {
        Ok(f) => f.warnings.clone(),
        Err(e) => vec![e.to_string()],
    };
    let Some([_, z0, d]) = case.bead else {
        // an empty field: any answer without a warning is an object found where there is none
        let o = match (&r, why.is_empty()) {
            (Ok(f), true) => Outcome::Answer {
                value: 1.0,
                truth: 0.0,
                sigma: None,
                rel_limit: Some(0.05),
                what: format!(
                    "an object found at z {:.3} µm in an empty field: {}",
                    f.z_best,
                    case.describe()
                ),
            },
            _ => Outcome::Flagged(why),
        };
        return (vec![(keys[2], o)], r.ok());
    };
    let f = match &r {
        Ok(f) if why.is_empty() => f,
        _ => {
            let o = keys[..2]
                .iter()
                .map(|&k| (k, Outcome::Flagged(why.clone())))
                .collect();
            return (o, r.ok());
        }
    };
    let read = truth
        .pipeline
        .iter()
        .find(|p| p.0 == case.pixel_nm)
        .map_or(f64::NAN, |p| p.1);
    let (z_peak, s_peak) = match truth.of_bead(optics, d) {
        Ok(t) => t,
        // the truth could not be computed: the scene counts as not rendered
        Err(_) => {
            return (
                keys[..2].iter().map(|&k| (k, Outcome::Refused)).collect(),
                r.ok(),
            )
        }
    };
    let answers = [
        ("z_best", "µm", f.z_best, z0 + z_peak, f.z_err),
        (
            "max_sens",
            "µm⁻¹",
            f.max_sens,
            s_peak * read,
            f.max_sens_err,
        ),
    ];
    let o = keys
        .iter()
        .zip(answers)
        .map(|(&k, (name, unit, value, truth, sigma))| {
            let what = format!(
                "{name} {value:.5} ± {:.5} {unit} vs truth {truth:.5}: {}",
                sigma.unwrap_or(f64::NAN),
                case.describe()
            );
            (
                k,
                Outcome::Answer {
                    value,
                    truth,
                    sigma,
                    rel_limit: None,
                    what,
                },
            )
        })
        .collect();
    (o, r.ok())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::mie_beam::point_dipole_error;

    /// A 199.7 nm polystyrene bead is rendered by the Mie tier (the point dipole is 1.3 % too
    /// sensitive there): its truth is its own focus curve, whose peak sits below the reference's
    /// d³ scaling by the point dipole's error as the Mie tier's own maximum-sensitivity search
    /// measures it (a path apart: `point_dipole_error` searches the Mie response, this renders
    /// the scene). A 120 nm bead stays a point dipole and is scaled exactly.
    #[test]
    fn a_bead_the_simulator_renders_by_mie_gets_its_own_focus_truth() {
        let optics = Optics::default();
        let (z_ref, s_ref) = bead_focus(&optics, REF_D_NM).unwrap();
        let truth = FocusTruth {
            z_peak: z_ref,
            s_peak: s_ref,
            pipeline: [(0, 0.0); 5],
        };
        let d = 199.7;
        assert!(renders_by_mie(&optics, d).unwrap());
        let err = point_dipole_error(&optics, d, REF_BEAD_N).unwrap();
        assert!(err > 0.01, "the point dipole is {err} off at {d} nm");
        let (_, s) = truth.of_bead(&optics, d).unwrap();
        let scaled = s_ref * (d / REF_D_NM).powi(3);
        let implied = scaled / s - 1.0;
        assert!(
            (implied - err).abs() < 0.05 * err,
            "rendered Mie bead: point dipole {implied:+.4} too sensitive, domain check {err:+.4}"
        );
        assert!(!renders_by_mie(&optics, 120.0).unwrap());
        let (z, s) = truth.of_bead(&optics, 120.0).unwrap();
        assert_eq!((z, s), (z_ref, s_ref * (120.0f64 / REF_D_NM).powi(3)));
    }

    /// `focus::focus_curve_ratio`, the ratio of the parabola curvatures over a z window W and
    /// over 2W on the noise-free focus curve, describes the renderer's focus curve: 60 and 110 nm
    /// beads (point dipoles) and a 199 nm one (the Mie tier), at 25, 50 and 100 nm rows. The
    /// table holds the lowest ratio measured; every curve's lies at most 2 % above it at W = 0.4
    /// and 0.6 µm, 6 % at 0.8 µm (the curves part as the window reaches their sides).
    #[test]
    fn the_focus_curve_ratio_matches_the_rendered_focus_curves() {
        use crate::analysis::focus::focus_curve_ratio;
        use crate::analysis::peaks::{peak_1d, PeakOptions};
        let optics = Optics::default();
        for (d, step) in [(60.0, 50), (110.0, 100), (110.0, 25), (199.0, 50)] {
            let case = FocusCase {
                bead: Some([0.1, 0.3, d]),
                noise: 0.0,
                pixel_nm: 50,
                z_step_nm: step,
                seed: 1,
            };
            let img = render_xz(&optics, &case).unwrap();
            let f = focus_search(&img, &FocusOptions::default()).unwrap();
            let z: Vec<f64> = f.rows.iter().map(|r| r.coord).collect();
            let v: Vec<f64> = f
                .rows
                .iter()
                .map(|r| r.peak().map_or(f64::NAN, |p| p.value))
                .collect();
            let curv = |w: f64| {
                let o = PeakOptions {
                    window_um: w,
                    ..Default::default()
                };
                peak_1d(&z, &v, &o).unwrap().curvature
            };
            for (w, tol) in [(0.4, 0.02), (0.6, 0.02), (0.8, 0.06)] {
                let table = focus_curve_ratio(w).unwrap();
                let r = curv(w) / curv(2.0 * w);
                assert!(
                    r >= table - 2e-3 && r <= table * (1.0 + tol),
                    "{d} nm, {step} nm rows, W = {w} µm: ratio {r:.4}, table {table:.4}"
                );
            }
        }
        assert_eq!(focus_curve_ratio(0.0), Some(1.0));
        assert_eq!(focus_curve_ratio(0.9), None);
    }
}
