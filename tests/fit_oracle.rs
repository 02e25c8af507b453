//! The fit's own Levenberg–Marquardt solver (analysis/fit/lm.rs) against the
//! `levenberg-marquardt` crate, the design card's solver kept as an oracle: on random bead scenes
//! (1–4 beads of random weight and position, detector noise), both minimise the same objective
//! (`full_jacobian`'s residuals, equal to the fit's accumulated normal equations to 1e-10:
//! fit.rs `compressed_problem_matches_full_normal_equations`) from the same start and must
//! reach the same minimum.

use bfpscope::analysis::fit::{fit_beads, full_jacobian, BeadInit, Channels, FitOptions};
use bfpscope::analysis::Template;
use bfpscope::data::Image;
use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{DMatrix, DVector, Dyn, Owned};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The bead fit as the crate sees it: residuals and Jacobian over every valid pixel.
struct BeadProblem<'a> {
    sx: &'a Image,
    sy: &'a Image,
    tpl: &'a Template,
    p: DVector<f64>,
}

impl BeadProblem<'_> {
    fn beads(&self) -> Vec<BeadInit> {
        self.p
            .as_slice()
            .chunks(3)
            .map(|c| BeadInit {
                weight: c[0],
                x: c[1],
                y: c[2],
            })
            .collect()
    }
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for BeadProblem<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.p.copy_from(x);
    }
    fn params(&self) -> DVector<f64> {
        self.p.clone()
    }
    fn residuals(&self) -> Option<DVector<f64>> {
        full_jacobian(self.sx, self.sy, self.tpl, &self.beads(), Channels::Both)
            .ok()
            .map(|(r, _)| r)
    }
    fn jacobian(&self) -> Option<DMatrix<f64>> {
        full_jacobian(self.sx, self.sy, self.tpl, &self.beads(), Channels::Both)
            .ok()
            .map(|(_, j)| j)
    }
}

#[test]
fn own_solver_and_crate_reach_the_same_minimum_on_random_bead_scenes() {
    let tpl = Template::analytic_standin(0.4, 0.02, 1.6).unwrap();
    let x: Vec<f64> = (0..48).map(|i| i as f64 * 0.05).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(20261127);
    for scene in 0..6 {
        let n = 1 + scene % 4;
        // beads at least 0.5 µm apart (resolved: no degeneracy handling in play)
        let mut truth: Vec<(f64, f64, f64)> = vec![];
        while truth.len() < n {
            let b = (
                rng.random_range(0.5..1.85),
                rng.random_range(0.5..1.85),
                rng.random_range(0.5..2.0),
            );
            if truth.iter().all(|t| (t.0 - b.0).hypot(t.1 - b.1) > 0.5) {
                truth.push(b);
            }
        }
        let [mut sx, mut sy, _] = tpl.render(&truth, &x, &x);
        let peak = sx.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for v in sx.iter_mut().chain(sy.iter_mut()) {
            *v += 0.02 * peak * (rng.random::<f64>() - 0.5);
        }
        let (sx, sy) = (
            Image::new(sx, x.clone(), x.clone()),
            Image::new(sy, x.clone(), x.clone()),
        );
        let init: Vec<BeadInit> = truth
            .iter()
            .map(|&(bx, by, w)| BeadInit {
                x: bx + 0.03,
                y: by - 0.02,
                weight: w * 0.9,
            })
            .collect();
        let ours = fit_beads(
            &sx,
            &sy,
            &tpl,
            &FitOptions {
                init: Some(init.clone()),
                ftol: 1e-14,
                xtol: 1e-14,
                gtol: 0.0,
                merge_degenerate: false,
                resolve_separation: 0.0,
                ..FitOptions::default()
            },
        )
        .unwrap();
        let p0: Vec<f64> = init.iter().flat_map(|b| [b.weight, b.x, b.y]).collect();
        let (solved, report) = LevenbergMarquardt::new()
            .with_ftol(1e-14)
            .with_xtol(1e-14)
            .with_gtol(0.0)
            .minimize(BeadProblem {
                sx: &sx,
                sy: &sy,
                tpl: &tpl,
                p: DVector::from_vec(p0),
            });
        assert!(
            report.termination.was_successful(),
            "scene {scene}: the crate stopped with {:?}",
            report.termination
        );
        // the same objective value (the crate reports ½‖r‖²) ...
        let rss_crate = 2.0 * report.objective_function;
        assert!(
            (ours.rss / rss_crate - 1.0).abs() < 1e-9,
            "scene {scene}: RSS {} (ours) vs {rss_crate} (crate)",
            ours.rss
        );
        // ... at the same parameters: far inside each parameter's 1σ (a thousandth of it)
        assert_eq!(ours.beads.len(), n);
        for (i, b) in ours.beads.iter().enumerate() {
            let c = &solved.p.as_slice()[3 * i..3 * i + 3];
            for (name, a, o, s) in [
                ("weight", b.weight, c[0], b.weight_err.unwrap()),
                ("x", b.x, c[1], b.x_err.unwrap()),
                ("y", b.y, c[2], b.y_err.unwrap()),
            ] {
                assert!(
                    (a - o).abs() < 1e-3 * s,
                    "scene {scene}, bead {i}: {name} {a} (ours) vs {o} (crate), σ {s}"
                );
            }
        }
    }
}
