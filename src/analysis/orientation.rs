//! Filament orientation (Sec. 4.2, the 5-step procedure, Fig. 4d).
//!
//! - [`AngleCurve`]: the calibration curve — maximum Sx and Sy sensitivity of a uniform
//!   bead-model filament versus its angle to the QPD y-axis, at 19 angles spanning 180°
//!   (−90°…90° in 10° steps; ±90° are the same orientation and are averaged), computed from the
//!   template through the same measurement pipeline as the data (pixel size, derivative stencil,
//!   parabola window), interpolated periodically (period 180°, cubic convolution).
//! - [`measure_filament`]: steps 4–5 — maximum S_x sensitivity per row and S_y sensitivity per
//!   column, the filament orientation from a straight-line fit through the maxima positions
//!   (rows: x = a + b·y, angle = atan b; columns: y = a + b·x, angle = atan2(1, b)), the channel
//!   chosen as the paper prescribes (closer to the y-axis, |angle| ≤ 45°: S_x per row; closer to
//!   the x-axis: S_y per column), and the correction to the sensitivity the filament would give
//!   along the y-axis: sens_corr = sens × curve.sx(0°)/curve.sx(θ) (rows) or
//!   × curve.sx(0°)/curve.sy(θ) (columns).
//!
//! Angles in degrees, from the +y axis towards +x, in (−90°, 90°].

use super::bead_model::{straight_filament_max_sens, BeadModelOptions};
use super::peaks::{col_peaks, row_peaks, LinePeak, PeakOptions};
use super::sensitivity::{sensitivity, Axis, Stencil};
use super::stats::{linfit, summary};
use super::template::Template;
use super::{check_range, AnalysisError, Result};
use crate::data::Image;
use serde::{Deserialize, Serialize};

/// The measurement pipeline for maximum sensitivities: derivative stencil, parabola window,
/// and detection threshold (per-line SNR; 0 = off).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MeasureOptions {
    pub stencil: Stencil,
    /// Parabola window, µm (paper: 0.4).
    pub window_um: f64,
    /// Per-line maxima below min_snr × line noise are ignored (0: keep all).
    pub min_snr: f64,
    /// Maxima farther than this from the fitted filament line are ignored, µm.
    pub max_offset_um: f64,
    /// Only maxima of at least this fraction of the strongest maxima (90th percentile) are used
    /// to fit the filament line (the sensitivities are then read from every line near it).
    pub line_fraction: f64,
}

impl Default for MeasureOptions {
    fn default() -> Self {
        Self { stencil: Stencil::Central2, window_um: 0.4, min_snr: 0.0, max_offset_um: 0.2, line_fraction: 0.5 }
    }
}

impl MeasureOptions {
    pub(crate) fn validate(&self) -> Result<()> {
        check_range("window_um", self.window_um, 1e-3, 100.0)?;
        check_range("min_snr", self.min_snr, 0.0, 1e6)?;
        check_range("max_offset_um", self.max_offset_um, 0.0, 100.0)?;
        check_range("line_fraction", self.line_fraction, 0.0, 1.0)?;
        Ok(())
    }
    pub(crate) fn peak_options(&self) -> PeakOptions {
        PeakOptions { window_um: self.window_um, min_snr: self.min_snr, ..Default::default() }
    }
}

/// Options of [`AngleCurve::compute`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AngleCurveOptions {
    /// Angles spanning 180° (paper: 19).
    pub n_angles: usize,
    /// Pixel size of the scans the curve will be applied to, µm.
    pub pixel_um: f64,
    /// Bead-model filament: diameter (nm) and index (None: the template's reference bead).
    pub d_nm: Option<f64>,
    pub n: Option<f64>,
    pub bead_model: BeadModelOptions,
    pub measure: MeasureOptions,
}

impl Default for AngleCurveOptions {
    fn default() -> Self {
        Self { n_angles: 19, pixel_um: 0.05, d_nm: None, n: None, bead_model: BeadModelOptions::default(), measure: MeasureOptions::default() }
    }
}

/// Calibration curve of maximum sensitivities versus filament angle (Fig. 4d), normalised so
/// that the S_x maximum at 0° is 1.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AngleCurve {
    /// Angles of the nodes (degrees, −90 ≤ θ < 90, uniform; period 180°).
    pub angles_deg: Vec<f64>,
    /// Normalised maximum S_x and S_y sensitivities at the nodes.
    pub sx: Vec<f64>,
    pub sy: Vec<f64>,
    /// Un-normalised S_x maximum at 0° (reference-bead units): the bead-model sensitivity.
    pub sx0: f64,
    pub options: AngleCurveOptions,
}

impl AngleCurve {
    /// Compute the curve from a template (step 2 of the paper's procedure).
    pub fn compute(tpl: &Template, opts: &AngleCurveOptions) -> Result<AngleCurve> {
        check_range("n_angles", opts.n_angles as f64, 5.0, 721.0)?;
        let d = opts.d_nm.unwrap_or(tpl.reference.d_nm);
        let n = opts.n.unwrap_or(tpl.reference.n);
        let k = opts.n_angles - 1; // unique orientations
        let step = 180.0 / k as f64;
        let mut angles = Vec::with_capacity(k);
        let mut sx = Vec::with_capacity(k);
        let mut sy = Vec::with_capacity(k);
        for i in 0..k {
            let a = -90.0 + i as f64 * step;
            let (x, y) = straight_filament_max_sens(tpl, d, n, a, opts.pixel_um, &opts.measure, &opts.bead_model)?;
            angles.push(a);
            sx.push(x);
            sy.push(y);
        }
        // The node at +90° is the same orientation as −90°: average them.
        let (x90, y90) = straight_filament_max_sens(tpl, d, n, 90.0, opts.pixel_um, &opts.measure, &opts.bead_model)?;
        sx[0] = 0.5 * (sx[0] + x90);
        sy[0] = 0.5 * (sy[0] + y90);
        let mut c = AngleCurve { angles_deg: angles, sx: sx.clone(), sy: sy.clone(), sx0: 1.0, options: *opts };
        let s0 = c.eval_raw(0.0).0;
        if !(s0 > 0.0) {
            return Err(AnalysisError::Failed(format!("bead-model S_x maximum at 0° is {s0}: the template gives no filament signal")));
        }
        c.sx = sx.iter().map(|v| v / s0).collect();
        c.sy = sy.iter().map(|v| v / s0).collect();
        c.sx0 = s0;
        Ok(c)
    }

    fn eval_raw(&self, angle_deg: f64) -> (f64, f64) {
        let k = self.angles_deg.len();
        let step = 180.0 / k as f64;
        let t = (angle_deg + 90.0).rem_euclid(180.0) / step;
        let i = t.floor() as isize;
        let f = t - i as f64;
        let w = keys(f);
        let idx = |j: isize| (j.rem_euclid(k as isize)) as usize;
        let (mut a, mut b) = (0.0, 0.0);
        for (m, wm) in w.iter().enumerate() {
            let j = idx(i - 1 + m as isize);
            a += wm * self.sx[j];
            b += wm * self.sy[j];
        }
        (a, b)
    }

    /// Normalised (S_x, S_y) maximum sensitivity at any angle (periodic cubic interpolation).
    pub fn eval(&self, angle_deg: f64) -> (f64, f64) {
        self.eval_raw(angle_deg)
    }

    /// Correction factor for a filament at `angle_deg` measured in `channel`: multiply the
    /// measured maximum sensitivity by it to get the value along the QPD y-axis (step 5).
    /// Errors when the curve is not positive at that angle in that channel.
    pub fn correction(&self, angle_deg: f64, channel: Channel) -> Result<f64> {
        let (a, b) = self.eval(angle_deg);
        let s0 = self.eval(0.0).0;
        let v = match channel {
            Channel::SxRows => a,
            Channel::SyCols => b,
        };
        if !(v > 1e-6 * s0.abs()) {
            return Err(AnalysisError::Failed(format!(
                "the calibration curve is {v:.3e} at {angle_deg:.1}° in {channel:?}: the filament is invisible there, use the other channel"
            )));
        }
        Ok(s0 / v)
    }
}

fn keys(t: f64) -> [f64; 4] {
    let t2 = t * t;
    let t3 = t2 * t;
    [0.5 * (-t3 + 2.0 * t2 - t), 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0), 0.5 * (-3.0 * t3 + 4.0 * t2 + t), 0.5 * (t3 - t2)]
}

/// Which maxima a filament measurement uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Channel {
    /// ∂Sx/∂x maxima per row (filament closer to the QPD y-axis).
    SxRows,
    /// ∂Sy/∂y maxima per column (filament closer to the QPD x-axis).
    SyCols,
}

/// One maximum along a filament.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FilamentPoint {
    /// Position of the maximum, µm.
    pub x: f64,
    pub y: f64,
    /// Arc position along the filament (projection on its direction), µm, increasing.
    pub arc_um: f64,
    /// Measured maximum sensitivity and its 1σ (None if undetermined).
    pub sens: f64,
    pub sens_err: Option<f64>,
    /// Corrected to the QPD y-axis orientation (step 5).
    pub sens_corr: f64,
}

/// A straight-line fit through maxima positions.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LineFit {
    pub angle_deg: f64,
    pub angle_err_deg: f64,
    /// Intercept and slope (rows: x = a + b·y; columns: y = a + b·x).
    pub a: f64,
    pub b: f64,
    pub n: usize,
}

/// Result of [`measure_filament`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FilamentMeasurement {
    pub channel: Channel,
    pub angle_deg: f64,
    pub angle_err_deg: f64,
    pub line: LineFit,
    /// The other channel's line fit, when it had enough points (for comparison).
    pub other_line: Option<LineFit>,
    /// Correction factor applied (sens_corr = factor·sens).
    pub factor: f64,
    pub points: Vec<FilamentPoint>,
    /// Mean, std and sem of sens_corr over the points.
    pub mean_corr: f64,
    pub std_corr: f64,
    pub sem_corr: f64,
    /// The sensitivity image of the chosen channel (∂Sx/∂x or ∂Sy/∂y), for SBR and plots.
    pub sens: Image,
}

/// Fit a line through the strong maxima of `lines` (rows if `rows`), with 3σ clipping.
fn fit_lines(lines: &[LinePeak], rows: bool, fraction: f64) -> Option<LineFit> {
    let vals: Vec<f64> = lines.iter().filter_map(|l| l.peak().map(|p| p.value)).collect();
    if vals.len() < 3 {
        return None;
    }
    let mut sorted = vals.clone();
    sorted.sort_by(|a, b| a.total_cmp(b));
    let p90 = sorted[((sorted.len() - 1) as f64 * 0.9).round() as usize];
    let thr = fraction * p90;
    let mut pts: Vec<(f64, f64)> = lines.iter().filter_map(|l| l.peak().filter(|p| p.value >= thr).map(|p| (l.coord, p.pos))).collect();
    for _ in 0..5 {
        if pts.len() < 3 {
            return None;
        }
        let (t, s): (Vec<f64>, Vec<f64>) = pts.iter().copied().unzip();
        let f = linfit(&t, &s, None).ok()?;
        let res: Vec<f64> = pts.iter().map(|p| p.1 - f.intercept - f.slope * p.0).collect();
        let sd = super::stats::robust_std(&res).unwrap_or(0.0).max(1e-6);
        let keep: Vec<(f64, f64)> = pts.iter().zip(&res).filter(|(_, r)| r.abs() <= 3.0 * sd).map(|(p, _)| *p).collect();
        if keep.len() == pts.len() {
            let (angle, err) = if rows {
                (f.slope.atan().to_degrees(), (f.slope_err / (1.0 + f.slope * f.slope)).to_degrees())
            } else {
                let mut a = 1.0f64.atan2(f.slope).to_degrees();
                if a > 90.0 {
                    a -= 180.0;
                }
                (a, (f.slope_err / (1.0 + f.slope * f.slope)).to_degrees())
            };
            return Some(LineFit { angle_deg: angle, angle_err_deg: err, a: f.intercept, b: f.slope, n: pts.len() });
        }
        pts = keep;
    }
    None
}

/// Steps 4–5 of Sec. 4.2 on one scan (see the module docs). `sx`, `sy`: the raw channels of an
/// XY scan. Errors: no straight filament found in either channel (fewer than 3 usable maxima),
/// a curve computed at a pixel size differing by more than 5 % from the scan's, bad options.
pub fn measure_filament(sx: &Image, sy: &Image, curve: &AngleCurve, opts: &MeasureOptions) -> Result<FilamentMeasurement> {
    opts.validate()?;
    let px = sx.dx().abs().max(sx.dy().abs());
    if px > 0.0 && ((px - curve.options.pixel_um) / px).abs() > 0.05 {
        return Err(AnalysisError::BadInput {
            name: "curve",
            reason: format!("calibration computed for {} µm pixels, the scan has {px} µm: recompute the curve with pixel_um = {px}", curve.options.pixel_um),
        });
    }
    let sxs = sensitivity(sx, Axis::X, opts.stencil)?;
    let sys = sensitivity(sy, Axis::Y, opts.stencil)?;
    let po = opts.peak_options();
    let rp = row_peaks(&sxs, &po)?;
    let cp = col_peaks(&sys, &po)?;
    let lr = fit_lines(&rp, true, opts.line_fraction);
    let lc = fit_lines(&cp, false, opts.line_fraction);
    let use_rows = match (&lr, &lc) {
        (Some(r), Some(c)) => {
            if r.angle_deg.abs() <= 45.0 && c.angle_deg.abs() >= 45.0 {
                // Both self-consistent (near 45°): the one further from its blind direction.
                r.angle_deg.abs() <= 90.0 - c.angle_deg.abs() || r.n >= c.n
            } else {
                r.angle_deg.abs() <= 45.0 || c.angle_deg.abs() < 45.0 && r.n >= c.n
            }
        }
        (Some(_), None) => true,
        (None, Some(_)) => false,
        (None, None) => {
            return Err(AnalysisError::Failed("no filament found: fewer than 3 aligned maxima of ∂Sx/∂x per row and of ∂Sy/∂y per column".into()));
        }
    };
    let (line, other, lines, sens, channel) = if use_rows {
        (lr.unwrap(), lc, rp, sxs, Channel::SxRows)
    } else {
        (lc.unwrap(), lr, cp, sys, Channel::SyCols)
    };
    let angle = line.angle_deg;
    let factor = curve.correction(angle, channel)?;
    let th = angle.to_radians();
    let dir = (th.sin(), th.cos());
    let mut points = Vec::new();
    for l in &lines {
        let Some(p) = l.peak() else { continue };
        let (x, y) = if use_rows { (p.pos, l.coord) } else { (l.coord, p.pos) };
        // Distance from the fitted line measured along the line direction of the scan axis,
        // converted to perpendicular distance.
        let pred = line.a + line.b * l.coord;
        let along = (p.pos - pred).abs();
        let perp = along / (1.0 + line.b * line.b).sqrt();
        if perp > opts.max_offset_um {
            continue;
        }
        points.push(FilamentPoint { x, y, arc_um: x * dir.0 + y * dir.1, sens: p.value, sens_err: p.value_err, sens_corr: p.value * factor });
    }
    if points.len() < 3 {
        return Err(AnalysisError::Failed(format!("only {} maxima lie on the fitted filament line", points.len())));
    }
    points.sort_by(|a, b| a.arc_um.total_cmp(&b.arc_um));
    let a0 = points[0].arc_um;
    for p in points.iter_mut() {
        p.arc_um -= a0;
    }
    let s = summary(&points.iter().map(|p| p.sens_corr).collect::<Vec<_>>())?;
    Ok(FilamentMeasurement {
        channel,
        angle_deg: angle,
        angle_err_deg: line.angle_err_deg,
        line,
        other_line: other,
        factor,
        points,
        mean_corr: s.mean,
        std_corr: s.std,
        sem_corr: s.sem,
        sens,
    })
}
