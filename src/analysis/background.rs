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
//! 5-point) down to `detect_snr` × its robust noise, and never below objects of `min_weight`
//! reference beads (on noise-free or very quiet data the robust noise is ~0, and CLEAN would
//! otherwise take the filament's own faint residue in that channel for dozens of objects);
//! then the multi-bead fit with bead adding (BIC) up to `max_objects`. Objects whose fitted weight is not positive are kept in the fit
//! (they describe the data) but reported.

use super::fit::{
    clean_peaks, detection_map, fit_beads, BeadInit, Channels, FitOptions, FitResult,
    GrowCandidates,
};
use super::stats::robust_std;
use super::template::Template;
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

/// Rows and columns at each edge left out of the search for remaining features (the half-width
/// of the 5-point derivative stencil).
const EDGE: usize = 2;

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
    check_range("detect_snr", opts.detect_snr, 0.0, 1e6)?;
    check_range("max_objects", opts.max_objects as f64, 1.0, 10_000.0)?;
    check_range("min_weight", opts.min_weight, 0.0, 1e6)?;
    let ch = match opts.axis {
        FilamentAxis::Y => Channels::Sy,
        FilamentAxis::X => Channels::Sx,
    };
    let d = detection_map(sx, sy, ch, opts.fit.detect_stencil)?;
    let noise = robust_std(&d.data.iter().copied().collect::<Vec<_>>()).unwrap_or(0.0);
    let init: Vec<BeadInit> = clean_peaks(
        &d,
        tpl,
        ch,
        opts.max_objects,
        opts.detect_snr * noise,
        opts.min_weight,
        0.0,
    )
    .into_iter()
    .map(|(b, _)| b)
    .collect();
    // what the same detection still finds after the removal, down to REMAINING_SNR (and, on
    // noise-free data, never below the default smallest object: the filament's faint residue
    // in this channel is not an object)
    let remaining = |sx: &Image, sy: &Image| -> Result<Vec<Remaining>> {
        let mut d = detection_map(sx, sy, ch, opts.fit.detect_stencil)?;
        // the two outermost rows and columns are left out: there the 5-point derivative is
        // one-sided and its noise larger than the map's (noise alone crossed 5σ there)
        let (rows, cols) = d.data.dim();
        for ((r, c), v) in d.data.indexed_iter_mut() {
            if r < EDGE || c < EDGE || r + EDGE >= rows || c + EDGE >= cols {
                *v = f64::NAN;
            }
        }
        Ok(clean_peaks(
            &d,
            tpl,
            ch,
            MAX_REMAINING,
            REMAINING_SNR * noise,
            opts.min_weight.min(DEFAULT_MIN_WEIGHT),
            0.0,
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
        });
    }
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
    })
}
