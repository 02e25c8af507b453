//! Quantitative analysis of BFP scans: every step the paper computes from images.
//!
//! Sections and equations refer to the paper and supplement in `seed/000_a01c3b91f68df4b7.txt`
//! (see `docs/analysis.md` for the map from paper to functions). No I/O and no Rhai here: clean
//! Rust functions with units in their doc comments. Positions and lengths are in µm, diameters in
//! nm, masses in kDa/MDa (the name says which), linear densities in MDa/µm; signals are in the
//! units of the scan (after template normalisation: "reference-bead units", where the reference
//! bead's maximum ∂Sx/∂x is 1).
//!
//! | topic | file | paper |
//! |---|---|---|
//! | derivative images ∂Sx/∂x, ∂Sy/∂y | [`sensitivity`] | Sec. 3.2 |
//! | sub-pixel maxima per row / column, 2-D peaks | [`peaks`] | Sec. 5 (parabola over 0.4 µm) |
//! | reference template (from scans or the model) | [`template`], [`template_from_scans`] | Sec. 3.1, Fig. 2 |
//! | multi-bead template fit | [`fit`] | eq. multiBeadFit, suppl. S7 |
//! | Cramér–Rao bounds of the data taken | [`crlb`] | suppl. S8 (noise) |
//! | whole-image straight-filament model, bounds and fit | [`filament_fit`] | Sec. 4.2 |
//! | one bead fitted to readings at arbitrary points, the informative pattern | [`point_fit`] | eq. multiBeadFit |
//! | filament bead model | [`bead_model`] | Sec. 4.2 |
//! | orientation calibration and correction | [`orientation`] | Sec. 4.2 steps 1–5, Fig. 4d |
//! | n_corr, mass of a volume | [`scaling`] | eq. nCor, Sec. 3.2 |
//! | n_corr, mass, diameter, linear density | [`quantities`] | eqs. nCor, colDiam, OurColD, mtLinDens |
//! | the maximum-sensitivity pipeline's options | [`measure`] | Sec. 5 |
//! | point-object background removal | [`background`] | Sec. 6 |
//! | signal-to-background ratio | [`sbr`] | Sec. 6 |
//! | the filament analyses of a scan with their input checks | [`checked`] | Sec. 4.2, 6 |
//! | aggregate removal and a microtubule's linear density | [`microtubule`] | Sec. 6, eq. mtLinDens |
//! | focus search | [`focus`] | suppl. S5 |
//! | Cramér–Rao bound of the best focus | [`focus_crlb`] | suppl. S5, S8 |
//! | histograms, summaries, linear fits | [`stats`] | Fig. 3c, Fig. 6d |
//! | image sampling, polyline profiles | [`profile`] | Fig. 5c |
//!
//! Conventions (shared with `docs/physics.md`): scene positions are stage coordinates; the image
//! of a bead at `p` is `template(s − p)` for the pixel at stage position `s`, so
//! `tpl.eval(x − x_i, y − y_i)` is the bead at `(x_i, y_i)` and ∂Sx/∂x is positive at its centre.
//! Filament angles are measured from the QPD +y axis towards +x, in degrees, in (−90°, 90°].
//!
//! Bad input gives an [`AnalysisError`] naming the argument, its value and the allowed range. NaN
//! pixels mark missing data (an aborted scan): they are skipped by every reduction, and derived
//! images carry NaN only where no finite input supports the value (documented per function).

// NaN-aware comparisons are deliberate throughout: `!(x > 0.0)` is true for NaN, `x <= 0.0` is not.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod background;
pub mod bead_model;
pub mod beam_fit;
pub mod checked;
pub mod crlb;
pub mod domain;
pub mod faint;
pub mod filament_fit;
pub mod fit;
pub mod focus;
pub mod focus_crlb;
pub mod kind;
pub mod measure;
pub mod microtubule;
pub mod orientation;
pub mod peaks;
pub mod point_fit;
pub mod profile;
pub mod quantities;
pub mod sbr;
pub mod scaling;
pub mod sensitivity;
pub mod spec;
pub mod stats;
pub mod template;
pub mod template_from_scans;

pub use background::{remove_point_background, BackgroundOptions, BackgroundResult, FilamentAxis};
pub use bead_model::{BeadModelOptions, Filament};
pub use fit::{
    detect_beads, fit_beads, Bead, BeadInit, Channels, Degeneracy, FitOptions, FitResult,
    FitStatus, GrowCriterion,
};
pub use orientation::{AngleCurve, AngleCurveOptions, FilamentMeasurement, MeasureOptions};
pub use peaks::{LinePeak, Peak, PeakMiss, PeakOptions};
pub use quantities::n_corr;
pub use sensitivity::{sensitivity, Axis, Stencil};
pub use template::{RefBead, Template, TemplateSource};

/// Errors of the analysis functions. Messages name the argument, its value and what is allowed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AnalysisError {
    /// A numeric argument outside its allowed range (or not finite).
    #[error("{name} = {value} is out of range: {allowed}")]
    OutOfRange {
        name: &'static str,
        value: f64,
        allowed: String,
    },
    /// An argument that is unusable for a stated reason (shape, size, content).
    #[error("{name}: {reason}")]
    BadInput { name: &'static str, reason: String },
    /// The template does not cover what the fit needs (truncated template, bead off the image).
    #[error("template does not cover the fit region: {0}")]
    TemplateCoverage(String),
    /// More beads than the image can support.
    #[error("too many beads: {0}")]
    TooManyBeads(String),
    /// A computation that could not produce a meaningful answer (stated why).
    #[error("{0}")]
    Failed(String),
}

impl From<crate::optics::OpticsError> for AnalysisError {
    fn from(e: crate::optics::OpticsError) -> Self {
        match e {
            crate::optics::OpticsError::OutOfRange {
                name,
                value,
                allowed,
            } => AnalysisError::OutOfRange {
                name,
                value,
                allowed,
            },
            crate::optics::OpticsError::Invalid(s) => AnalysisError::BadInput {
                name: "optics",
                reason: s,
            },
        }
    }
}

/// Result alias of the analysis module.
pub type Result<T> = std::result::Result<T, AnalysisError>;

/// Check `lo <= value <= hi` (finite); the optics' check, as an analysis error.
pub(crate) fn check_range(name: &'static str, value: f64, lo: f64, hi: f64) -> Result<f64> {
    Ok(crate::optics::params::check_range(name, value, lo, hi)?)
}

/// Check `value > lo` (finite); the optics' check, as an analysis error.
pub(crate) fn check_above(name: &'static str, value: f64, lo: f64) -> Result<f64> {
    Ok(crate::optics::params::check_above(name, value, lo)?)
}

/// [`check_above`] 0 for every (name, value), in order: the first one not positive is the error.
pub(crate) fn check_positive(values: &[(&'static str, f64)]) -> Result<()> {
    for &(name, value) in values {
        check_above(name, value, 0.0)?;
    }
    Ok(())
}

/// Validate an axis: at least `min_len` values, finite, strictly monotonic and (nearly) uniform
/// (relative step deviation ≤ 1e-3). Returns the signed mean step (0 for a single value).
pub(crate) fn check_axis(name: &'static str, a: &[f64], min_len: usize) -> Result<f64> {
    if a.len() < min_len {
        return Err(AnalysisError::BadInput {
            name,
            reason: format!("axis has {} values; at least {min_len} are needed", a.len()),
        });
    }
    if a.iter().any(|v| !v.is_finite()) {
        return Err(AnalysisError::BadInput {
            name,
            reason: "axis contains non-finite values".into(),
        });
    }
    if a.len() < 2 {
        return Ok(0.0);
    }
    let h = crate::data::image::axis_step(a);
    if h == 0.0 {
        return Err(AnalysisError::BadInput {
            name,
            reason: "axis is not strictly monotonic".into(),
        });
    }
    for w in a.windows(2) {
        let d = w[1] - w[0];
        if d * h <= 0.0 || ((d - h) / h).abs() > 1e-3 {
            return Err(AnalysisError::BadInput {
                name,
                reason: format!("axis is not regular: step {d} µm differs from the mean step {h} µm by more than 0.1%"),
            });
        }
    }
    Ok(h)
}

/// Map from coordinates to indices on a regular axis (`x0 + i·h`, h may be negative).
#[derive(Debug, Clone, Copy)]
pub(crate) struct AxisMap {
    pub x0: f64,
    pub h: f64,
    pub n: usize,
}

impl AxisMap {
    pub fn new(a: &[f64]) -> Self {
        Self {
            x0: a.first().copied().unwrap_or(0.0),
            h: crate::data::image::axis_step(a),
            n: a.len(),
        }
    }
    /// Index of the sample nearest to `x`, `None` when `x` lies more than half a step outside
    /// the axis (or is not finite).
    pub fn nearest(&self, x: f64) -> Option<usize> {
        if self.n == 0 || !x.is_finite() {
            return None;
        }
        if self.h == 0.0 {
            return Some(0);
        }
        let i = ((x - self.x0) / self.h).round();
        (i >= 0.0 && i < self.n as f64).then_some(i as usize)
    }
    /// Index range of samples whose coordinate lies in `[lo, hi]`.
    pub fn range(&self, lo: f64, hi: f64) -> std::ops::Range<usize> {
        if self.n == 0 || !(lo <= hi) {
            return 0..0;
        }
        if self.h == 0.0 {
            return if self.x0 >= lo && self.x0 <= hi {
                0..1
            } else {
                0..0
            };
        }
        let (a, b) = ((lo - self.x0) / self.h, (hi - self.x0) / self.h);
        let (a, b) = if a <= b { (a, b) } else { (b, a) };
        let i0 = a.ceil().max(0.0);
        let i1 = (b.floor() + 1.0).min(self.n as f64);
        if i1 <= i0 {
            0..0
        } else {
            i0 as usize..i1 as usize
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axis_map_nearest_rounds_and_refuses_outside() {
        let m = AxisMap::new(&[1.0, 0.5, 0.0]);
        assert_eq!(m.nearest(0.74), Some(1));
        assert_eq!(m.nearest(0.76), Some(0));
        assert_eq!(m.nearest(-0.24), Some(2));
        assert_eq!(m.nearest(-0.26), None);
        assert_eq!(m.nearest(1.26), None);
        assert_eq!(m.nearest(f64::NAN), None);
    }

    #[test]
    fn axis_map_ranges_both_directions() {
        let up = AxisMap {
            x0: 0.0,
            h: 0.1,
            n: 11,
        };
        assert_eq!(up.range(0.25, 0.55), 3..6);
        assert_eq!(up.range(-1.0, 0.0), 0..1);
        assert_eq!(up.range(1.01, 2.0), 0..0);
        let down = AxisMap {
            x0: 1.0,
            h: -0.1,
            n: 11,
        };
        assert_eq!(down.range(0.25, 0.55), 5..8);
        let e = check_axis("x", &[0.0, 0.1, 0.3], 2)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("x: axis is not regular: step 0.1"), "{e}");
        let e = check_axis("x", &[0.0], 2).unwrap_err().to_string();
        assert_eq!(e, "x: axis has 1 values; at least 2 are needed");
        assert!((check_axis("x", &[1.0, 0.9, 0.8], 2).unwrap() + 0.1).abs() < 1e-12);
    }
}
