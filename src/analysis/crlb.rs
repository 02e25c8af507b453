//! Cramér–Rao lower bounds of the data actually taken: the floor under every error bar
//! (DESIGN.md, "Accuracy costs time"; the paper's noise model, suppl. S8).
//!
//! For a forward model μ_p(θ) sampled at points p with independent Gaussian noise of standard
//! deviation σ_p (white detector noise; a read averaging n samples of σ_s each has
//! σ_p = σ_s/√n, see [`pixel_sigma`]) the Fisher information is
//!
//! I(θ) = Σ_p (1/σ_p²) ∂μ_p/∂θ ∂μ_p/∂θᵀ,
//!
//! and every unbiased estimator of θ has a covariance of at least I⁻¹: its 1σ is at least
//! CRLB_k = √((I⁻¹)_kk). Least squares on a model linear in θ reaches the bound exactly (its
//! covariance is (XᵀWX)⁻¹ = I⁻¹, tested); a non-linear least-squares fit reaches it
//! asymptotically (at high SNR), which the Monte-Carlo test measures.
//!
//! Models here: the template bead model of the fit (eq. multiBeadFit; parameters weight, x, y
//! per bead, [`beads_crlb`]) and the straight bead-model filament of Sec. 4.2 (offset, angle,
//! weight per length, a background per channel; [`crate::analysis::filament_fit::LineFilament`]
//! provides μ and ∂μ/∂θ). Units: whatever the model's parameters are in (µm, radians,
//! reference-bead units); σ in the data's (instrument) units. No I/O.

use super::template::BeadInit;
use super::template::Template;
use super::{check_positive, AnalysisError, Result};
use nalgebra::DMatrix;

/// Per-pixel noise σ of a read averaging the samples of `dwell_s` at `rate_hz`, each of noise
/// `sigma_sample` (white detector noise, suppl. S8): σ_s/√n with n = round(dwell·rate) ≥ 1, the
/// count the scan engine reads (`instrument::samples_per_point`) and the simulator's
/// `detector_noise` divides by. Units: those of `sigma_sample`.
pub fn pixel_sigma(sigma_sample: f64, dwell_s: f64, rate_hz: f64) -> Result<f64> {
    if !(sigma_sample.is_finite() && sigma_sample >= 0.0) {
        return Err(AnalysisError::OutOfRange {
            name: "sigma_sample",
            value: sigma_sample,
            allowed: "finite and ≥ 0".into(),
        });
    }
    check_positive(&[("dwell_s", dwell_s), ("rate_hz", rate_hz)])?;
    // whole samples, at least one: the count of `instrument::samples_per_point` (analysis does
    // not import the instrument)
    let n = ((dwell_s * rate_hz).round()).max(1.0);
    Ok(sigma_sample / n.sqrt())
}

/// Accumulated Fisher information of independent Gaussian samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Fisher {
    pub info: DMatrix<f64>,
    /// Samples added.
    pub n_samples: usize,
}

impl Fisher {
    pub fn new(n_params: usize) -> Self {
        Self {
            info: DMatrix::zeros(n_params, n_params),
            n_samples: 0,
        }
    }

    /// Add one sample with gradient ∂μ/∂θ and noise σ (> 0; a sample with σ ≤ 0 or not finite
    /// carries no usable information and is skipped).
    pub fn add(&mut self, grad: &[f64], sigma: f64) {
        if !(sigma > 0.0 && sigma.is_finite()) {
            return;
        }
        let w = 1.0 / (sigma * sigma);
        let n = self.info.nrows();
        for i in 0..n {
            let gi = grad[i] * w;
            if gi == 0.0 {
                continue;
            }
            for j in i..n {
                self.info[(i, j)] += gi * grad[j];
            }
        }
        self.n_samples += 1;
    }

    /// The symmetric information matrix (upper triangle mirrored).
    pub fn matrix(&self) -> DMatrix<f64> {
        let n = self.info.nrows();
        DMatrix::from_fn(n, n, |i, j| {
            if i <= j {
                self.info[(i, j)]
            } else {
                self.info[(j, i)]
            }
        })
    }

    /// The Cramér–Rao covariance I⁻¹ (by a Cholesky factorisation of the diagonally scaled
    /// matrix). Errors: a parameter the data carry no information about (zero diagonal, named by
    /// `names` when given), or a singular information matrix (parameters not separately
    /// identifiable).
    pub fn covariance(&self, names: &[&str]) -> Result<DMatrix<f64>> {
        let a = self.matrix();
        let n = a.nrows();
        let name = |k: usize| names.get(k).copied().unwrap_or("parameter").to_string();
        let mut d = vec![0.0; n];
        for k in 0..n {
            let v = a[(k, k)];
            if !(v > 0.0 && v.is_finite()) {
                return Err(AnalysisError::Failed(format!(
                    "Cramér–Rao bound: the data carry no information about {} (parameter {k}; Fisher information {v})",
                    name(k)
                )));
            }
            d[k] = v.sqrt();
        }
        let s = DMatrix::from_fn(n, n, |i, j| a[(i, j)] / (d[i] * d[j]));
        let Some(ch) = s.cholesky() else {
            return Err(AnalysisError::Failed(
                "Cramér–Rao bound: the Fisher information is singular (the parameters are not separately identifiable from these data)".into(),
            ));
        };
        let inv = ch.inverse();
        let cov = DMatrix::from_fn(n, n, |i, j| inv[(i, j)] / (d[i] * d[j]));
        if cov.iter().any(|v| !v.is_finite()) || (0..n).any(|k| !(cov[(k, k)] > 0.0)) {
            return Err(AnalysisError::Failed(
                "Cramér–Rao bound: the Fisher information is numerically singular".into(),
            ));
        }
        Ok(cov)
    }

    /// CRLB_k = √((I⁻¹)_kk) for every parameter (units of the parameter). Errors as
    /// [`Fisher::covariance`].
    pub fn bounds(&self, names: &[&str]) -> Result<Vec<f64>> {
        let c = self.covariance(names)?;
        Ok((0..c.nrows()).map(|k| c[(k, k)].sqrt()).collect())
    }
}

/// Bound of one bead of the template model: 1σ floors of its weight (reference-bead units) and
/// position (µm).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BeadBound {
    pub weight: f64,
    pub x: f64,
    pub y: f64,
}

/// The Cramér–Rao bounds of the beads' weights and positions under the multi-bead template
/// model (eq. multiBeadFit) at the beads `beads` (parameters (weight, x, y) per bead, in that
/// order, as the fit's), for an image sampled at columns `x` and rows `y` (µm) in the channels
/// `channels` (0 = Sx, 1 = Sy). `sigma(ch, row, col)` gives each pixel's noise in instrument
/// units, or None for a pixel not taken (missing, NaN). The model is the template divided by
/// its `norm_factor` (instrument units), as the fit's: ∂μ/∂C = T/f, ∂μ/∂x = −C·∂T/∂u/f,
/// ∂μ/∂y = −C·∂T/∂v/f. Errors: no beads, a parameter the data carry no information about (a
/// bead out of the template's reach of every pixel, or a weight of 0 for its position), a
/// singular information matrix.
pub fn beads_crlb(
    tpl: &Template,
    beads: &[BeadInit],
    x: &[f64],
    y: &[f64],
    channels: &[usize],
    sigma: &dyn Fn(usize, usize, usize) -> Option<f64>,
) -> Result<Vec<BeadBound>> {
    if beads.is_empty() {
        return Err(AnalysisError::BadInput {
            name: "beads",
            reason: "no beads: the bound needs at least one".into(),
        });
    }
    let np = 3 * beads.len();
    let mut f = Fisher::new(np);
    let inv_f = 1.0 / tpl.norm_factor;
    let ((u0, u1), (v0, v1)) = tpl.extent();
    let mut g = vec![0.0; np];
    for &ch in channels {
        for (r, &yr) in y.iter().enumerate() {
            for (c, &xc) in x.iter().enumerate() {
                let Some(s) = sigma(ch, r, c) else { continue };
                let mut any = false;
                for (i, b) in beads.iter().enumerate() {
                    let (u, v) = (xc - b.x, yr - b.y);
                    if u < u0 || u > u1 || v < v0 || v > v1 {
                        g[3 * i] = 0.0;
                        g[3 * i + 1] = 0.0;
                        g[3 * i + 2] = 0.0;
                        continue;
                    }
                    let t = tpl.eval_grad(u, v);
                    g[3 * i] = t.v[ch] * inv_f;
                    g[3 * i + 1] = -b.weight * t.du[ch] * inv_f;
                    g[3 * i + 2] = -b.weight * t.dv[ch] * inv_f;
                    any = true;
                }
                if any {
                    f.add(&g, s);
                } else {
                    f.n_samples += 1;
                }
            }
        }
    }
    let names: Vec<String> = (0..beads.len())
        .flat_map(|i| {
            [
                format!("bead {i}'s weight"),
                format!("bead {i}'s x"),
                format!("bead {i}'s y"),
            ]
        })
        .collect();
    let names: Vec<&str> = names.iter().map(|s| s.as_str()).collect();
    let b = f.bounds(&names)?;
    Ok((0..beads.len())
        .map(|i| BeadBound {
            weight: b[3 * i],
            x: b[3 * i + 1],
            y: b[3 * i + 2],
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analysis::fit::{fit_beads, FitOptions};
    use crate::data::Image;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    fn axis(n: usize, h: f64) -> Vec<f64> {
        (0..n)
            .map(|i| (i as f64 - 0.5 * (n - 1) as f64) * h)
            .collect()
    }

    /// A Gaussian spot A·exp(−r²/w²) of known amplitude sampled on a fine symmetric grid: the
    /// amplitude's bound is σ/√Σg² (g the unit spot), and with position unknown too the cross
    /// terms vanish by symmetry, so it stays σ/√Σg²; the position's is σ/(A·√Σ(∂g/∂x)²), which
    /// on a grid of pitch h tends to σ·h·√2/(A·√π), independent of w.
    #[test]
    fn gaussian_spot_bounds_match_closed_forms() {
        let (w, h, a, sig) = (0.3, 0.02, 2.5, 0.01);
        let xs = axis(121, h);
        let mut f1 = Fisher::new(1);
        let mut f3 = Fisher::new(3);
        let (mut sg2, mut sdg2) = (0.0, 0.0);
        for &y in &xs {
            for &x in &xs {
                let g = (-(x * x + y * y) / (w * w)).exp();
                let dgx = 2.0 * x / (w * w) * g; // ∂μ/∂x0 / A
                let dgy = 2.0 * y / (w * w) * g;
                sg2 += g * g;
                sdg2 += dgx * dgx;
                f1.add(&[g], sig);
                f3.add(&[g, a * dgx, a * dgy], sig);
            }
        }
        let b1 = f1.bounds(&["A"]).unwrap();
        let b3 = f3.bounds(&["A", "x", "y"]).unwrap();
        let amp = sig / sg2.sqrt();
        assert!((b1[0] / amp - 1.0).abs() < 1e-12, "{} vs {amp}", b1[0]);
        assert!((b3[0] / amp - 1.0).abs() < 1e-9, "{} vs {amp}", b3[0]);
        let pos = sig / (a * sdg2.sqrt());
        assert!((b3[1] / pos - 1.0).abs() < 1e-9);
        assert!((b3[2] / pos - 1.0).abs() < 1e-9);
        // the continuum limit, independent of the spot's width
        let cont = sig * h * 2f64.sqrt() / (a * std::f64::consts::PI.sqrt());
        assert!((b3[1] / cont - 1.0).abs() < 1e-3, "{} vs {cont}", b3[1]);
        let amp_cont = sig * h / (w * (std::f64::consts::PI / 2.0).sqrt());
        assert!((b3[0] / amp_cont - 1.0).abs() < 1e-3);
    }

    /// A model linear in θ, μ = Xθ with per-point σ: the bound is the weighted least-squares
    /// covariance (XᵀWX)⁻¹ exactly.
    #[test]
    fn linear_model_bound_is_the_least_squares_covariance() {
        let n = 50;
        let xm = DMatrix::from_fn(n, 3, |i, j| {
            let t = i as f64 / n as f64;
            [1.0, t, (3.0 * t).sin()][j]
        });
        let sig: Vec<f64> = (0..n).map(|i| 0.1 + 0.01 * (i % 7) as f64).collect();
        let mut f = Fisher::new(3);
        for i in 0..n {
            let row: Vec<f64> = (0..3).map(|j| xm[(i, j)]).collect();
            f.add(&row, sig[i]);
        }
        let w = DMatrix::from_fn(
            n,
            n,
            |i, j| {
                if i == j {
                    1.0 / (sig[i] * sig[i])
                } else {
                    0.0
                }
            },
        );
        let cov = (xm.transpose() * w * &xm).try_inverse().unwrap();
        let c = f.covariance(&[]).unwrap();
        assert!((c - &cov).amax() < 1e-12 * cov.amax());
        let b = f.bounds(&[]).unwrap();
        for k in 0..3 {
            assert!((b[k] - cov[(k, k)].sqrt()).abs() < 1e-12 * b[k]);
        }
    }

    #[test]
    fn uninformative_and_unidentifiable_parameters_are_errors() {
        let mut f = Fisher::new(2);
        f.add(&[1.0, 0.0], 1.0);
        let e = f.bounds(&["a", "b"]).unwrap_err().to_string();
        assert!(e.contains("no information about b"), "{e}");
        let mut f = Fisher::new(2);
        f.add(&[1.0, 2.0], 1.0);
        f.add(&[2.0, 4.0], 0.5);
        let e = f.bounds(&["a", "b"]).unwrap_err().to_string();
        assert!(e.contains("singular"), "{e}");
        // σ ≤ 0 or NaN adds nothing
        let mut f = Fisher::new(1);
        f.add(&[1.0], 0.0);
        f.add(&[1.0], f64::NAN);
        assert_eq!(f.n_samples, 0);
    }

    #[test]
    fn pixel_sigma_follows_the_sample_count() {
        // 10 ms at 100 kHz: 1000 samples
        let s = pixel_sigma(2e-3, 0.01, 1e5).unwrap();
        assert!((s - 2e-3 / 1000f64.sqrt()).abs() < 1e-15);
        // below one sample: one sample
        assert_eq!(pixel_sigma(2e-3, 1e-7, 1e5).unwrap(), 2e-3);
        let e = pixel_sigma(2e-3, -1.0, 1e5).unwrap_err().to_string();
        assert!(e.contains("dwell_s = -1"), "{e}");
        let e = pixel_sigma(f64::NAN, 1.0, 1e5).unwrap_err().to_string();
        assert!(e.contains("sigma_sample = NaN"), "{e}");
    }

    /// The analytic stand-in Sx = u·g, Sy = v·g (g = exp(−r²/w²)) centred on a symmetric grid:
    /// Σ(Tx² + Ty²) → (1/h²)∫r²e^(−2r²/w²)dA = πw⁴/(4h²), so CRLB(C) = 2σh/(√π·w²).
    #[test]
    fn bead_weight_bound_of_the_standin_matches_its_closed_form() {
        let (w, h, sig) = (0.4, 0.05, 1e-3);
        let tpl = Template::analytic_standin(w, 0.01, 2.0).unwrap();
        let xs = axis(61, h);
        let b = beads_crlb(
            &tpl,
            &[BeadInit {
                x: 0.0,
                y: 0.0,
                weight: 1.0,
            }],
            &xs,
            &xs,
            &[0, 1],
            &|_, _, _| Some(sig),
        )
        .unwrap();
        let want = 2.0 * sig * h / (std::f64::consts::PI.sqrt() * w * w) * tpl.norm_factor;
        assert!(
            (b[0].weight / want - 1.0).abs() < 2e-3,
            "{:?} vs {want}",
            b[0]
        );
        // x and y symmetric
        assert!((b[0].x / b[0].y - 1.0).abs() < 1e-9);
        // no beads, or a bead no pixel sees: errors
        let e = beads_crlb(&tpl, &[], &xs, &xs, &[0], &|_, _, _| Some(sig)).unwrap_err();
        assert!(e.to_string().contains("no beads"), "{e}");
        let far = [BeadInit {
            x: 50.0,
            y: 0.0,
            weight: 1.0,
        }];
        let e = beads_crlb(&tpl, &far, &xs, &xs, &[0, 1], &|_, _, _| Some(sig)).unwrap_err();
        assert!(
            e.to_string()
                .contains("no information about bead 0's weight"),
            "{e}"
        );
    }

    /// A good estimator reaches the bound: over 300 noise seeds the template fit's weight and
    /// positions scatter by the CRLB within the statistical error of a standard deviation
    /// (1/√(2N) = 4.1 %; 3σ allowed), and with σ given the fit's own 1σ equals the bound.
    #[test]
    fn fit_scatter_over_seeds_reaches_the_bound() {
        let tpl = Template::analytic_standin(0.4, 0.02, 1.6).unwrap();
        let xs: Vec<f64> = (0..41).map(|i| i as f64 * 0.05).collect();
        let truth = (1.03, 0.98, 1.0);
        let [sx0, sy0, _] = tpl.render_instrument(&[truth], &xs, &xs);
        let sig = 0.05 / tpl.norm_factor; // 5 % of the peak
        let bound = beads_crlb(
            &tpl,
            &[BeadInit {
                x: truth.0,
                y: truth.1,
                weight: truth.2,
            }],
            &xs,
            &xs,
            &[0, 1],
            &|_, _, _| Some(sig),
        )
        .unwrap()[0];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let n = 300;
        let (mut w, mut x, mut y) = (vec![], vec![], vec![]);
        for k in 0..n {
            let mut noisy = |a: &ndarray::Array2<f64>| {
                let mut a = a.clone();
                a.mapv_inplace(|v| {
                    let z: f64 = StandardNormal.sample(&mut rng);
                    v + sig * z
                });
                Image::new(a, xs.clone(), xs.clone())
            };
            let (sx, sy) = (noisy(&sx0), noisy(&sy0));
            let r = fit_beads(
                &sx,
                &sy,
                &tpl,
                &FitOptions {
                    init: Some(vec![BeadInit {
                        x: 1.0,
                        y: 1.0,
                        weight: 1.0,
                    }]),
                    sigma: Some(sig),
                    ..Default::default()
                },
            )
            .unwrap();
            let b = r.beads[0];
            if k == 0 {
                let e = b.weight_err.unwrap();
                assert!((e / bound.weight - 1.0).abs() < 0.02, "{e} vs {bound:?}");
            }
            w.push(b.weight);
            x.push(b.x);
            y.push(b.y);
        }
        let sd = |v: &[f64]| {
            let m = v.iter().sum::<f64>() / v.len() as f64;
            (v.iter().map(|a| (a - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
        };
        let tol = 3.0 / (2.0 * n as f64).sqrt();
        for (name, s, b) in [
            ("weight", sd(&w), bound.weight),
            ("x", sd(&x), bound.x),
            ("y", sd(&y), bound.y),
        ] {
            assert!(
                (s / b - 1.0).abs() < tol,
                "{name}: scatter {s} vs CRLB {b} (ratio {})",
                s / b
            );
        }
    }
}
