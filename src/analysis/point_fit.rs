//! One bead's template model fitted to readings at an arbitrary set of stage points — the
//! analysis of a targeted measurement, whose points sit where the Fisher information is, not on
//! a raster (DESIGN.md, "Accuracy costs time"; the model of eq. multiBeadFit).
//!
//! Model: at stage point p_k the channel ch reads μ = (w/f)·T_ch(p_k − b) + c_ch, with b = (x,
//! y) the bead's position (µm), w its weight (reference-bead units), f the template's
//! `norm_factor`, c_ch a constant background per channel (optional). Least squares by the
//! project's Levenberg–Marquardt (`fit::lm`); 1σ from σ²(JᵀJ)⁻¹; the Cramér–Rao bounds of the
//! same points at the solution with the same σ; [`design_points`] gives the points where one
//! reading carries the most information about the weight.

use super::crlb::Fisher;
use super::template::Template;
use super::{check_above, AnalysisError, Result};
use serde::{Deserialize, Serialize};

/// One reading: stage position (µm) and the Sx, Sy it read (scan units).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PointReading {
    pub x: f64,
    pub y: f64,
    pub sx: f64,
    pub sy: f64,
}

/// Result of [`fit_bead_points`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PointFit {
    pub x: f64,
    pub y: f64,
    pub weight: f64,
    /// Backgrounds (Sx, Sy); 0 when not fitted.
    pub background: [f64; 2],
    /// 1σ (x µm, y µm, weight).
    pub err: [f64; 3],
    /// Cramér–Rao bounds of the points at the fit with σ (x µm, y µm, weight).
    pub crlb: [f64; 3],
    pub sigma: f64,
    pub sigma_estimated: bool,
    pub rss: f64,
    pub n_residuals: usize,
    pub status: crate::analysis::fit::FitStatus,
    pub reason: String,
}

/// Fit one bead (x, y, weight and, with `background`, a constant per channel) to `points` from
/// the start `init` = (x, y, weight). `sigma`: the readings' noise (None: from the residuals,
/// which needs more residuals than parameters). Errors: too few readings, non-finite values, a
/// bead out of the template's reach of every point, a singular information matrix (a pattern
/// that does not separate the parameters).
pub fn fit_bead_points(
    tpl: &Template,
    points: &[PointReading],
    init: [f64; 3],
    sigma: Option<f64>,
    background: bool,
) -> Result<PointFit> {
    use crate::analysis::fit::{levenberg_marquardt, Tolerances};
    let np = if background { 5 } else { 3 };
    let m = 2 * points.len();
    if m < np + usize::from(sigma.is_none()) {
        return Err(AnalysisError::BadInput {
            name: "points",
            reason: format!(
                "{} readings give {m} values; the fit of {np} parameters needs more{}",
                points.len(),
                if sigma.is_none() {
                    " (and one more to estimate σ)"
                } else {
                    ""
                }
            ),
        });
    }
    for p in points {
        if ![p.x, p.y, p.sx, p.sy].iter().all(|v| v.is_finite()) {
            return Err(AnalysisError::BadInput {
                name: "points",
                reason: format!("a reading is not finite: {p:?}"),
            });
        }
    }
    if let Some(s) = sigma {
        check_above("sigma", s, 0.0)?;
    }
    let inv_f = 1.0 / tpl.norm_factor;
    // residual rows: (value, gradient) for θ = (x, y, w, bx, by)
    let rows = |p: &[f64]| {
        let mut out = Vec::with_capacity(m);
        for q in points {
            let t = tpl.eval_grad(q.x - p[0], q.y - p[1]);
            for (ch, d) in [q.sx, q.sy].into_iter().enumerate() {
                let bg = if background { p[3 + ch] } else { 0.0 };
                let mu = p[2] * t.v[ch] * inv_f + bg;
                let mut g = [
                    -p[2] * t.du[ch] * inv_f,
                    -p[2] * t.dv[ch] * inv_f,
                    t.v[ch] * inv_f,
                    0.0,
                    0.0,
                ];
                if background {
                    g[3 + ch] = 1.0;
                }
                out.push((mu - d, g));
            }
        }
        out
    };
    let eval = |p: &[f64]| {
        let mut a = nalgebra::DMatrix::zeros(np, np);
        let mut g = nalgebra::DVector::zeros(np);
        let mut rss = 0.0;
        for (r, j) in rows(p) {
            rss += r * r;
            for u in 0..np {
                g[u] += j[u] * r;
                for v in 0..np {
                    a[(u, v)] += j[u] * j[v];
                }
            }
        }
        (rss, a, g)
    };
    let mut p0 = vec![init[0], init[1], init[2]];
    if background {
        p0.extend([0.0, 0.0]);
    }
    let raw = levenberg_marquardt(
        eval,
        p0,
        &Tolerances {
            ftol: 1e-12,
            xtol: 1e-12,
            gtol: 1e-12,
            patience: 200,
        },
    );
    let p = raw.p.clone();
    let dof = m.saturating_sub(np).max(1);
    let (sigma, est) = match sigma {
        Some(s) => (s, false),
        None => ((raw.rss / dof as f64).sqrt(), true),
    };
    let names = ["x", "y", "weight", "Sx background", "Sy background"];
    let mut info = Fisher::new(np);
    for (_, j) in rows(&p) {
        info.add(&j[..np], sigma);
    }
    let crlb = info.bounds(&names[..np])?;
    let err = Fisher {
        info: raw.jtj.clone() / (sigma * sigma),
        n_samples: m,
    }
    .bounds(&names[..np])?;
    Ok(PointFit {
        x: p[0],
        y: p[1],
        weight: p[2],
        background: if background { [p[3], p[4]] } else { [0.0; 2] },
        err: [err[0], err[1], err[2]],
        crlb: [crlb[0], crlb[1], crlb[2]],
        sigma,
        sigma_estimated: est,
        rss: raw.rss,
        n_residuals: m,
        status: raw.status,
        reason: raw.reason,
    })
}

/// The lateral distance r (µm) from a bead's centre, along x, at which one Sx reading carries
/// the most information about the bead's weight: the maximum of |T_x(r, 0)| over
/// 0 < r ≤ `r_max` (by symmetry the same r along y for Sy of a round beam; the template's own
/// Sy is used for the y arm).
pub fn design_radius(tpl: &Template, r_max: f64) -> Result<[f64; 2]> {
    check_above("r_max", r_max, 0.0)?;
    let n = 2000;
    let best = |ch: usize| {
        let mut b = (0.0f64, 0.0f64);
        for i in 1..=n {
            let r = r_max * i as f64 / n as f64;
            let v = if ch == 0 {
                tpl.eval(r, 0.0)[0]
            } else {
                tpl.eval(0.0, r)[1]
            };
            if v.abs() > b.1 {
                b = (r, v.abs());
            }
        }
        b.0
    };
    Ok([best(0), best(1)])
}

/// The cross pattern around (x, y): (x ± r_x, y) and (x, y ± r_y), with the radii of
/// [`design_radius`]: Sx on the x arm (its lobes) and Sy on the y arm carry the weight, Sy on
/// the x arm (∂Sy/∂y) the y position, Sx on the y arm (∂Sx/∂x) the x position, and the
/// opposite ends of each arm cancel a constant background.
pub fn design_points(tpl: &Template, x: f64, y: f64) -> Result<Vec<[f64; 2]>> {
    let ((u0, u1), (v0, v1)) = tpl.extent();
    let r = design_radius(tpl, u1.min(-u0).min(v1).min(-v0))?;
    Ok(vec![
        [x - r[0], y],
        [x + r[0], y],
        [x, y - r[1]],
        [x, y + r[1]],
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Readings rendered from the template itself at a known bead come back exactly (noise-free,
    /// σ given), from a start 50 nm and 20 % off; the bounds scale with σ.
    #[test]
    fn a_bead_is_recovered_from_its_cross_pattern() {
        let tpl = Template::analytic_standin(0.4, 0.02, 1.6).unwrap();
        let (bx, by, w) = (0.03, -0.02, 1.3);
        let mut pts = vec![];
        for k in 0..3 {
            for p in design_points(&tpl, 0.01 * k as f64, 0.0).unwrap() {
                let t = tpl.eval(p[0] - bx, p[1] - by);
                pts.push(PointReading {
                    x: p[0],
                    y: p[1],
                    sx: w * t[0] / tpl.norm_factor + 1e-4,
                    sy: w * t[1] / tpl.norm_factor - 2e-4,
                });
            }
        }
        let f = fit_bead_points(&tpl, &pts, [0.08, 0.0, 1.0], Some(1e-3), true).unwrap();
        assert!((f.x - bx).abs() < 1e-9 && (f.y - by).abs() < 1e-9, "{f:?}");
        assert!((f.weight - w).abs() < 1e-9, "{f:?}");
        assert!((f.background[0] - 1e-4).abs() < 1e-12);
        // σ given: the fit's 1σ is the bound at the solution
        for k in 0..3 {
            assert!((f.err[k] / f.crlb[k] - 1.0).abs() < 1e-6, "{f:?}");
        }
        let g = fit_bead_points(&tpl, &pts, [0.08, 0.0, 1.0], Some(2e-3), true).unwrap();
        assert!((g.crlb[2] / f.crlb[2] - 2.0).abs() < 1e-9);
        // the cross's radius is where |Sx| peaks along x
        let r = design_radius(&tpl, 1.0).unwrap();
        let v = |x: f64| tpl.eval(x, 0.0)[0].abs();
        assert!(
            v(r[0]) >= v(r[0] - 0.01) && v(r[0]) >= v(r[0] + 0.01),
            "{r:?}"
        );
        // too few readings
        let e = fit_bead_points(&tpl, &pts[..2], [0.0, 0.0, 1.0], None, true)
            .unwrap_err()
            .to_string();
        assert!(e.contains("2 readings give 4 values"), "{e}");
    }
}
