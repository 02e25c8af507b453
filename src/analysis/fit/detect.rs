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
    Ok(clean(&d, tpl, channels, n, DETECT_SMOOTH_UM))
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
pub(crate) fn template_dmap_peak(tpl: &Template, ch: Channels) -> (f64, f64, f64) {
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
pub(crate) fn clean(
    d: &Image,
    tpl: &Template,
    ch: Channels,
    n: usize,
    smooth_um: f64,
) -> Vec<BeadInit> {
    clean_peaks(d, tpl, ch, n, 0.0, 0.0, smooth_um, [0, 0])
        .into_iter()
        .map(|(b, _)| b)
        .collect()
}

/// CLEAN: up to `n` beads from the detection map, stopping when the highest remaining maximum is
/// not above `min_peak` (instrument units of the map) or its bead would weigh no more than
/// `min_weight` (reference-bead units); each bead with the height of its maximum in the
/// detection map (the map's units) when it was taken. Maxima are looked for at least `skip`
/// (columns, rows) pixels from the map's edges.
#[allow(clippy::too_many_arguments)]
pub(crate) fn clean_peaks(
    d: &Image,
    tpl: &Template,
    ch: Channels,
    n: usize,
    min_peak: f64,
    min_weight: f64,
    smooth_um: f64,
    skip: [usize; 2],
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
        let (rows, cols) = look.dim();
        for ((r, c), &v) in look.indexed_iter() {
            if v.is_finite() && within(r, c, (rows, cols), skip) && best.is_none_or(|b| v > b.2) {
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

/// The robust noise (1.4826·MAD) of the detection map `d` smoothed as [`clean_peaks`] smooths
/// it before taking its maxima (σ `smooth_um`; 0: not smoothed): the scale its thresholds are
/// set in, over the pixels at least `skip` (columns, rows) from the edges. `None` when none of
/// them is finite.
pub(crate) fn smoothed_noise(d: &Image, smooth_um: f64, skip: [usize; 2]) -> Option<f64> {
    noise_within(&smoothed_map(d, smooth_um), skip)
}

/// The robust noise (1.4826·MAD) of the pixels of `m` at least `skip` (columns, rows) from its
/// edges; `None` when none of them is finite.
pub(crate) fn noise_within(m: &Array2<f64>, skip: [usize; 2]) -> Option<f64> {
    let dim = m.dim();
    let v: Vec<f64> = m
        .indexed_iter()
        .filter(|((r, c), _)| within(*r, *c, dim, skip))
        .map(|(_, &v)| v)
        .collect();
    crate::analysis::stats::robust_std(&v)
}

/// Is pixel (`r`, `c`) of a map of `(rows, cols)` at least `skip` (columns, rows) from its edges?
pub(crate) fn within(r: usize, c: usize, (rows, cols): (usize, usize), skip: [usize; 2]) -> bool {
    r >= skip[1] && c >= skip[0] && r + skip[1] < rows && c + skip[0] < cols
}

/// The detection map `d` smoothed as [`clean_peaks`] smooths it (σ `smooth_um`; 0: a copy).
pub(crate) fn smoothed_map(d: &Image, smooth_um: f64) -> Array2<f64> {
    if smooth_um > 0.0 {
        let (ax, ay) = (AxisMap::new(&d.x), AxisMap::new(&d.y));
        gaussian_smooth(&d.data, ax.h, ay.h, smooth_um)
    } else {
        d.data.clone()
    }
}

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

/// The grow step's candidates: where one more bead, of the template's shape and any positive
/// weight, lowers χ² of the residuals `rx`, `ry` the most. The matched filter: a bead at c
/// lowers χ² by (Σ T_c·R)² / (σ²·Σ T_c²) (the linear least-squares gain of its weight, T_c the
/// template centred on c, the sums over the fitted channels' valid pixels), so the candidates
/// are the `k` strongest local maxima of g(c) = (Σ T_c·R)² / Σ T_c² with Σ T_c·R > 0, strongest
/// first. This is the detector a bead in white noise calls for: the derivative map of
/// [`clean`] at 17 nm pixels and 7× the paper's noise offered only its noise maxima while a
/// 47 nm bead 56σ strong (a χ² gain of ~3 000) was never tried. The sums run on the residuals
/// binned to about `w0_um`/8 (the template barely changes over a bin), candidates at the
/// bins' centres refined by a parabola through the gain's neighbours; each candidate's weight
/// is Σ T·R / Σ T² (reference-bead units).
pub(crate) fn matched_candidates(
    rx: &Image,
    ry: &Image,
    tpl: &Template,
    ch: Channels,
    k: usize,
    w0_um: f64,
) -> Vec<BeadInit> {
    let (ax, ay) = (AxisMap::new(&rx.x), AxisMap::new(&rx.y));
    if ax.n == 0 || ay.n == 0 || ax.h == 0.0 || ay.h == 0.0 {
        return vec![];
    }
    let pitch = w0_um / 8.0;
    let bin = |h: f64| ((pitch / h.abs()).round() as usize).max(1);
    let (bx, by) = (bin(ax.h), bin(ay.h));
    let (mx, my) = (ax.n / bx, ay.n / by);
    if mx == 0 || my == 0 {
        return vec![];
    }
    let (ox, oy) = ((ax.n - mx * bx) / 2, (ay.n - my * by) / 2);
    let chans = ch.list();
    // binned residuals: the mean of each channel's valid pixels, and their count
    let mut mean = vec![[0.0f64; 2]; mx * my];
    let mut count = vec![[0.0f64; 2]; mx * my];
    for (ci, &c) in chans.iter().enumerate() {
        let img = if c == 0 { rx } else { ry };
        for j in 0..my {
            for i in 0..mx {
                let (mut s, mut n) = (0.0, 0.0);
                for r in oy + j * by..oy + (j + 1) * by {
                    for q in ox + i * bx..ox + (i + 1) * bx {
                        let v = img.data[[r, q]];
                        if v.is_finite() {
                            s += v;
                            n += 1.0;
                        }
                    }
                }
                if n > 0.0 {
                    mean[j * mx + i][ci] = s / n;
                    count[j * mx + i][ci] = n;
                }
            }
        }
    }
    // the template on the bins' lattice of offsets, its negligible tail left out
    let (px, py) = (bx as f64 * ax.h, by as f64 * ay.h);
    let ((u0, u1), (v0, v1)) = tpl.extent();
    let reach = |lo: f64, hi: f64, p: f64| -> (i64, i64) {
        let (a, b) = ((lo / p).ceil() as i64, (hi / p).floor() as i64);
        (a.min(b), a.max(b))
    };
    let (di0, di1) = reach(u0, u1, px);
    let (dj0, dj1) = reach(v0, v1, py);
    let mut kern: Vec<(i64, i64, [f64; 2])> = Vec::new();
    let mut peak = 0.0f64;
    for dj in dj0..=dj1 {
        for di in di0..=di1 {
            let s = tpl.eval(di as f64 * px, dj as f64 * py);
            let t = [s[chans[0]], chans.get(1).map_or(0.0, |&c| s[c])];
            peak = peak.max(t[0].abs()).max(t[1].abs());
            kern.push((di, dj, t));
        }
    }
    kern.retain(|(_, _, t)| t[0].abs().max(t[1].abs()) > 1e-4 * peak);
    if !(peak > 0.0) {
        return vec![];
    }
    // the gain and the weight's numerator at every bin centre
    use rayon::prelude::*;
    let cells: Vec<(f64, f64, f64)> = (0..mx * my)
        .into_par_iter()
        .map(|idx| {
            let (i, j) = ((idx % mx) as i64, (idx / mx) as i64);
            let (mut num, mut den) = (0.0, 0.0);
            for &(di, dj, t) in &kern {
                let (ii, jj) = (i + di, j + dj);
                if ii < 0 || jj < 0 || ii >= mx as i64 || jj >= my as i64 {
                    continue;
                }
                let b = jj as usize * mx + ii as usize;
                for ci in 0..chans.len() {
                    let n = count[b][ci];
                    num += n * t[ci] * mean[b][ci];
                    den += n * t[ci] * t[ci];
                }
            }
            let gain = if num > 0.0 && den > 0.0 {
                num * num / den
            } else {
                0.0
            };
            (gain, num, den)
        })
        .collect();
    let g = |i: i64, j: i64| -> Option<f64> {
        (i >= 0 && j >= 0 && i < mx as i64 && j < my as i64)
            .then(|| cells[j as usize * mx + i as usize].0)
    };
    let mut maxima: Vec<(f64, usize)> = (0..mx * my)
        .filter(|&idx| {
            let (i, j) = ((idx % mx) as i64, (idx / mx) as i64);
            let v = cells[idx].0;
            v > 0.0
                && (-1..=1).all(|dj| {
                    (-1..=1).all(|di| {
                        (di == 0 && dj == 0)
                            || g(i + di, j + dj)
                                .is_none_or(|w| w < v || (w == v && (dj, di) > (0, 0)))
                    })
                })
        })
        .map(|idx| (cells[idx].0, idx))
        .collect();
    maxima.sort_by(|a, b| b.0.total_cmp(&a.0));
    let centre = |o: usize, m: usize, b: usize, a: &[f64]| -> f64 {
        let lo = o + m * b;
        a[lo..lo + b].iter().sum::<f64>() / b as f64
    };
    maxima
        .into_iter()
        .take(k)
        .map(|(v, idx)| {
            let (i, j) = (idx % mx, idx / mx);
            let para = |a: Option<f64>, c: Option<f64>| match (a, c) {
                (Some(a), Some(c)) if a - 2.0 * v + c < 0.0 => {
                    (0.5 * (a - c) / (a - 2.0 * v + c)).clamp(-0.5, 0.5)
                }
                _ => 0.0,
            };
            let (i_, j_) = (i as i64, j as i64);
            let fx = para(g(i_ - 1, j_), g(i_ + 1, j_));
            let fy = para(g(i_, j_ - 1), g(i_, j_ + 1));
            let (_, num, den) = cells[idx];
            BeadInit {
                x: centre(ox, i, bx, &rx.x) + fx * px,
                y: centre(oy, j, by, &rx.y) + fy * py,
                weight: num / den * tpl.norm_factor,
            }
        })
        .collect()
}
