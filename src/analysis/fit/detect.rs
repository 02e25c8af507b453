//! Initial guesses for the bead fit: CLEAN on the detection map ∂Sx/∂x + ∂Sy/∂y (or the one
//! fitted channel's sensitivity); see the parent module's "Initial guesses".

use super::super::sensitivity::{sensitivity, Axis, Stencil};
use super::super::template::Template;
use super::super::{check_range, AxisMap, Result};
use super::types::*;
use crate::data::Image;
use ndarray::Array2;

/// Automatic initial guesses (the same the fit uses when `init` is not given): `n` beads by CLEAN
/// on the detection map ∂Sx/∂x + ∂Sy/∂y (or the one channel's sensitivity) with the given
/// stencil. Fewer than `n` are returned when the map has no further positive maximum.
pub fn detect_beads(
    sx: &Image,
    sy: &Image,
    tpl: &Template,
    channels: Channels,
    n: usize,
    stencil: Stencil,
) -> Result<Vec<BeadInit>> {
    check_range("n", n as f64, 1.0, 10_000.0)?;
    let d = detection_map(sx, sy, channels, stencil)?;
    Ok(clean(&d, tpl, channels, n))
}

/// The detection map: ∂Sx/∂x + ∂Sy/∂y (or the fitted channel's sensitivity).
pub(crate) fn detection_map(sx: &Image, sy: &Image, ch: Channels, st: Stencil) -> Result<Image> {
    let a = match ch {
        Channels::Sy => None,
        _ => Some(sensitivity(sx, Axis::X, st)?),
    };
    let b = match ch {
        Channels::Sx => None,
        _ => Some(sensitivity(sy, Axis::Y, st)?),
    };
    Ok(match (a, b) {
        (Some(a), Some(b)) => Image::new(&a.data + &b.data, a.x, a.y),
        (Some(a), None) => a,
        (None, Some(b)) => b,
        (None, None) => unreachable!(),
    })
}

/// The template's own detection response and its peak.
pub(super) fn template_dmap_peak(tpl: &Template, ch: Channels) -> (f64, f64, f64) {
    let g = &tpl.grid;
    let f = |u: f64, v: f64| {
        let s = g.eval_grad(u, v);
        match ch {
            Channels::Both => s.du[0] + s.dv[1],
            Channels::Sx => s.du[0],
            Channels::Sy => s.dv[1],
        }
    };
    g.max_of(f)
}

/// CLEAN: up to `n` beads from the detection map, every positive maximum taken (no
/// threshold; [`clean_peaks`] with thresholds and the peaks' heights).
pub(crate) fn clean(d: &Image, tpl: &Template, ch: Channels, n: usize) -> Vec<BeadInit> {
    clean_peaks(d, tpl, ch, n, 0.0, 0.0, DETECT_SMOOTH_UM)
        .into_iter()
        .map(|(b, _)| b)
        .collect()
}

/// CLEAN: up to `n` beads from the detection map, stopping when the highest remaining maximum is
/// not above `min_peak` (instrument units of the map) or its bead would weigh no more than
/// `min_weight` (reference-bead units); each bead with the height of its maximum in the
/// detection map (the map's units) when it was taken.
pub(crate) fn clean_peaks(
    d: &Image,
    tpl: &Template,
    ch: Channels,
    n: usize,
    min_peak: f64,
    min_weight: f64,
    smooth_um: f64,
) -> Vec<(BeadInit, f64)> {
    let (pu, pv, d0) = template_dmap_peak(tpl, ch);
    if !(d0 > 0.0) {
        return vec![];
    }
    let mut work = d.data.clone();
    let (ax, ay) = (AxisMap::new(&d.x), AxisMap::new(&d.y));
    let ((u0, u1), (v0, v1)) = tpl.extent();
    let sub = |work: &mut Array2<f64>, b: &BeadInit| {
        for r in ay.range(b.y + v0, b.y + v1) {
            for c in ax.range(b.x + u0, b.x + u1) {
                let s = tpl.eval_grad(d.x[c] - b.x, d.y[r] - b.y);
                let t = match ch {
                    Channels::Both => s.du[0] + s.dv[1],
                    Channels::Sx => s.du[0],
                    Channels::Sy => s.dv[1],
                };
                work[[r, c]] -= b.weight * t / tpl.norm_factor;
            }
        }
    };
    let mut out = Vec::new();
    for _ in 0..n {
        // The maximum is looked for on the map smoothed at a physical scale: the finite
        // difference's noise grows as 1/pixel, and at 19 nm pixels its largest spike beat a
        // 59 nm bead 170σ above the noise (a bead 0.9 µm away was "found" in its place).
        let smoothed;
        let look = if smooth_um > 0.0 {
            smoothed = gaussian_smooth(&work, ax.h, ay.h, smooth_um);
            &smoothed
        } else {
            &work
        };
        let mut best: Option<(usize, usize, f64)> = None;
        for ((r, c), &v) in look.indexed_iter() {
            if v.is_finite() && best.is_none_or(|b| v > b.2) {
                best = Some((r, c, v));
            }
        }
        let Some((r, c, v)) = best else { break };
        if !(v > 0.0 && v > min_peak && v * tpl.norm_factor / d0 > min_weight) {
            break;
        }
        let para = |a: Option<f64>, b: f64, cc: Option<f64>| -> f64 {
            match (a, cc) {
                (Some(a), Some(cc)) if a.is_finite() && cc.is_finite() => {
                    let den = a - 2.0 * b + cc;
                    if den < 0.0 {
                        (0.5 * (a - cc) / den).clamp(-0.5, 0.5)
                    } else {
                        0.0
                    }
                }
                _ => 0.0,
            }
        };
        let (rows, cols) = look.dim();
        let fx = para(
            (c > 0).then(|| look[[r, c - 1]]),
            v,
            (c + 1 < cols).then(|| look[[r, c + 1]]),
        );
        let fy = para(
            (r > 0).then(|| look[[r - 1, c]]),
            v,
            (r + 1 < rows).then(|| look[[r + 1, c]]),
        );
        let x = d.x[c] + fx * ax.h - pu;
        let y = d.y[r] + fy * ay.h - pv;
        // Instrument units → reference-bead units: the bead's D peak is C·d0/norm_factor.
        let b = BeadInit {
            x,
            y,
            weight: v * tpl.norm_factor / d0,
        };
        sub(&mut work, &b);
        out.push((b, v));
    }
    out
}

/// The σ of the Gaussian the detection map is smoothed with before its maximum is taken, µm:
/// small beside the map's peak (≈ 0.15 µm wide in the paper's beam: the peak drops by ≈ 4 %),
/// large beside the smallest pixels (10 nm), so the maximum's noise no longer grows as 1/pixel.
pub(crate) const DETECT_SMOOTH_UM: f64 = 0.04;

/// `a` smoothed by a separable Gaussian of σ `sigma_um` (pixels `hx`, `hy` µm), NaN pixels left
/// out of the weighted mean (and NaN where no finite pixel is within reach).
fn gaussian_smooth(a: &Array2<f64>, hx: f64, hy: f64, sigma_um: f64) -> Array2<f64> {
    let kernel = |h: f64| -> Vec<f64> {
        let s = sigma_um / h.abs().max(1e-12);
        let r = (3.0 * s).ceil() as i64;
        (-r..=r)
            .map(|k| (-0.5 * (k as f64 / s).powi(2)).exp())
            .collect()
    };
    let pass = |src: &Array2<f64>, k: &[f64], along_cols: bool| -> Array2<f64> {
        let (rows, cols) = src.dim();
        let r = (k.len() / 2) as i64;
        Array2::from_shape_fn((rows, cols), |(i, j)| {
            let (mut num, mut den) = (0.0, 0.0);
            for (m, w) in k.iter().enumerate() {
                let o = m as i64 - r;
                let (ii, jj) = if along_cols {
                    (i as i64, j as i64 + o)
                } else {
                    (i as i64 + o, j as i64)
                };
                if ii < 0 || jj < 0 || ii >= rows as i64 || jj >= cols as i64 {
                    continue;
                }
                let v = src[[ii as usize, jj as usize]];
                if v.is_finite() {
                    num += w * v;
                    den += w;
                }
            }
            if den > 0.0 {
                num / den
            } else {
                f64::NAN
            }
        })
    };
    let t = pass(a, &kernel(hx), true);
    pass(&t, &kernel(hy), false)
}
