//! The values scripts hold: [`ScanRef`] (`Scan`), [`ImageRef`] (`Image`), [`ProfileRef`]
//! (`Profile`), and the analysis values [`TemplateRef`] (`Template`), [`FitRef`]
//! (`FitResult`), [`CurveRef`] (`AngleCurve`), [`FilamentRef`] (`FilamentMeasurement`) with their
//! printing. Large arrays sit behind `Arc`, so passing them around in scripts is cheap. A leaf:
//! the context keeps the last partial scan, `types.rs` (which re-exports these) binds their
//! properties, printing and arithmetic.

use crate::analysis::{AngleCurve, FilamentMeasurement, FitResult, Template};
use crate::data::{Image, Profile, Scan};
use rhai::Dynamic;
use std::sync::Arc;

/// A scan in a script (`Scan`).
#[derive(Debug, Clone)]
pub struct ScanRef {
    pub scan: Arc<Scan>,
    /// Where it was saved, if it was.
    pub path: Option<Arc<str>>,
}

/// An image in a script (`Image`).
#[derive(Debug, Clone)]
pub struct ImageRef(pub Arc<Image>);

/// A 1-D curve in a script (`Profile`).
#[derive(Debug, Clone)]
pub struct ProfileRef(pub Arc<Profile>);

impl ScanRef {
    pub fn new(scan: Scan, path: Option<String>) -> Self {
        Self {
            scan: Arc::new(scan),
            path: path.map(Arc::from),
        }
    }
}

#[derive(Debug, Clone)]
pub struct TemplateRef(pub Arc<Template>);
/// The `tpl` argument of the bindings that model with a template (for [`Doc::arg_of`](super::registry::Doc::arg_of)).
pub const TEMPLATE_ARG: (&str, &str, &str, &str) =
    ("tpl", "Template", "", "the point-particle template");
/// A multi-bead fit in a script (`FitResult`).
#[derive(Debug, Clone)]
pub struct FitRef(pub Arc<FitResult>);
/// An orientation calibration curve in a script (`AngleCurve`).
#[derive(Debug, Clone)]
pub struct CurveRef(pub Arc<AngleCurve>);
/// A measured filament in a script (`FilamentMeasurement`).
#[derive(Debug, Clone)]
pub struct FilamentRef(pub Arc<FilamentMeasurement>);

impl std::fmt::Display for TemplateRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let t = &self.0;
        let src = match &t.source {
            crate::analysis::TemplateSource::Model { .. } => "physics model".to_string(),
            crate::analysis::TemplateSource::Scans { n_beads, .. } => {
                format!("{n_beads} measured beads")
            }
            crate::analysis::TemplateSource::Analytic { .. } => "analytic stand-in".to_string(),
        };
        write!(
            f,
            "Template({src}; {}×{} nodes every {} µm; reference {} nm, n = {}; norm_factor {:.4e})",
            t.grid.nu,
            t.grid.nv,
            super::words::fmt_num(t.grid.h),
            super::words::fmt_num(t.reference.d_nm),
            super::words::fmt_num(t.reference.n),
            t.norm_factor
        )
    }
}

impl std::fmt::Display for FitRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let r = &self.0;
        write!(
            f,
            "FitResult({} beads, χ² = {:.4e}, dof {}, status {:?}: {}{})",
            r.beads.len(),
            r.chi2,
            r.dof,
            r.status,
            r.reason,
            if r.is_degenerate() {
                format!(", {} degeneracies", r.degeneracies.len())
            } else {
                String::new()
            }
        )?;
        for (i, b) in r.beads.iter().enumerate().filter(|(_, b)| !b.found()) {
            write!(f, "\n  {}", super::words::not_found_words(i, b))?;
        }
        Ok(())
    }
}

impl std::fmt::Display for CurveRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let c = &self.0;
        write!(
            f,
            "AngleCurve({} angles, pixel {} µm, bead-model sensitivity at 0° {:.4})",
            c.angles_deg.len(),
            c.options.pixel_um,
            c.sx0
        )
    }
}

impl std::fmt::Display for FilamentRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let m = &self.0;
        write!(
            f,
            "FilamentMeasurement({:?}, angle {:.2}° ± {:.2}°, {} maxima, corrected sensitivity {:.4} ± {:.4})",
            m.channel,
            m.angle_deg,
            m.angle_err_deg,
            m.points.len(),
            m.mean_corr,
            m.sem_corr
        )
    }
}

/// Printing of this module's types (the REPL's `show`).
pub fn show_custom(v: &Dynamic) -> Option<String> {
    if let Some(t) = v.read_lock::<TemplateRef>() {
        return Some(t.to_string());
    }
    if let Some(t) = v.read_lock::<FitRef>() {
        return Some(t.to_string());
    }
    if let Some(t) = v.read_lock::<CurveRef>() {
        return Some(t.to_string());
    }
    if let Some(t) = v.read_lock::<FilamentRef>() {
        return Some(t.to_string());
    }
    None
}

/// Register the analysis types' names and printing with the engine (part of the `types` family).
pub fn register_types(e: &mut rhai::Engine) {
    register_printable::<TemplateRef>(e, "Template");
    register_printable::<FitRef>(e, "FitResult");
    register_printable::<CurveRef>(e, "AngleCurve");
    register_printable::<FilamentRef>(e, "FilamentMeasurement");
}

/// Register the script type `T` under `name`, printed (`print`, `to_string`, `to_debug`) by its
/// `Display`.
pub fn register_printable<T: std::fmt::Display + Clone + Send + Sync + 'static>(
    e: &mut rhai::Engine,
    name: &str,
) {
    e.register_type_with_name::<T>(name)
        .register_fn("to_string", |s: &mut T| s.to_string())
        .register_fn("to_debug", |s: &mut T| s.to_string());
}
