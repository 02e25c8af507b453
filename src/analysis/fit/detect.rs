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
    clean_peaks(d, tpl, ch, n, 0.0, 0.0)
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
        let mut best: Option<(usize, usize, f64)> = None;
        for ((r, c), &v) in work.indexed_iter() {
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
        let (rows, cols) = work.dim();
        let fx = para(
            (c > 0).then(|| work[[r, c - 1]]),
            v,
            (c + 1 < cols).then(|| work[[r, c + 1]]),
        );
        let fy = para(
            (r > 0).then(|| work[[r - 1, c]]),
            v,
            (r + 1 < rows).then(|| work[[r + 1, c]]),
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
