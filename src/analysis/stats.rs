//! Statistics: histograms, summaries (mean/std/sem), weighted and unweighted straight-line fits
//! with parameter uncertainties (e.g. the log-log slope (∂Sx/∂x)max ∝ d^{3.02±0.04} of Fig. 3c,
//! the histogram of maximum sensitivities of Fig. 6d).
//!
//! NaN values are missing data: they are skipped and counted (`n_skipped`).

use super::{AnalysisError, Result};
use serde::{Deserialize, Serialize};

/// Summary statistics of the finite values.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    /// Number of finite values used.
    pub n: usize,
    /// Number of non-finite values skipped.
    pub n_skipped: usize,
    pub mean: f64,
    /// Sample standard deviation (n − 1 in the denominator); 0 for a single value.
    pub std: f64,
    /// Standard error of the mean, std/√n.
    pub sem: f64,
    pub min: f64,
    pub max: f64,
}

/// Mean, sample std, sem, min, max of the finite values. Error if there are none.
pub fn summary(values: &[f64]) -> Result<Summary> {
    let fin: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    let n = fin.len();
    if n == 0 {
        return Err(AnalysisError::BadInput {
            name: "values",
            reason: "no finite values".into(),
        });
    }
    let mean = fin.iter().sum::<f64>() / n as f64;
    let var = if n > 1 {
        fin.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64
    } else {
        0.0
    };
    let std = var.sqrt();
    Ok(Summary {
        n,
        n_skipped: values.len() - n,
        mean,
        std,
        sem: std / (n as f64).sqrt(),
        min: fin.iter().copied().fold(f64::INFINITY, f64::min),
        max: fin.iter().copied().fold(f64::NEG_INFINITY, f64::max),
    })
}

/// Median of the finite values (None if there are none).
pub fn median(values: &[f64]) -> Option<f64> {
    let mut v: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    })
}

/// The von Neumann ratio of a sequence and its z-score under independence: d = Σ (x_{i+1} −
/// x_i)² / Σ (x_i − x̄)² (von Neumann 1941, "Distribution of the ratio of the mean square
/// successive difference to the variance", Ann. Math. Stat. 12, 367; the Durbin–Watson statistic
/// of a constant). For n independent normal values E[d] = 2 and Var[d] = 4(n − 2)/((n − 1)(n +
/// 1)); a slow structure (a bump, a dip, a trend spanning several values) makes d small, z =
/// (d − 2)/√Var negative. Non-finite values are skipped; `None` below 3 values or when all are
/// equal (no spread to compare with).
pub fn von_neumann(values: &[f64]) -> Option<(f64, f64)> {
    let v: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    let n = v.len();
    if n < 3 {
        return None;
    }
    let mean = v.iter().sum::<f64>() / n as f64;
    let ss: f64 = v.iter().map(|x| (x - mean).powi(2)).sum();
    if ss <= 0.0 {
        return None;
    }
    let diff: f64 = v.windows(2).map(|w| (w[1] - w[0]).powi(2)).sum();
    let d = diff / ss;
    let nf = n as f64;
    let var = 4.0 * (nf - 2.0) / ((nf - 1.0) * (nf + 1.0));
    Some((d, (d - 2.0) / var.sqrt()))
}

/// Robust standard deviation: 1.4826 × median absolute deviation (σ for Gaussian data).
pub fn robust_std(values: &[f64]) -> Option<f64> {
    let m = median(values)?;
    let dev: Vec<f64> = values
        .iter()
        .filter(|v| v.is_finite())
        .map(|v| (v - m).abs())
        .collect();
    median(&dev).map(|d| 1.4826 * d)
}

/// A histogram: `counts[i]` values fell in `[edges[i], edges[i+1])` (the last bin is closed).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Histogram {
    /// `bins + 1` bin edges, increasing.
    pub edges: Vec<f64>,
    /// Values per bin; bin `k` is `[edges[k], edges[k+1])`, the last bin includes its right edge.
    pub counts: Vec<u64>,
    /// Finite values outside the range (only when a range was given).
    pub n_outside: usize,
    /// NaN values skipped (unmeasured pixels of an aborted scan are NaN).
    pub n_skipped: usize,
    /// All values were equal and no range was given: one bin centred on the value, 10 % of it
    /// wide (1 wide around 0), since finer bins would only show where the edges happen to fall.
    pub all_equal: bool,
}

impl Histogram {
    /// Bin centres.
    pub fn centres(&self) -> Vec<f64> {
        self.edges.windows(2).map(|w| 0.5 * (w[0] + w[1])).collect()
    }
    /// Number of values counted (NaN and outside excluded).
    pub fn count(&self) -> u64 {
        self.counts.iter().sum()
    }
}

/// Largest number of bins of a histogram.
pub const MAX_BINS: usize = 10_000;

/// The one histogram of the project (the `histogram` binding and `plot_hist` both use it):
/// `bins` (1..=[`MAX_BINS`]) equal bins over `range`, by default from the smallest to the largest
/// value. NaN values are skipped and counted; an infinite value is an error naming its index
/// (it has no bin, and dropping it would hide a bad input).
pub fn histogram(values: &[f64], bins: usize, range: Option<(f64, f64)>) -> Result<Histogram> {
    if !(1..=MAX_BINS).contains(&bins) {
        return Err(AnalysisError::OutOfRange {
            name: "bins",
            value: bins as f64,
            allowed: format!("1 ≤ bins ≤ {MAX_BINS}"),
        });
    }
    if let Some((k, v)) = values.iter().enumerate().find(|(_, v)| v.is_infinite()) {
        return Err(AnalysisError::BadInput {
            name: "values",
            reason: format!("values[{k}] = {v}: values must be finite (NaN is skipped)"),
        });
    }
    let fin: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    let n_skipped = values.len() - fin.len();
    let mut all_equal = false;
    let (lo, hi, bins) = match range {
        Some((lo, hi)) => {
            if !(lo.is_finite() && hi.is_finite() && hi > lo) {
                return Err(AnalysisError::BadInput {
                    name: "range",
                    reason: format!("[{lo}, {hi}] must be finite with hi > lo"),
                });
            }
            (lo, hi, bins)
        }
        None => {
            if fin.is_empty() {
                return Err(AnalysisError::BadInput {
                    name: "values",
                    reason: if values.is_empty() {
                        "no data (empty list)".into()
                    } else {
                        format!("all {} values are NaN", values.len())
                    },
                });
            }
            let lo = fin.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = fin.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            if hi > lo {
                (lo, hi, bins)
            } else {
                all_equal = true;
                let half = if lo == 0.0 { 0.5 } else { 0.05 * lo.abs() };
                (lo - half, lo + half, 1)
            }
        }
    };
    let w = (hi - lo) / bins as f64;
    let mut edges: Vec<f64> = (0..=bins).map(|i| lo + i as f64 * w).collect();
    edges[bins] = hi;
    let mut counts = vec![0u64; bins];
    let mut n_outside = 0;
    for v in fin {
        if v < lo || v > hi {
            n_outside += 1;
            continue;
        }
        let i = (((v - lo) / w).floor() as usize).min(bins - 1);
        counts[i] += 1;
    }
    Ok(Histogram {
        edges,
        counts,
        n_outside,
        n_skipped,
        all_equal,
    })
}

/// Straight-line fit y = intercept + slope·x.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LinFit {
    pub slope: f64,
    pub intercept: f64,
    /// 1σ uncertainties. Weighted fit: from the given σ_y (not rescaled); unweighted fit: from the
    /// scatter of the residuals (s² = Σr²/(n−2)); zero when n = 2.
    pub slope_err: f64,
    pub intercept_err: f64,
    /// Covariance of (slope, intercept).
    pub cov: f64,
    /// Σ r² (unweighted) or Σ (r/σ)² (weighted).
    pub chi2: f64,
    /// Coefficient of determination.
    pub r2: f64,
    pub n: usize,
}

/// Least-squares straight line through the points with finite x and y (and σ > 0 when given).
/// `sigma_y`: per-point 1σ uncertainties → weighted fit (weights 1/σ²). Errors: fewer than two
/// usable points, or all x equal.
pub fn linfit(x: &[f64], y: &[f64], sigma_y: Option<&[f64]>) -> Result<LinFit> {
    if x.len() != y.len() {
        return Err(AnalysisError::BadInput {
            name: "y",
            reason: format!("length {} differs from x length {}", y.len(), x.len()),
        });
    }
    if let Some(s) = sigma_y {
        if s.len() != x.len() {
            return Err(AnalysisError::BadInput {
                name: "sigma_y",
                reason: format!("length {} differs from x length {}", s.len(), x.len()),
            });
        }
    }
    let mut pts = Vec::with_capacity(x.len());
    for i in 0..x.len() {
        let w = match sigma_y {
            Some(s) => {
                if !(s[i].is_finite() && s[i] > 0.0) {
                    continue;
                }
                1.0 / (s[i] * s[i])
            }
            None => 1.0,
        };
        if x[i].is_finite() && y[i].is_finite() {
            pts.push((x[i], y[i], w));
        }
    }
    let n = pts.len();
    if n < 2 {
        return Err(AnalysisError::BadInput {
            name: "x",
            reason: format!("{n} usable points; a line needs at least 2"),
        });
    }
    let sw: f64 = pts.iter().map(|p| p.2).sum();
    let xm = pts.iter().map(|p| p.2 * p.0).sum::<f64>() / sw;
    let ym = pts.iter().map(|p| p.2 * p.1).sum::<f64>() / sw;
    let sxx: f64 = pts.iter().map(|p| p.2 * (p.0 - xm).powi(2)).sum();
    let sxy: f64 = pts.iter().map(|p| p.2 * (p.0 - xm) * (p.1 - ym)).sum();
    let syy: f64 = pts.iter().map(|p| p.2 * (p.1 - ym).powi(2)).sum();
    if !(sxx > 1e-300) {
        return Err(AnalysisError::BadInput {
            name: "x",
            reason: "all x values are equal: the slope is undetermined".into(),
        });
    }
    let slope = sxy / sxx;
    let intercept = ym - slope * xm;
    let chi2: f64 = pts
        .iter()
        .map(|p| p.2 * (p.1 - intercept - slope * p.0).powi(2))
        .sum();
    // Var(slope) = s²/Sxx, Var(b) = s²(1/Σw + x̄²/Sxx), Cov = −x̄ s²/Sxx with s² = 1 (weighted) or
    // the residual variance (unweighted).
    let s2 = if sigma_y.is_some() {
        1.0
    } else if n > 2 {
        chi2 / (n - 2) as f64
    } else {
        0.0
    };
    let var_slope = s2 / sxx;
    let var_b = s2 * (1.0 / sw + xm * xm / sxx);
    let r2 = if syy > 0.0 { 1.0 - chi2 / syy } else { 1.0 };
    Ok(LinFit {
        slope,
        intercept,
        slope_err: var_slope.sqrt(),
        intercept_err: var_b.sqrt(),
        cov: -xm * var_slope,
        chi2,
        r2,
        n,
    })
}

/// Power law y = a·x^p by a line through (ln x, ln y); σ_y propagates as σ_y/y. Points with
/// x ≤ 0 or y ≤ 0 are rejected with an error naming the first one (a logarithm needs positive
/// values). Returns the fit in log space: `slope` = p, `intercept` = ln a.
pub fn loglog_fit(x: &[f64], y: &[f64], sigma_y: Option<&[f64]>) -> Result<LinFit> {
    for (i, (&a, &b)) in x.iter().zip(y).enumerate() {
        if !(a > 0.0) || !(b > 0.0) {
            return Err(AnalysisError::BadInput {
                name: "x, y",
                reason: format!("point {i} = ({a}, {b}): a log-log fit needs x > 0 and y > 0"),
            });
        }
    }
    let lx: Vec<f64> = x.iter().map(|v| v.ln()).collect();
    let ly: Vec<f64> = y.iter().map(|v| v.ln()).collect();
    let ls: Option<Vec<f64>> = sigma_y.map(|s| s.iter().zip(y).map(|(s, y)| s / y).collect());
    linfit(&lx, &ly, ls.as_deref())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn von_neumann_of_a_trend_and_of_white_noise() {
        // a straight line: Σ diff² = n − 1, Σ (i − ī)² = n(n² − 1)/12, so d = 12/(n(n + 1))
        for n in [3usize, 10, 33] {
            let x: Vec<f64> = (0..n).map(|i| 2.0 - 0.5 * i as f64).collect();
            let (d, z) = von_neumann(&x).unwrap();
            let nf = n as f64;
            assert!((d - 12.0 / (nf * (nf + 1.0))).abs() < 1e-12, "n {n}: d {d}");
            assert!(z < 0.0);
        }
        // alternating values: every difference is 2a, every deviation a: d = 4(n − 1)/n
        let x: Vec<f64> = (0..20)
            .map(|i| if i % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        assert!((von_neumann(&x).unwrap().0 - 4.0 * 19.0 / 20.0).abs() < 1e-12);
        // independent normal values (Box–Muller on a seeded generator): the mean of d is 2 and
        // z has unit variance (its closed-form variance); 4000 sequences of 30
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(41);
        let (mut sd, mut sz2) = (0.0, 0.0);
        let m = 4000;
        for _ in 0..m {
            let x: Vec<f64> = (0..30)
                .map(|_| {
                    let (u, v): (f64, f64) = (rng.random(), rng.random());
                    (-2.0 * (1.0 - u).ln()).sqrt() * (std::f64::consts::TAU * v).cos()
                })
                .collect();
            let (d, z) = von_neumann(&x).unwrap();
            sd += d;
            sz2 += z * z;
        }
        let (md, vz) = (sd / m as f64, sz2 / m as f64);
        // standard errors: of the mean of d √(Var/m) = 0.0055, of mean z² about √(2/m) = 0.022
        assert!((md - 2.0).abs() < 0.02, "mean d {md}");
        assert!((vz - 1.0).abs() < 0.08, "var z {vz}");
        assert!(von_neumann(&[1.0, 1.0, 1.0]).is_none());
        assert!(von_neumann(&[1.0, 2.0]).is_none());
    }

    #[test]
    fn summary_closed_form() {
        let s = summary(&[1.0, 2.0, 3.0, 4.0, f64::NAN]).unwrap();
        assert_eq!(s.n, 4);
        assert_eq!(s.n_skipped, 1);
        assert!((s.mean - 2.5).abs() < 1e-15);
        assert!((s.std - (5.0f64 / 3.0).sqrt()).abs() < 1e-15);
        assert!((s.sem - s.std / 2.0).abs() < 1e-15);
        let e = summary(&[f64::NAN]).unwrap_err().to_string();
        assert_eq!(e, "values: no finite values");
    }

    #[test]
    fn histogram_counts_and_edges() {
        let h = histogram(
            &[0.0, 0.1, 0.5, 0.99, 1.0, 2.0, f64::NAN],
            2,
            Some((0.0, 1.0)),
        )
        .unwrap();
        assert_eq!(h.counts, vec![2, 3]);
        assert_eq!(h.n_outside, 1);
        assert_eq!(h.n_skipped, 1);
        assert_eq!(h.centres(), vec![0.25, 0.75]);
        let e = histogram(&[1.0], 0, None).unwrap_err().to_string();
        assert!(e.starts_with("bins = 0 is out of range: 1 ≤ bins ≤"), "{e}");
        let h1 = histogram(&[3.0, 3.0], 4, None).unwrap();
        assert!(h1.all_equal);
        assert_eq!(
            (h1.counts.clone(), h1.edges.clone()),
            (vec![2], vec![2.85, 3.15])
        );
        let h0 = histogram(&[0.0, 0.0], 4, None).unwrap();
        assert_eq!(h0.edges, vec![-0.5, 0.5]);
        let e = histogram(&[1.0, f64::NEG_INFINITY], 3, None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("values[1] = -inf"), "{e}");
        let e = histogram(&[1.0], MAX_BINS + 1, None)
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            format!(
                "bins = {} is out of range: 1 ≤ bins ≤ {MAX_BINS}",
                MAX_BINS + 1
            )
        );
    }

    #[test]
    fn linfit_exact_line_and_errors() {
        let x: Vec<f64> = (0..10).map(|i| i as f64).collect();
        let y: Vec<f64> = x.iter().map(|x| 2.0 - 0.5 * x).collect();
        let f = linfit(&x, &y, None).unwrap();
        assert!((f.slope + 0.5).abs() < 1e-12 && (f.intercept - 2.0).abs() < 1e-12);
        assert!(f.slope_err < 1e-12 && (f.r2 - 1.0).abs() < 1e-12);
        // Weighted with σ: slope error = σ/√Sxx for equal weights.
        let s = vec![0.1; 10];
        let fw = linfit(&x, &y, Some(&s)).unwrap();
        assert!((fw.slope_err - 0.1 / 82.5f64.sqrt()).abs() < 1e-12);
        let e = linfit(&[1.0, 1.0], &[1.0, 2.0], None)
            .unwrap_err()
            .to_string();
        assert_eq!(e, "x: all x values are equal: the slope is undetermined");
        let e = linfit(&[1.0], &[1.0], None).unwrap_err().to_string();
        assert_eq!(e, "x: 1 usable points; a line needs at least 2");
    }

    #[test]
    fn loglog_recovers_power() {
        let d = [110.0, 130.0, 160.0, 200.0];
        let s: Vec<f64> = d
            .iter()
            .map(|d: &f64| 3.0 * (d / 110.0).powf(3.02))
            .collect();
        let f = loglog_fit(&d, &s, None).unwrap();
        assert!((f.slope - 3.02).abs() < 1e-12);
        let e = loglog_fit(&[1.0, -1.0], &[1.0, 1.0], None)
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "x, y: point 1 = (-1, 1): a log-log fit needs x > 0 and y > 0"
        );
    }
}
