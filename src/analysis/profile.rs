//! Interpolated sampling of images and profiles along polylines (e.g. the line profile along the
//! fibril centre of Fig. 5c, the line profiles across filaments of Fig. 4c).

use super::{check_above, check_axis, AnalysisError, AxisMap, Result};
use crate::data::{segment_lengths, Image, Profile};
use crate::optics::grid::Interp;

/// Value of `img` at (x, y) µm by bilinear or Keys cubic-convolution interpolation (a = −1/2).
///
/// Returns `None` outside the pixel-centre extent of the image and when any pixel the stencil
/// uses is NaN (missing data is never interpolated over). At the outermost pixel intervals the
/// cubic stencil replicates the edge pixel. Images with a single row or column are interpolated
/// along the other axis only (and only exactly on the single row/column coordinate).
pub fn sample(img: &Image, x: f64, y: f64, interp: Interp) -> Option<f64> {
    if !(x.is_finite() && y.is_finite()) || img.rows() == 0 || img.cols() == 0 {
        return None;
    }
    let ax = AxisMap::new(&img.x);
    let ay = AxisMap::new(&img.y);
    let (fx, wx) = frac(&ax, x)?;
    let (fy, wy) = frac(&ay, y)?;
    let (kx, ky) = match interp {
        Interp::Linear => (lin_w(wx), lin_w(wy)),
        Interp::Cubic => (cub_w(wx), cub_w(wy)),
    };
    let (ox, oy) = match interp {
        Interp::Linear => (0isize, 0isize),
        Interp::Cubic => (-1, -1),
    };
    let mut acc = 0.0;
    for (b, &wyb) in ky.iter().enumerate() {
        if wyb == 0.0 {
            continue;
        }
        let r = (fy + oy + b as isize).clamp(0, img.rows() as isize - 1) as usize;
        for (a, &wxa) in kx.iter().enumerate() {
            if wxa == 0.0 {
                continue;
            }
            let c = (fx + ox + a as isize).clamp(0, img.cols() as isize - 1) as usize;
            let v = img.data[[r, c]];
            if !v.is_finite() {
                return None;
            }
            acc += wxa * wyb * v;
        }
    }
    Some(acc)
}

/// Integer base index and fraction of coordinate `t` on an axis; None outside.
fn frac(a: &AxisMap, t: f64) -> Option<(isize, f64)> {
    if a.n == 1 {
        return if (t - a.x0).abs() <= 1e-9 {
            Some((0, 0.0))
        } else {
            None
        };
    }
    let f = (t - a.x0) / a.h;
    let eps = 1e-9;
    if f < -eps || f > (a.n - 1) as f64 + eps {
        return None;
    }
    let f = f.clamp(0.0, (a.n - 1) as f64);
    let i = (f.floor() as isize).min(a.n as isize - 2);
    Some((i, f - i as f64))
}

fn lin_w(t: f64) -> Vec<f64> {
    vec![1.0 - t, t]
}

fn cub_w(t: f64) -> Vec<f64> {
    let t2 = t * t;
    let t3 = t2 * t;
    vec![
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    ]
}

/// Profile of `img` along the polyline `points` ([x, y] µm), sampled every `step_um` of arc
/// length (the last vertex is always included). `t` of the result is the arc length from the
/// first vertex (µm), `t_name` = "arc length". Samples outside the image or touching NaN pixels
/// are omitted (their arc length is absent from `t`, so gaps stay visible).
///
/// Errors: fewer than two vertices, non-finite vertices, a zero-length polyline, step ≤ 0, more
/// than 10⁶ samples.
pub fn profile_polyline(
    img: &Image,
    points: &[[f64; 2]],
    step_um: f64,
    interp: Interp,
) -> Result<Profile> {
    check_above("step_um", step_um, 0.0)?;
    if img.rows() > 1 {
        check_axis("img.y", &img.y, 1)?;
    }
    if img.cols() > 1 {
        check_axis("img.x", &img.x, 1)?;
    }
    if points.len() < 2 {
        return Err(AnalysisError::BadInput {
            name: "points",
            reason: format!("{} vertices; a polyline needs at least 2", points.len()),
        });
    }
    if points.iter().flatten().any(|v| !v.is_finite()) {
        return Err(AnalysisError::BadInput {
            name: "points",
            reason: "vertices must be finite".into(),
        });
    }
    let seg = segment_lengths(points);
    let total: f64 = seg.iter().sum();
    if !(total > 0.0) {
        return Err(AnalysisError::BadInput {
            name: "points",
            reason: "polyline has zero length".into(),
        });
    }
    let n = (total / step_um).floor() as usize + 1;
    if n > 1_000_000 {
        return Err(AnalysisError::OutOfRange {
            name: "step_um",
            value: step_um,
            allowed: format!(
                "step_um ≥ {} (at most 10⁶ samples along {total} µm)",
                total / 1e6
            ),
        });
    }
    let mut ts: Vec<f64> = (0..n).map(|i| i as f64 * step_um).collect();
    if total - ts[n - 1] > 1e-9 * total {
        ts.push(total);
    }
    let (mut t_out, mut v_out) = (Vec::new(), Vec::new());
    let mut k = 0;
    let mut s0 = 0.0;
    for t in ts {
        while k + 1 < seg.len() && t > s0 + seg[k] {
            s0 += seg[k];
            k += 1;
        }
        let f = if seg[k] > 0.0 {
            ((t - s0) / seg[k]).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let x = points[k][0] + f * (points[k + 1][0] - points[k][0]);
        let y = points[k][1] + f * (points[k + 1][1] - points[k][1]);
        if let Some(v) = sample(img, x, y, interp) {
            t_out.push(t);
            v_out.push(v);
        }
    }
    let mut p = Profile::new(t_out, v_out);
    p.t_name = "arc length".into();
    Ok(p)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    fn plane() -> Image {
        let x: Vec<f64> = (0..20).map(|i| i as f64 * 0.1).collect();
        let y: Vec<f64> = (0..15).map(|i| 1.0 - i as f64 * 0.1).collect();
        let data = Array2::from_shape_fn((15, 20), |(r, c)| 2.0 * x[c] - 3.0 * y[r] + 1.0);
        Image::new(data, x, y)
    }

    #[test]
    fn interpolation_reproduces_planes() {
        let img = plane();
        for interp in [Interp::Linear, Interp::Cubic] {
            for &(x, y) in &[(0.37, 0.22), (0.0, 1.0), (1.9, -0.4), (1.05, 0.55)] {
                let v = sample(&img, x, y, interp).unwrap();
                assert!(
                    (v - (2.0 * x - 3.0 * y + 1.0)).abs() < 1e-12,
                    "{interp:?} at ({x},{y}): {v}"
                );
            }
        }
        assert!(sample(&img, 2.0, 0.0, Interp::Cubic).is_none());
        let mut holed = img.clone();
        holed.data[[5, 5]] = f64::NAN;
        assert!(sample(&holed, 0.5, 0.5, Interp::Cubic).is_none());
        assert!(sample(&holed, 1.5, 0.5, Interp::Cubic).is_some());
    }

    #[test]
    fn polyline_profile_arc_length() {
        let img = plane();
        let p = profile_polyline(
            &img,
            &[[0.1, 0.0], [0.4, 0.0], [0.4, 0.4]],
            0.1,
            Interp::Cubic,
        )
        .unwrap();
        assert_eq!(p.t.len(), 8);
        assert!((p.t[7] - 0.7).abs() < 1e-12);
        // Along the second leg x = 0.4, y = t − 0.3.
        assert!((p.v[5] - (0.8 - 3.0 * 0.2 + 1.0)).abs() < 1e-9);
        let e = profile_polyline(&img, &[[0.1, 0.0]], 0.1, Interp::Cubic)
            .unwrap_err()
            .to_string();
        assert_eq!(e, "points: 1 vertices; a polyline needs at least 2");
        let e = profile_polyline(&img, &[[0.1, 0.0], [0.2, 0.0]], 0.0, Interp::Cubic)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("step_um = 0 is out of range"), "{e}");
    }
}
