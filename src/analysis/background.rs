//! Background removal of point-like objects (Sec. 6): a uniform filament along the QPD y-axis is
//! (nearly) invisible in S_y, while point-like objects (protein aggregates, glass defects) show in
//! both channels. So the point objects are found and fitted in S_y alone (eq. multiBeadFit on one
//! channel), and their S_x templates, with the fitted positions and weights, are subtracted from
//! S_x. For a filament along the x-axis the roles swap: fit S_x, subtract from S_y.
//!
//! (The paper's Sec. 6 says "a uniform filament oriented along the QPD x-axis remains invisible
//! in the S_y channel"; by the symmetry argument of Sec. 4.2 and its own Fig. 6 — microtubule
//! along y, invisible in S_y — it is the filament along the **y**-axis that vanishes from S_y.
//! [`FilamentAxis::Y`] implements the latter.)
//!
//! Detection: CLEAN on the fitted channel's sensitivity (∂Sy/∂y or ∂Sx/∂x, Savitzky–Golay
//! 5-point), smoothed at `DETECT_SMOOTH_UM` (0.04 µm, as `fit_beads` smooths its detection), down
//! to `detect_snr` × the smoothed map's robust noise, and never below objects of `min_weight`
//! reference beads (on noise-free or very quiet data the robust noise is ~0, and CLEAN would
//! otherwise take the filament's own faint residue in that channel for dozens of objects); the
//! edges, where the derivative is one-sided and the smoothing averages fewer pixels, are not
//! searched. CLEAN's components closer than the fit's `min_separation` are merged into one
//! before the fit (`merge_repeated`: where an object's response is not the template's, CLEAN
//! takes the same place again and again). Then the multi-bead fit with bead adding (BIC) up to
//! `max_objects`, its candidates
//! from the unsmoothed map (smoothing along a filament favours its own residue). Objects whose
//! fitted weight is not positive are kept in the fit (they describe the data) but reported.
//!
//! Before 2026-12-06 (fifth session) the detection was not smoothed: at 20 nm pixels one-pixel
//! noise spikes passed 6σ, and each template CLEAN subtracted for one left side lobes that
//! passed next (60 objects, the fit's limit, where a scene held 3 aggregates; 335 s of fit).
//!
//! The premise, a filament that does not show in the fitted channel, is checked by
//! [`filament_visibility`] (the protocol `aggregates::remove` refuses above
//! `analysis::microtubule::MAX_FILAMENT_VISIBILITY`).

use super::fit::{
    clean_peaks, closest_pair, detection_map, fit_beads, merge_pair, noise_within, smoothed_map,
    smoothed_noise, template_dmap_peak, within, BeadInit, Channels, FitOptions, FitResult,
    GrowCandidates, DETECT_SMOOTH_UM,
};
use super::template::Template;
use super::AxisMap;
use super::{check_range, Result};
use crate::data::Image;
use serde::{Deserialize, Serialize};

/// Orientation of the filament whose background is removed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum FilamentAxis {
    /// Along the QPD y-axis: fit S_y, subtract from S_x (Fig. 6).
    #[default]
    Y,
    /// Along the QPD x-axis: fit S_x, subtract from S_y.
    X,
}

impl FilamentAxis {
    /// The channel the point objects are fitted in: the one this filament does not show in.
    pub(crate) fn fitted_channel(self) -> Channels {
        match self {
            FilamentAxis::Y => Channels::Sy,
            FilamentAxis::X => Channels::Sx,
        }
    }

    /// The closer axis for a filament at `angle_deg` from the y-axis.
    pub fn from_angle(angle_deg: f64) -> Self {
        if angle_deg.abs() <= 45.0 {
            FilamentAxis::Y
        } else {
            FilamentAxis::X
        }
    }
}

/// Default smallest object removed, reference-bead units: 1 % of a 110 nm polystyrene bead,
/// below the 40 nm protein aggregates of Sec. 6 (≈ 0.024: (40/110)³ × the Clausius–Mossotti
/// ratio of n = 1.45 to 1.572 in water, 0.50).
pub const DEFAULT_MIN_WEIGHT: f64 = 0.01;

/// After the removal, a point-like feature still standing this many times above the detection
/// map's robust noise is reported ([`BackgroundResult::remaining`]). Why 5: the largest of N
/// independent normal values reaches √(2 ln N) σ, 5.0σ for a 512 × 512 map (and the
/// Savitzky–Golay map has fewer independent pixels), so noise alone gives a 5σ feature in
/// fewer than 1 in 10 such maps (N·P(Z > 5) = 262144 × 2.9e-7 = 0.075), while an object the
/// fit left behind (below `detect_snr` = 6 by default, below `min_weight`, or beyond
/// `max_objects`) at SNR 5–6 and up is reported, not silently kept.
pub const REMAINING_SNR: f64 = 5.0;

/// Rows and columns at each edge left out of the detection map (the half-width of the 5-point
/// derivative stencil: there the derivative is one-sided and its noise larger than the map's;
/// noise alone crossed 5σ there), before the smoothing's own band is added
/// ([`edge_masked_map`]).
const EDGE: usize = 2;

/// The detection map of the fitted channel with NaN in the [`EDGE`] band at each edge, and how many
/// columns and rows from each edge its maxima and its noise are not taken: that band plus the
/// reach of the detection's smoothing ([`DETECT_SMOOTH_UM`], three σ), where the smoothed map
/// averages fewer pixels and its noise is larger than the noise the thresholds are set in.
/// Without that margin, CLEAN took edge noise for objects (a microtubule alone at the paper's
/// noise: 8 "objects" on a 4 µm field, most in the top and bottom rows).
fn edge_masked_map(
    sx: &Image,
    sy: &Image,
    opts: &BackgroundOptions,
) -> Result<(Image, [usize; 2])> {
    let ch = opts.axis.fitted_channel();
    let mut d = detection_map(sx, sy, ch, opts.fit.detect_stencil)?;
    let (rows, cols) = d.data.dim();
    for ((r, c), v) in d.data.indexed_iter_mut() {
        if r < EDGE || c < EDGE || r + EDGE >= rows || c + EDGE >= cols {
            *v = f64::NAN;
        }
    }
    let (ax, ay) = (AxisMap::new(&d.x), AxisMap::new(&d.y));
    let reach = |h: f64| EDGE + (3.0 * DETECT_SMOOTH_UM / h.abs().max(1e-12)).ceil() as usize;
    let skip = [reach(ax.h), reach(ay.h)];
    Ok((d, skip))
}

/// Most remaining features listed (however few objects the fit was allowed).
const MAX_REMAINING: usize = 1000;

/// A point-like feature left in the fitted channel after the removal (see [`REMAINING_SNR`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Remaining {
    /// Position (µm) and weight (reference-bead units) as the detection estimates them.
    pub x: f64,
    pub y: f64,
    pub weight: f64,
    /// Its peak in the detection map over the map's robust noise (before the removal); `None`
    /// on noise-free data.
    pub snr: Option<f64>,
}

/// Options of [`remove_point_background`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct BackgroundOptions {
    pub axis: FilamentAxis,
    /// Initial detections: sensitivity maxima above detect_snr × robust noise of the map.
    pub detect_snr: f64,
    /// Largest number of point objects fitted.
    pub max_objects: usize,
    /// Smallest point object detected, reference-bead units (weight C: a 110 nm polystyrene
    /// bead is 1; a 40 nm protein aggregate ≈ 0.024).
    pub min_weight: f64,
    /// Fit options (channels, init, n_beads and grow are set by this function).
    pub fit: FitOptions,
}

impl Default for BackgroundOptions {
    fn default() -> Self {
        Self {
            axis: FilamentAxis::Y,
            detect_snr: 6.0,
            max_objects: 60,
            min_weight: DEFAULT_MIN_WEIGHT,
            fit: FitOptions::default(),
        }
    }
}

/// Result of [`remove_point_background`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BackgroundResult {
    /// Channels with the fitted point objects subtracted (the filament's channel is the one
    /// that matters: S_x for `FilamentAxis::Y`).
    pub sx: Image,
    pub sy: Image,
    /// The fit of the point objects in the other channel (None when nothing was detected).
    pub fit: Option<FitResult>,
    /// Point-like features still in the fitted channel after the removal, at
    /// [`REMAINING_SNR`] or more (strongest first; none on a clean removal).
    pub remaining: Vec<Remaining>,
    /// The faintest point object the detection takes, reference-bead units: CLEAN's threshold
    /// (`detect_snr` × the smoothed map's robust noise, never below `min_weight`) as a weight.
    /// Objects below it stay in the scan (`None`: the template has no positive peak in the
    /// fitted channel).
    pub detection_limit: Option<f64>,
}

/// The detection threshold of [`remove_point_background`]'s CLEAN (instrument units of the
/// detection map): `detect_snr` × the smoothed map's robust `noise`, and never below the peak
/// of an object of `min_weight` reference beads.
fn clean_threshold(noise: f64, tpl: &Template, opts: &BackgroundOptions) -> f64 {
    let (_, _, d0) = template_dmap_peak(tpl, opts.axis.fitted_channel());
    let floor = if d0 > 0.0 {
        opts.min_weight * d0 / tpl.norm_factor
    } else {
        0.0
    };
    (opts.detect_snr * noise).max(floor)
}

/// [`BackgroundResult::detection_limit`]: CLEAN's threshold at the smoothed map's robust `noise`
/// as a weight (reference-bead units, as CLEAN weighs what it takes: the smoothed map's peak over
/// the template's unsmoothed one, so at most a few % below the weight of an object just taken).
fn detection_limit(noise: f64, tpl: &Template, opts: &BackgroundOptions) -> Option<f64> {
    let (_, _, d0) = template_dmap_peak(tpl, opts.axis.fitted_channel());
    (d0 > 0.0).then(|| clean_threshold(noise, tpl, opts) * tpl.norm_factor / d0)
}

/// How strongly a filament shows in the channel [`remove_point_background`] fits (the premise of
/// Sec. 6 is that it does not): the median of that channel's detection map (smoothed as CLEAN
/// smooths it) at the filament's maxima `at` (x, y µm), over CLEAN's threshold. Near 0 for a
/// filament along the axis; at 1 and above, CLEAN takes the filament itself for a row of point
/// objects, and subtracting their templates erases it from the other channel. `None` when no
/// point of `at` lies on the map or the threshold is 0.
pub fn filament_visibility(
    sx: &Image,
    sy: &Image,
    tpl: &Template,
    opts: &BackgroundOptions,
    at: &[[f64; 2]],
) -> Result<Option<f64>> {
    let (d, skip) = edge_masked_map(sx, sy, opts)?;
    let smooth = smoothed_map(&d, DETECT_SMOOTH_UM);
    let t = clean_threshold(noise_within(&smooth, skip).unwrap_or(0.0), tpl, opts);
    if !(t > 0.0) {
        return Ok(None);
    }
    let (ax, ay) = (AxisMap::new(&d.x), AxisMap::new(&d.y));
    let v: Vec<f64> = at
        .iter()
        .filter_map(|&[x, y]| {
            let c = ax.nearest(x)?;
            let r = ay.nearest(y)?;
            let v = smooth[[r, c]];
            (within(r, c, smooth.dim(), skip) && v.is_finite()).then_some(v)
        })
        .collect();
    Ok(super::stats::median(&v).map(|m| m / t))
}

/// CLEAN's detections and the scale they were found at.
struct Detected {
    init: Vec<BeadInit>,
    /// The smoothed detection map's robust noise (its units).
    noise: f64,
    /// Columns and rows at each edge not searched ([`edge_masked_map`]).
    skip: [usize; 2],
}

fn detect(sx: &Image, sy: &Image, tpl: &Template, opts: &BackgroundOptions) -> Result<Detected> {
    check_range("detect_snr", opts.detect_snr, 0.0, 1e6)?;
    check_range("max_objects", opts.max_objects as f64, 1.0, 10_000.0)?;
    check_range("min_weight", opts.min_weight, 0.0, 1e6)?;
    let (d, skip) = edge_masked_map(sx, sy, opts)?;
    let noise = smoothed_noise(&d, DETECT_SMOOTH_UM, skip).unwrap_or(0.0);
    let init: Vec<BeadInit> = clean_peaks(
        &d,
        tpl,
        opts.axis.fitted_channel(),
        opts.max_objects,
        opts.detect_snr * noise,
        opts.min_weight,
        DETECT_SMOOTH_UM,
        skip,
    )
    .into_iter()
    .map(|(b, _)| b)
    .collect();
    Ok(Detected { init, noise, skip })
}

/// The point objects [`remove_point_background`]'s CLEAN detects (before its fit): positions
/// (µm) and weights (reference-bead units) as the detection estimates them. Cheap beside the
/// removal: a check before it.
pub fn detect_point_objects(
    sx: &Image,
    sy: &Image,
    tpl: &Template,
    opts: &BackgroundOptions,
) -> Result<Vec<BeadInit>> {
    detect(sx, sy, tpl, opts).map(|d| d.init)
}

/// CLEAN's components closer than `min_sep` (µm) merged into one, weights summed, at their
/// weight-averaged position (closest pair first, as the fit merges such pairs after its LM run:
/// here before it). CLEAN takes a component where the residual still peaks; where an object's
/// response is not exactly the template's (an aggregate on the filament) it takes the same
/// place again and again, and each repeat cost the fit an LM run over every bead (one seed-99
/// sweep scene: 60 components at 17 places, 5912 s of fit).
fn merge_repeated(mut init: Vec<BeadInit>, min_sep: f64) -> Vec<BeadInit> {
    while let Some((i, j, _)) = closest_pair(&init, min_sep) {
        let b = init.remove(j);
        init[i] = merge_pair(init[i], b);
    }
    init
}

/// Remove point-like objects from a filament scan (Sec. 6). Errors from the fit (shapes,
/// template coverage) propagate; an image without detectable point objects is returned
/// unchanged with `fit = None`.
pub fn remove_point_background(
    sx: &Image,
    sy: &Image,
    tpl: &Template,
    opts: &BackgroundOptions,
) -> Result<BackgroundResult> {
    let Detected { init, noise, skip } = detect(sx, sy, tpl, opts)?;
    let ch = opts.axis.fitted_channel();
    let detection_limit = detection_limit(noise, tpl, opts);
    // what the same detection still finds after the removal, down to REMAINING_SNR (and, on
    // noise-free data, never below the default smallest object: the filament's faint residue
    // in this channel is not an object)
    let remaining = |sx: &Image, sy: &Image| -> Result<Vec<Remaining>> {
        let (d, _) = edge_masked_map(sx, sy, opts)?;
        Ok(clean_peaks(
            &d,
            tpl,
            ch,
            MAX_REMAINING,
            REMAINING_SNR * noise,
            opts.min_weight.min(DEFAULT_MIN_WEIGHT),
            DETECT_SMOOTH_UM,
            skip,
        )
        .into_iter()
        .map(|(b, v)| Remaining {
            x: b.x,
            y: b.y,
            weight: b.weight,
            snr: (noise > 0.0).then(|| v / noise),
        })
        .collect())
    };
    if init.is_empty() {
        return Ok(BackgroundResult {
            sx: sx.clone(),
            sy: sy.clone(),
            fit: None,
            remaining: remaining(sx, sy)?,
            detection_limit,
        });
    }
    let init = merge_repeated(init, opts.fit.min_separation * opts.fit.w0_um);
    let fo = FitOptions {
        channels: ch,
        init: Some(init),
        n_beads: None,
        grow: true,
        max_beads: opts.max_objects,
        detect_smooth_um: 0.0,
        grow_candidates: GrowCandidates::DetectionMap,
        ..opts.fit.clone()
    };
    let fit = fit_beads(sx, sy, tpl, &fo)?;
    let sub = |img: &Image, m: &Image| {
        let mut out = img.clone();
        out.data = &img.data - &m.data;
        out
    };
    let (csx, csy) = (sub(sx, &fit.model_sx), sub(sy, &fit.model_sy));
    let remaining = remaining(&csx, &csy)?;
    Ok(BackgroundResult {
        sx: csx,
        sy: csy,
        fit: Some(fit),
        remaining,
        detection_limit,
    })
}

/// Where a removed point object's subtraction can move a filament's maxima: the offsets (u, v)
/// from the object, on a square grid of `step_um` out to ±`half_um`, at which its template's
/// derivative along the measured channel's axis (∂Sx/∂x for a filament along y, ∂Sy/∂y along x:
/// what `measure_filament` reads) is at least [`FOOTPRINT_FRAC`] of its peak. An error of the
/// object's fitted weight or position moves a maximum there by at least that fraction of its
/// effect at the object; `microtubule::density` leaves such maxima out of μ (a cleaned scan
/// carries the footprint and the objects in its metadata, `background_removed`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Footprint {
    pub step_um: f64,
    pub half_um: f64,
    /// One string per v (from −half to +half), one character per u: '1' inside, '0' outside.
    pub rows: Vec<String>,
}

/// The fraction of a removed object's peak derivative that bounds its [`Footprint`]: along the
/// filament the default template's reaches 0.36 µm, across it the derivative's negative lobe
/// 0.27–0.66 µm and its ring at 0.82–0.98 µm. In the truth sweep's microtubules (seed 2026,
/// N = 2000), leaving these maxima out took the in-domain answers with objects removed from a
/// mean error of −0.54σ and 2σ coverage 0.89 to −0.1σ and 0.94 (the same answers replayed).
/// Tried and not kept: a reach scaled by each object's weight against the filament's level
/// (at 5 % of it) left fewer maxima near bright objects and did worse (2σ coverage 0.91, one
/// answer at 4.4σ).
pub const FOOTPRINT_FRAC: f64 = 0.1;

/// Half the side of the footprint's grid, µm: beyond 1 µm the default template's derivative
/// stays below 3 % of its peak.
const FOOTPRINT_HALF_UM: f64 = 1.0;

/// The footprint's grid step, µm.
const FOOTPRINT_STEP_UM: f64 = 0.025;

impl Footprint {
    /// The footprint of `tpl` for a filament along `axis` (see [`Footprint`]).
    pub fn of(tpl: &Template, axis: FilamentAxis) -> Footprint {
        let der = |u: f64, v: f64| {
            let s = tpl.eval_grad(u, v);
            match axis {
                FilamentAxis::Y => s.du[0].abs(),
                FilamentAxis::X => s.dv[1].abs(),
            }
        };
        let peak = der(0.0, 0.0);
        let (h, st) = (FOOTPRINT_HALF_UM, FOOTPRINT_STEP_UM);
        let n = (2.0 * h / st).round() as usize;
        let rows = (0..=n)
            .map(|iv| {
                let v = -h + iv as f64 * st;
                (0..=n)
                    .map(|iu| {
                        let u = -h + iu as f64 * st;
                        if der(u, v) >= FOOTPRINT_FRAC * peak {
                            '1'
                        } else {
                            '0'
                        }
                    })
                    .collect()
            })
            .collect();
        Footprint {
            step_um: st,
            half_um: h,
            rows,
        }
    }

    /// Whether the offset (u, v) µm from an object lies inside (the nearest grid node's).
    pub fn contains(&self, u: f64, v: f64) -> bool {
        if u.abs() > self.half_um || v.abs() > self.half_um || !(self.step_um > 0.0) {
            return false;
        }
        let iu = ((u + self.half_um) / self.step_um).round() as usize;
        let iv = ((v + self.half_um) / self.step_um).round() as usize;
        self.rows
            .get(iv)
            .and_then(|r| r.as_bytes().get(iu))
            .is_some_and(|&c| c == b'1')
    }
}

#[cfg(test)]
mod footprint_tests {
    use super::{FilamentAxis, Footprint, FOOTPRINT_FRAC};
    use crate::analysis::template::Template;

    /// The closed-form stand-in Sx = u·g, g = exp(−r²/w²): ∂Sx/∂u = (1 − 2u²/w²)·g, whose
    /// peak is 1 at the origin. Along v it falls to FOOTPRINT_FRAC at w·√(ln 1/FOOTPRINT_FRAC);
    /// along u it crosses zero at w/√2 and has a negative lobe of depth 2e^(−3/2) at w·√(3/2).
    #[test]
    fn the_footprint_of_the_closed_form_template_follows_its_derivative() {
        let w = 0.3;
        let tpl = Template::analytic_standin(w, 0.01, 1.6).unwrap();
        let f = Footprint::of(&tpl, FilamentAxis::Y);
        let d = |u: f64| ((1.0 - 2.0 * u * u / (w * w)) * (-(u * u) / (w * w)).exp()).abs();
        // along the filament (v): the reach w·√(ln 10) = 0.455 µm, within a grid step
        let reach_v = w * (1.0 / FOOTPRINT_FRAC).ln().sqrt();
        assert!(f.contains(0.0, 0.0) && f.contains(0.0, reach_v - 0.03));
        assert!(f.contains(0.0, -(reach_v - 0.03)));
        assert!(!f.contains(0.0, reach_v + 0.03) && !f.contains(0.0, -(reach_v + 0.03)));
        // across it (u): the central lobe, the zero crossing, the negative lobe and its edge
        let zero = w / 2f64.sqrt();
        let lobe = w * 1.5f64.sqrt();
        assert!(d(lobe) > FOOTPRINT_FRAC && d(zero) < 1e-12);
        assert!(!f.contains(zero, 0.0) && !f.contains(-zero, 0.0));
        assert!(f.contains(lobe, 0.0) && f.contains(-lobe, 0.0));
        // the lobe's outer edge by bisection on the closed form
        let (mut a, mut b) = (lobe, 3.0 * w);
        for _ in 0..60 {
            let m = 0.5 * (a + b);
            if d(m) > FOOTPRINT_FRAC {
                a = m
            } else {
                b = m
            }
        }
        assert!(
            f.contains(a - 0.03, 0.0) && !f.contains(a + 0.03, 0.0),
            "edge {a}"
        );
        assert!(!f.contains(0.99, 0.99) && !f.contains(5.0, 0.0));
        // a filament along x reads ∂Sy/∂y: the same footprint with u and v swapped
        let g = Footprint::of(&tpl, FilamentAxis::X);
        for (u, v) in [
            (0.0, 0.3),
            (0.3, 0.0),
            (0.0, lobe),
            (lobe, 0.0),
            (0.2, 0.35),
        ] {
            assert_eq!(f.contains(u, v), g.contains(v, u), "({u}, {v})");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn b(x: f64, y: f64, weight: f64) -> BeadInit {
        BeadInit { x, y, weight }
    }

    #[test]
    fn cleans_repeats_are_one_object_with_their_summed_weight() {
        // three places, CLEAN's components 0.01–0.03 µm apart at each; min_sep 0.12 µm
        let init = vec![
            b(-0.74, -0.43, 0.10),
            b(0.25, -0.39, 0.06),
            b(-0.73, -0.42, 0.05),
            b(1.27, -0.36, 0.02),
            b(0.26, -0.37, 0.04),
            b(-0.75, -0.41, 0.05),
        ];
        let m = merge_repeated(init, 0.12);
        assert_eq!(m.len(), 3, "{m:?}");
        let at = |x: f64| m.iter().find(|p| (p.x - x).abs() < 0.05).copied().unwrap();
        // weights add; the position is the weight-averaged one
        let a = at(-0.74);
        assert!((a.weight - 0.20).abs() < 1e-12, "{a:?}");
        let xa = (-0.74 * 0.10 - 0.73 * 0.05 - 0.75 * 0.05) / 0.20;
        let ya = (-0.43 * 0.10 - 0.42 * 0.05 - 0.41 * 0.05) / 0.20;
        assert!(
            (a.x - xa).abs() < 1e-12 && (a.y - ya).abs() < 1e-12,
            "{a:?}"
        );
        let c = at(0.25);
        assert!((c.weight - 0.10).abs() < 1e-12, "{c:?}");
        assert!(
            (c.x - 0.254).abs() < 1e-12 && (c.y + 0.382).abs() < 1e-12,
            "{c:?}"
        );
        assert_eq!(at(1.27), b(1.27, -0.36, 0.02));
        // two objects just beyond the separation stay two
        let two = merge_repeated(vec![b(0.0, 0.0, 0.1), b(0.121, 0.0, 0.1)], 0.12);
        assert_eq!(two.len(), 2);
    }
}
