//! The degeneracy policy of the bead fit: one LM run, then the checks that a converged fit
//! is not degenerate (beads merged when closer than `min_separation`·w0, beads out of reach
//! dropped, the condition of JᵀJ, weights absorbing each other) and the statistics (see the
//! parent module's docs). The numerics are in `normal.rs`.

use super::super::{AnalysisError, Result};
use super::lm::{levenberg_marquardt, scaled_condition, RawFit, Tolerances};
use super::problem::FitData;
use super::types::*;
use crate::data::Image;
use ndarray::Array2;

impl FitData<'_> {
    /// One LM run from `init` (see [`levenberg_marquardt`]).
    pub(super) fn run_lm(&self, init: &[BeadInit], opts: &FitOptions) -> Result<RawFit> {
        let x0: Vec<f64> = init.iter().flat_map(|b| [b.weight, b.x, b.y]).collect();
        let tol = Tolerances {
            ftol: opts.ftol,
            xtol: opts.xtol,
            gtol: opts.gtol,
            patience: opts.patience,
        };
        let raw = levenberg_marquardt(|p| self.accumulate(p), x0, &tol);
        if raw.p.iter().any(|v| !v.is_finite()) {
            return Err(AnalysisError::Failed(format!(
                "the optimiser returned non-finite parameters ({})",
                raw.reason
            )));
        }
        Ok(raw)
    }

    /// LM fit with all degeneracy checks (see the module docs).
    pub(super) fn fit_with_degeneracy(
        &self,
        init: Vec<BeadInit>,
        opts: &FitOptions,
    ) -> Result<FitResult> {
        let mut res = self.fit_merge_close(init, opts, Vec::new())?;
        let lim = opts.resolve_separation * self.w0;
        'outer: while opts.merge_degenerate && lim > 0.0 && res.beads.len() > 1 {
            let b = &res.beads;
            let mut pairs: Vec<(usize, usize, f64)> = Vec::new();
            for i in 0..b.len() {
                for j in i + 1..b.len() {
                    let d = (b[i].x - b[j].x).hypot(b[i].y - b[j].y);
                    if d < lim {
                        pairs.push((i, j, d));
                    }
                }
            }
            pairs.sort_by(|a, b| a.2.total_cmp(&b.2));
            for (i, j, d) in pairs {
                let (a, c) = (b[i], b[j]);
                let mut init: Vec<BeadInit> = b
                    .iter()
                    .enumerate()
                    .filter(|(k, _)| *k != i && *k != j)
                    .map(|(_, x)| BeadInit {
                        x: x.x,
                        y: x.y,
                        weight: x.weight,
                    })
                    .collect();
                init.push(merge_pair(
                    BeadInit {
                        x: a.x,
                        y: a.y,
                        weight: a.weight,
                    },
                    BeadInit {
                        x: c.x,
                        y: c.y,
                        weight: c.weight,
                    },
                ));
                let mut deg = res.degeneracies.clone();
                let alt0 = self.fit_merge_close(init, opts, Vec::new())?;
                if alt0.bic <= res.bic || a.insignificant() || c.insignificant() {
                    deg.push(Degeneracy::Unresolved {
                        a: [a.x, a.y, a.weight],
                        b: [c.x, c.y, c.weight],
                        distance_um: d,
                        delta_bic: res.bic - alt0.bic,
                    });
                    deg.extend(alt0.degeneracies.iter().cloned());
                    let total = res.total_evaluations + alt0.total_evaluations;
                    res = alt0;
                    res.degeneracies = deg;
                    res.total_evaluations = total;
                    continue 'outer;
                }
            }
            break;
        }
        // Weights consistent with zero.
        let extra: Vec<Degeneracy> = res
            .beads
            .iter()
            .filter(|b| b.insignificant())
            .map(|b| Degeneracy::Insignificant {
                x: b.x,
                y: b.y,
                weight: b.weight,
                weight_err: b.weight_err,
            })
            .collect();
        res.degeneracies.extend(extra);
        Ok(res)
    }

    /// LM fit with merging of pairs closer than min_separation·w0 and dropping of beads out of
    /// reach, then the statistics.
    pub(super) fn fit_merge_close(
        &self,
        init: Vec<BeadInit>,
        opts: &FitOptions,
        mut degeneracies: Vec<Degeneracy>,
    ) -> Result<FitResult> {
        let mut beads = init;
        let mut total_eval = 0;
        let mut raw;
        loop {
            raw = self.run_lm(&beads, opts)?;
            total_eval += raw.evaluations;
            let cur: Vec<BeadInit> = raw
                .p
                .chunks(3)
                .map(|b| BeadInit {
                    weight: b[0],
                    x: b[1],
                    y: b[2],
                })
                .collect();
            // Beads out of reach.
            let (keep, gone): (Vec<BeadInit>, Vec<BeadInit>) =
                cur.iter().partition(|b| self.reaches(b.x, b.y));
            if !gone.is_empty() && !keep.is_empty() {
                for b in &gone {
                    degeneracies.push(Degeneracy::BeadOutside {
                        x: b.x,
                        y: b.y,
                        weight: b.weight,
                    });
                }
                beads = keep;
                continue;
            }
            if let Some((i, j, d)) = closest_pair(&cur, self.min_sep) {
                let (a, b) = (cur[i], cur[j]);
                degeneracies.push(Degeneracy::CloseBeads {
                    a: [a.x, a.y, a.weight],
                    b: [b.x, b.y, b.weight],
                    distance_um: d,
                    merged: opts.merge_degenerate,
                });
                if opts.merge_degenerate {
                    let merged = merge_pair(a, b);
                    let mut next: Vec<BeadInit> = cur
                        .iter()
                        .enumerate()
                        .filter(|(k, _)| *k != i && *k != j)
                        .map(|(_, b)| *b)
                        .collect();
                    next.push(merged);
                    beads = next;
                    continue;
                }
            }
            break;
        }
        // Statistics at the solution.
        let p = &raw.p;
        let nb = p.len() / 3;
        // The optimiser's last accepted evaluation is the one at the solution.
        let (rss, jtj) = (raw.rss, &raw.jtj);
        let np = p.len();
        let dof = self.m.saturating_sub(np);
        let (sigma, est) = match opts.sigma {
            Some(s) => (s, false),
            None => ((rss / dof.max(1) as f64).sqrt(), true),
        };
        let chi2 = if sigma > 0.0 {
            rss / (sigma * sigma)
        } else {
            0.0
        };
        let mf = self.m as f64;
        let bic = match opts.sigma {
            Some(_) => chi2 + np as f64 * mf.ln(),
            None => mf * (rss.max(1e-300) / mf).ln() + np as f64 * mf.ln(),
        };
        // The condition number and the covariance are independent O(n³) steps: computed side by
        // side (the covariance is dropped if the problem is ill-conditioned).
        let (condition, cov) = rayon::join(
            || scaled_condition(jtj),
            || {
                jtj.clone()
                    .cholesky()
                    .map(|c| c.inverse() * (sigma * sigma))
            },
        );
        let ill = !(condition <= opts.cond_limit);
        if ill {
            degeneracies.push(Degeneracy::IllConditioned { condition });
        }
        let cov = if ill { None } else { cov };
        let beads_out: Vec<Bead> = (0..nb)
            .map(|i| {
                let e = |k: usize| {
                    cov.as_ref()
                        .map(|c| c[(3 * i + k, 3 * i + k)].max(0.0).sqrt())
                };
                Bead {
                    weight: p[3 * i],
                    x: p[3 * i + 1],
                    y: p[3 * i + 2],
                    weight_err: e(0),
                    x_err: e(1),
                    y_err: e(2),
                    x_crlb: None,
                    y_crlb: None,
                    weight_crlb: None,
                }
            })
            .collect();
        let [msx, msy] = self.model(p);
        let shape = msx.dim();
        let dsx = Array2::from_shape_vec(shape, self.ch_data[0].clone()).expect("shape");
        let dsy = Array2::from_shape_vec(shape, self.ch_data[1].clone()).expect("shape");
        let img = |a: Array2<f64>| Image::new(a, self.x.clone(), self.y.clone());
        Ok(FitResult {
            beads: beads_out,
            residual_sx: img(&dsx - &msx),
            residual_sy: img(&dsy - &msy),
            model_sx: img(msx),
            model_sy: img(msy),
            rss,
            chi2,
            dof,
            n_residuals: self.m,
            sigma,
            sigma_estimated: est,
            bic,
            iterations: raw.iterations,
            evaluations: raw.evaluations,
            total_evaluations: total_eval,
            status: raw.status,
            reason: raw.reason,
            condition,
            degeneracies,
            history: vec![],
            warnings: vec![],
            bead_warnings: vec![],
        })
    }
}

/// The closest pair of `beads` nearer than `min_sep` (µm): their indices and distance.
pub(crate) fn closest_pair(beads: &[BeadInit], min_sep: f64) -> Option<(usize, usize, f64)> {
    let mut pair: Option<(usize, usize, f64)> = None;
    for i in 0..beads.len() {
        for j in i + 1..beads.len() {
            let d = (beads[i].x - beads[j].x).hypot(beads[i].y - beads[j].y);
            if d < min_sep && pair.is_none_or(|p| d < p.2) {
                pair = Some((i, j, d));
            }
        }
    }
    pair
}
