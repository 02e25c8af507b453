//! Sensitivity images (Sec. 3.2): S_x sensitivity = ∂Sx/∂x, S_y sensitivity = ∂Sy/∂y.
//!
//! The derivative is taken along the image's horizontal axis (columns, `Axis::X`) or vertical
//! axis (rows, `Axis::Y`) with a [`Stencil`], a documented accuracy/noise knob. Units: signal
//! units per µm.
//!
//! **Noise amplification.** For white pixel noise of standard deviation σ and pixel spacing h,
//! the derivative's noise is `σ · gain / h` with `gain = Stencil::noise_gain()`:
//!
//! | stencil | interior formula | gain | truncation error |
//! |---|---|---|---|
//! | `Central2` (default) | (f₊₁ − f₋₁)/2h | 1/√2 ≈ 0.707 | h²f‴/6 |
//! | `Central5` | (−f₊₂ + 8f₊₁ − 8f₋₁ + f₋₂)/12h | √130/12 ≈ 0.950 | h⁴f⁽⁵⁾/30 |
//! | `SavitzkyGolay{m}` | Σₖ k·f₊ₖ / (h Σₖ k²), k = −m..m (quadratic SG) | 1/√(m(m+1)(2m+1)/3) (m=2: 0.316) | ≈ m(m+1)h²f‴/6·… (smooths) |
//!
//! Central2 is what "taking the derivative at each location" means for most users; its bias for a
//! bead of w0 = 0.4 µm sampled at 50 nm is ≈ −h²/w0² = −1.6 % at the peak. Every quantitative step
//! in this crate compares like with like (the calibration curves and bead models are run through
//! the same stencil at the same pixel size), so the bias cancels.
//!
//! **Edges.** The output has the input's size (no shrink). Where the full stencil does not fit
//! (image edges) or touches a NaN pixel, the derivative falls back, in order, to: the quadratic
//! least-squares derivative over the same number of points shifted inside (SG only), the central
//! 2-point difference, the one-sided 2-point difference (gain √2, error h·f″/2). A pixel is NaN in
//! the output only when neither neighbour pair around it is finite (missing data stays missing).
//! An image with a single sample along the derivative axis is an error (no derivative exists).

use super::{check_axis, AnalysisError, Result};
use crate::data::Image;
use ndarray::Array2;
use serde::{Deserialize, Serialize};

/// Direction of the derivative: `X` along the horizontal axis (columns; x of XY and XZ scans),
/// `Y` along the vertical axis (rows; y of XY scans).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Axis {
    X,
    Y,
}

impl Axis {
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "x" | "X" => Some(Axis::X),
            "y" | "Y" => Some(Axis::Y),
            _ => None,
        }
    }
}

/// Derivative stencil (accuracy / noise knob; see the module table).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Stencil {
    /// Central 2-point difference (default).
    #[default]
    Central2,
    /// Central 5-point difference (fourth order).
    Central5,
    /// Savitzky–Golay smoothing derivative, quadratic over 2m+1 points (m = `half_width` ≥ 1).
    SavitzkyGolay { half_width: usize },
}

impl Stencil {
    /// Noise amplification of the interior stencil: σ(derivative) = gain · σ(pixel) / h.
    pub fn noise_gain(&self) -> f64 {
        match *self {
            Stencil::Central2 => std::f64::consts::FRAC_1_SQRT_2,
            Stencil::Central5 => 130f64.sqrt() / 12.0,
            Stencil::SavitzkyGolay { half_width: m } => {
                let m = m.max(1) as f64;
                1.0 / (m * (m + 1.0) * (2.0 * m + 1.0) / 3.0).sqrt()
            }
        }
    }

    /// The correlation of the derivative's noise at lags of 1–4 pixels, for independent pixel
    /// noise: Σᵢ wᵢ·wᵢ₊ₗ / Σᵢ wᵢ² over the stencil's weights w (central difference: 0, −½;
    /// five-point: −16, −64, 16, −1 over 130; Savitzky–Golay, weights ∝ k for |k| ≤ m: its
    /// lags up to 4, the longer ones of m > 2 dropped). Pixels near the edge, where the
    /// Savitzky–Golay window is shifted, are taken as interior ones.
    pub fn noise_acf(&self) -> [f64; 4] {
        let w: Vec<f64> = match *self {
            Stencil::Central2 => vec![-1.0, 0.0, 1.0],
            Stencil::Central5 => vec![1.0, -8.0, 0.0, 8.0, -1.0],
            Stencil::SavitzkyGolay { half_width: m } => {
                let m = m.max(1) as i64;
                (-m..=m).map(|k| k as f64).collect()
            }
        };
        let norm: f64 = w.iter().map(|x| x * x).sum();
        let mut out = [0.0; 4];
        for (l, o) in out.iter_mut().enumerate() {
            let lag = l + 1;
            *o = (0..w.len().saturating_sub(lag))
                .map(|i| w[i] * w[i + lag])
                .sum::<f64>()
                / norm;
        }
        out
    }

    /// How many pixels away a derivative pixel may read, at most: 1 (central2), 2 (central5),
    /// 2m for Savitzky–Golay (m inside; a pixel within m of the edge reads the window shifted
    /// inside, up to 2m away). The fallbacks at edges and NaN pixels reach no farther.
    pub fn reach(&self) -> usize {
        match *self {
            Stencil::Central2 => 1,
            Stencil::Central5 => 2,
            Stencil::SavitzkyGolay { half_width } => 2 * half_width,
        }
    }

    /// The name [`Stencil::parse`] reads: `"central2"`, `"central5"`, `"sg<2m+1>"`.
    pub fn name(&self) -> String {
        match *self {
            Stencil::Central2 => "central2".into(),
            Stencil::Central5 => "central5".into(),
            Stencil::SavitzkyGolay { half_width } => format!("sg{}", 2 * half_width + 1),
        }
    }

    /// Parse `"central2"`, `"central5"`, `"sg5"`/`"sg7"`/… (SG with 2m+1 points).
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "central2" | "central" => Some(Stencil::Central2),
            "central5" => Some(Stencil::Central5),
            _ => {
                let n: usize = s.strip_prefix("sg")?.parse().ok()?;
                (n >= 3 && n % 2 == 1).then_some(Stencil::SavitzkyGolay {
                    half_width: (n - 1) / 2,
                })
            }
        }
    }

    fn validate(&self) -> Result<()> {
        if let Stencil::SavitzkyGolay { half_width } = *self {
            if !(1..=50).contains(&half_width) {
                return Err(AnalysisError::OutOfRange {
                    name: "half_width",
                    value: half_width as f64,
                    allowed: "1 ≤ half_width ≤ 50".into(),
                });
            }
        }
        Ok(())
    }
}

/// Sensitivity image: derivative of `img` along `axis` (signal units per µm).
///
/// Errors: fewer than 2 samples along `axis`, irregular or non-monotonic axis, bad stencil.
pub fn sensitivity(img: &Image, axis: Axis, stencil: Stencil) -> Result<Image> {
    stencil.validate()?;
    let (name, ax) = match axis {
        Axis::X => ("img.x", &img.x),
        Axis::Y => ("img.y", &img.y),
    };
    let h = check_axis(name, ax, 2).map_err(|e| match e {
        AnalysisError::BadInput { name, reason } if ax.len() < 2 => AnalysisError::BadInput {
            name,
            reason: format!("{reason}: a derivative along {axis:?} needs at least 2 samples along that axis (1-pixel-wide scan)"),
        },
        e => e,
    })?;
    let (rows, cols) = img.data.dim();
    let mut out = Array2::<f64>::zeros((rows, cols));
    match axis {
        Axis::X => {
            for r in 0..rows {
                let line: Vec<f64> = img.data.row(r).to_vec();
                let d = derivative_1d(&line, h, stencil);
                out.row_mut(r).iter_mut().zip(d).for_each(|(o, v)| *o = v);
            }
        }
        Axis::Y => {
            for c in 0..cols {
                let line: Vec<f64> = img.data.column(c).to_vec();
                let d = derivative_1d(&line, h, stencil);
                out.column_mut(c)
                    .iter_mut()
                    .zip(d)
                    .for_each(|(o, v)| *o = v);
            }
        }
    }
    let mut res = Image::new(out, img.x.clone(), img.y.clone());
    res.x_name = img.x_name.clone();
    res.y_name = img.y_name.clone();
    res.flags = derived_flags(img, axis, stencil);
    Ok(res)
}

/// The clipped and dark pixels of the derivative of `img` along `axis` by `stencil`: every
/// pixel whose stencil reaches a flagged pixel of `img` (None when `img` has no flags).
pub fn derived_flags(
    img: &Image,
    axis: Axis,
    stencil: Stencil,
) -> Option<std::sync::Arc<crate::data::clip::PixelFlags>> {
    let reach = stencil.reach();
    let (rx, ry) = match axis {
        Axis::X => (reach, 0),
        Axis::Y => (0, reach),
    };
    let what = match axis {
        Axis::X => "the sensitivity ∂/∂x",
        Axis::Y => "the sensitivity ∂/∂y",
    };
    img.flags
        .as_ref()
        .map(|f| std::sync::Arc::new(f.derived(what, rx, ry)))
}

/// Derivative of equally spaced samples `v` (spacing `h`, may be negative) with the fallbacks
/// documented in the module header. Output has the input's length; NaN exactly where the input
/// is NaN or has no finite neighbour.
pub fn derivative_1d(v: &[f64], h: f64, stencil: Stencil) -> Vec<f64> {
    let n = v.len();
    let fin = |i: isize| i >= 0 && (i as usize) < n && v[i as usize].is_finite();
    let at = |i: isize| v[i as usize];
    let mut out = vec![f64::NAN; n];
    for (i, o) in out.iter_mut().enumerate() {
        let ii = i as isize;
        if !fin(ii) {
            continue;
        }
        let mut d = None;
        match stencil {
            Stencil::Central2 => {}
            Stencil::Central5 => {
                if (-2..=2).all(|k| k == 0 || fin(ii + k)) {
                    d = Some(
                        (-at(ii + 2) + 8.0 * at(ii + 1) - 8.0 * at(ii - 1) + at(ii - 2))
                            / (12.0 * h),
                    );
                }
            }
            Stencil::SavitzkyGolay { half_width } => {
                let m = half_width as isize;
                let len = 2 * m + 1;
                if len as usize <= n {
                    let start = (ii - m).clamp(0, n as isize - len);
                    if (start..start + len).all(fin) {
                        d = if start == ii - m {
                            let mut s = 0.0;
                            for k in -m..=m {
                                s += k as f64 * at(ii + k);
                            }
                            let den = (m * (m + 1) * (2 * m + 1) / 3) as f64;
                            Some(s / (den * h))
                        } else {
                            quad_slope(v, start as usize, len as usize, i).map(|s| s / h)
                        };
                    }
                }
            }
        }
        if d.is_none() && fin(ii - 1) && fin(ii + 1) {
            d = Some((at(ii + 1) - at(ii - 1)) / (2.0 * h));
        }
        if d.is_none() && fin(ii) && fin(ii + 1) {
            d = Some((at(ii + 1) - at(ii)) / h);
        }
        if d.is_none() && fin(ii) && fin(ii - 1) {
            d = Some((at(ii) - at(ii - 1)) / h);
        }
        if let Some(d) = d {
            *o = d;
        }
    }
    out
}

/// Slope (per sample) at index `at` of the least-squares quadratic through v[start..start+len].
fn quad_slope(v: &[f64], start: usize, len: usize, at: usize) -> Option<f64> {
    // Fit a + b k + c k² with k = j − at; slope at k = 0 is b.
    let mut s = [0.0f64; 5];
    let mut t = [0.0f64; 3];
    for j in start..start + len {
        let k = j as f64 - at as f64;
        let mut p = 1.0;
        for e in s.iter_mut() {
            *e += p;
            p *= k;
        }
        t[0] += v[j];
        t[1] += k * v[j];
        t[2] += k * k * v[j];
    }
    let m = nalgebra::Matrix3::new(s[0], s[1], s[2], s[1], s[2], s[3], s[2], s[3], s[4]);
    let sol = m.lu().solve(&nalgebra::Vector3::new(t[0], t[1], t[2]))?;
    sol[1].is_finite().then_some(sol[1])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stencils_exact_on_polynomials() {
        let h = 0.05;
        let v: Vec<f64> = (0..30)
            .map(|i| {
                let x = i as f64 * h;
                1.0 + 2.0 * x - 0.7 * x * x
            })
            .collect();
        for st in [
            Stencil::Central2,
            Stencil::Central5,
            Stencil::SavitzkyGolay { half_width: 3 },
        ] {
            let d = derivative_1d(&v, h, st);
            for i in 1..29 {
                let x = i as f64 * h;
                assert!(
                    (d[i] - (2.0 - 1.4 * x)).abs() < 1e-9,
                    "{st:?} at {i}: {}",
                    d[i]
                );
            }
        }
        // Central5 is exact for quartics in the interior.
        let q: Vec<f64> = (0..30).map(|i| (i as f64 * h).powi(4)).collect();
        let d = derivative_1d(&q, h, Stencil::Central5);
        assert!((d[10] - 4.0 * (10.0 * h).powi(3)).abs() < 1e-9);
    }

    #[test]
    fn noise_gain_matches_simulation() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let nd = Normal::new(0.0, 1.0).unwrap();
        let v: Vec<f64> = (0..200_000).map(|_| nd.sample(&mut rng)).collect();
        for st in [
            Stencil::Central2,
            Stencil::Central5,
            Stencil::SavitzkyGolay { half_width: 2 },
        ] {
            let d = derivative_1d(&v, 1.0, st);
            let inner = &d[10..d.len() - 10];
            let var = inner.iter().map(|x| x * x).sum::<f64>() / inner.len() as f64;
            assert!(
                (var.sqrt() / st.noise_gain() - 1.0).abs() < 0.01,
                "{st:?}: {}",
                var.sqrt()
            );
        }
    }

    #[test]
    fn nan_fallbacks() {
        let v = [0.0, 1.0, f64::NAN, 3.0, 4.0, f64::NAN, f64::NAN, 7.0];
        let d = derivative_1d(&v, 1.0, Stencil::Central5);
        assert_eq!(d[0], 1.0);
        assert_eq!(d[1], 1.0); // backward
        assert!(d[2].is_nan()); // missing input stays missing
        assert_eq!(d[3], 1.0); // forward
        assert_eq!(d[4], 1.0); // backward
        assert!(d[7].is_nan()); // isolated sample
        assert!(d.iter().filter(|x| x.is_nan()).count() == 4);
    }

    #[test]
    fn parse_stencils() {
        assert_eq!(
            Stencil::parse("sg5"),
            Some(Stencil::SavitzkyGolay { half_width: 2 })
        );
        assert_eq!(Stencil::parse("sg4"), None);
        assert_eq!(Stencil::parse("central5"), Some(Stencil::Central5));
        for st in [
            Stencil::Central2,
            Stencil::Central5,
            Stencil::SavitzkyGolay { half_width: 3 },
        ] {
            assert_eq!(Stencil::parse(&st.name()), Some(st), "{}", st.name());
        }
        assert_eq!(Stencil::SavitzkyGolay { half_width: 2 }.name(), "sg5");
    }
}
