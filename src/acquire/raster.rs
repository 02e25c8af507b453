//! Hardware-timed raster lines: binning a line's digitiser samples into pixels by the stage's
//! *measured* position (issue 21). Pure functions, no I/O; the raster engine that drives the
//! wave generator and the digitiser is still to be written (docs/hardware.md §10).
//!
//! Conventions: positions in µm, times in s. A line of `n` pixels from `from` to `to` has its
//! pixel centres at `from + i·w`, `w = (to − from)/(n − 1)` (as the point-by-point scans), and
//! pixel `i` takes the samples whose measured position lies within `w/2` of its centre
//! (half-open: `[c − w/2, c + w/2)` in the sweep direction).

/// A line binned into pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct LineBins {
    /// Mean of the samples per pixel.
    pub mean: Vec<f64>,
    /// Samples per pixel.
    pub count: Vec<usize>,
    /// Mean measured position of the samples per pixel, µm (its distance from the pixel's
    /// centre is the residual position error of the binning).
    pub position: Vec<f64>,
}

/// The stage position at each digitiser sample: the recorder's positions (`record`, one per
/// `record_dt` s from the generator's start) interpolated linearly at `t = delay + k·sample_dt`
/// for `k = 0 … n − 1` (`delay`: the digitiser's first sample after the generator's start,
/// s). `Err` when a sample falls outside the record or an argument is not usable.
pub fn positions_at_samples(
    record: &[f64],
    record_dt: f64,
    n: usize,
    sample_dt: f64,
    delay: f64,
) -> Result<Vec<f64>, String> {
    if record.len() < 2 {
        return Err(format!(
            "record of {} points: at least 2 are needed",
            record.len()
        ));
    }
    for (name, v) in [("record_dt", record_dt), ("sample_dt", sample_dt)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(format!("{name} = {v} s: must be finite and > 0"));
        }
    }
    if !(delay.is_finite() && delay >= 0.0) {
        return Err(format!("delay = {delay} s: must be finite and ≥ 0"));
    }
    let last = (record.len() - 1) as f64;
    (0..n)
        .map(|k| {
            let u = (delay + k as f64 * sample_dt) / record_dt;
            if u > last + 1e-9 {
                return Err(format!(
                    "digitiser sample {k} at {:.6} s is after the record's end at {:.6} s",
                    u * record_dt,
                    last * record_dt
                ));
            }
            let i = (u.floor() as usize).min(record.len() - 2);
            let f = (u - i as f64).clamp(0.0, 1.0);
            Ok(record[i] + f * (record[i + 1] - record[i]))
        })
        .collect()
}

/// Bin `values` (one per sample) by their measured `positions` into `n` pixels from `from`
/// to `to` (µm). Samples outside the line (speed-up, speed-down, lag) are left out. `Err`
/// names a pixel without samples (the line was too fast for the digitiser) or a bad argument.
pub fn bin_line(
    positions: &[f64],
    values: &[f64],
    from: f64,
    to: f64,
    n: usize,
) -> Result<LineBins, String> {
    if positions.len() != values.len() {
        return Err(format!(
            "{} positions for {} samples",
            positions.len(),
            values.len()
        ));
    }
    if n < 2 {
        return Err(format!("n = {n} pixels: at least 2"));
    }
    if !(from.is_finite() && to.is_finite()) || from == to {
        return Err(format!(
            "line from {from} to {to} µm: must be finite and distinct"
        ));
    }
    let w = (to - from) / (n - 1) as f64;
    let mut sum = vec![0.0; n];
    let mut pos = vec![0.0; n];
    let mut count = vec![0usize; n];
    for (&x, &v) in positions.iter().zip(values) {
        if !(x.is_finite() && v.is_finite()) {
            continue;
        }
        let u = (x - from) / w + 0.5;
        if u < 0.0 || u >= n as f64 {
            continue;
        }
        let i = u as usize;
        sum[i] += v;
        pos[i] += x;
        count[i] += 1;
    }
    if let Some(i) = count.iter().position(|&c| c == 0) {
        return Err(format!(
            "pixel {i} (centre {:.4} µm) got no sample: the line is too fast for the digitiser's rate",
            from + i as f64 * w
        ));
    }
    Ok(LineBins {
        mean: sum.iter().zip(&count).map(|(s, &c)| s / c as f64).collect(),
        position: pos.iter().zip(&count).map(|(s, &c)| s / c as f64).collect(),
        count,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stage sweeping 0 → 6.3 µm at 1 µm/ms under a first-order lag τ: the signal is a
    /// function of the *true* position. Binning by the measured position recovers the
    /// profile; binning by the commanded position is off by about v·τ.
    #[test]
    fn binning_by_measured_position_removes_the_lag() {
        let (v, tau, dt) = (1000.0, 0.5e-3, 1e-6); // µm/s, s, s
        let n_pix = 64;
        let (from, to) = (0.0, 6.3);
        let f = |x: f64| (x * 1.3).sin(); // the scene along the line
        let t_end = 7.8e-3;
        let steps = (t_end / dt) as usize;
        let (mut cmd, mut x) = (Vec::new(), Vec::new());
        let mut p = -0.5; // start at rest before the line
        for k in 0..steps {
            let c = -0.5 + v * (k as f64 * dt);
            p += (1.0 - (-dt / tau).exp()) * (c - p);
            cmd.push(c);
            x.push(p);
        }
        let values: Vec<f64> = x.iter().map(|&p| f(p)).collect();
        let good = bin_line(&x, &values, from, to, n_pix).unwrap();
        let by_cmd = bin_line(&cmd, &values, from, to, n_pix).unwrap();
        let w = (to - from) / (n_pix - 1) as f64;
        for i in 0..n_pix {
            let c = from + i as f64 * w;
            // the mean of f over a pixel differs from f(c) by ≤ f''·w²/24 ≈ 1.69·0.01/24
            assert!((good.mean[i] - f(c)).abs() < 1e-3, "{i}");
            // the samples' mean position is the centre to within one sample spacing v·dt
            assert!(
                (good.position[i] - c).abs() <= v * dt,
                "{i}: {}",
                good.position[i]
            );
        }
        // by the command, the profile is shifted by v·τ = 0.5 µm: far off somewhere
        let worst = (0..n_pix)
            .map(|i| (by_cmd.mean[i] - f(from + i as f64 * w)).abs())
            .fold(0.0, f64::max);
        assert!(worst > 0.4, "{worst}");
    }

    #[test]
    fn positions_interpolate_the_record_and_refuse_samples_after_it() {
        let rec = [0.0, 1.0, 4.0];
        let p = positions_at_samples(&rec, 1e-3, 5, 0.5e-3, 0.0).unwrap();
        assert_eq!(p, vec![0.0, 0.5, 1.0, 2.5, 4.0]);
        let e = positions_at_samples(&rec, 1e-3, 6, 0.5e-3, 0.0).unwrap_err();
        assert!(e.contains("sample 5") && e.contains("0.002000 s"), "{e}");
        assert!(positions_at_samples(&rec, 0.0, 1, 1.0, 0.0)
            .unwrap_err()
            .contains("record_dt = 0"));
    }

    #[test]
    fn an_empty_pixel_is_named() {
        let x = [0.0, 0.1, 0.9, 1.0];
        let e = bin_line(&x, &[1.0; 4], 0.0, 1.0, 3).unwrap_err();
        assert!(
            e.starts_with("pixel 1 (centre 0.5000 µm) got no sample"),
            "{e}"
        );
        assert!(bin_line(&x, &[1.0; 3], 0.0, 1.0, 3).is_err());
    }
}
