//! Focus search (suppl. S5): from an XZ (or YZ) scan of a small object, the maximum sensitivity
//! of each z row (parabola over `window_um`, as in Sec. 5), then the best z by a parabola through
//! the row maxima around the best row (over `z_window_um`), with its uncertainty, and the z range
//! over which the maximum sensitivity stays within `level` (paper: 98 %) of its peak.
//!
//! Input: the channel image with the lateral scan axis as columns and z as rows (Sx of an XZ
//! scan; Sy of a YZ scan with y as columns). Units: z and positions in µm.

pub use super::peaks::{max_sens_sys_rel, MAX_SENS_SYS_REL, MAX_SENS_SYS_REL_100NM, ROW_PEAK_SNR};
use super::peaks::{peak_1d, row_peaks, LinePeak, PeakOptions};
use super::peaks::{window_sigma, with_misfit};
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
    // The noise of one sensitivity pixel, from the whole image (thousands of differences):
    // the rows' parabolas and the parabola over z take their σ from it, not from their own few
    // residuals (a parabola over 7 rows has 4 degrees of freedom: its residual σ is Student-t
    // distributed and put one answer in 30 beyond "4σ" in the truth sweep). Where the rows'
    // maxima lie far closer to their parabola than that noise allows (a noise-free or a small,
    // coarse scan, whose differences are the object's own curvature, not noise), the
    // residuals' σ is used as before.
    let mut c = focus_curve(&sens, opts, sens_pixel_noise(img, opts.stencil))?;
    // one row's maximum against the noise of its parabola (before any fallback)
    let row_snr = c.row_sigma.filter(|&r| r > 0.0).map(|r| c.p.value / r);
    if c.quieter_than_noise {
        c = focus_curve(&sens, opts, None)?;
    }
    let FocusCurve { rows, z, v, p, .. } = c;
    let mut p = p;
    // the vertex's σ with a curvature no steeper than the curve's sides support
    let k = steep_top(&z, &v, opts.z_window_um, p.curvature);
    p.pos_err = p.pos_err.map(|e| e * k);
    // the method's own systematic, in quadrature (noise-free, its σ would claim exactness)
    p.pos_err = p.pos_err.map(|e| e.hypot(z_best_sys_um(row_step(&z))));
    p.value_err = p
        .value_err
        .map(|e| e.hypot(max_sens_sys_rel(img.dx().abs()) * p.value.abs()));
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
    let mut warnings = warnings(&z, &p, opts.z_window_um, lateral_edge(&sens, &rows));
    if let Some(e) = p
        .value_err
        .filter(|&e| e > 0.0 && p.value < FOCUS_PEAK_SNR * e)
    {
        warnings.push(format!(
            "the focus curve's peak {:.4} ± {e:.4} is {:.1}σ, below {FOCUS_PEAK_SNR}σ: the rows' maxima are picked from noise as much as from the object, and z_best and its σ do not hold (scan slower, or with larger pixels)",
            p.value,
            p.value / e
        ));
    }
    if let Some(k) = row_snr.filter(|&k| k < ROW_PEAK_SNR) {
        warnings.push(format!(
            "one row's maximum is {k:.1}σ of its own noise, below {ROW_PEAK_SNR}σ: each row's maximum is picked from the noise and reads high, so max_sens is biased up beyond its σ (scan slower, or with larger pixels)"
        ));
    }
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

/// The warnings of a focus search: the best z within one and a half rows, or half the z
/// window, of the scan's end (the parabola then leans on one side only: a 53 nm bead 0.3 µm
/// beyond the end of the z range was put 0.16 µm inside it, 1.6 rows from the end, in the truth
/// sweep), the lateral maximum of the best rows at the scan's edge.
fn warnings(
    z: &[f64],
    p: &super::peaks::Peak,
    z_window_um: f64,
    edge: Option<String>,
) -> Vec<String> {
    let mut w = vec![];
    let (zmin, zmax) = (z[0].min(z[z.len() - 1]), z[0].max(z[z.len() - 1]));
    let step = row_step(z);
    // (less a rounding's worth: a window that just reaches the end is not cut)
    let margin = (1.5 * step).max(0.5 * z_window_um) * (1.0 - 1e-6);
    if p.pos - zmin < margin || zmax - p.pos < margin {
        w.push(format!(
            "the best z = {:.3} µm is within {margin:.3} µm (one and a half rows, or half the z window) of the end of the scan's z range [{zmin:.3}, {zmax:.3}] µm: the maximum may lie beyond it; widen the z range",
            p.pos
        ));
    }
    w.extend(edge);
    w
}

/// The mean step between the z rows `z` (µm; 0 for one row).
fn row_step(z: &[f64]) -> f64 {
    crate::data::image::axis_step(z).abs()
}

/// The rows' maxima and the parabola over z through them.
struct FocusCurve {
    rows: Vec<LinePeak>,
    z: Vec<f64>,
    v: Vec<f64>,
    p: super::peaks::Peak,
    /// χ² of the rows about the parabola below its 0.01 % point for the noise `sens_sigma`: that
    /// noise is not what scatters the rows (at the 1 % point, one noisy answer in a hundred fell
    /// back on its few residuals' σ: a 199 nm bead's z_best then claimed 1.5 nm where the other
    /// noise draws gave 3.5 nm, and was 5.6σ off in the truth sweep).
    quieter_than_noise: bool,
    /// σ of one row's maximum (its parabola's) from the image's noise, when known.
    row_sigma: Option<f64>,
}

/// The focus curve of a sensitivity image with the noise of one sensitivity pixel `sens_sigma`
/// (None: each parabola's σ from its residuals).
fn focus_curve(sens: &Image, opts: &FocusOptions, sens_sigma: Option<f64>) -> Result<FocusCurve> {
    let row_opts = PeakOptions {
        window_um: opts.window_um,
        sigma: sens_sigma,
        acf: opts.stencil.noise_acf(),
        ..Default::default()
    };
    let rows = row_peaks(sens, &row_opts)?;
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
    // the rows' maxima carry the σ of their parabolas: those within the z window of the best
    // row (the defocused rows' flatter parabolas have wider σ; their RMS over every row put
    // z_best's σ up to 1.4× its scatter at 6.5× the paper's noise)
    let ibest = (0..v.len())
        .filter(|&i| v[i].is_finite())
        .max_by(|&a, &b| v[a].total_cmp(&v[b]))
        .unwrap_or(0);
    let row_sigma = sens_sigma.and_then(|_| window_sigma(&rows, z[ibest], 0.5 * opts.z_window_um));
    let z_opts = PeakOptions {
        window_um: opts.z_window_um,
        sigma: row_sigma,
        ..Default::default()
    };
    let p = peak_1d(&z, &v, &z_opts)
        .map_err(|m| AnalysisError::Failed(format!("no maximum of the sensitivity over z: {m}")))?;
    let (p, quieter_than_noise) = with_misfit(p, &z, &v, &z_opts);
    Ok(FocusCurve {
        rows,
        z,
        v,
        p,
        quieter_than_noise,
        row_sigma,
    })
}

/// The factor (≥ 1) by which the vertex's σ widens where the parabola over the z window is
/// steeper than the curve's sides support: |c| / (r·|c₂|), with c the curvature over the
/// window, c₂ over twice the window, and r their ratio on the noise-free focus curve
/// ([`focus_curve_ratio`]); 1 where c is no steeper than that.
///
/// Why: z_best = −c1/(2c2) is a ratio, and its σ falls as the measured curvature rises. A noise
/// draw that steepens the few rows of the window (7 rows of 100 nm over 0.6 µm, read at 3–10σ of
/// curvature) narrows the σ of the very answer it moves: over 400 noise draws of each of ten
/// scenes (40–200 nm beads, 1–8× the paper's noise, 20–100 nm pixels, 25–100 nm rows), the
/// answers whose window read 5–10σ of curvature held 59–63 % of their 1σ intervals, and 16 of
/// 2 971 lay beyond 4σ (a Gaussian: 0.2). Twice the window holds four times the rows and reads
/// the curvature at ~5× the SNR, so a steepened top shows against it. With the factor: none
/// beyond 4σ, 1σ coverage 0.73, 2σ 0.965, and 0.69–0.71 at ≥ 15σ of curvature (where it is
/// ~1). The vertex itself is unchanged: the wider parabola's is biased by the curve's
/// non-parabolic sides wherever its window is not centred on the peak.
fn steep_top(z: &[f64], v: &[f64], z_window_um: f64, curvature: f64) -> f64 {
    let Some(r) = focus_curve_ratio(z_window_um) else {
        return 1.0;
    };
    // only the curvature is read: it does not depend on the rows' σ
    let o = PeakOptions {
        window_um: 2.0 * z_window_um,
        ..Default::default()
    };
    match peak_1d(z, v, &o) {
        Ok(w) if w.curvature < 0.0 && curvature < 0.0 => (curvature / (r * w.curvature)).max(1.0),
        _ => 1.0,
    }
}

/// The ratio of the focus curve's parabola curvatures over a z window W and over 2W, noise-free
/// (the paper's optics, 40–200 nm beads, the 199 nm one by the Mie tier; 25–100 nm rows):
/// 1.072–1.082 at W = 0.4 µm, 1.167–1.182 at 0.6 µm, 1.27–1.33 at 0.8 µm; the lowest of each,
/// interpolated in W² from 1 at W = 0. None beyond 0.8 µm (a window of 1.6 µm reaches the
/// curve's turning points, and the ratio no longer measures the top).
pub fn focus_curve_ratio(z_window_um: f64) -> Option<f64> {
    const TABLE: [(f64, f64); 4] = [(0.0, 1.0), (0.4, 1.072), (0.6, 1.167), (0.8, 1.27)];
    let w = z_window_um;
    if !(0.0..=0.8 + 1e-9).contains(&w) {
        return None;
    }
    TABLE.windows(2).find(|p| w <= p[1].0 + 1e-9).map(|p| {
        let (a, b) = (p[0], p[1]);
        let f = (w * w - a.0 * a.0) / (b.0 * b.0 - a.0 * a.0);
        a.1 + f * (b.1 - a.1)
    })
}

/// The noise of one sensitivity pixel (1σ): the image's robust pixel noise
/// ([`pixel_noise_d4`], fourth differences along the lateral axis) through the
/// stencil's noise gain, σ(∂S/∂x) = gain·σ(S)/h (Sec. 3.2). None on noise-free data.
fn sens_pixel_noise(img: &Image, stencil: Stencil) -> Option<f64> {
    if img.x.len() < 2 {
        return None;
    }
    let h = img.dx().abs();
    let (noise, count) = pixel_noise_d4(img);
    let s = stencil.noise_gain() * noise / h;
    (count >= MIN_NOISE_DIFFERENCES && s > 0.0 && s.is_finite()).then_some(s)
}

/// The fewest fourth differences the image's noise is read from: below it (a 9 × 9 scan has 45)
/// the object's own curvature fills them, the estimate is the signal's, and the parabolas take
/// their σ from their residuals instead. The truth sweep's XZ scans hold 1 200–24 000.
pub const MIN_NOISE_DIFFERENCES: usize = 1000;

/// Robust pixel noise from fourth differences along the rows, 1.4826·MAD/√70 (white noise:
/// Var(Δ⁴) = 70σ²): an XZ scan's defocused rows spread the object's smooth signal over most
/// pixels. First differences (`domain::pixel_noise`) read the signal's slope as noise at low
/// noise (the truth sweep's z_best σ came out 1.7× its scatter at 300× the detection SNR);
/// second differences still read its curvature (the rows' σ came out 1.2–2× their scatter at
/// 0.3–1× the paper's noise, and 1σ intervals of z_best held 77 % of the sweep's answers);
/// each further difference takes another power of pixel size over the object's width off the
/// signal. Also returns how many differences it read.
fn pixel_noise_d4(img: &Image) -> (f64, usize) {
    let mut d = Vec::with_capacity(img.data.len());
    for row in img.data.rows() {
        d.extend(
            row.windows(5)
                .into_iter()
                .map(|w| w[4] - 4.0 * w[3] + 6.0 * w[2] - 4.0 * w[1] + w[0])
                .filter(|v| v.is_finite()),
        );
    }
    (
        super::stats::robust_std(&d).unwrap_or(0.0) / 70f64.sqrt(),
        d.len(),
    )
}

/// The focus search's systematic error of z_best (µm, 1σ) for z rows `step_um` apart: the
/// parabola over the z window against the point-dipole focus curve's peak, which depends on
/// where the rows fall on the curve. Noise-free, 40–200 nm beads at random positions (314
/// scenes of the sweep's draw) were off by 0.15, 0.36 and 0.68 nm RMS at 25, 50 and 100 nm
/// rows (at most 0.26, 0.56 and 1.3 nm): [`Z_BEST_SYS_PER_STEP`] of the step. (A flat 1 nm made
/// the 1σ intervals of answers whose σ is under 3 nm hold 83–95 % of the sweep's answers; 2 nm,
/// 80 % of all.)
pub fn z_best_sys_um(step_um: f64) -> f64 {
    Z_BEST_SYS_PER_STEP * step_um.abs()
}

/// z_best's systematic per unit of the z rows' step ([`z_best_sys_um`]): 0.7 nm at 100 nm rows.
pub const Z_BEST_SYS_PER_STEP: f64 = 0.007;

/// The focus curve's peak (the parabola over z) must stand this many of its σ above zero for
/// z_best and its σ to hold: below it the rows' maxima are picked from the noise (a 73 nm bead
/// at 9× the paper's noise, its peak at 8σ, was put 0.28 µm off, 7σ, in the truth sweep; at
/// 10–15σ one answer in 22 was 5σ off, at 15–20σ none beyond 2.5σ).
pub const FOCUS_PEAK_SNR: f64 = 15.0;

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
    if img.x.len() < 2 {
        return None;
    }
    let h = img.dx().abs();
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
    let step = sens.dx().abs();
    (best.pos - x0 < 1.5 * step || x1 - best.pos < 1.5 * step).then(|| {
        format!(
            "the object's maximum at x = {:.3} µm is at the scan's lateral edge [{x0:.3}, {x1:.3}] µm: centre the object in the scan",
            best.pos
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// `steep_top`: a focus curve that is a parabola over twice the window (its sides support
    /// every bit of its top's curvature) keeps the vertex's σ; the same rows with the three
    /// at the top raised by 0.3 of the drop across the window (a draw that steepens the top)
    /// widen it by the top's curvature over r times the sides'; a window beyond the table's
    /// 0.8 µm leaves it alone.
    #[test]
    fn a_top_steeper_than_its_sides_widens_the_vertex_sigma() {
        let z: Vec<f64> = (0..41).map(|i| -2.0 + 0.1 * i as f64).collect();
        let v: Vec<f64> = z.iter().map(|&t| 1.0 - 0.5 * (t - 0.03).powi(2)).collect();
        let curv = |v: &[f64], w: f64| {
            let o = PeakOptions {
                window_um: w,
                ..Default::default()
            };
            peak_1d(&z, v, &o).unwrap().curvature
        };
        assert!((curv(&v, 0.6) + 1.0).abs() < 1e-9);
        assert_eq!(steep_top(&z, &v, 0.6, curv(&v, 0.6)), 1.0);
        let mut top = v.clone();
        // the drop across ±0.3 µm is 0.045: the rows at −0.1, 0 and 0.1 µm up by 0.0135
        for t in &mut top[19..22] {
            *t += 0.0135;
        }
        let (c, c2) = (curv(&top, 0.6), curv(&top, 1.2));
        let r = focus_curve_ratio(0.6).unwrap();
        assert!(c / c2 > 1.05 * r, "top {c}, sides {c2}");
        let k = steep_top(&z, &top, 0.6, c);
        assert!((k - c / (r * c2)).abs() < 1e-12 && k > 1.05, "factor {k}");
        assert_eq!(steep_top(&z, &top, 0.9, c), 1.0);
    }

    /// A smooth bump, as an XZ scan's rows hold it (0.3–0.45 µm wide along x, 25 nm pixels,
    /// 500× the noise), plus white noise of known σ: the fourth differences give σ back within
    /// 4 % (the robust estimate's own scatter over 11 000 differences is about 1.5 %), where the
    /// second differences read the bump's curvature and come out more than 10 % high.
    #[test]
    fn fourth_differences_read_the_noise_under_a_smooth_signal() {
        let (nx, nz, h, sigma) = (121, 101, 0.025, 1e-3);
        let x: Vec<f64> = (0..nx).map(|i| (i as f64 - 60.0) * h).collect();
        let z: Vec<f64> = (0..nz).map(|i| i as f64 * 0.02).collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let n = Normal::new(0.0, sigma).unwrap();
        let data = ndarray::Array2::from_shape_fn((nz, nx), |(iz, ix)| {
            let w = 0.3 * (1.0 + 0.5 * (z[iz] - 1.0).powi(2));
            0.5 * (-(x[ix] / w).powi(2)).exp() + n.sample(&mut rng)
        });
        let img = Image::new(data.clone(), x, z);
        let (d4, count) = pixel_noise_d4(&img);
        assert_eq!(count, nz * (nx - 4));
        assert!((d4 / sigma - 1.0).abs() < 0.04, "fourth differences: {d4}");
        let mut d2 = vec![];
        for row in data.rows() {
            d2.extend(row.windows(3).into_iter().map(|w| w[2] - 2.0 * w[1] + w[0]));
        }
        let d2 = crate::analysis::stats::robust_std(&d2).unwrap() / 6f64.sqrt();
        assert!(d2 / sigma > 1.1, "second differences: {d2}");
    }
}
