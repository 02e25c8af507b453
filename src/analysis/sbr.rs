//! Signal-to-background ratio of a filament (Sec. 6), both ways the paper defines it:
//!
//! (a) `sbr_background` = mean maximum sensitivity along the filament / standard deviation of
//!     the sensitivity image in a region away from the filament (pixels farther than
//!     `exclusion_um` from the fitted filament line);
//! (b) `sbr_uniformity` = mean / standard deviation of the maximum sensitivity along the
//!     filament.
//!
//! Region rule: the filament's ends are excluded — the analysis starts `skip_um` (paper: 1.2 µm)
//! after the first non-zero maximum and, with `both_ends`, stops `skip_um` before the last one.
//! A "non-zero maximum" is a row (column) maximum lying on the fitted filament line (within
//! `MeasureOptions::max_offset_um`) and above `nonzero_snr` × the background std (default 0: any
//! maximum on the line), and the first one must start a run of at least `min_run` consecutive
//! rows (columns) on the line — beyond the filament's end, maxima are noise at random positions
//! and only rarely several in a row on the line. Sensitivities are the raw maxima of the
//! measured channel (the orientation correction would scale signal and background alike).

use super::orientation::{Channel, FilamentMeasurement};
use super::stats::summary;
use super::{check_range, AnalysisError, Result};
use serde::{Deserialize, Serialize};

/// Options of [`sbr`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SbrOptions {
    /// Skipped arc length from the first (and last) non-zero maximum, µm.
    pub skip_um: f64,
    pub both_ends: bool,
    /// Background pixels are farther than this from the filament line, µm.
    pub exclusion_um: f64,
    /// A maximum is "non-zero" above nonzero_snr × background std (0: any maximum on the line).
    pub nonzero_snr: f64,
    /// Consecutive lines on the filament needed to start (and end) it.
    pub min_run: usize,
}

impl Default for SbrOptions {
    fn default() -> Self {
        Self { skip_um: 1.2, both_ends: true, exclusion_um: 1.0, nonzero_snr: 0.0, min_run: 3 }
    }
}

/// Result of [`sbr`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SbrResult {
    /// Method (a).
    pub sbr_background: f64,
    /// Method (b).
    pub sbr_uniformity: f64,
    /// Mean and std of the maxima in the region, signal units/µm.
    pub mean_sens: f64,
    pub std_sens: f64,
    /// Std of the sensitivity image away from the filament.
    pub background_std: f64,
    /// Arc-length range analysed, µm (measured from the first maximum of the measurement).
    pub arc_start: f64,
    pub arc_end: f64,
    pub n_points: usize,
    pub n_background: usize,
}

/// SBR of a measured filament (see the module docs). Errors: no background pixels (filament
/// fills the image), no non-zero maximum, a region shorter than two maxima after the skips.
pub fn sbr(meas: &FilamentMeasurement, opts: &SbrOptions) -> Result<SbrResult> {
    check_range("skip_um", opts.skip_um, 0.0, 1e4)?;
    check_range("exclusion_um", opts.exclusion_um, 0.0, 1e4)?;
    check_range("nonzero_snr", opts.nonzero_snr, 0.0, 1e6)?;
    check_range("min_run", opts.min_run as f64, 1.0, 1e6)?;
    let img = &meas.sens;
    let (a, b) = (meas.line.a, meas.line.b);
    let norm = (1.0 + b * b).sqrt();
    let mut bg = Vec::new();
    for r in 0..img.rows() {
        for c in 0..img.cols() {
            let v = img.data[[r, c]];
            if !v.is_finite() {
                continue;
            }
            let (x, y) = (img.x[c], img.y[r]);
            let d = match meas.channel {
                Channel::SxRows => (x - a - b * y).abs() / norm,
                Channel::SyCols => (y - a - b * x).abs() / norm,
            };
            if d > opts.exclusion_um {
                bg.push(v);
            }
        }
    }
    if bg.len() < 2 {
        return Err(AnalysisError::Failed(format!(
            "no background region: fewer than 2 pixels lie more than {} µm from the filament",
            opts.exclusion_um
        )));
    }
    let bs = summary(&bg)?;
    let thr = opts.nonzero_snr * bs.std;
    let ok: Vec<&super::orientation::FilamentPoint> = meas.points.iter().filter(|p| p.sens > thr).collect();
    let run = opts.min_run.max(1);
    // Points are in arc order; consecutive lines differ by 1 in index.
    let starts_run = |seq: &[&super::orientation::FilamentPoint], k: usize| -> bool {
        if k + run > seq.len() {
            return false;
        }
        (k..k + run - 1).all(|i| seq[i].line.abs_diff(seq[i + 1].line) == 1)
    };
    let first = (0..ok.len()).find(|&k| starts_run(&ok, k)).map(|k| ok[k]);
    let rev: Vec<&super::orientation::FilamentPoint> = ok.iter().rev().copied().collect();
    let last = (0..rev.len()).find(|&k| starts_run(&rev, k)).map(|k| rev[k]);
    let (Some(first), Some(last)) = (first, last) else {
        return Err(AnalysisError::Failed(format!(
            "no non-zero maximum along the filament: no run of {run} consecutive lines above {thr:.3e} on the line"
        )));
    };
    let start = first.arc_um + opts.skip_um;
    let end = if opts.both_ends { last.arc_um - opts.skip_um } else { f64::INFINITY };
    let vals: Vec<f64> = meas.points.iter().filter(|p| p.arc_um >= start && p.arc_um <= end).map(|p| p.sens).collect();
    if vals.len() < 2 {
        return Err(AnalysisError::Failed(format!(
            "fewer than 2 maxima between {start:.2} and {end:.2} µm: the filament is too short for {} µm skips",
            opts.skip_um
        )));
    }
    let s = summary(&vals)?;
    let safe = |num: f64, den: f64| if den > 0.0 { num / den } else { f64::MAX };
    Ok(SbrResult {
        sbr_background: safe(s.mean, bs.std),
        sbr_uniformity: safe(s.mean, s.std),
        mean_sens: s.mean,
        std_sens: s.std,
        background_std: bs.std,
        arc_start: start,
        arc_end: end.min(last.arc_um),
        n_points: s.n,
        n_background: bs.n,
    })
}
