//! The fit's Levenberg–Marquardt solver on the normal equations (Moré 1978, "The
//! Levenberg–Marquardt algorithm: implementation and theory", Lecture Notes in Math. 630;
//! MINPACK's `lmder` stopping tests; Nielsen's damping update, IMM-REP-1999-05).
//!
//! Why our own and not the `levenberg-marquardt` crate (the design card's choice, kept as a
//! dev-dependency oracle): the crate works on the M × N Jacobian (QR per iteration), while the
//! bead fit's JᵀJ, Jᵀr and ‖r‖² are accumulated tile by tile without ever forming J; solving
//! the N × N damped normal equations by a profile-skipping Cholesky saved a measured 13 % of
//! fit time (docs/analysis.md). The price is that this solver must be tested at least as well
//! as the crate is: the unit tests below run it on standard problems with known minima
//! (Moré, Garbow & Hillstrom 1981, ACM TOMS 7, 17: Rosenbrock, Powell singular, Osborne 1 and
//! the rank-1 linear function), `solve_damped` against nalgebra's Cholesky, and
//! tests/fit_oracle.rs fits random bead scenes with both solvers.
//!
//! No I/O, no knowledge of beads: a problem is a closure giving (‖r‖², JᵀJ, Jᵀr) at p.

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// How the optimiser stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FitStatus {
    /// ftol/xtol/gtol met or residuals zero.
    Converged,
    /// Evaluation budget (patience) exhausted.
    MaxEvaluations,
    /// Numerical failure or tolerances below machine precision (see `reason`).
    Failed,
}

/// What one run of [`levenberg_marquardt`] gives.
#[derive(Debug, Clone)]
pub struct RawFit {
    pub p: Vec<f64>,
    pub status: FitStatus,
    pub reason: String,
    /// Accepted points, the initial one included.
    pub iterations: usize,
    /// Evaluations of the problem (trial steps included).
    pub evaluations: usize,
    /// RSS and JᵀJ at `p` (the last accepted evaluation).
    pub rss: f64,
    pub jtj: DMatrix<f64>,
}

/// The stopping tests' tolerances (MINPACK's meaning) and the evaluation budget.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tolerances {
    /// Relative reduction of the RSS, actual and predicted.
    pub ftol: f64,
    /// Relative step, ‖Dδ‖ ≤ xtol·‖Dp‖.
    pub xtol: f64,
    /// Cosine between the residuals and any column of J.
    pub gtol: f64,
    /// Evaluations allowed = patience × (n + 1).
    pub patience: usize,
}

/// Condition number of D⁻¹AD⁻¹ with D = √diag(A) (1e300 when singular).
pub fn scaled_condition(a: &DMatrix<f64>) -> f64 {
    let n = a.nrows();
    if n == 0 {
        return 1.0;
    }
    let d: Vec<f64> = (0..n).map(|i| a[(i, i)].max(0.0).sqrt()).collect();
    if d.iter().any(|&v| !(v > 0.0)) {
        return 1e300;
    }
    let s = DMatrix::from_fn(n, n, |i, j| a[(i, j)] / (d[i] * d[j]));
    let ev = s.symmetric_eigenvalues();
    let (lo, hi) = ev
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    if !(lo > 0.0) || !hi.is_finite() {
        1e300
    } else {
        (hi / lo).min(1e300)
    }
}

/// Levenberg–Marquardt on the normal equations: minimise ‖r(p)‖² given, at any p, the
/// Gauss–Newton matrix A = JᵀJ, the gradient g = Jᵀr and the RSS ‖r‖² (`eval`; a non-finite
/// RSS or A means the point is refused). Each step solves
/// (A + λ·D²) δ = −g by a Cholesky factorisation ([`solve_damped`]), with Moré's scaling
/// Dⱼ = max over the iterates of √Aⱼⱼ (the column norms of J; 1 for a column that has always been
/// zero). The step is accepted when its gain ratio ρ = actual / predicted reduction of the RSS is
/// at least 1e-4; then λ ← λ·max(1/3, 1 − (2ρ − 1)³), else λ ← λ·ν, ν ← 2ν (Nielsen's rule,
/// λ₀ = 1e-3, i.e. the first step is nearly Gauss–Newton). The stopping tests are MINPACK's
/// (`lmder`, the ones the `levenberg-marquardt` crate used before):
/// - gtol: maxⱼ |gⱼ| / (√Aⱼⱼ ‖r‖) ≤ gtol at an accepted point (gradient orthogonal to the
///   residuals);
/// - ftol: the relative actual reduction 1 − ‖r₊‖²/‖r‖² and the predicted one
///   (δᵀAδ + 2λ‖Dδ‖²)/‖r‖² both ≤ ftol (and ρ ≤ 2);
/// - xtol: ‖Dδ‖ ≤ xtol·‖Dp‖;
/// - residuals exactly zero;
/// - the evaluation budget patience × (n + 1);
/// - the same tests at machine precision when the tolerances are below it: `Failed`, "no
///   further improvement possible".
///
/// One evaluation per trial step; the last accepted one is returned with the result (RSS and A at
/// the solution, for the statistics). `iterations` counts accepted points (including the
/// initial one).
pub fn levenberg_marquardt(
    mut eval: impl FnMut(&[f64]) -> (f64, DMatrix<f64>, DVector<f64>),
    mut p: Vec<f64>,
    opts: &Tolerances,
) -> RawFit {
    let n = p.len();
    let max_eval = opts.patience.saturating_mul(n + 1);
    let finite = |rss: f64, a: &DMatrix<f64>, g: &DVector<f64>| {
        rss.is_finite() && a.iter().all(|v| v.is_finite()) && g.iter().all(|v| v.is_finite())
    };
    let (mut rss, mut a, mut g) = eval(&p);
    let (mut nres, mut njac) = (1usize, 1usize);
    let done = |p: Vec<f64>, status, reason: String, njac, nres, rss, jtj| RawFit {
        p,
        status,
        reason,
        iterations: njac,
        evaluations: nres,
        rss,
        jtj,
    };
    if !finite(rss, &a, &g) {
        return done(
            p,
            FitStatus::Failed,
            "non-finite residuals or Jacobian at the initial parameters".into(),
            njac,
            nres,
            rss,
            a,
        );
    }
    let mut dscale = vec![0.0f64; n];
    let mut lambda = 1e-3;
    let mut nu = 2.0;
    loop {
        // Moré's scaling and the gradient test at the accepted point.
        let fnorm = rss.sqrt();
        if rss == 0.0 {
            return done(
                p,
                FitStatus::Converged,
                "residuals are zero".into(),
                njac,
                nres,
                rss,
                a,
            );
        }
        let mut gnorm = 0.0f64;
        for j in 0..n {
            let c = a[(j, j)].max(0.0).sqrt();
            if c > 0.0 {
                gnorm = gnorm.max(g[j].abs() / (c * fnorm));
            }
            dscale[j] = dscale[j].max(c);
            if dscale[j] == 0.0 {
                dscale[j] = 1.0;
            }
        }
        if let Some((status, reason)) = gradient_stop(gnorm, opts) {
            return done(p, status, reason, njac, nres, rss, a);
        }
        let d2: Vec<f64> = dscale.iter().map(|d| d * d).collect();
        let xnorm = scaled_norm(&p, &dscale);
        // Trial steps until one is accepted or a test stops.
        loop {
            let Some(delta) = solve_damped(&a, lambda, &d2, &g) else {
                // Not positive definite to rounding: more damping, no evaluation spent.
                lambda = (lambda * nu).max(1e-12);
                nu *= 2.0;
                if !(lambda < 1e300) {
                    return done(
                        p,
                        FitStatus::Failed,
                        "the damped normal equations could not be factorised".into(),
                        njac,
                        nres,
                        rss,
                        a,
                    );
                }
                continue;
            };
            let pnorm = scaled_norm(&delta, &dscale);
            let trial: Vec<f64> = p.iter().zip(&delta).map(|(x, d)| x + d).collect();
            let (rss1, a1, g1) = eval(&trial);
            nres += 1;
            let ok = finite(rss1, &a1, &g1);
            let actred = if ok && 0.1 * rss1.sqrt() < fnorm {
                1.0 - rss1 / rss
            } else {
                -1.0
            };
            let prered = predicted_reduction(&a, &delta, lambda, pnorm, rss);
            let ratio = if prered != 0.0 { actred / prered } else { 0.0 };
            let accepted = ratio >= 1e-4;
            if accepted {
                p = trial;
                (rss, a, g) = (rss1, a1, g1);
                njac += 1;
                lambda *= (1.0 - (2.0 * ratio - 1.0).powi(3)).max(1.0 / 3.0);
                nu = 2.0;
            } else {
                lambda *= nu;
                nu *= 2.0;
            }
            let trial = Trial {
                actred,
                prered,
                ratio,
                pnorm,
                xnorm,
                nres,
                max_eval,
            };
            if let Some((status, reason)) = trial.stop(opts) {
                return done(p, status, reason, njac, nres, rss, a);
            }
            if accepted {
                break;
            }
        }
    }
}

/// The gradient test at an accepted point: converged when the gradient is orthogonal to the
/// residuals within `gtol`, failed when that tolerance is below machine precision.
fn gradient_stop(gnorm: f64, opts: &Tolerances) -> Option<(FitStatus, String)> {
    if gnorm <= opts.gtol {
        return Some((
            FitStatus::Converged,
            "converged (gradient orthogonal to residuals, gtol)".into(),
        ));
    }
    if gnorm <= f64::EPSILON {
        return Some((
            FitStatus::Failed,
            "no further improvement possible: gtol is below machine precision".into(),
        ));
    }
    None
}

/// Predicted relative reduction of a step δ that solves the damped system:
/// (δᵀAδ + 2λ‖Dδ‖²)/‖r‖² (`pnorm` = ‖Dδ‖, `rss` = ‖r‖²).
fn predicted_reduction(a: &DMatrix<f64>, delta: &[f64], lambda: f64, pnorm: f64, rss: f64) -> f64 {
    let n = delta.len();
    let mut dad = 0.0;
    for i in 0..n {
        let mut s = 0.0;
        for j in 0..n {
            s += a[(i, j)] * delta[j];
        }
        dad += delta[i] * s;
    }
    (dad.max(0.0) + 2.0 * lambda * pnorm * pnorm) / rss
}

/// One trial step's numbers, for the stopping tests.
#[derive(Clone, Copy)]
struct Trial {
    /// Actual and predicted relative reduction of ‖r‖², and their ratio.
    actred: f64,
    prered: f64,
    ratio: f64,
    /// Scaled step and parameter norms.
    pnorm: f64,
    xnorm: f64,
    /// Evaluations so far and the budget.
    nres: usize,
    max_eval: usize,
}

impl Trial {
    /// MINPACK's tests after a trial step, in its order: ftol/xtol met (converged), the
    /// evaluation budget spent, then either tolerance below machine precision (failed).
    fn stop(&self, opts: &Tolerances) -> Option<(FitStatus, String)> {
        let eps = f64::EPSILON;
        let (actred, prered, ratio) = (self.actred, self.prered, self.ratio);
        let (pnorm, xnorm, nres) = (self.pnorm, self.xnorm, self.nres);
        let ftol_met = actred.abs() <= opts.ftol && prered <= opts.ftol && 0.5 * ratio <= 1.0;
        let xtol_met = pnorm <= opts.xtol * xnorm;
        if ftol_met || xtol_met {
            return Some((
                FitStatus::Converged,
                format!("converged (ftol: {ftol_met}, xtol: {xtol_met})"),
            ));
        }
        if nres >= self.max_eval {
            return Some((
                FitStatus::MaxEvaluations,
                format!("evaluation budget exhausted ({nres} evaluations)"),
            ));
        }
        if actred.abs() <= eps && prered <= eps && 0.5 * ratio <= 1.0 {
            return Some((
                FitStatus::Failed,
                "no further improvement possible: ftol is below machine precision".into(),
            ));
        }
        if pnorm <= eps * xnorm {
            return Some((
                FitStatus::Failed,
                "no further improvement possible: xtol is below machine precision".into(),
            ));
        }
        None
    }
}

/// δ solving (A + λ·diag(d2)) δ = −g for a symmetric A, by a Cholesky factorisation that skips
/// the leading zeros of each row (JᵀJ is block-sparse: a row's profile starts at the first bead
/// its bead's window overlaps, and the factor keeps that profile). None when the matrix is not
/// positive definite to rounding or the solution is not finite.
pub fn solve_damped(
    a: &DMatrix<f64>,
    lambda: f64,
    d2: &[f64],
    g: &DVector<f64>,
) -> Option<Vec<f64>> {
    let n = a.nrows();
    // A is symmetric: its column-major storage read row-major is A itself.
    let s = a.as_slice();
    let first: Vec<usize> = (0..n)
        .map(|i| (0..i).find(|&j| s[i * n + j] != 0.0).unwrap_or(i))
        .collect();
    let mut l = vec![0.0; n * n];
    for i in 0..n {
        let fi = first[i];
        for j in fi..=i {
            let lo = fi.max(first[j]);
            let (ri, rj) = (&l[i * n + lo..i * n + j], &l[j * n + lo..j * n + j]);
            let dot: f64 = ri.iter().zip(rj).map(|(x, y)| x * y).sum();
            let mut v = s[i * n + j] - dot;
            if i == j {
                v += lambda * d2[i];
                if !(v > 0.0) {
                    return None;
                }
                l[i * n + i] = v.sqrt();
            } else {
                l[i * n + j] = v / l[j * n + j];
            }
        }
    }
    // L y = −g, then Lᵀ δ = y.
    let mut y = vec![0.0; n];
    for i in 0..n {
        let fi = first[i];
        let dot: f64 = l[i * n + fi..i * n + i]
            .iter()
            .zip(&y[fi..i])
            .map(|(x, y)| x * y)
            .sum();
        y[i] = (-g[i] - dot) / l[i * n + i];
    }
    for i in (0..n).rev() {
        y[i] /= l[i * n + i];
        let yi = y[i];
        for k in first[i]..i {
            y[k] -= l[i * n + k] * yi;
        }
    }
    y.iter().all(|v| v.is_finite()).then_some(y)
}

/// ‖D·v‖₂, the scaled norm of MINPACK's `lmder` (D = diag(`dscale`)).
fn scaled_norm(v: &[f64], dscale: &[f64]) -> f64 {
    v.iter()
        .zip(dscale)
        .map(|(x, d)| (x * d).powi(2))
        .sum::<f64>()
        .sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    type Resid = fn(&[f64]) -> (Vec<f64>, DMatrix<f64>);

    /// (‖r‖², JᵀJ, Jᵀr) of a residual function with its analytic Jacobian.
    fn normal_eq(f: Resid) -> impl FnMut(&[f64]) -> (f64, DMatrix<f64>, DVector<f64>) {
        move |p| {
            let (r, j) = f(p);
            let r = DVector::from_vec(r);
            (r.norm_squared(), j.transpose() * &j, j.transpose() * &r)
        }
    }

    fn tight(patience: usize) -> Tolerances {
        Tolerances {
            ftol: 1e-15,
            xtol: 1e-15,
            gtol: 0.0,
            patience,
        }
    }

    /// MGH problem 1, Rosenbrock: r = (10(x₂ − x₁²), 1 − x₁), from (−1.2, 1); minimum 0 at (1, 1).
    fn rosenbrock(p: &[f64]) -> (Vec<f64>, DMatrix<f64>) {
        let (x1, x2) = (p[0], p[1]);
        (
            vec![10.0 * (x2 - x1 * x1), 1.0 - x1],
            DMatrix::from_row_slice(2, 2, &[-20.0 * x1, 10.0, -1.0, 0.0]),
        )
    }

    #[test]
    fn rosenbrock_reaches_its_minimum() {
        let r = levenberg_marquardt(normal_eq(rosenbrock), vec![-1.2, 1.0], &tight(100));
        assert_ne!(r.status, FitStatus::MaxEvaluations, "{}", r.reason);
        assert!(
            (r.p[0] - 1.0).abs() < 1e-10 && (r.p[1] - 1.0).abs() < 1e-10,
            "{:?}",
            r.p
        );
        assert!(r.rss < 1e-24, "{}", r.rss);
        // MINPACK's lmder needs 16 Jacobians and 21 evaluations from this start; a solver that
        // wandered would need far more
        assert!(r.evaluations <= 40, "{} evaluations", r.evaluations);
    }

    /// MGH problem 13, Powell singular: r = (x₁ + 10x₂, √5(x₃ − x₄), (x₂ − 2x₃)², √10(x₁ − x₄)²)
    /// from (3, −1, 0, 1); minimum 0 at the origin, where J is singular (rank 2): the
    /// convergence is only linear there, the test is that the solver gets there at all.
    fn powell_singular(p: &[f64]) -> (Vec<f64>, DMatrix<f64>) {
        let (x1, x2, x3, x4) = (p[0], p[1], p[2], p[3]);
        let (s5, s10) = (5f64.sqrt(), 10f64.sqrt());
        (
            vec![
                x1 + 10.0 * x2,
                s5 * (x3 - x4),
                (x2 - 2.0 * x3).powi(2),
                s10 * (x1 - x4).powi(2),
            ],
            DMatrix::from_row_slice(
                4,
                4,
                &[
                    1.0,
                    10.0,
                    0.0,
                    0.0,
                    0.0,
                    0.0,
                    s5,
                    -s5,
                    0.0,
                    2.0 * (x2 - 2.0 * x3),
                    -4.0 * (x2 - 2.0 * x3),
                    0.0,
                    2.0 * s10 * (x1 - x4),
                    0.0,
                    0.0,
                    -2.0 * s10 * (x1 - x4),
                ],
            ),
        )
    }

    #[test]
    fn powell_singular_reaches_the_singular_minimum() {
        let r = levenberg_marquardt(
            normal_eq(powell_singular),
            vec![3.0, -1.0, 0.0, 1.0],
            &tight(200),
        );
        assert!(
            r.p.iter().all(|v| v.abs() < 1e-4),
            "{:?} ({})",
            r.p,
            r.reason
        );
        assert!(r.rss < 1e-16, "{} ({})", r.rss, r.reason);
    }

    /// MGH problem 17, Osborne 1: y = x₁ + x₂e^(−t x₄) + x₃e^(−t x₅), t = 10(i − 1), 33 points;
    /// from (0.5, 1.5, −1, 0.01, 0.02); minimum ‖r‖² = 5.46489e-5.
    const OSBORNE1_Y: [f64; 33] = [
        0.844, 0.908, 0.932, 0.936, 0.925, 0.908, 0.881, 0.850, 0.818, 0.784, 0.751, 0.718, 0.685,
        0.658, 0.628, 0.603, 0.580, 0.558, 0.538, 0.522, 0.506, 0.490, 0.478, 0.467, 0.457, 0.448,
        0.438, 0.431, 0.424, 0.420, 0.414, 0.411, 0.406,
    ];

    fn osborne1(p: &[f64]) -> (Vec<f64>, DMatrix<f64>) {
        let mut r = vec![0.0; 33];
        let mut j = DMatrix::zeros(33, 5);
        for (i, y) in OSBORNE1_Y.iter().enumerate() {
            let t = 10.0 * i as f64;
            let (e4, e5) = ((-t * p[3]).exp(), (-t * p[4]).exp());
            r[i] = p[0] + p[1] * e4 + p[2] * e5 - y;
            j[(i, 0)] = 1.0;
            j[(i, 1)] = e4;
            j[(i, 2)] = e5;
            j[(i, 3)] = -t * p[1] * e4;
            j[(i, 4)] = -t * p[2] * e5;
        }
        (r, j)
    }

    #[test]
    fn osborne1_reaches_the_published_minimum() {
        let r = levenberg_marquardt(
            normal_eq(osborne1),
            vec![0.5, 1.5, -1.0, 0.01, 0.02],
            &tight(200),
        );
        // MGH: f = 5.46489e-5 (six digits published)
        assert!(
            (r.rss / 5.46489e-5 - 1.0).abs() < 1e-5,
            "{} ({})",
            r.rss,
            r.reason
        );
        // the minimiser (0.3754, 1.9358, −1.4647, 0.01287, 0.02212), to its printed digits
        for (v, want, tol) in [
            (r.p[0], 0.3754, 1e-4),
            (r.p[1], 1.9358, 1e-4),
            (r.p[2], -1.4647, 1e-4),
            (r.p[3], 0.01287, 1e-5),
            (r.p[4], 0.02212, 1e-5),
        ] {
            assert!((v - want).abs() < tol, "{:?}", r.p);
        }
    }

    /// MGH problem 33, linear function of rank 1: rᵢ = i·Σⱼ j·xⱼ − 1, i = 1…m, n = 5, m = 10. J
    /// has rank 1 everywhere (JᵀJ singular): every step needs the damping. Minimum
    /// ‖r‖² = m(m − 1)/(2(2m + 1)) on the hyperplane Σⱼ j·xⱼ = 3/(2m + 1).
    fn linear_rank1(p: &[f64]) -> (Vec<f64>, DMatrix<f64>) {
        let (m, n) = (10, 5);
        let s: f64 = (0..n).map(|j| (j + 1) as f64 * p[j]).sum();
        let r = (0..m).map(|i| (i + 1) as f64 * s - 1.0).collect();
        let j = DMatrix::from_fn(m, n, |i, j| ((i + 1) * (j + 1)) as f64);
        (r, j)
    }

    #[test]
    fn rank_deficient_linear_function_reaches_its_minimum() {
        let r = levenberg_marquardt(normal_eq(linear_rank1), vec![1.0; 5], &tight(100));
        let m = 10.0;
        let fmin = m * (m - 1.0) / (2.0 * (2.0 * m + 1.0));
        assert!(
            (r.rss / fmin - 1.0).abs() < 1e-12,
            "{} vs {fmin} ({})",
            r.rss,
            r.reason
        );
        let s: f64 =
            r.p.iter()
                .enumerate()
                .map(|(j, x)| (j + 1) as f64 * x)
                .sum();
        // on the minimum's hyperplane: near it ‖r‖² grows by Σᵢ i²·Δs² = 385·Δs², so ftol's
        // 1e-15 relative reduction (of ‖r‖² = 2.14) leaves Δs up to √(2.14e-15/385) ≈ 2.4e-9
        assert!((s - 3.0 / (2.0 * m + 1.0)).abs() < 1e-8, "{s}");
        assert!(r.p.iter().all(|v| v.is_finite()));
        // the rank shows in the condition number of the scaled JᵀJ
        assert!(
            scaled_condition(&r.jtj) > 1e12,
            "{}",
            scaled_condition(&r.jtj)
        );
    }

    #[test]
    fn budget_and_nonfinite_starts_are_reported() {
        let r = levenberg_marquardt(normal_eq(rosenbrock), vec![-1.2, 1.0], &tight(1));
        assert_eq!(r.status, FitStatus::MaxEvaluations);
        assert_eq!(r.evaluations, 3, "patience 1 × (n + 1) evaluations");
        let r = levenberg_marquardt(normal_eq(rosenbrock), vec![f64::NAN, 1.0], &tight(10));
        assert_eq!(r.status, FitStatus::Failed);
        assert_eq!(
            r.reason,
            "non-finite residuals or Jacobian at the initial parameters"
        );
    }

    /// A symmetric positive semi-definite matrix with the bead fit's block profile: 3 × 3
    /// blocks, each coupled only to its neighbours (leading zeros in every row), from a seeded
    /// LCG.
    fn banded_spd(nb: usize, seed: u64) -> DMatrix<f64> {
        let mut s = seed;
        let mut rnd = move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let n = 3 * nb;
        // J with 8 rows per bead touching its own block and the next one
        let m = 8 * nb;
        let mut j = DMatrix::zeros(m, n);
        for b in 0..nb {
            for r in 0..8 {
                for c in 3 * b..(3 * b + 6).min(n) {
                    j[(8 * b + r, c)] = rnd();
                }
            }
        }
        j.transpose() * j
    }

    #[test]
    fn solve_damped_equals_nalgebra_cholesky() {
        for (nb, seed) in [(1, 1), (4, 2), (13, 3), (40, 4)] {
            let a = banded_spd(nb, seed);
            let n = a.nrows();
            let d2: Vec<f64> = (0..n).map(|i| a[(i, i)]).collect();
            let g = DVector::from_fn(n, |i, _| ((i * 7919) % 13) as f64 - 6.0);
            for lambda in [0.0, 1e-3, 1.0, 1e3] {
                let ours = solve_damped(&a, lambda, &d2, &g).expect("positive definite");
                let mut m = a.clone();
                for i in 0..n {
                    m[(i, i)] += lambda * d2[i];
                }
                let want = m.cholesky().expect("SPD").solve(&(-&g));
                let scale = want.amax();
                for i in 0..n {
                    assert!(
                        (ours[i] - want[i]).abs() <= 1e-9 * scale,
                        "nb {nb}, λ {lambda}, i {i}: {} vs {}",
                        ours[i],
                        want[i]
                    );
                }
            }
        }
        // singular without damping: refused, not a wild step
        let mut a = banded_spd(2, 9);
        for k in 0..6 {
            a[(0, k)] = 0.0;
            a[(k, 0)] = 0.0;
        }
        let g = DVector::from_element(6, 1.0);
        assert!(solve_damped(&a, 0.0, &[1.0; 6], &g).is_none());
        assert!(solve_damped(&a, 1e-6, &[1.0; 6], &g).is_some());
    }
}
