//! Focus search (suppl. S5): from an XZ (or YZ) scan of a small object, the maximum sensitivity
//! of each z row (parabola over `window_um`, as in Sec. 5), then the best z by a parabola through
//! the row maxima around the best row (over `z_window_um`), with its uncertainty, and the z range
//! over which the maximum sensitivity stays within `level` (paper: 98 %) of its peak.
//!
//! Input: the channel image with the lateral scan axis as columns and z as rows (Sx of an XZ
//! scan; Sy of a YZ scan with y as columns). Units: z and positions in µm.

use super::peaks::{peak_1d, row_peaks, LinePeak, PeakOptions};
use super::sensitivity::{sensitivity, Axis, Stencil};
use super::{check_range, AnalysisError, Result};
use crate::data::Image;
use serde::{Deserialize, Serialize};

/// Options of [`focus_search`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FocusOptions {
    pub stencil: Stencil,
    /// Lateral parabola window, µm.
    pub window_um: f64,
    /// Window of the parabola over z, µm.
    pub z_window_um: f64,
    /// Fraction of the peak defining the tolerated z range (paper: 0.98).
    pub level: f64,
}

impl Default for FocusOptions {
    fn default() -> Self {
        Self {
            stencil: Stencil::Central2,
            window_um: 0.4,
            z_window_um: 0.6,
            level: 0.98,
        }
    }
}

/// Result of [`focus_search`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FocusResult {
    /// Best z (µm) and its 1σ (None when the parabola has no residual degrees of freedom).
    pub z_best: f64,
    pub z_err: Option<f64>,
    /// Maximum sensitivity at z_best.
    pub max_sens: f64,
    pub max_sens_err: Option<f64>,
    /// Lower and upper z where the sensitivity falls to `level`·max_sens: the crossings of the
    /// fitted parabola over z when they lie inside its window (robust to the noise of single
    /// rows), otherwise the first row maxima below the level walking out from the best row
    /// (linear interpolation); None on a side where they stay above it up to the end of the scan.
    pub z_lo: Option<f64>,
    pub z_hi: Option<f64>,
    /// Per-row maxima (rows are z).
    pub rows: Vec<LinePeak>,
    /// Where the answer leaves its domain, in words; empty when z_best and its σ hold.
    #[serde(default)]
    pub warnings: Vec<String>,
}

/// Best focus from an XZ/YZ scan channel (see the module docs). Errors: fewer than 3 rows with a
/// maximum, no maximum over z (best row at the scan's end: extend the z range), bad options.
pub fn focus_search(img: &Image, opts: &FocusOptions) -> Result<FocusResult> {
    check_range("z_window_um", opts.z_window_um, 1e-3, 1e3)?;
    check_range("level", opts.level, 0.0, 1.0)?;
    super::kind::require_plane("focus_search", img, &["XZ", "YZ"])?;
    let sens = sensitivity(img, Axis::X, opts.stencil)?;
    let rows = row_peaks(
        &sens,
        &PeakOptions {
            window_um: opts.window_um,
            ..Default::default()
        },
    )?;
    let z: Vec<f64> = rows.iter().map(|r| r.coord).collect();
    let v: Vec<f64> = rows
        .iter()
        .map(|r| r.peak().map(|p| p.value).unwrap_or(f64::NAN))
        .collect();
    let n_ok = v.iter().filter(|x| x.is_finite()).count();
    if n_ok < 3 {
        return Err(AnalysisError::Failed(format!(
            "only {n_ok} z rows show a sensitivity maximum; at least 3 are needed"
        )));
    }
    let p = peak_1d(
        &z,
        &v,
        &PeakOptions {
            window_um: opts.z_window_um,
            ..Default::default()
        },
    )
    .map_err(|m| AnalysisError::Failed(format!("no maximum of the sensitivity over z: {m}")))?;
    let thr = opts.level * p.value;
    // Walk outwards from the best row to the first crossings.
    let ib = p.index;
    let cross = |range: Box<dyn Iterator<Item = usize>>| -> Option<f64> {
        let mut prev = ib;
        for i in range {
            if v[i].is_finite() {
                if v[i] < thr {
                    let f = (v[prev] - thr) / (v[prev] - v[i]);
                    return Some(z[prev] + f * (z[i] - z[prev]));
                }
                prev = i;
            }
        }
        None
    };
    let a = cross(Box::new((0..ib).rev()));
    let b = cross(Box::new(ib + 1..z.len()));
    let (z_lo, z_hi) = match (a, b) {
        (Some(a), Some(b)) => (Some(a.min(b)), Some(a.max(b))),
        (a, b) => {
            if z.first() <= z.last() {
                (a, b)
            } else {
                (b, a)
            }
        }
    };
    // The level crossings of the fitted parabola, z_best ± √(2(1 − level)·max/|2c|): robust to
    // the noise of the individual row maxima (a 2 % band is easily within it). Used when they
    // lie inside the fitted window and the scan; otherwise the walked crossings above.
    let half = (2.0 * (1.0 - opts.level) * p.value / -p.curvature).sqrt();
    let (zmin, zmax) = (z[0].min(z[z.len() - 1]), z[0].max(z[z.len() - 1]));
    let (z_lo, z_hi) = if half.is_finite()
        && half <= 0.5 * opts.z_window_um
        && p.pos - half >= zmin
        && p.pos + half <= zmax
    {
        (Some(p.pos - half), Some(p.pos + half))
    } else {
        (z_lo, z_hi)
    };
    let mut warnings = warnings(&z, &p, lateral_edge(&sens, &rows));
    warnings.extend(detection(img, opts.stencil, p.value));
    Ok(FocusResult {
        z_best: p.pos,
        z_err: p.pos_err,
        max_sens: p.value,
        max_sens_err: p.value_err,
        z_lo,
        z_hi,
        rows,
        warnings,
    })
}

/// The warnings of a focus search: the best z within one and a half rows of the scan's
/// end (the parabola then leans on one side only), the lateral maximum of the best rows at the
/// scan's edge.
fn warnings(z: &[f64], p: &super::peaks::Peak, edge: Option<String>) -> Vec<String> {
    let mut w = vec![];
    let (zmin, zmax) = (z[0].min(z[z.len() - 1]), z[0].max(z[z.len() - 1]));
    let step = if z.len() > 1 {
        (zmax - zmin) / (z.len() - 1) as f64
    } else {
        0.0
    };
    if p.pos - zmin < 1.5 * step || zmax - p.pos < 1.5 * step {
        w.push(format!(
            "the best z = {:.3} µm is within one and a half rows of the end of the scan's z range [{zmin:.3}, {zmax:.3}] µm: the maximum may lie beyond it; widen the z range",
            p.pos
        ));
    }
    w.extend(edge);
    w
}

/// Detection threshold of a focus search: the best sensitivity (the parabola over z through
/// the rows' parabola maxima) over the 1σ noise of one sensitivity pixel. The parabolas
/// average the noise: on the simulator at the paper's detector noise, a 41 × 41 XZ scan of an
/// empty field gave 0.5–1.2× (9 seeds), a 110 nm polystyrene bead 4.0–4.3× at 1 ms per pixel
/// and 1.6–2.1× at 0.1 ms (where one answer in eight was 0.4 µm off). The pixel noise is
/// measured robustly from the data, and an object's own structure raises it a little (by a
/// third next to the bead): a conservative scale.
pub const FOCUS_DETECT_SNR: f64 = 2.5;

/// A warning when the best sensitivity `best` is below [`FOCUS_DETECT_SNR`] × the noise of one
/// sensitivity pixel: no object in range, the "maximum" is noise. The noise is the image's
/// robust pixel noise (`domain::pixel_noise`, first differences along the lateral axis)
/// through the stencil's noise gain, σ(∂S/∂x) = gain · σ(S) / h (Sec. 3.2). None on noise-free
/// data (no noise to compare with).
fn detection(img: &Image, stencil: Stencil, best: f64) -> Option<String> {
    let n = img.x.len();
    let h = if n > 1 {
        (img.x[n - 1] - img.x[0]).abs() / (n - 1) as f64
    } else {
        return None;
    };
    let sigma = stencil.noise_gain() * super::domain::pixel_noise(img, true) / h;
    (sigma > 0.0 && best.is_finite() && best < FOCUS_DETECT_SNR * sigma).then(|| {
        format!(
            "no object in range: the best sensitivity {best:.4} is {:.1}× the noise of one sensitivity pixel ({sigma:.4}), below the detection threshold of {FOCUS_DETECT_SNR}×: the maximum is noise, z_best means nothing (is an object within the scan's lateral and z range?)",
            best / sigma
        )
    })
}

/// A warning when the rows' maxima sit within half a parabola window of the lateral edge.
fn lateral_edge(sens: &Image, rows: &[LinePeak]) -> Option<String> {
    let (x0, x1) = (
        sens.x[0].min(sens.x[sens.x.len() - 1]),
        sens.x[0].max(sens.x[sens.x.len() - 1]),
    );
    let best = rows
        .iter()
        .filter_map(|r| r.peak())
        .max_by(|a, b| a.value.total_cmp(&b.value))?;
    let step = (x1 - x0) / (sens.x.len().max(2) - 1) as f64;
    (best.pos - x0 < 1.5 * step || x1 - best.pos < 1.5 * step).then(|| {
        format!(
            "the object's maximum at x = {:.3} µm is at the scan's lateral edge [{x0:.3}, {x1:.3}] µm: centre the object in the scan",
            best.pos
        )
    })
}
