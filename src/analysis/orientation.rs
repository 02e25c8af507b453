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
//! **Finding the filament among other objects.** The line is found robustly: every local
//! maximum of each row (column) above `detect_snr` × the pixel noise of the sensitivity image
//! (robust, from first differences) is a candidate
//! (sub-pixel by the parabola), a RANSAC search (deterministic, 4000 candidate pairs from lines at
//! least 5 apart) picks the line with the most rows (columns) having a candidate within
//! `max_offset_um`, refined by least squares on the inliers. The maxima along the filament are
//! then read from each row (column) by a parabola over `window_um` centred where the line crosses
//! it, so point objects elsewhere in the row do not replace the filament's maximum and the noisy
//! discrete maximum does not bias the value upwards. The maxima must form one filament
//! (`kind::check_filament_maxima`: not a single point object, whatever the scan's size and noise; `kind::check_filament_continuity`:
//! not point objects in a row with no signal between them); if the preferred channel's line
//! fails, the other channel's line is tried. [`measure_filament_along`] does the last step for a
//! given line (e.g. to measure the same filament before and after background removal).
//!
//! Angles in degrees, from the +y axis towards +x, in (−90°, 90°].

use super::bead_model::{straight_filament_max_sens, BeadModelOptions};
pub use super::measure::MeasureOptions;
use super::peaks::{peak_1d, peak_at, PeakOptions};
use super::sensitivity::{sensitivity, Axis};
use super::stats::{linfit, robust_std, summary};
use super::template::Template;
use super::{check_range, AnalysisError, Result};
use crate::data::Image;
use crate::optics::grid::keys_weights;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Options of [`AngleCurve::compute`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AngleCurveOptions {
    /// Angles spanning 180° (paper: 19).
    pub n_angles: usize,
    /// Pixel size of the scans the curve will be applied to, µm. The Rust default is 0.05 µm;
    /// the `angle_curve` binding requires it (or takes it from a scan), and `measure_filament`
    /// refuses a scan whose pixel size differs by more than 5 % (docs/physics.md §11).
    pub pixel_um: f64,
    /// Bead-model filament: diameter (nm) and index (None: the template's reference bead).
    pub d_nm: Option<f64>,
    pub n: Option<f64>,
    pub bead_model: BeadModelOptions,
    pub measure: MeasureOptions,
}

impl Default for AngleCurveOptions {
    fn default() -> Self {
        Self {
            n_angles: 19,
            pixel_um: 0.05,
            d_nm: None,
            n: None,
            bead_model: BeadModelOptions::default(),
            measure: MeasureOptions::default(),
        }
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
    /// The template's norm_factor (reference-bead units per instrument unit): measurements
    /// convert scan sensitivities with it.
    #[serde(default = "one")]
    pub norm_factor: f64,
    pub options: AngleCurveOptions,
    /// The template the curve was computed from (not saved with the curve): the forward model
    /// of the Cramér–Rao bounds `measure_filament` attaches (`FilamentMeasurement::crlb`).
    #[serde(skip)]
    pub template: Option<std::sync::Arc<Template>>,
}

fn one() -> f64 {
    1.0
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
            let (x, y) = straight_filament_max_sens(
                tpl,
                d,
                n,
                a,
                opts.pixel_um,
                &opts.measure,
                &opts.bead_model,
            )?;
            angles.push(a);
            sx.push(x);
            sy.push(y);
        }
        // The node at +90° is the same orientation as −90°: average them.
        let (x90, y90) = straight_filament_max_sens(
            tpl,
            d,
            n,
            90.0,
            opts.pixel_um,
            &opts.measure,
            &opts.bead_model,
        )?;
        sx[0] = 0.5 * (sx[0] + x90);
        sy[0] = 0.5 * (sy[0] + y90);
        let mut c = AngleCurve {
            angles_deg: angles,
            sx: sx.clone(),
            sy: sy.clone(),
            sx0: 1.0,
            norm_factor: tpl.norm_factor,
            options: *opts,
            template: Some(std::sync::Arc::new(tpl.clone())),
        };
        let s0 = c.eval_raw(0.0).0;
        if !(s0 > 0.0) {
            return Err(AnalysisError::Failed(format!(
                "bead-model S_x maximum at 0° is {s0}: the template gives no filament signal"
            )));
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
        let w = keys_weights(f);
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
    /// Row (S_x) or column (S_y) index the maximum comes from.
    pub line: usize,
    /// Position of the maximum, µm.
    pub x: f64,
    pub y: f64,
    /// Arc position along the filament (projection on its direction), µm, increasing.
    pub arc_um: f64,
    /// Measured maximum sensitivity and its 1σ (None if undetermined), reference-bead units/µm
    /// (the scan's value × the template's norm_factor).
    pub sens: f64,
    pub sens_err: Option<f64>,
    /// Corrected to the QPD y-axis orientation (step 5).
    pub sens_corr: f64,
    /// At least `end_margin_um` from every end of the filament inside the scan: only these
    /// maxima enter the mean (an end lowers the maxima near it).
    #[serde(default = "yes")]
    pub interior: bool,
}

fn yes() -> bool {
    true
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
    /// Arc positions (µm, on the points' arc axis) of the filament's ends inside the scan, where
    /// its maxima fall to half their plateau; None where it runs out of the scan.
    #[serde(default)]
    pub ends_um: [Option<f64>; 2],
    /// Where the answer leaves its domain, in words; empty when the mean and its σ hold.
    #[serde(default)]
    pub warnings: Vec<String>,
    /// The sensitivity image of the chosen channel (∂Sx/∂x or ∂Sy/∂y) in reference-bead
    /// units/µm, for SBR and plots.
    pub sens: Image,
    /// Cramér–Rao bounds of the straight bead-model filament at the measured line and
    /// sensitivity (see [`FilamentCrlb`]); None when the curve carries no template (a curve
    /// loaded from a file) or the bound does not exist (no noise, no signal).
    #[serde(default)]
    pub crlb: Option<FilamentCrlb>,
}

/// The information limit of a filament measurement: the Cramér–Rao bounds (1σ floors) of the
/// whole-image straight bead-model filament (`analysis::filament_fit`) at the measured angle,
/// line and sensitivity, from the scan's Sx and Sy pixels with their robust pixel noise.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FilamentCrlb {
    pub angle_deg: f64,
    /// Perpendicular position of the line, µm.
    pub offset_um: f64,
    /// Of `mean_corr`, reference-bead units/µm.
    pub mean_corr: f64,
    /// Relative bound of the linear density (= of mean_corr) and of the diameter.
    pub lin_dens_rel: f64,
    pub diameter_rel: f64,
    /// Pixel noise used (Sx, Sy; instrument units): 1.4826·MAD/√2 of the first differences
    /// along the image axis closer to the filament's (robust to the objects' signal).
    pub sigma: [f64; 2],
}

/// A candidate maximum: (line index, line coordinate, position along the line, value).
type Cand = (usize, f64, f64, f64);

/// Pixel noise of a sensitivity image from first differences along its lines (robust to the
/// objects' extended signal): 1.4826·MAD/√2, in the image's units.
fn pixel_noise(sens: &Image, rows: bool) -> f64 {
    let mut diffs = Vec::with_capacity(sens.data.len());
    let lines: Box<dyn Iterator<Item = ndarray::ArrayView1<f64>>> = if rows {
        Box::new(sens.data.rows().into_iter())
    } else {
        Box::new(sens.data.columns().into_iter())
    };
    for r in lines {
        diffs.extend(
            r.windows(2)
                .into_iter()
                .map(|w| w[1] - w[0])
                .filter(|d| d.is_finite()),
        );
    }
    robust_std(&diffs).unwrap_or(0.0) / std::f64::consts::SQRT_2
}

/// 1σ of a parabola's value at the centre of a window of ±`half` over samples every `step`, per
/// unit of sample noise: √((XᵀX)⁻¹₀₀) of the least-squares quadratic, = S4/(n·S4 − S2²) under
/// the root for the symmetric abscissae k (n samples, S2 = Σk², S4 = Σk⁴).
fn parabola_value_noise(half: f64, step: f64) -> f64 {
    if !(step > 0.0 && half >= step) {
        return f64::NAN;
    }
    let m = (half / step + 1e-9).floor() as i64;
    let (mut n, mut s2, mut s4) = (0.0, 0.0, 0.0);
    for i in -m..=m {
        let k = i as f64 * step / half;
        n += 1.0;
        s2 += k * k;
        s4 += k.powi(4);
    }
    let det = n * s4 - s2 * s2;
    if det > 0.0 {
        (s4 / det).sqrt()
    } else {
        f64::NAN
    }
}

/// What the filament checks need of a sensitivity image, computed once per scan: its pixel
/// noise along its lines ([`pixel_noise`]) and its largest value (instrument units).
#[derive(Clone, Copy)]
struct Levels {
    noise: f64,
    max: f64,
}

impl Levels {
    fn of(sens: &Image, rows: bool) -> Levels {
        Levels {
            noise: pixel_noise(sens, rows),
            max: sens
                .data
                .iter()
                .cloned()
                .filter(|v| v.is_finite())
                .fold(0.0, f64::max),
        }
    }
}

/// Candidate maxima of the lines of `sens` (`noise`: its pixel noise).
fn candidates(sens: &Image, rows: bool, noise: f64, opts: &MeasureOptions) -> Vec<Cand> {
    let thr = (opts.detect_snr * noise).max(0.0);
    let (nl, t): (usize, &[f64]) = if rows {
        (sens.rows(), &sens.x)
    } else {
        (sens.cols(), &sens.y)
    };
    let po = PeakOptions {
        window_um: opts.window_um,
        ..Default::default()
    };
    let mut out = Vec::new();
    for l in 0..nl {
        let v: Vec<f64> = if rows {
            sens.data.row(l).to_vec()
        } else {
            sens.data.column(l).to_vec()
        };
        let coord = if rows { sens.y[l] } else { sens.x[l] };
        let mut loc: Vec<(usize, f64)> = (1..v.len().saturating_sub(1))
            .filter(|&i| v[i].is_finite() && v[i] > thr && v[i] > v[i - 1] && v[i] >= v[i + 1])
            .map(|i| (i, v[i]))
            .collect();
        loc.sort_by(|a, b| b.1.total_cmp(&a.1));
        loc.truncate(6);
        for (i, _) in loc {
            // Parabola on the neighbourhood of this local maximum only.
            let (lo, hi) = (t[i] - opts.window_um, t[i] + opts.window_um);
            let idx: Vec<usize> = (0..v.len())
                .filter(|&k| t[k] >= lo.min(hi) && t[k] <= hi.max(lo))
                .collect();
            let tt: Vec<f64> = idx.iter().map(|&k| t[k]).collect();
            let vv: Vec<f64> = idx.iter().map(|&k| v[k]).collect();
            if let Ok(p) = peak_1d(&tt, &vv, &po) {
                if (p.pos - t[i]).abs() <= 0.5 * opts.window_um {
                    out.push((l, coord, p.pos, p.value));
                }
            }
        }
    }
    out
}

/// Perpendicular distance of a candidate from the line pos = a + b·coord.
#[inline]
fn dist(a: f64, b: f64, coord: f64, pos: f64) -> f64 {
    (pos - a - b * coord).abs() / (1.0 + b * b).sqrt()
}

/// For each line, the candidate closest to the line (if within `tol`).
fn inliers(c: &[Cand], a: f64, b: f64, tol: f64) -> Vec<Cand> {
    let mut best: std::collections::BTreeMap<usize, (f64, Cand)> =
        std::collections::BTreeMap::new();
    for &p in c {
        let d = dist(a, b, p.1, p.2);
        if d <= tol && best.get(&p.0).is_none_or(|q| d < q.0) {
            best.insert(p.0, (d, p));
        }
    }
    best.into_values().map(|v| v.1).collect()
}

/// Relative 1σ of the orientation-corrected mean that no amount of data removes, for a filament
/// at `angle_deg` (from the y axis): the correction curve's interpolation between its angles
/// and the parabola's sub-pixel bias against the curve's own offset average. Noise-free straight
/// fibrils of the truth sweep (`bfpscope sweep --replay`, 2–8 µm, 20–100 nm pixels, several
/// positions) read within 0.05–0.15 % of the truth in the diameter (0.1–0.3 % in the mean) away
/// from 45°, and up to 0.4 % in the diameter near 45° (most at 100 nm pixels, where a row
/// crosses the line obliquely over few pixels): [`CORRECTION_SYS_REL`] ⊕
/// [`CORRECTION_SYS_REL_45`]·exp(−((|angle| − 45°)/10°)²). (A flat 0.3 % made the diameter's
/// 1σ intervals hold 77 % of the seed-7 sweep's answers; without any term a low-noise answer's
/// σ, 0.02 %, made those 4σ errors.)
pub fn correction_sys_rel(angle_deg: f64) -> f64 {
    let a = angle_deg.abs().min(180.0 - angle_deg.abs());
    CORRECTION_SYS_REL.hypot(CORRECTION_SYS_REL_45 * (-((a - 45.0) / 10.0).powi(2)).exp())
}

/// [`correction_sys_rel`] away from 45°, relative to the corrected mean.
pub const CORRECTION_SYS_REL: f64 = 0.0015;

/// [`correction_sys_rel`]'s bump at 45°, relative to the corrected mean.
pub const CORRECTION_SYS_REL_45: f64 = 0.006;

/// Above this relative σ of the corrected mean (the σ of a diameter from it is half), the answer
/// is flagged: a fibril diameter is wanted to 5 % (Sec. 4.3), which needs σ_d ≤ 1.25 % to hold
/// at 4σ.
pub const MAX_REL_SEM: f64 = 0.025;

/// The filament angle (degrees from the y axis, in (−90, 90]) of the line pos = a + slope·coord
/// through row maxima (`rows`: x against y) or column maxima (y against x).
fn line_angle(slope: f64, rows: bool) -> f64 {
    if rows {
        slope.atan().to_degrees()
    } else {
        let mut a = 1.0f64.atan2(slope).to_degrees();
        if a > 90.0 {
            a -= 180.0;
        }
        a
    }
}

/// RANSAC line through candidates (see the module docs).
fn ransac_line(c: &[Cand], rows: bool, tol: f64) -> Option<LineFit> {
    if c.len() < 3 {
        return None;
    }
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut next = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 33) as usize
    };
    // Score: the number of lines with an inlier, then the summed sensitivity of the inliers (a
    // faint filament among strong point objects must beat a line through a few of them). The
    // focus's side lobes (the vector beam's overshoot, the derivative's) put a parallel line of
    // weak maxima 0.7–0.8 µm beside a filament; near 45° that line can cross more of the scan's
    // lines than the filament itself (an 85 nm fibril at −43° was measured on its 11 % lobe, 60
    // lines against 42). So the line of most lines × median maximum is also kept, and it wins
    // when it runs parallel to the first within the lobe's distance: then the first is its lobe.
    let mut best: Option<(usize, f64, f64, f64)> = None;
    let mut best_m: Option<(f64, f64, f64)> = None;
    for _ in 0..4000 {
        let (i, j) = (next() % c.len(), next() % c.len());
        let (p, q) = (c[i], c[j]);
        if p.0.abs_diff(q.0) < 5 {
            continue;
        }
        let b = (q.2 - p.2) / (q.1 - p.1);
        let a = p.2 - b * p.1;
        let inl = inliers(c, a, b, tol);
        let (n, sum) = (inl.len(), inl.iter().map(|p| p.3).sum::<f64>());
        if best.is_none_or(|bb| n > bb.0 || (n == bb.0 && sum > bb.3)) {
            best = Some((n, a, b, sum));
        }
        let vals: Vec<f64> = inl.iter().map(|p| p.3).collect();
        let score = n as f64 * super::stats::median(&vals).unwrap_or(0.0).max(0.0);
        if best_m.is_none_or(|bb| score > bb.0) {
            best_m = Some((score, a, b));
        }
    }
    let (_, mut a, mut b, _) = best?;
    if let Some((_, am, bm)) = best_m {
        let mid = c.iter().map(|p| p.1).sum::<f64>() / c.len() as f64;
        let offset = dist(a, b, mid, am + bm * mid);
        let parallel = (b.atan() - bm.atan()).abs().to_degrees() < 3.0;
        if parallel && offset >= LOBE_SEARCH_UM.0 && offset <= LOBE_SEARCH_UM.1 {
            (a, b) = (am, bm);
        }
    }
    let mut pts = Vec::new();
    for _ in 0..3 {
        pts = inliers(c, a, b, tol);
        if pts.len() < 3 {
            return None;
        }
        let t: Vec<f64> = pts.iter().map(|p| p.1).collect();
        let s: Vec<f64> = pts.iter().map(|p| p.2).collect();
        let f = linfit(&t, &s, None).ok()?;
        a = f.intercept;
        b = f.slope;
    }
    let t: Vec<f64> = pts.iter().map(|p| p.1).collect();
    let s: Vec<f64> = pts.iter().map(|p| p.2).collect();
    let f = linfit(&t, &s, None).ok()?;
    let err = (f.slope_err / (1.0 + f.slope * f.slope)).to_degrees();
    let angle = line_angle(f.slope, rows);
    Some(LineFit {
        angle_deg: angle,
        angle_err_deg: err,
        a: f.intercept,
        b: f.slope,
        n: pts.len(),
    })
}

/// Steps 4–5 of Sec. 4.2 on one scan (see the module docs). `sx`, `sy`: the raw channels of an
/// XY scan. Errors: no straight filament found in either channel (fewer than 3 aligned maxima),
/// a curve computed at a pixel size differing by more than 5 % from the scan's, bad options.
pub fn measure_filament(
    sx: &Image,
    sy: &Image,
    curve: &AngleCurve,
    opts: &MeasureOptions,
) -> Result<FilamentMeasurement> {
    opts.validate()?;
    super::kind::require_plane("measure_filament", sx, &["XY"])?;
    check_pixel(sx, curve)?;
    let sxs = sensitivity(sx, Axis::X, opts.stencil)?;
    let sys = sensitivity(sy, Axis::Y, opts.stencil)?;
    let levels = [Levels::of(&sxs, true), Levels::of(&sys, false)];
    // A faint filament among strong point objects may clear `detect_snr` in too few lines for
    // its line to win the search; the maxima checks keep a lower threshold from taking a line
    // of point objects, so the search is repeated at lower thresholds before giving up.
    let mut first_err = None;
    let mut tried = Vec::new();
    for scale in RETRY_SNR_SCALES {
        let o = MeasureOptions {
            detect_snr: opts.detect_snr * scale,
            ..*opts
        };
        if tried.contains(&o.detect_snr) {
            continue;
        }
        tried.push(o.detect_snr);
        match find_filament(&sxs, &sys, levels, curve, &o) {
            Ok(mut m) => {
                if let Some(w) = side_lobe_check(&m)? {
                    m.warnings.push(w);
                }
                m.warnings.extend(row_snr_check(&m));
                let rel = m.sem_corr / m.mean_corr;
                if !(rel <= MAX_REL_SEM) {
                    m.warnings.push(format!(
                        "the corrected mean is known to {:.1} % (sem_corr/mean_corr): a diameter from it only to {:.1} %, short of the 5 % a fibril diameter needs; measure a longer stretch or dwell longer",
                        100.0 * rel,
                        50.0 * rel
                    ));
                }
                m.crlb = measurement_crlb(sx, sy, curve, &m).ok();
                return Ok(m);
            }
            Err(e) => {
                first_err.get_or_insert(e);
            }
        }
    }
    Err(match first_err {
        Some(AnalysisError::Failed(m)) if tried.len() > 1 => AnalysisError::Failed(format!(
            "{m} (searched with candidate maxima above {} × the pixel noise)",
            tried
                .iter()
                .map(|t| format!("{t}"))
                .collect::<Vec<_>>()
                .join(", ")
        )),
        Some(e) => e,
        None => AnalysisError::Failed("no filament found".into()),
    })
}

/// One interior maximum against its own 1σ (the median of the rows' parabolas), corrected
/// mean over corrected σ; None where no parabola has a σ.
fn row_snr(m: &FilamentMeasurement) -> Option<f64> {
    let errs: Vec<f64> = m
        .points
        .iter()
        .filter(|p| p.interior)
        .filter_map(|p| p.sens_err)
        .collect();
    let e = super::stats::median(&errs)? * m.factor.abs();
    (e > 0.0).then(|| m.mean_corr / e)
}

/// A warning where one maximum stands under [`FILAMENT_ROW_SNR`] σ of its own noise.
fn row_snr_check(m: &FilamentMeasurement) -> Option<String> {
    let k = row_snr(m).filter(|&k| k < FILAMENT_ROW_SNR)?;
    Some(format!(
        "one maximum along the filament is {k:.1}σ of its own noise, below {FILAMENT_ROW_SNR}σ: the mean and its sem are not verified for maxima that faint (dwell longer, or use larger pixels)"
    ))
}

/// One maximum along a filament (a row's parabola over the fixed window on the line) must
/// stand this many σ of its own noise for the mean of the maxima to hold. Below it a row's
/// curvature is as noisy as its value, and the vertex's second-order bias correction, taken at
/// the noisy curvature, over-corrects: in the truth sweep (seed 2026, 2000 fibrils) a 58 nm
/// fibril at 7.7× the paper's noise and 20 nm pixels, its maxima at 6σ, read 3.4 % thin at
/// 4.2σ. Flagging below 6σ, 8σ and 10σ left 318, 311 and 301 of 328 answers in the domain with
/// 1σ coverage 0.742, 0.749 and 0.764 and none beyond 4σ; the answers at the lowest SNR
/// (small pixels at high noise) still lean low by 0.7σ on average. Since the maxima are read
/// where the neighbours put the filament ([`at_neighbours_vertex`], 2026-12-07) that cause is
/// gone: flagging below 4σ or 6σ kept the fibril sweeps calibrated with no outlier at seeds
/// 2026, 7 and 99 (334/356/375 and 320/341/367 answers in the domain against 310/329/358 at
/// 8σ; 1σ 0.71–0.75, 2σ 0.95–0.96), and the flag is at 4σ since 2026-12-07 (twelfth
/// session), with the microtubule family measured there (docs/accuracy.md).
pub const FILAMENT_ROW_SNR: f64 = 4.0;

/// Perpendicular distances (µm) from a filament line at which its own side lobes are looked
/// for: the focus's overshoot puts a parallel line of maxima of ∂S/∂x about 0.7–0.8 µm beside a
/// filament in the paper's beam (measured on the simulator's vector focus), at 9–11 % of the
/// filament's own maxima.
const LOBE_SEARCH_UM: (f64, f64) = (0.45, 1.1);

/// Whether the measured line could be a side lobe of a stronger parallel filament (see
/// [`LOBE_SEARCH_UM`]): refused when, at most of the interior maxima where both sides were
/// seen, the sensitivity within the search band beside the line exceeds twice the maximum on
/// it; flagged when no interior maximum has both sides of the band inside the scan (the line
/// runs within ~1 µm of the scan's edge, where the filament could lie beyond it).
fn side_lobe_check(m: &FilamentMeasurement) -> Result<Option<String>> {
    use crate::optics::grid::Interp;
    let th = m.angle_deg.to_radians();
    let nrm = (th.cos(), -th.sin());
    let step = m.sens.dx().abs().max(m.sens.dy().abs()).max(0.01);
    let (mut seen, mut stronger) = (0usize, 0usize);
    for p in m.points.iter().filter(|p| p.interior) {
        let mut both = true;
        let mut beside = f64::NEG_INFINITY;
        for side in [-1.0, 1.0] {
            let mut r = LOBE_SEARCH_UM.0;
            while r <= LOBE_SEARCH_UM.1 {
                let (x, y) = (p.x + side * r * nrm.0, p.y + side * r * nrm.1);
                match super::profile::sample(&m.sens, x, y, Interp::Linear) {
                    Some(v) => beside = beside.max(v),
                    None => both = false,
                }
                r += step;
            }
        }
        if both {
            seen += 1;
            stronger += (beside > 2.0 * p.sens) as usize;
        }
    }
    if seen > 0 && 2 * stronger > seen {
        return Err(AnalysisError::Failed(format!(
            "the maxima are a side lobe: at {stronger} of {seen} maxima a line {:.2}–{:.2} µm beside them is more than twice as strong; the filament itself is that line",
            LOBE_SEARCH_UM.0, LOBE_SEARCH_UM.1
        )));
    }
    Ok((seen == 0).then(|| {
        format!(
            "the line runs within {:.1} µm of the scan's edge along its whole measured stretch: it may be the side lobe (9–11 %) of a filament beyond the edge; scan with the filament at least {:.1} µm inside",
            LOBE_SEARCH_UM.1, LOBE_SEARCH_UM.1
        )
    }))
}

/// The Cramér–Rao bounds of a measured filament (see [`FilamentCrlb`]): the line through the
/// scan's centre row (column) as measured, λ = mean_corr·λ_curve/sx0 (the curve's filament has
/// weight per length λ_curve and the maximum sensitivity sx0 at 0°, and the corrected
/// sensitivity is proportional to λ), both channels with their robust pixel noise.
fn measurement_crlb(
    sx: &Image,
    sy: &Image,
    curve: &AngleCurve,
    m: &FilamentMeasurement,
) -> Result<FilamentCrlb> {
    use super::filament_fit::{lambda_of_diameter, line_crlb, LineFilament};
    let tpl = curve.template.as_ref().ok_or_else(|| {
        AnalysisError::Failed("the curve carries no template (loaded from a file)".into())
    })?;
    let d = curve.options.d_nm.unwrap_or(tpl.reference.d_nm);
    let n = curve.options.n.unwrap_or(tpl.reference.n);
    let lambda = m.mean_corr * lambda_of_diameter(tpl, d, n)? / curve.sx0;
    let mid = |a: &[f64]| 0.5 * (a[0] + a[a.len() - 1]);
    let centre = match m.channel {
        Channel::SxRows => {
            let y = mid(&sx.y);
            [m.line.a + m.line.b * y, y]
        }
        Channel::SyCols => {
            let x = mid(&sx.x);
            [x, m.line.a + m.line.b * x]
        }
    };
    // first differences along the image axis closer to the filament's: the filament's own
    // signal varies least that way
    let along_rows = m.angle_deg.abs() > 45.0;
    let sigma = [pixel_noise(sx, along_rows), pixel_noise(sy, along_rows)];
    let fil = LineFilament {
        centre,
        offset_um: 0.0,
        angle_deg: m.angle_deg,
        lambda,
        background: [0.0, 0.0],
        spacing_um: curve.options.bead_model.spacing_nm * 1e-3,
    };
    let valid = |ch: usize, r: usize, c: usize| {
        let img = if ch == 0 { sx } else { sy };
        img.data[[r, c]].is_finite().then_some(sigma[ch])
    };
    let b = line_crlb(tpl, &fil, &sx.x, &sx.y, &[0, 1], &valid)?;
    Ok(FilamentCrlb {
        angle_deg: b.angle_deg,
        offset_um: b.offset_um,
        mean_corr: b.lambda_rel * m.mean_corr.abs(),
        lin_dens_rel: b.lambda_rel,
        diameter_rel: b.diameter_rel,
        sigma,
    })
}

/// Fractions of `detect_snr` at which [`measure_filament`] searches for the filament's line,
/// in order (4σ, 3σ, 2.5σ at the default).
pub const RETRY_SNR_SCALES: [f64; 3] = [1.0, 0.75, 0.625];

/// One search of [`measure_filament`] at `opts.detect_snr`: the line in each channel, the
/// preferred one measured first; if its maxima are not one filament (a point object, or point
/// objects in a row with no filament signal between them), the other channel's line if it is
/// self-consistent. Both failing: the preferred line's reason.
fn find_filament(
    sxs: &Image,
    sys: &Image,
    levels: [Levels; 2],
    curve: &AngleCurve,
    opts: &MeasureOptions,
) -> Result<FilamentMeasurement> {
    let lr = ransac_line(
        &candidates(sxs, true, levels[0].noise, opts),
        true,
        opts.max_offset_um,
    );
    let lc = ransac_line(
        &candidates(sys, false, levels[1].noise, opts),
        false,
        opts.max_offset_um,
    );
    let frac_r = lr.map(|l| l.n as f64 / sxs.rows() as f64).unwrap_or(0.0);
    let frac_c = lc.map(|l| l.n as f64 / sys.cols() as f64).unwrap_or(0.0);
    let ok_r = lr.is_some_and(|l| l.angle_deg.abs() <= 45.0);
    let ok_c = lc.is_some_and(|l| l.angle_deg.abs() >= 45.0);
    let use_rows = match (ok_r, ok_c) {
        // Both self-consistent: the one covering more of its lines.
        (true, true) => frac_r >= frac_c,
        (true, false) => true,
        (false, true) => false,
        (false, false) => match (lr, lc) {
            (None, None) => {
                return Err(AnalysisError::Failed("no filament found: fewer than 3 aligned maxima of ∂Sx/∂x per row and of ∂Sy/∂y per column".into()));
            }
            _ => frac_r >= frac_c,
        },
    };
    let rows_line = (lr, lc, Channel::SxRows, sxs, levels[0], ok_r);
    let cols_line = (lc, lr, Channel::SyCols, sys, levels[1], ok_c);
    let order = if use_rows {
        [rows_line, cols_line]
    } else {
        [cols_line, rows_line]
    };
    let mut first_err = None;
    for (i, (line, other, channel, sens, lv, ok)) in order.into_iter().enumerate() {
        let Some(line) = line else { continue };
        if i > 0 && !ok {
            continue;
        }
        let attempt = measure_sens_along(sens.clone(), curve, channel, line, opts).and_then(
            |(m, trace, sigma, short)| {
                // one maximum's 1σ: the parabolas' own, and at least what the image's pixel
                // noise gives a parabola over the window. At coarse pixels the parabolas' own
                // (from 2 degrees of freedom, and of the fits that succeeded) came out 2–3×
                // low: a lone bead's noisy tails then counted as 4σ maxima of a filament.
                let t = if channel == Channel::SxRows {
                    &sens.x
                } else {
                    &sens.y
                };
                let step = if t.len() > 1 {
                    ((t[t.len() - 1] - t[0]) / (t.len() - 1) as f64).abs()
                } else {
                    0.0
                };
                let from_pixels =
                    lv.noise * curve.norm_factor * parabola_value_noise(0.5 * opts.window_um, step);
                let sigma = match (sigma.is_finite(), from_pixels.is_finite()) {
                    (true, true) => sigma.max(from_pixels),
                    (true, false) => sigma,
                    _ => from_pixels,
                };
                let image_max = lv.max * curve.norm_factor;
                super::kind::check_filament_maxima(&trace, sigma, image_max)?;
                super::kind::check_filament_continuity(&trace, sigma, line.angle_deg)?;
                match short {
                    Some(e) => Err(e),
                    None => Ok(m),
                }
            },
        );
        match attempt {
            Ok(mut m) => {
                m.other_line = other;
                return Ok(m);
            }
            Err(e) => {
                first_err.get_or_insert(e);
            }
        }
    }
    Err(first_err.unwrap_or_else(|| {
        AnalysisError::Failed("no filament found: no line of aligned maxima".into())
    }))
}

fn check_pixel(sx: &Image, curve: &AngleCurve) -> Result<()> {
    let px = sx.dx().abs().max(sx.dy().abs());
    if px > 0.0 && ((px - curve.options.pixel_um) / px).abs() > 0.05 {
        return Err(AnalysisError::BadInput {
            name: "curve",
            reason: format!("calibration computed for {} µm pixels, the scan has {px} µm: recompute the curve with pixel_um = {px}", curve.options.pixel_um),
        });
    }
    Ok(())
}

/// Maxima along a given filament line (rows for `Channel::SxRows`: x = a + b·y; columns:
/// y = a + b·x), read within ±`window_um` of the line in each row (column) — e.g. the same
/// filament before and after background removal. Errors: fewer than 3 maxima on the line.
pub fn measure_filament_along(
    sx: &Image,
    sy: &Image,
    curve: &AngleCurve,
    channel: Channel,
    line: LineFit,
    opts: &MeasureOptions,
) -> Result<FilamentMeasurement> {
    opts.validate()?;
    check_pixel(sx, curve)?;
    let sens = match channel {
        Channel::SxRows => sensitivity(sx, Axis::X, opts.stencil)?,
        Channel::SyCols => sensitivity(sy, Axis::Y, opts.stencil)?,
    };
    let (m, _, _, short) = measure_sens_along(sens, curve, channel, line, opts)?;
    match short {
        Some(e) => Err(e),
        None => Ok(m),
    }
}

/// The arc positions (µm) of a filament's ends inside the scan from its line trace (every line
/// the filament line crosses, in order, with the maximum read there or NaN): where the
/// three-line median of the maxima (no maximum counting as 0) first reaches half the plateau
/// (the 90th percentile of the medians), walking in from each end of the trace, interpolated
/// between lines. None at a side where the first line already carries the filament (it runs out
/// of the scan there).
///
/// Beside them, the scan's edge where an end may lie just beyond it (`near_edge`): the first
/// line already carries the filament but below its plateau by more than 5 % (and 3 `sigma`, one
/// maximum's noise), as the maxima within ~0.8 µm of an end are (50 % at the end itself). A
/// 2.6 µm fibril whose end lay 0.02 µm inside the edge was read 3.8 % thin and 1.9° off, its
/// lowered maxima counted as interior. None where the first line is on the plateau.
fn filament_ends(trace: &[(f64, f64, usize)], sigma: f64) -> FilamentEnds {
    let n = trace.len();
    if n < 3 {
        return FilamentEnds::default();
    }
    let v = |i: usize| {
        let x = trace[i].1;
        if x.is_finite() {
            x
        } else {
            0.0
        }
    };
    let med: Vec<f64> = (0..n)
        .map(|i| {
            let mut w = [v(i.saturating_sub(1)), v(i), v((i + 1).min(n - 1))];
            w.sort_by(f64::total_cmp);
            w[1]
        })
        .collect();
    let mut sorted = med.clone();
    sorted.sort_by(f64::total_cmp);
    let plateau = sorted[((n - 1) as f64 * 0.9).round() as usize];
    if !(plateau > 0.0) {
        return FilamentEnds::default();
    }
    let half = 0.5 * plateau;
    let end = |idx: &mut dyn Iterator<Item = usize>| -> Option<f64> {
        let mut prev: Option<usize> = None;
        for i in idx {
            if med[i] >= half {
                let p = prev?;
                let f = (half - med[p]) / (med[i] - med[p]);
                return Some(trace[p].0 + f * (trace[i].0 - trace[p].0));
            }
            prev = Some(i);
        }
        None
    };
    let a = end(&mut (0..n));
    let b = end(&mut (0..n).rev());
    // The edge test: the mean of the EDGE_LINES lines at the edge (those with a maximum)
    // against the plateau's median (the 90th percentile stands ~1σ high in noise: a 2.25 µm
    // fibril at 5× the paper's noise, its end 0.04 µm beyond the edge, was not seen, and its
    // interior line was bent 2° by the end's maxima)
    let on: Vec<f64> = med.iter().copied().filter(|&m| m >= half).collect();
    let level = super::stats::median(&on).unwrap_or(plateau);
    // `lines`: the trace's lines from the edge inwards
    // (`count` lines, lowered by more than `rel` of the level and 3σ of their mean)
    let lowered = |lines: &[usize], count: usize, rel: f64| {
        let vals: Vec<f64> = lines
            .iter()
            .take(count)
            .map(|&k| trace[k].1)
            .filter(|x| x.is_finite())
            .collect();
        let (m, k) = if vals.len() >= 2 {
            (vals.iter().sum::<f64>() / vals.len() as f64, vals.len())
        } else {
            (med[lines[0]], 1)
        };
        let low = level - (3.0 * sigma / (k as f64).sqrt()).max(rel * level);
        m >= half && m < low
    };
    let edge = |found: Option<f64>, lines: &mut dyn Iterator<Item = usize>| {
        let lines: Vec<usize> = lines.take(EDGE_LINES).collect();
        (found.is_none()
            && (lowered(&lines, EDGE_LINES, EDGE_LOWERED_REL)
                || lowered(&lines, 2, EDGE_LOWERED_REL_2)))
        .then_some(trace[lines[0]].0)
    };
    let (ea, eb) = (edge(a, &mut (0..n)), edge(b, &mut (0..n).rev()));
    // the trace runs in line order; the arc may run either way along it
    let swap = match (a, b) {
        (Some(a), Some(b)) => a > b,
        _ => trace[0].0 > trace[n - 1].0,
    };
    if swap {
        FilamentEnds {
            ends: [b, a],
            near_edge: [eb, ea],
        }
    } else {
        FilamentEnds {
            ends: [a, b],
            near_edge: [ea, eb],
        }
    }
}

/// How far below its plateau (relative) the maximum on the scan's edge line must lie for
/// [`filament_ends`] to take an end just beyond the edge: the maxima fall to 50 % at an end and
/// are within 5 % of the plateau from ≈ 0.5 µm in (the paper's focus).
const EDGE_LOWERED_REL: f64 = 0.05;

/// The same for the mean of the two lines at the edge: where 4 lines span much of an end's
/// reach (75–100 nm pixels at an oblique angle: 0.3 µm of arc), an end just beyond the edge
/// lowers their mean by less than 5 % while the last two stand 10–20 % low. A 2.33 µm fibril at
/// −58° and 75 nm pixels, its end 0.05 µm beyond the edge, read 3.2 % thin noise-free (the end's
/// maxima counted as interior bent its line 2°, and the correction with it): the 4 lines stood
/// 4.7 % low, the last two 12 %.
const EDGE_LOWERED_REL_2: f64 = 0.10;

/// Lines at the scan's edge whose maxima [`filament_ends`] averages to tell an end just beyond
/// it: 4 lines are 0.08–0.4 µm of arc at 20–100 nm pixels, where an end 0.05 µm beyond the edge
/// lowers the maxima by 10–20 %; their mean halves one maximum's noise.
const EDGE_LINES: usize = 4;

/// A filament's ends inside the scan, and the scan's edge where an end may lie just beyond it
/// (arc positions, µm; see [`filament_ends`]).
#[derive(Debug, Clone, Copy, Default)]
struct FilamentEnds {
    ends: [Option<f64>; 2],
    near_edge: [Option<f64>; 2],
}

/// Every scan line a filament line crosses, in line order: (arc position µm, maximum read there
/// or NaN), for the checks of `kind`.
type LineTrace = Vec<(f64, f64)>;

/// The number of interior maxima where an end (or the scan's edge near one) cut maxima off and
/// at least 3 interior ones are left: where the interior line is refitted and carries the
/// end's systematics (None otherwise).
fn ends_cut_maxima(points: &[FilamentPoint]) -> Option<usize> {
    let n_in = points.iter().filter(|p| p.interior).count();
    (n_in >= 3 && n_in < points.len()).then_some(n_in)
}

/// The line refitted on the interior maxima alone where an end cut some off: an end's maxima
/// bend and fade, and near 45° a degree of angle moves the correction by percents (a 2.3 µm
/// fibril at −42° was read at −49.7° from all its maxima, its diameter 16 % low).
fn refit_on_interior(points: &[FilamentPoint], line: LineFit, rows: bool) -> LineFit {
    let Some(n_in) = ends_cut_maxima(points) else {
        return line;
    };
    let (c, q): (Vec<f64>, Vec<f64>) = points
        .iter()
        .filter(|p| p.interior)
        .map(|p| if rows { (p.y, p.x) } else { (p.x, p.y) })
        .unzip();
    match linfit(&c, &q, None) {
        Ok(f) => LineFit {
            angle_deg: line_angle(f.slope, rows),
            angle_err_deg: (f.slope_err / (1.0 + f.slope * f.slope)).to_degrees(),
            a: f.intercept,
            b: f.slope,
            n: n_in,
        },
        Err(_) => line,
    }
}

/// The systematic errors an end leaves on the interior maxima, where an end (or the scan's
/// edge near one) cut maxima off: the angle's 1σ widened by [`END_ANGLE_SYS_DEG_UM`] / s and
/// the relative 1σ of the mean [`END_VALUE_SYS_UM`] / s, s the arc span of the interior maxima
/// (µm). Returns the line and that relative 1σ (0 where no end cut maxima off).
fn with_end_systematics(points: &[FilamentPoint], mut line: LineFit) -> (LineFit, f64) {
    if ends_cut_maxima(points).is_none() {
        return (line, 0.0);
    }
    let arcs = points.iter().filter(|p| p.interior).map(|p| p.arc_um);
    let (lo, hi) = arcs.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), a| {
        (lo.min(a), hi.max(a))
    });
    // (a span of one pixel or less: the 10 nm floor keeps the terms finite and large)
    let span = (hi - lo).max(0.01);
    line.angle_err_deg = line.angle_err_deg.hypot(END_ANGLE_SYS_DEG_UM / span);
    (line, END_VALUE_SYS_UM / span)
}

/// An end's systematic on the angle of the interior maxima's line, deg·µm (divided by their arc
/// span). An end reaches past `end_margin_um` (0.8 µm) through the response's tails: it bends
/// the row maxima's positions by nanometres, which over a short interior turn the line. On
/// noise-free 80 nm fibrils (20, 50 and 100 nm pixels, six angles, both ends in the scan) the
/// interior line's angle was off by 0.7° rms at an interior span of 0.2 µm (1.7° at most),
/// 0.35° at 0.6 µm, 0.14° at 1.2 µm and under 0.06° at 2 µm; near 45° a degree moves the
/// correction by 3 %, and the truth sweep's fibrils under 2.5 µm had 1σ coverage 0.42.
pub const END_ANGLE_SYS_DEG_UM: f64 = 0.2;

/// An end's systematic on the mean of the interior maxima, relative·µm (divided by their arc
/// span): the end lowers them a little beyond `end_margin_um`. On the same fibrils near 0° and
/// 90° (where the angle does not move the correction) the mean was low by 0.6–1.0 % at an
/// interior span of 0.2 µm, 0.4–0.6 % at 0.6 µm and 0.2 % at 1.2 µm.
pub const END_VALUE_SYS_UM: f64 = 0.003;

/// The orientation correction at `line`'s angle applied to every maximum (`sens_corr`), and its
/// relative 1σ from the angle's (the correction's slope × the angle's σ).
fn apply_correction(
    points: &mut [FilamentPoint],
    curve: &AngleCurve,
    channel: Channel,
    line: &LineFit,
) -> Result<(f64, f64)> {
    let angle = line.angle_deg;
    let factor = curve.correction(angle, channel)?;
    for p in points.iter_mut() {
        p.sens_corr = p.sens * factor;
    }
    Ok((
        factor,
        correction_rel_err(curve, channel, angle, line.angle_err_deg)?,
    ))
}

/// The relative 1σ of the orientation correction at `angle_deg` from the angle's 1σ
/// `angle_err_deg`: the correction's slope (central difference over ±0.5°) × σ(angle) / factor.
pub fn correction_rel_err(
    curve: &AngleCurve,
    channel: Channel,
    angle_deg: f64,
    angle_err_deg: f64,
) -> Result<f64> {
    let factor = curve.correction(angle_deg, channel)?;
    let h = 0.5;
    let d = (curve.correction(angle_deg + h, channel)?
        - curve.correction(angle_deg - h, channel)?)
        / (2.0 * h);
    Ok((d * angle_err_deg / factor).abs())
}

/// Lines on either side of a maximum whose vertices place it ([`at_neighbours_vertex`]).
const NEIGHBOUR_LINES: usize = 5;

/// One line the filament line crosses: its samples, the crossing (µm along the line) and the
/// vertex's offset from the crossing (None: its parabola had no vertex inside the window).
struct Crossing {
    samples: Vec<f64>,
    pred: f64,
    offset: Option<f64>,
}

/// Each line's maximum read where its neighbours put the filament: its parabola (the window
/// fixed on the line's crossing, as `peak_at` fitted it) evaluated at the median of the vertex
/// offsets from the crossing of the [`NEIGHBOUR_LINES`] lines with a vertex on either side
/// (itself left out, so the position is independent of its own noise), minus ½f''·var for the
/// position's own scatter. The line's vertex value c0 − c1²/(4c2) divides by its own noisy
/// curvature, and its second-order correction over-corrects once the curvature is known to a
/// few σ only (a 20 nm microtubule at 3° from y read 1.3 % low at 3× the paper's noise, 6 % at
/// 20 nm pixels); the value at a given position is linear in the samples. `points` include
/// the lines without a vertex between the first and the last with one: leaving
/// them out selects on the noise (a concave fit with its vertex inside the window has a higher
/// c0), which biased the mean up by 2 % at 3× the noise.
fn at_neighbours_vertex(
    points: &mut Vec<FilamentPoint>,
    crossings: &BTreeMap<usize, Crossing>,
    t: &[f64],
    po: &PeakOptions,
) {
    let offs: Vec<(usize, f64)> = crossings
        .iter()
        .filter_map(|(&l, c)| c.offset.map(|o| (l, o)))
        .collect();
    points.retain_mut(|p| {
        let Some(c) = crossings.get(&p.line) else {
            return true;
        };
        let at = offs.partition_point(|&(l, _)| l < p.line);
        let after = offs[at..]
            .iter()
            .filter(|&&(l, _)| l != p.line)
            .take(NEIGHBOUR_LINES);
        let nb: Vec<f64> = offs[..at]
            .iter()
            .rev()
            .take(NEIGHBOUR_LINES)
            .chain(after)
            .map(|&(_, o)| o)
            .collect();
        let (Some(med), true) = (super::stats::median(&nb), nb.len() >= 2) else {
            return c.offset.is_some();
        };
        let dev: Vec<f64> = nb.iter().map(|d| (d - med).abs()).collect();
        let mad = super::stats::median(&dev).unwrap_or(0.0);
        // the median's variance: π/2 × σ²/n for normal scatter
        let var = std::f64::consts::FRAC_PI_2 * (1.4826 * mad).powi(2) / nb.len() as f64;
        match super::peaks::parabola_at(t, &c.samples, c.pred, c.pred + med, po) {
            Ok(a) => {
                p.sens = a.value - 0.5 * a.curvature * var;
                p.sens_err = a.value_err;
                true
            }
            // keep the vertex of a line that has one (its neighbours' position is outside its
            // window)
            Err(_) => c.offset.is_some(),
        }
    });
}

/// The lines without a vertex inside the stretch of lines with one (`points`, arcs counted
/// from `a0` along `dir`), as points at their crossings, to be read by [`at_neighbours_vertex`];
/// `interior(arc)` says whether an arc (µm, absolute) is far enough from the ends.
fn add_vertexless_lines(
    points: &mut Vec<FilamentPoint>,
    crossings: &BTreeMap<usize, Crossing>,
    sens: &Image,
    rows: bool,
    dir: (f64, f64),
    a0: f64,
    interior: impl Fn(f64) -> bool,
) {
    let (lmin, lmax) = points
        .iter()
        .fold((usize::MAX, 0), |(a, b), p| (a.min(p.line), b.max(p.line)));
    if lmin > lmax {
        return;
    }
    for (&l, c) in crossings.range(lmin..=lmax) {
        if c.offset.is_some() {
            continue;
        }
        let coord = if rows { sens.y[l] } else { sens.x[l] };
        let (x, y) = if rows {
            (c.pred, coord)
        } else {
            (coord, c.pred)
        };
        let arc = x * dir.0 + y * dir.1;
        points.push(FilamentPoint {
            line: l,
            x,
            y,
            arc_um: arc - a0,
            sens: f64::NAN,
            sens_err: None,
            sens_corr: f64::NAN,
            interior: interior(arc),
        });
    }
}

/// What [`read_crossings`] reads: the points, the crossings by line index, the trace.
type Crossings = (
    Vec<FilamentPoint>,
    BTreeMap<usize, Crossing>,
    Vec<(f64, f64, usize)>,
);

/// Every line `line` crosses: its maximum as a point where its parabola (window fixed on the
/// crossing) has a vertex within `max_offset_um` of the line; the crossings inside the scan
/// (samples, crossing, vertex offset); the trace: (arc µm, maximum, line index) of each line
/// crossed inside the scan, in line order, the maximum NaN where none was read (for the checks
/// of `kind`).
fn read_crossings(
    sens: &Image,
    line: &LineFit,
    rows: bool,
    factor: f64,
    po: &PeakOptions,
    opts: &MeasureOptions,
) -> Crossings {
    let th = line.angle_deg.to_radians();
    let dir = (th.sin(), th.cos());
    let (nl, t): (usize, &[f64]) = if rows {
        (sens.rows(), &sens.x)
    } else {
        (sens.cols(), &sens.y)
    };
    let mut points = Vec::new();
    let mut crossings = BTreeMap::new();
    let mut trace: Vec<(f64, f64, usize)> = Vec::new();
    let (t_lo, t_hi) = (
        t.first().copied().unwrap_or(0.0),
        t.last().copied().unwrap_or(0.0),
    );
    for l in 0..nl {
        let coord = if rows { sens.y[l] } else { sens.x[l] };
        let pred = line.a + line.b * coord;
        let inside = pred >= t_lo.min(t_hi) && pred <= t_hi.max(t_lo);
        if inside {
            let (x, y) = if rows { (pred, coord) } else { (coord, pred) };
            trace.push((x * dir.0 + y * dir.1, f64::NAN, l));
        }
        let vv: Vec<f64> = (0..t.len())
            .map(|k| {
                if rows {
                    sens.data[[l, k]]
                } else {
                    sens.data[[k, l]]
                }
            })
            .collect();
        // Parabola on a window fixed on the line's crossing: no selection bias from the noisy
        // maximum, nor from a window that follows the noise (the line is fitted to all rows).
        let p = peak_at(t, &vv, pred, po)
            .ok()
            .filter(|p| dist(line.a, line.b, coord, p.pos) <= opts.max_offset_um);
        if inside || p.is_some() {
            let offset = p.map(|p| p.pos - pred);
            crossings.insert(
                l,
                Crossing {
                    samples: vv,
                    pred,
                    offset,
                },
            );
        }
        let Some(p) = p else {
            continue;
        };
        let (x, y) = if rows { (p.pos, coord) } else { (coord, p.pos) };
        if let Some(tr) = trace.last_mut().filter(|tr| tr.2 == l) {
            tr.1 = p.value;
        }
        points.push(FilamentPoint {
            line: l,
            x,
            y,
            arc_um: x * dir.0 + y * dir.1,
            sens: p.value,
            sens_err: p.value_err,
            sens_corr: p.value * factor,
            interior: true,
        });
    }
    (points, crossings, trace)
}

/// The maxima along `line`, the line trace and one maximum's 1σ (median of the parabolas';
/// NaN when none has one).
fn measure_sens_along(
    mut sens: Image,
    curve: &AngleCurve,
    channel: Channel,
    line: LineFit,
    opts: &MeasureOptions,
) -> Result<(FilamentMeasurement, LineTrace, f64, Option<AnalysisError>)> {
    // Instrument units → reference-bead units.
    sens.data.mapv_inplace(|v| v * curve.norm_factor);
    let rows = channel == Channel::SxRows;
    let factor = curve.correction(line.angle_deg, channel)?;
    let th = line.angle_deg.to_radians();
    let dir = (th.sin(), th.cos());
    let po = opts.peak_options();
    let t: &[f64] = if rows { &sens.x } else { &sens.y };
    let (mut points, crossings, trace) = read_crossings(&sens, &line, rows, factor, &po, opts);
    if points.len() < 3 {
        return Err(AnalysisError::Failed(format!(
            "only {} maxima lie on the filament line",
            points.len()
        )));
    }
    points.sort_by(|a, b| a.arc_um.total_cmp(&b.arc_um));
    // 1σ of one line's maximum: the median of the parabolas' own (robust to a few poor fits)
    let errs: Vec<f64> = points.iter().filter_map(|p| p.sens_err).collect();
    let sigma = super::stats::median(&errs).unwrap_or(f64::NAN);
    let found = filament_ends(&trace, if sigma.is_finite() { sigma } else { 0.0 });
    let ends = found.ends;
    // an end found inside the scan, else the edge where an end may lie just beyond it
    let bound = [
        ends[0].or(found.near_edge[0]),
        ends[1].or(found.near_edge[1]),
    ];
    // far enough from the ends (an arc in µm, before `a0` is taken off)
    let interior = |arc: f64| {
        bound[0].is_none_or(|e| arc >= e + opts.end_margin_um)
            && bound[1].is_none_or(|e| arc <= e - opts.end_margin_um)
    };
    let a0 = points[0].arc_um;
    for p in points.iter_mut() {
        p.interior = interior(p.arc_um);
        p.arc_um -= a0;
    }
    let ends_um = ends.map(|e| e.map(|e| e - a0));
    let line = refit_on_interior(&points, line, rows);
    let (line, end_rel) = with_end_systematics(&points, line);
    add_vertexless_lines(&mut points, &crossings, &sens, rows, dir, a0, interior);
    at_neighbours_vertex(&mut points, &crossings, t, &po);
    points.sort_by(|a, b| a.arc_um.total_cmp(&b.arc_um));
    let angle = line.angle_deg;
    let (factor, rel_factor_err) = apply_correction(&mut points, curve, channel, &line)?;
    let interior: Vec<f64> = points
        .iter()
        .filter(|p| p.interior)
        .map(|p| p.sens_corr)
        .collect();
    // Too short to measure: refused by the callers once the kind checks have spoken (a lone
    // bead is "not a filament" before it is "too short").
    let short = (interior.len() < 3).then(|| {
        let len = match (ends, found.near_edge) {
            ([Some(a), Some(b)], _) => format!("{:.2} µm long", b - a),
            (_, [None, None]) => "cut by an end".to_string(),
            _ => "cut by an end, with an end just beyond the scan's edge".to_string(),
        };
        AnalysisError::Failed(format!(
            "the filament is too short to measure: it is {len} inside the scan, and its maxima within end_margin_um = {} µm of an end are lowered by the end (to 50 % at the end), which leaves {} of {} maxima (at least 3 are needed); scan a longer stretch, or lower end_margin_um knowing the bias",
            opts.end_margin_um,
            interior.len(),
            points.len()
        ))
    });
    let interior = if short.is_some() {
        points.iter().map(|p| p.sens_corr).collect()
    } else {
        interior
    };
    let mut s = summary(&interior)?;
    if rel_factor_err.is_finite() {
        s.sem = s.sem.hypot(s.mean * rel_factor_err);
    }
    s.sem = s
        .sem
        .hypot(s.mean * correction_sys_rel(angle))
        .hypot(s.mean * end_rel);
    let trace: LineTrace = trace.into_iter().map(|(arc, v, _)| (arc, v)).collect();
    let m = FilamentMeasurement {
        channel,
        angle_deg: angle,
        angle_err_deg: line.angle_err_deg,
        line,
        other_line: None,
        factor,
        points,
        mean_corr: s.mean,
        std_corr: s.std,
        sem_corr: s.sem,
        ends_um,
        warnings: vec![],
        sens,
        crlb: None,
    };
    Ok((m, trace, sigma, short))
}
