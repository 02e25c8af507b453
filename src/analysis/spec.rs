//! SPEC's after-scan statistics of a line scan channel: `peak` (position of the largest
//! deviation), `com` (centre of mass), `fwhm` (full width at half maximum) and `cen` (the
//! middle of the half-maximum crossings), as SPEC prints them after a scan.
//!
//! QPD signals are signed and sit on an offset, so the statistics use the deviation from the
//! line's median, w = |v − median(v)|: a bead's Sz dip and Sx swing both count as a peak.

use super::{AnalysisError, Result};

/// `#{peak, peak_value, com, fwhm, cen}` of one line (positions in the units of `t`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LineStats {
    pub peak: f64,
    /// The channel's value at the peak (not the deviation).
    pub peak_value: f64,
    pub com: f64,
    pub fwhm: f64,
    pub cen: f64,
}

fn median(v: &[f64]) -> f64 {
    let mut s: Vec<f64> = v.to_vec();
    s.sort_by(|a, b| a.total_cmp(b));
    let n = s.len();
    if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    }
}

/// The statistics of `v` sampled at `t` (finite samples only; at least 3).
pub fn line_stats(t: &[f64], v: &[f64]) -> Result<LineStats> {
    let pts: Vec<(f64, f64)> = t
        .iter()
        .zip(v)
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .map(|(a, b)| (*a, *b))
        .collect();
    if pts.len() < 3 {
        return Err(AnalysisError::BadInput {
            name: "scan",
            reason: format!(
                "{} measured points; peak/cen/com/fwhm need at least 3",
                pts.len()
            ),
        });
    }
    let vs: Vec<f64> = pts.iter().map(|p| p.1).collect();
    let base = median(&vs);
    let w: Vec<f64> = vs.iter().map(|x| (x - base).abs()).collect();
    let (imax, wmax) =
        w.iter().enumerate().fold(
            (0, f64::NEG_INFINITY),
            |a, (i, x)| if *x > a.1 { (i, *x) } else { a },
        );
    if wmax <= 0.0 {
        return Err(AnalysisError::Failed(
            "the channel is flat along the line: no peak".into(),
        ));
    }
    let sw: f64 = w.iter().sum();
    let com = pts.iter().zip(&w).map(|(p, x)| p.0 * x).sum::<f64>() / sw;
    let half = 0.5 * wmax;
    // half-maximum crossings on each side of the peak, linearly interpolated
    let cross = |i: usize, j: usize| -> f64 {
        let (t0, t1, w0, w1) = (pts[i].0, pts[j].0, w[i], w[j]);
        t0 + (half - w0) / (w1 - w0) * (t1 - t0)
    };
    let mut left = pts[0].0;
    for i in (0..imax).rev() {
        if w[i] < half {
            left = cross(i, i + 1);
            break;
        }
    }
    let mut right = pts[pts.len() - 1].0;
    for i in imax + 1..pts.len() {
        if w[i] < half {
            right = cross(i - 1, i);
            break;
        }
    }
    Ok(LineStats {
        peak: pts[imax].0,
        peak_value: pts[imax].1,
        com,
        fwhm: (right - left).abs(),
        cen: 0.5 * (left + right),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaussian_on_an_offset_gives_its_centre_and_width() {
        // σ = 0.2 µm at 0.3 µm on an offset of 5, dips down (as a bead in Sz)
        let t: Vec<f64> = (0..401).map(|i| -2.0 + 0.01 * i as f64).collect();
        let v: Vec<f64> = t
            .iter()
            .map(|x| 5.0 - 2.0 * (-(x - 0.3) * (x - 0.3) / (2.0 * 0.04)).exp())
            .collect();
        let s = line_stats(&t, &v).unwrap();
        assert!((s.peak - 0.3).abs() < 1e-9);
        assert!((s.peak_value - 3.0).abs() < 1e-9);
        assert!((s.cen - 0.3).abs() < 1e-4, "{s:?}");
        assert!(
            (s.fwhm - 2.0 * (2.0 * 2f64.ln()).sqrt() * 0.2).abs() < 1e-3,
            "{s:?}"
        );
        assert!((s.com - 0.3).abs() < 1e-3, "{s:?}");
        let e = line_stats(&t, &vec![1.0; t.len()]).unwrap_err().to_string();
        assert_eq!(e, "the channel is flat along the line: no peak");
        let e = line_stats(&t[..2], &v[..2]).unwrap_err().to_string();
        assert_eq!(
            e,
            "scan: 2 measured points; peak/cen/com/fwhm need at least 3"
        );
    }
}
