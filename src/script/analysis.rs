//! Analysis bindings: every quantitative step of the paper on scans (`src/analysis/`).
//!
//! Families: `sensitivity` (derivatives, maxima, focus, profiles), `templates` (reference
//! templates, multi-bead fit, bead model), `filaments` (orientation calibration, filament
//! measurement, SBR, background removal, diameters, linear density, masses) and `stats`.
//! Units at the boundary: µm for positions, nm for diameters, kDa / MDa·µm⁻¹ for masses and
//! linear densities; sensitivities in the scan's units per µm, or reference-bead units per µm
//! after a template's normalisation (the reference bead's max ∂Sx/∂x = 1).
//!
//! Custom types: `Template`, `FitResult`, `AngleCurve`, `FilamentMeasurement`.

use super::ctx::Ctx;
use super::registry::{err, fail, num, numbers, Doc, Opts, RResult, Registrar};
use super::types::{floats, json_to_dynamic, ImageRef, ProfileRef, ScanRef};
use crate::acquire::plan::linspace;
use crate::analysis::bead_model::{filament_beads, render_scene};
use crate::analysis::fit::Bead as FitBead;
use crate::analysis::focus::{focus_search, FocusOptions};
use crate::analysis::orientation::{measure_filament, Channel};
use crate::analysis::peaks::{col_peaks, point_peak, row_peaks};
use crate::analysis::profile::profile_polyline;
use crate::analysis::quantities::{
    fibril_diameter_nm, point_object, protofilaments, DiameterCalib, LinDensCalib,
};
use crate::analysis::sbr::{sbr, SbrOptions};
use crate::analysis::stats::{histogram, linfit, loglog_fit, summary, MAX_BINS};
use crate::analysis::template::FromScansOptions;
use crate::analysis::{
    fit_beads, remove_point_background, sensitivity, AngleCurve, AngleCurveOptions,
    BackgroundOptions, BeadInit, BeadModelOptions, Channels, FilamentAxis, FilamentMeasurement,
    FitOptions, FitResult, GrowCriterion, LinePeak, MeasureOptions, PeakOptions, RefBead, Stencil,
    Template,
};
use crate::data::{Image, Scan, ScanStatus};
use crate::optics::grid::Interp;
use crate::optics::rayleigh::DetectorModel;
use rhai::{Array, Dynamic, Map};
use serde::Serialize;
use std::sync::Arc;

/// A reference template in a script (`Template`).
#[derive(Debug, Clone)]
pub struct TemplateRef(pub Arc<Template>);
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
            t.grid.nu, t.grid.nv, t.grid.h, t.reference.d_nm, t.reference.n, t.norm_factor
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
        )
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

/// Any serialisable value as a Rhai map/array.
fn to_dyn<T: Serialize>(v: &T) -> Dynamic {
    json_to_dynamic(&serde_json::to_value(v).unwrap_or_default())
}

fn to_map<T: Serialize>(v: &T) -> Map {
    to_dyn(v).try_cast::<Map>().unwrap_or_default()
}

fn stencil_of(who: &str, o: &Opts, default: Stencil) -> RResult<Stencil> {
    match o.string("stencil")? {
        None => Ok(default),
        Some(s) => Stencil::parse(&s).map_or_else(
            || {
                fail(format!(
                    "{who}: stencil = \"{s}\" is not one of \"central2\", \"central5\", \"sg5\", \"sg7\", … (Savitzky–Golay with an odd number ≥ 3 of points)"
                ))
            },
            Ok,
        ),
    }
}

fn pos_f64(who: &str, o: &Opts, key: &str, default: f64, lo: f64, hi: f64) -> RResult<f64> {
    let v = o.f64_or(key, default)?;
    if !(v >= lo && v <= hi) {
        return fail(format!(
            "{who}: {key} = {v} is out of range: {lo} ≤ {key} ≤ {hi}"
        ));
    }
    Ok(v)
}

fn count(who: &str, o: &Opts, key: &str, lo: i64, hi: i64) -> RResult<Option<usize>> {
    match o.int(key)? {
        None => Ok(None),
        Some(v) if (lo..=hi).contains(&v) => Ok(Some(v as usize)),
        Some(v) => fail(format!(
            "{who}: {key} = {v} is out of range: {lo} ≤ {key} ≤ {hi}"
        )),
    }
}

fn peak_opts(who: &str, o: &Opts) -> RResult<PeakOptions> {
    Ok(PeakOptions {
        window_um: pos_f64(who, o, "window_um", 0.4, 1e-3, 100.0)?,
        min_value: o.f64("min_value")?,
        min_snr: pos_f64(who, o, "min_snr", 0.0, 0.0, 1e6)?,
        sigma: o.f64("sigma")?,
    })
}

fn measure_opts(who: &str, o: &Opts, base: MeasureOptions) -> RResult<MeasureOptions> {
    Ok(MeasureOptions {
        stencil: stencil_of(who, o, base.stencil)?,
        window_um: pos_f64(who, o, "window_um", base.window_um, 1e-3, 100.0)?,
        min_snr: pos_f64(who, o, "min_snr", base.min_snr, 0.0, 1e6)?,
        max_offset_um: pos_f64(who, o, "max_offset_um", base.max_offset_um, 0.0, 100.0)?,
        detect_snr: pos_f64(who, o, "detect_snr", base.detect_snr, 0.0, 1e6)?,
    })
}

/// Keys of the bead-model measurement pipeline shared by the calibrations (`pipeline_opts`).
const PIPELINE_KEYS: &[(&str, &str, &str, &str)] = &[
    (
        "pixel_um",
        "float",
        "µm",
        "optional: pixel size of the scans (default 0.05)",
    ),
    (
        "spacing_nm",
        "float",
        "nm",
        "optional: bead-model spacing (default 50)",
    ),
    (
        "stencil",
        "string",
        "",
        "optional: derivative stencil (default central2)",
    ),
    (
        "window_um",
        "float",
        "µm",
        "optional: parabola window (default 0.4)",
    ),
];

/// Pixel size, measurement options and bead-model options from the `PIPELINE_KEYS`.
fn pipeline_opts(who: &str, o: &Opts) -> RResult<(f64, MeasureOptions, BeadModelOptions)> {
    // only the declared keys: stencil and window; the rest of the measurement keeps its defaults
    let base = MeasureOptions::default();
    let mo = MeasureOptions {
        stencil: stencil_of(who, o, base.stencil)?,
        window_um: pos_f64(who, o, "window_um", base.window_um, 1e-3, 100.0)?,
        ..base
    };
    let bm = BeadModelOptions {
        spacing_nm: o.f64_or("spacing_nm", 50.0)?,
    };
    Ok((o.f64_or("pixel_um", 0.05)?, mo, bm))
}

fn line_peaks(v: &[LinePeak]) -> Array {
    v.iter()
        .map(|lp| {
            let mut m = Map::new();
            m.insert("line".into(), (lp.line as i64).into());
            m.insert("coord".into(), lp.coord.into());
            match &lp.result {
                Ok(p) => {
                    m.insert("ok".into(), true.into());
                    for (k, v) in to_map(p) {
                        m.insert(k, v);
                    }
                }
                Err(miss) => {
                    m.insert("ok".into(), false.into());
                    m.insert("miss".into(), miss.to_string().into());
                }
            }
            Dynamic::from_map(m)
        })
        .collect()
}

fn bead_map(b: &FitBead) -> Dynamic {
    to_dyn(b)
}

/// `[#{x, y, weight}]` → (x, y, weight) triples.
fn bead_list(who: &str, v: &Dynamic) -> RResult<Vec<(f64, f64, f64)>> {
    let Some(a) = v.read_lock::<Array>() else {
        return fail(format!(
            "{who}: beads must be an array of #{{x, y, weight}} maps (µm, reference-bead units), got {}",
            v.type_name()
        ));
    };
    a.iter()
        .enumerate()
        .map(|(i, b)| {
            let Some(m) = b.read_lock::<Map>() else {
                return fail(format!(
                    "{who}: beads[{i}] must be #{{x, y, weight}}, got {b}"
                ));
            };
            let g = |k: &str, d: Option<f64>| -> RResult<f64> {
                match (m.get(k), d) {
                    (Some(v), _) => num(who, &format!("beads[{i}].{k}"), v),
                    (None, Some(d)) => Ok(d),
                    (None, None) => fail(format!("{who}: beads[{i}] lacks `{k}` (µm)")),
                }
            };
            Ok((g("x", None)?, g("y", None)?, g("weight", Some(1.0))?))
        })
        .collect()
}

/// `#{points: [[x, y], …], d_nm: 50.0 | [..], n: 1.41}` → a bead-model filament.
fn filament_arg(who: &str, v: &Dynamic) -> RResult<crate::analysis::Filament> {
    let Some(m) = v.read_lock::<Map>() else {
        return fail(format!(
            "{who}: a filament is #{{points: [[x, y], …], d_nm, n}}, got {}",
            v.type_name()
        ));
    };
    for k in m.keys() {
        if !["points", "d_nm", "n"].contains(&k.as_str()) {
            return fail(format!(
                "{who}: unknown filament key `{k}`; allowed keys: points, d_nm, n"
            ));
        }
    }
    let points = match m.get("points") {
        Some(p) => super::physics::points(who, p)?,
        None => return fail(format!("{who}: filament lacks `points` ([[x, y], …] µm)")),
    };
    let d_nm = match m.get("d_nm") {
        None => return fail(format!("{who}: filament lacks `d_nm` (nm)")),
        Some(d) if d.is_array() => numbers(who, "d_nm", d)?,
        Some(d) => vec![num(who, "d_nm", d)?],
    };
    let n = match m.get("n") {
        None => return fail(format!("{who}: filament lacks `n` (refractive index)")),
        Some(v) => num(who, "n", v)?,
    };
    let f = crate::analysis::Filament { points, d_nm, n };
    f.validate().map_err(|e| err(who, e))?;
    Ok(f)
}

/// The `x: [from, to], y: [from, to], nx, ny` keys of a grid map → regular axes (µm).
pub(crate) fn grid_axes(who: &str, o: &Opts) -> RResult<(Vec<f64>, Vec<f64>)> {
    let (x0, x1) = o.req_range("x")?;
    let (y0, y1) = o.req_range("y")?;
    let nx = o.req_int("nx")?;
    let ny = o.req_int("ny")?;
    for (k, v) in [("nx", nx), ("ny", ny)] {
        if !(1..=4096).contains(&v) {
            return fail(format!("{who}: {k} = {v} is out of range: 1 ≤ {k} ≤ 4096"));
        }
    }
    Ok((linspace(x0, x1, nx as usize), linspace(y0, y1, ny as usize)))
}

fn ref_bead(who: &str, o: &Opts, n_medium: f64) -> RResult<RefBead> {
    let d = RefBead::default();
    let r = RefBead {
        d_nm: o.f64_or("d_nm", d.d_nm)?,
        n: o.f64_or("n", d.n)?,
        n_medium,
        density_g_cm3: o.f64_or("density", d.density_g_cm3)?,
    };
    r.validate().map_err(|e| err(who, e))?;
    Ok(r)
}

fn scans_arg(who: &str, v: &Array) -> RResult<Vec<Arc<Scan>>> {
    v.iter()
        .enumerate()
        .map(|(i, s)| match s.read_lock::<ScanRef>() {
            Some(s) => Ok(s.scan.clone()),
            None => fail(format!(
                "{who}: scans[{i}] must be a Scan, got {}",
                s.type_name()
            )),
        })
        .collect()
}

fn scan_of(sx: Image, sy: Image, sz: Image, meta: serde_json::Value) -> ScanRef {
    ScanRef::new(
        Scan {
            sx,
            sy,
            sz,
            status: ScanStatus::Complete,
            meta,
        },
        None,
    )
}

const TPL: &str = "let t = template_model(#{h_um: 0.025});";
const ONE_BEAD: &str = "let t = template_model(#{h_um: 0.025}); let sc = render_beads(t, #{beads: [#{x: 0.1, y: -0.05, weight: 1.0}], x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 41, ny: 41});";

pub fn register(r: &mut Registrar) {
    let ctx = r.ctx();
    {
        let e = r.engine();
        e.register_type_with_name::<TemplateRef>("Template")
            .register_type_with_name::<FitRef>("FitResult")
            .register_type_with_name::<CurveRef>("AngleCurve")
            .register_type_with_name::<FilamentRef>("FilamentMeasurement");
        e.register_fn("to_string", |s: &mut TemplateRef| s.to_string())
            .register_fn("to_debug", |s: &mut TemplateRef| s.to_string())
            .register_fn("to_string", |s: &mut FitRef| s.to_string())
            .register_fn("to_debug", |s: &mut FitRef| s.to_string())
            .register_fn("to_string", |s: &mut CurveRef| s.to_string())
            .register_fn("to_debug", |s: &mut CurveRef| s.to_string())
            .register_fn("to_string", |s: &mut FilamentRef| s.to_string())
            .register_fn("to_debug", |s: &mut FilamentRef| s.to_string());
    }
    register_sensitivity(r);
    register_templates(r, &ctx);
    register_fit(r, &ctx);
    register_filaments(r, &ctx);
    register_stats(r);
}

// ------------------------------------------------------------------ sensitivity

fn register_sensitivity(r: &mut Registrar) {
    let d = Doc::func("sensitivity", "sensitivity")
        .arg("img", "Image | Scan", "", "an image (or a scan: Sx for axis x, Sy for axis y)")
        .map(
            "opts",
            "optional",
            &[
                ("axis", "string", "", "\"x\" (∂/∂x, default) or \"y\" (∂/∂y)"),
                ("stencil", "string", "", "\"central2\" (default), \"central5\", \"sg5\", \"sg7\", … (Savitzky–Golay)"),
            ],
        )
        .returns("Image", "the derivative, signal units per µm")
        .summary("sensitivity image ∂S/∂x or ∂S/∂y (Sec. 3.2)")
        .help("Central differences inside, one-sided at the edges (documented in docs/analysis.md). The noise gain of each stencil: σ(derivative) = gain·σ(pixel)/h with gain 0.707 (central2), 0.950 (central5), 0.316 (sg5). NaN pixels propagate only to the derivatives that use them.")
        .form("sensitivity(img) -> Image")
        .example(&format!("{ONE_BEAD} let s = sensitivity(sc); round(s.max() * t.norm_factor * 10.0) / 10.0"), "1.0")
        .example(&format!("{ONE_BEAD} sensitivity(sc.sx, #{{axis: \"z\"}})"), "error: axis = \"z\"");
    let spec = d.spec();
    let run = move |v: Dynamic, m: Map| -> RResult<ImageRef> {
        let o = Opts::new(&spec, &m)?;
        let ax = o.string("axis")?.unwrap_or_else(|| "x".into());
        let axis = crate::analysis::Axis::parse(&ax).map_or_else(
            || {
                fail(format!(
                    "sensitivity: axis = \"{ax}\" is not one of \"x\", \"y\""
                ))
            },
            Ok,
        )?;
        let st = stencil_of("sensitivity", &o, Stencil::Central2)?;
        let im: Arc<Image> = if let Some(s) = v.read_lock::<ScanRef>() {
            match axis {
                crate::analysis::Axis::X => Arc::new(s.scan.sx.clone()),
                crate::analysis::Axis::Y => Arc::new(s.scan.sy.clone()),
            }
        } else if let Some(i) = v.read_lock::<ImageRef>() {
            i.0.clone()
        } else {
            return fail(format!(
                "sensitivity: img must be an Image or a Scan, got {}",
                v.type_name()
            ));
        };
        let out = sensitivity(&im, axis, st).map_err(|e| err("sensitivity", e))?;
        Ok(ImageRef(Arc::new(out)))
    };
    let run2 = run.clone();
    r.bind(d, run);
    r.overload("sensitivity", move |v: Dynamic| run2(v, Map::new()));

    let keys: &[(&str, &str, &str, &str)] = &[
        (
            "window_um",
            "float",
            "µm",
            "optional: parabola window (default 0.4, Sec. 5)",
        ),
        (
            "min_snr",
            "float",
            "",
            "optional: reject maxima below min_snr × line noise (default 0)",
        ),
        (
            "min_value",
            "float",
            "",
            "optional: reject maxima below this value",
        ),
        (
            "sigma",
            "float",
            "",
            "optional: known pixel noise (default: from the fit residuals)",
        ),
    ];
    for (name, rows) in [("row_peaks", true), ("col_peaks", false)] {
        let d = Doc::func(name, "sensitivity")
            .arg("img", "Image", "", "usually a sensitivity image")
            .map("opts", "optional", keys)
            .form(&format!("{name}(img) -> array"))
            .returns("array", "per line: #{line, coord, ok, pos, value, pos_err, value_err, curvature, n_points, truncated} or #{line, coord, ok: false, miss}")
            .summary(if rows {
                "sub-pixel maximum of every row (x position) by a parabola over the window"
            } else {
                "sub-pixel maximum of every column (y position) by a parabola over the window"
            })
            .help("The parabola is fitted by least squares over the samples within ±window/2 of the discrete maximum; pos_err and value_err are 1σ from the residual scatter (or the given sigma). A line whose maximum sits on its first or last sample, or has no concave parabola, reports ok: false with the reason.")
            .example(
                &format!("{ONE_BEAD} let p = {name}(sensitivity(sc, #{{axis: \"{}\"}})); p.len()", if rows { "x" } else { "y" }),
                "41",
            )
            .example(&format!("{ONE_BEAD} {name}(sc.sx, #{{window_um: -1.0}})"), "error: window_um = -1");
        let spec = d.spec();
        let f = move |i: ImageRef, m: Map| -> RResult<Array> {
            let o = Opts::new(&spec, &m)?;
            let po = peak_opts(name, &o)?;
            let v = if rows {
                row_peaks(&i.0, &po)
            } else {
                col_peaks(&i.0, &po)
            }
            .map_err(|e| err(name, e))?;
            Ok(line_peaks(&v))
        };
        let f2 = f.clone();
        r.bind(d, f);
        r.overload(name, move |i: ImageRef| f2(i, Map::new()));
    }

    let d = Doc::func("max_sens", "sensitivity")
        .arg("img", "Image", "", "a sensitivity image around one point object")
        .map("opts", "optional", keys)
        .form("max_sens(img) -> map")
        .returns("map", "#{x, y, value, x_err, y_err, value_err, n_points} (µm; value in the image's units)")
        .summary("maximum sensitivity of a point object: row parabolas, refined across rows (Sec. 5)")
        .example(&format!("{ONE_BEAD} let m = max_sens(sensitivity(sc)); round(m.value * t.norm_factor / t.max_sens(0.05) * 100.0) / 100.0"), "1.0");
    let spec = d.spec();
    let f = move |i: ImageRef, m: Map| -> RResult<Map> {
        let o = Opts::new(&spec, &m)?;
        let po = peak_opts("max_sens", &o)?;
        let p = point_peak(&i.0, &po).map_err(|e| err("max_sens", e))?;
        Ok(to_map(&p))
    };
    let f2 = f.clone();
    r.bind(d, f);
    r.overload("max_sens", move |i: ImageRef| f2(i, Map::new()));

    let d = Doc::func("focus_search", "sensitivity")
        .arg("img", "Image | Scan", "", "an XZ (or YZ) scan channel: rows are z (a Scan: its Sx)")
        .map(
            "opts",
            "optional",
            &[
                ("stencil", "string", "", "optional: derivative stencil (default central2)"),
                ("window_um", "float", "µm", "optional: lateral parabola window (default 0.4)"),
                ("z_window_um", "float", "µm", "optional: window of the parabola over z (default 0.6)"),
                ("level", "float", "", "optional: fraction of the peak that defines the tolerated z range (default 0.98)"),
            ],
        )
        .form("focus_search(img) -> map")
        .returns("map", "#{z_best, z_err, max_sens, max_sens_err, z_lo, z_hi, rows} (µm; rows: per-z maxima)")
        .summary("best focus: max sensitivity per z row, parabola over z (suppl. S5)")
        .help("z_lo/z_hi: where the row maxima fall to level × max (paper: within 2 % over ±200 nm); () on a side where the scan ends first.");
    let spec = d.spec();
    let f = move |v: Dynamic, m: Map| -> RResult<Map> {
        let o = Opts::new(&spec, &m)?;
        let d = FocusOptions::default();
        let fo = FocusOptions {
            stencil: stencil_of("focus_search", &o, d.stencil)?,
            window_um: pos_f64("focus_search", &o, "window_um", d.window_um, 1e-3, 100.0)?,
            z_window_um: pos_f64("focus_search", &o, "z_window_um", d.z_window_um, 1e-3, 1e3)?,
            level: pos_f64("focus_search", &o, "level", d.level, 0.0, 1.0)?,
        };
        let im: Arc<Image> = if let Some(s) = v.read_lock::<ScanRef>() {
            Arc::new(s.scan.sx.clone())
        } else if let Some(i) = v.read_lock::<ImageRef>() {
            i.0.clone()
        } else {
            return fail(format!(
                "focus_search: img must be an Image or a Scan, got {}",
                v.type_name()
            ));
        };
        let res = focus_search(&im, &fo).map_err(|e| err("focus_search", e))?;
        let mut out = Map::new();
        out.insert("z_best".into(), res.z_best.into());
        out.insert("z_err".into(), to_dyn(&res.z_err));
        out.insert("max_sens".into(), res.max_sens.into());
        out.insert("max_sens_err".into(), to_dyn(&res.max_sens_err));
        out.insert("z_lo".into(), to_dyn(&res.z_lo));
        out.insert("z_hi".into(), to_dyn(&res.z_hi));
        out.insert("rows".into(), line_peaks(&res.rows).into());
        Ok(out)
    };
    let f2 = f.clone();
    r.bind(
        d.example(
            "let s = scene(); s.add_bead(#{x: 0.0, y: 0.0, z: 0.0, d_nm: 110.0, n: 1.572}); let t = template_model(#{h_um: 0.025}); let xs = []; let sc = simulate(s, #{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 5, ny: 5}); focus_search(sc.sx, #{level: 2.0})",
            "error: level = 2",
        ),
        f,
    );
    r.overload("focus_search", move |v: Dynamic| f2(v, Map::new()));

    let d = Doc::func("profile_along", "sensitivity")
        .arg("img", "Image", "", "any image")
        .arg("points", "array", "µm", "polyline [[x, y], …]")
        .opt(
            "step_um",
            "float",
            "µm",
            "sampling step along the arc (default: the pixel size)",
        )
        .returns(
            "Profile",
            "values vs arc length from the first vertex (bicubic interpolation)",
        )
        .summary("profile of an image along a polyline (Fig. 5c)")
        .example(
            &format!("{ONE_BEAD} profile_along(sc.sx, [[-0.5, 0.0], [0.5, 0.0]], 0.1).len"),
            "11",
        )
        .example(
            &format!("{ONE_BEAD} profile_along(sc.sx, [[0.0, 0.0]])"),
            "error: ",
        );
    let f = |i: ImageRef, p: Array, step: f64| -> RResult<ProfileRef> {
        let pts = super::physics::points("profile_along", &Dynamic::from_array(p))?;
        let pr = profile_polyline(&i.0, &pts, step, Interp::Cubic)
            .map_err(|e| err("profile_along", e))?;
        Ok(ProfileRef(Arc::new(pr)))
    };
    r.bind(d, f);
    r.overload("profile_along", move |i: ImageRef, p: Array| {
        let h = i.0.dx().abs().min(i.0.dy().abs());
        let h = if h > 0.0 { h } else { 0.01 };
        f(i, p, h)
    });
}

// ------------------------------------------------------------------ templates

fn register_templates(r: &mut Registrar, ctx: &Arc<Ctx>) {
    let d = Doc::func("template_model", "templates")
        .map(
            "opts",
            "optional",
            &[
                (
                    "h_um",
                    "float",
                    "µm",
                    "optional: node spacing (default 0.02; 0.001–0.2)",
                ),
                (
                    "z_um",
                    "float",
                    "µm",
                    "optional: axial offset of the bead from the focus (default 0)",
                ),
                (
                    "d_nm",
                    "float",
                    "nm",
                    "optional: reference bead diameter (default 110)",
                ),
                (
                    "n",
                    "float",
                    "",
                    "optional: reference bead index (default 1.572)",
                ),
                (
                    "density",
                    "float",
                    "g/cm³",
                    "optional: reference bead density (default 1.05)",
                ),
                (
                    "polarization",
                    "bool",
                    "",
                    "optional: vector dipole field (default false)",
                ),
            ],
        )
        .form("template_model() -> Template")
        .returns(
            "Template",
            "normalised so the reference bead's max ∂Sx/∂x = 1",
        )
        .summary("reference template from the physics model in the current optics (Sec. 3.1)")
        .example(&format!("{TPL} t.norm_factor > 0.0"), "true")
        .example("template_model(#{h_um: 5.0})", "error: h_um = 5");
    let spec = d.spec();
    let c = ctx.clone();
    let f = move |m: Map| -> RResult<TemplateRef> {
        let o = Opts::new(&spec, &m)?;
        let optics = c.optics.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let rb = ref_bead("template_model", &o, optics.n_medium)?;
        let det = DetectorModel {
            polarization: o.bool_or("polarization", false)?,
            ..Default::default()
        };
        let t = Template::from_optics(
            &optics,
            &det,
            rb,
            o.f64_or("h_um", 0.02)?,
            o.f64_or("z_um", 0.0)?,
        )
        .map_err(|e| err("template_model", e))?;
        Ok(TemplateRef(Arc::new(t)))
    };
    let f2 = f.clone();
    r.bind(d, f);
    r.overload("template_model", move || f2(Map::new()));

    let d = Doc::func("template_from_scans", "templates")
        .arg("scans", "array", "", "XY scans of reference beads [Scan, …]")
        .map(
            "opts",
            "optional",
            &[
                ("half_width_um", "float", "µm", "optional: half-width of the template (default 1.5)"),
                ("h_um", "float", "µm", "optional: node spacing (default: the finest pixel)"),
                ("beads_per_scan", "int", "", "optional: beads per scan (default: all isolated maxima)"),
                ("threshold", "float", "", "optional: detection threshold, fraction of the largest peak (default 0.3)"),
                ("iterations", "int", "", "optional: alignment iterations (default 2)"),
                ("d_nm", "float", "nm", "optional: reference bead diameter (default 110)"),
                ("n", "float", "", "optional: reference bead index (default 1.572)"),
                ("density", "float", "g/cm³", "optional: density (default 1.05)"),
            ],
        )
        .form("template_from_scans(scans) -> Template")
        .returns("Template", "aligned average of the beads, normalised so max ∂Sx/∂x = 1; .source tells the beads used and the misfit")
        .summary("reference template from measured scans of several reference beads: locate, align sub-pixel, average, normalise")
        .example(&format!("{TPL} let a = render_beads(t, #{{beads: [#{{x: 0.03, y: 0.0}}], x: [-2.0, 2.0], y: [-2.0, 2.0], nx: 81, ny: 81}}); let b = render_beads(t, #{{beads: [#{{x: -0.02, y: 0.04}}], x: [-2.0, 2.0], y: [-2.0, 2.0], nx: 81, ny: 81}}); template_from_scans([a, b]).source.n_beads"), "2")
        .example("template_from_scans([])", "error: no scans");
    let spec = d.spec();
    let c = ctx.clone();
    let f = move |a: Array, m: Map| -> RResult<TemplateRef> {
        let o = Opts::new(&spec, &m)?;
        let n_medium = c.optics.lock().unwrap_or_else(|e| e.into_inner()).n_medium;
        let rb = ref_bead("template_from_scans", &o, n_medium)?;
        let d = FromScansOptions::default();
        let fo = FromScansOptions {
            half_width_um: o.f64_or("half_width_um", d.half_width_um)?,
            h_um: o.f64("h_um")?,
            beads_per_scan: count("template_from_scans", &o, "beads_per_scan", 1, 10_000)?,
            threshold: o.f64_or("threshold", d.threshold)?,
            iterations: count("template_from_scans", &o, "iterations", 0, 100)?
                .unwrap_or(d.iterations),
        };
        let scans = scans_arg("template_from_scans", &a)?;
        let refs: Vec<&Scan> = scans.iter().map(|s| s.as_ref()).collect();
        let t = Template::from_scans(&refs, rb, &fo).map_err(|e| err("template_from_scans", e))?;
        Ok(TemplateRef(Arc::new(t)))
    };
    let f2 = f.clone();
    r.bind(d, f);
    r.overload("template_from_scans", move |a: Array| f2(a, Map::new()));

    // properties and methods
    r.getter(
        Doc::property("Template", "norm_factor")
            .returns("float", "factor applied to the source data so that max ∂Sx/∂x = 1 (reference-bead units per scan unit)")
            .summary("normalisation of the template")
            .example(&format!("{TPL} t.norm_factor > 1.0"), "true"),
        |t: &mut TemplateRef| t.0.norm_factor,
    );
    r.getter(
        Doc::property("Template", "reference")
            .returns("map", "#{d_nm, n, n_medium, density_g_cm3}")
            .summary("the reference bead the template represents")
            .example(&format!("{TPL} t.reference.d_nm"), "110.0"),
        |t: &mut TemplateRef| to_map(&t.0.reference),
    );
    r.getter(
        Doc::property("Template", "source")
            .returns(
                "map",
                "#{kind: \"model\" | \"scans\" | \"analytic\", …} (beads used, misfit)",
            )
            .summary("where the template came from")
            .example(&format!("{TPL} t.source.kind"), "\"model\""),
        |t: &mut TemplateRef| to_map(&t.0.source),
    );
    r.getter(
        Doc::property("Template", "h_um")
            .returns("float", "node spacing, µm")
            .summary("grid spacing of the template")
            .example(&format!("{TPL} t.h_um"), "0.025"),
        |t: &mut TemplateRef| t.0.grid.h,
    );
    r.bind(
        Doc::method("Template", "at")
            .arg("u", "float", "µm", "x − x_bead")
            .arg("v", "float", "µm", "y − y_bead")
            .returns(
                "map",
                "#{sx, sy, sz} in reference-bead units (interpolated)",
            )
            .summary("the template's response at a displacement from the bead")
            .example(&format!("{TPL} t.at(0.0, 0.0).sx"), "0.0"),
        |t: &mut TemplateRef, u: f64, v: f64| -> Map {
            let s = t.0.eval(u, v);
            let mut m = Map::new();
            m.insert("sx".into(), s[0].into());
            m.insert("sy".into(), s[1].into());
            m.insert("sz".into(), s[2].into());
            m
        },
    );
    r.bind(
        Doc::method("Template", "max_sens")
            .arg("pixel_um", "float", "µm", "pixel size of the scans to be measured")
            .opt("stencil", "string", "", "derivative stencil (default central2)")
            .returns("float", "max ∂Sx/∂x of the reference bead as the pixel pipeline measures it (≈ 1)")
            .summary("the reference bead's max sensitivity through the measurement pipeline (denominator of masses)")
            .example(&format!("{TPL} let m = t.max_sens(0.05); m > 0.9 && m < 1.0"), "true"),
        |t: &mut TemplateRef, px: f64| -> RResult<f64> {
            t.0.pipeline_max_sens(px, Stencil::Central2, 0.4)
                .map_err(|e| err("max_sens", e))
        },
    );
    r.overload(
        "max_sens",
        |t: &mut TemplateRef, px: f64, st: &str| -> RResult<f64> {
            let s = Stencil::parse(st).map_or_else(
                || fail(format!("max_sens: stencil = \"{st}\" is not one of \"central2\", \"central5\", \"sg5\", …")),
                Ok,
            )?;
            t.0.pipeline_max_sens(px, s, 0.4)
                .map_err(|e| err("max_sens", e))
        },
    );
    let c = ctx.clone();
    r.bind(
        Doc::method("Template", "save")
            .arg("path", "string", "", "file (JSON; relative: in the session folder; an existing file is kept and a numbered name used)")
            .returns("string", "the path written")
            .summary("save the template (JSON with grid, reference bead, source and the script's provenance)")
            .example(&format!("{TPL} let p = status().data_dir + \"/tpl_example.json\"; t.save(p); load_template(p).h_um"), "0.025"),
        move |t: &mut TemplateRef, path: &str| -> RResult<String> {
            super::console::save_template(&c, t, path, false)
        },
    );
    r.bind(
        Doc::func("load_template", "templates")
            .arg("path", "string", "", "a file written by template.save")
            .returns("Template", "")
            .summary("load a saved template")
            .example(
                "load_template(\"no/such/template.json\")",
                "error: load_template: no/such/template.json",
            ),
        |path: &str| -> RResult<TemplateRef> {
            let s = std::fs::read_to_string(path)
                .map_err(|e| err("load_template", format!("{path}: {e}")))?;
            let t = Template::from_json(&s)
                .map_err(|e| err("load_template", format!("{path}: {e}")))?;
            Ok(TemplateRef(Arc::new(t)))
        },
    );

    let d = Doc::func("render_beads", "templates")
        .arg("tpl", "Template", "", "the point-particle template")
        .map(
            "what",
            "objects and the grid",
            &[
                ("beads", "array", "", "optional: [#{x, y, weight}] point objects (µm; weight in reference-bead units, default 1)"),
                ("filaments", "array", "", "optional: [#{points: [[x, y], …], d_nm, n}] bead-model filaments (d_nm: one value or one per vertex)"),
                ("spacing_nm", "float", "nm", "optional: bead-model spacing (default 50, Sec. 4.2)"),
                ("x", "array", "µm", "[from, to]"),
                ("y", "array", "µm", "[from, to]"),
                ("nx", "int", "", "pixels along x"),
                ("ny", "int", "", "pixels along y"),
            ],
        )
        .returns("Scan", "noise-free scan in the template's instrument units (superposition, eq. ReEEpReEE; × norm_factor gives reference-bead units)")
        .summary("render point objects and filaments from a template (the bead model of Sec. 4.2)")
        .example(&format!("{ONE_BEAD} sc.sx.cols"), "41")
        .example(&format!("{TPL} render_beads(t, #{{filaments: [#{{points: [[0.0, -1.0], [0.0, 1.0]], d_nm: 50.0, n: 1.41}}], x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 21, ny: 21}}).rows"), "21")
        .example(&format!("{TPL} render_beads(t, #{{filaments: [#{{points: [[0.0, 0.0]], d_nm: 50.0, n: 1.41}}], x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 21, ny: 21}})"), "error: ");
    let spec = d.spec();
    r.bind(d, move |t: TemplateRef, m: Map| -> RResult<ScanRef> {
        let o = Opts::new(&spec, &m)?;
        let who = "render_beads";
        let beads = match m.get("beads") {
            Some(b) => bead_list(who, b)?,
            None => vec![],
        };
        let fils = match m.get("filaments") {
            Some(f) => match f.read_lock::<Array>() {
                Some(a) => a
                    .iter()
                    .map(|x| filament_arg(who, x))
                    .collect::<RResult<Vec<_>>>()?,
                None => {
                    return fail(format!(
                        "{who}: filaments must be an array of filament maps"
                    ))
                }
            },
            None => vec![],
        };
        let bm = BeadModelOptions {
            spacing_nm: o.f64_or("spacing_nm", 50.0)?,
        };
        let (x, y) = grid_axes(who, &o)?;
        let s = render_scene(&t.0, &beads, &fils, &bm, &x, &y).map_err(|e| err(who, e))?;
        // reference-bead units → the instrument units of the template's source (what a scan
        // of these objects records; fits and filament measurements expect those units)
        let k = 1.0 / t.0.norm_factor;
        let sc = |i: &Image| i.mul_scalar(k).map_err(|e| err(who, e));
        let meta =
            serde_json::json!({ "kind": "render_beads", "units": "instrument (template source)" });
        Ok(scan_of(sc(&s.sx)?, sc(&s.sy)?, sc(&s.sz)?, meta))
    });

    let d = Doc::func("bead_model", "templates")
        .arg("tpl", "Template", "", "the point-particle template")
        .arg("filament", "map", "", "#{points: [[x, y], …] (µm), d_nm (one or per vertex), n}")
        .opt("spacing_nm", "float", "nm", "bead spacing (default 50)")
        .returns("array", "[#{x, y, weight}] the beads (weights in reference-bead units: (3/4)·h·d²·n_corr / d_ref³·… , Sec. 4.2)")
        .summary("the beads of a filament's bead model")
        .example(&format!("{TPL} bead_model(t, #{{points: [[0.0, 0.0], [0.0, 1.0]], d_nm: 110.0, n: 1.572}}, 50.0).len()"), "20");
    let f = |t: TemplateRef, fm: Map, sp: f64| -> RResult<Array> {
        let fil = filament_arg("bead_model", &Dynamic::from_map(fm))?;
        let b = filament_beads(&t.0, &fil, &BeadModelOptions { spacing_nm: sp })
            .map_err(|e| err("bead_model", e))?;
        Ok(b.iter()
            .map(|&(x, y, w)| {
                let mut m = Map::new();
                m.insert("x".into(), x.into());
                m.insert("y".into(), y.into());
                m.insert("weight".into(), w.into());
                Dynamic::from_map(m)
            })
            .collect())
    };
    r.bind(d, f);
    r.overload("bead_model", move |t: TemplateRef, fm: Map| f(t, fm, 50.0));
}

// ------------------------------------------------------------------ fit

fn register_fit(r: &mut Registrar, ctx: &Arc<Ctx>) {
    let d = Doc::func("fit_beads", "templates")
        .arg("scan", "Scan", "", "XY scan (Sx and Sy)")
        .arg("tpl", "Template", "", "the point-particle template")
        .map(
            "opts",
            "optional",
            &[
                ("channels", "string", "", "optional: \"both\" (default, eq. multiBeadFit), \"sx\", \"sy\""),
                ("n_beads", "int", "", "optional: number of beads for automatic initial guesses from peaks"),
                ("init", "array", "", "optional: initial guesses [#{x, y, weight}]"),
                ("grow", "bool", "", "optional: add beads one at a time at the largest residual while the criterion improves (default when neither n_beads nor init)"),
                ("max_beads", "int", "", "optional: limit when growing (default 30)"),
                ("criterion", "string", "", "optional: \"bic\" (default) or \"rel_drop\""),
                ("min_drop", "float", "", "optional: RSS drop needed with criterion rel_drop (default 0.02)"),
                ("sigma", "float", "", "optional: pixel noise (default: from the residuals)"),
                ("ftol", "float", "", "optional: relative tolerance on the objective (default 1e-10)"),
                ("xtol", "float", "", "optional: relative tolerance on the parameters (default 1e-10)"),
                ("gtol", "float", "", "optional: gradient tolerance (default 1e-10)"),
                ("patience", "int", "", "optional: residual evaluations allowed = patience × (3n + 1) (default 100)"),
                ("min_separation", "float", "", "optional: beads closer than this × w0 are degenerate (default 0.25)"),
                ("merge_degenerate", "bool", "", "optional: merge degenerate pairs and refit (default true)"),
            ],
        )
        .form("fit_beads(scan, tpl) -> FitResult")
        .returns("FitResult", "beads with uncertainties, residual images, χ², status and reason, degeneracies")
        .summary("multi-bead template fit (eq. multiBeadFit) with Levenberg–Marquardt and an analytic Jacobian")
        .example(&format!("{ONE_BEAD} let f = fit_beads(sc, t, #{{n_beads: 1}}); round(f.beads[0].x * 1000.0)"), "100.0")
        .example(&format!("{ONE_BEAD} fit_beads(sc, t, #{{channels: \"sz\"}})"), "error: channels = \"sz\"");
    let spec = d.spec();
    let c = ctx.clone();
    let f = move |s: ScanRef, t: TemplateRef, m: Map| -> RResult<FitRef> {
        let who = "fit_beads";
        let o = Opts::new(&spec, &m)?;
        // the degeneracy and merge distances scale with the session's beam waist (set_optics)
        let d = FitOptions {
            w0_um: c.optics().w0_nm / 1000.0,
            ..FitOptions::default()
        };
        let channels = match o.string("channels")? {
            None => d.channels,
            Some(c) => Channels::parse(&c).map_or_else(
                || {
                    fail(format!(
                        "{who}: channels = \"{c}\" is not one of \"both\", \"sx\", \"sy\""
                    ))
                },
                Ok,
            )?,
        };
        let init = match m.get("init") {
            None => None,
            Some(v) => Some(
                bead_list(who, v)?
                    .into_iter()
                    .map(|(x, y, weight)| BeadInit { x, y, weight })
                    .collect(),
            ),
        };
        let criterion = match o.string("criterion")?.as_deref() {
            None | Some("bic") => GrowCriterion::Bic,
            Some("rel_drop") => GrowCriterion::RelDrop {
                min_drop: o.f64_or("min_drop", 0.02)?,
            },
            Some(c) => {
                return fail(format!(
                    "{who}: criterion = \"{c}\" is not one of \"bic\", \"rel_drop\""
                ))
            }
        };
        let fo = FitOptions {
            channels,
            n_beads: count(who, &o, "n_beads", 1, 10_000)?,
            init,
            grow: o.bool_or("grow", d.grow)?,
            max_beads: count(who, &o, "max_beads", 1, 10_000)?.unwrap_or(d.max_beads),
            criterion,
            sigma: o.f64("sigma")?,
            ftol: o.f64_or("ftol", d.ftol)?,
            xtol: o.f64_or("xtol", d.xtol)?,
            gtol: o.f64_or("gtol", d.gtol)?,
            patience: count(who, &o, "patience", 1, 1_000_000)?.unwrap_or(d.patience),
            min_separation: o.f64_or("min_separation", d.min_separation)?,
            merge_degenerate: o.bool_or("merge_degenerate", d.merge_degenerate)?,
            ..d
        };
        let r = fit_beads(&s.scan.sx, &s.scan.sy, &t.0, &fo).map_err(|e| err(who, e))?;
        Ok(FitRef(Arc::new(r)))
    };
    let f2 = f.clone();
    r.bind(d, f);
    r.overload("fit_beads", move |s: ScanRef, t: TemplateRef| {
        f2(s, t, Map::new())
    });

    let fx = format!("{ONE_BEAD} let f = fit_beads(sc, t, #{{n_beads: 1}});");
    r.getter(
        Doc::property("FitResult", "beads")
            .returns("array", "[#{x, y, weight, x_err, y_err, weight_err}] (µm, reference-bead units; errors 1σ or () when ill-conditioned)")
            .summary("the fitted beads")
            .example(&format!("{fx} round(f.beads[0].weight * 1000.0)"), "1000.0"),
        |f: &mut FitRef| -> Array { f.0.beads.iter().map(bead_map).collect() },
    );
    for (name, doc) in [
        ("chi2", "rss / σ²"),
        ("rss", "Σ (data − model)² over the fitted pixels"),
        ("sigma", "pixel noise used (given or estimated)"),
        ("bic", "Bayesian information criterion"),
        ("condition", "condition number of the column-scaled JᵀJ"),
        ("total_weight", "Σ weights (reference-bead units)"),
    ] {
        // Noise-free one-bead fixture: σ estimated from the residuals gives χ² = N − p exactly
        // (N = 2·41² residuals, p = 3); with σ given, BIC = χ² + p·ln N with χ² ≈ 0; the scaled
        // columns of JᵀJ are orthogonal by symmetry, so the condition number is 1.
        let sig = format!("{ONE_BEAD} let f = fit_beads(sc, t, #{{n_beads: 1, sigma: 0.001}});");
        let (ex, expect) = match name {
            "total_weight" => (format!("{fx} round(f.total_weight * 1000.0)"), "1000.0"),
            "chi2" => (format!("{fx} f.chi2"), "3359.0"),
            "rss" => (format!("{fx} f.rss < 1e-20"), "true"),
            "sigma" => (format!("{fx} f.sigma < 1e-15"), "true"),
            "bic" => (
                format!("{sig} abs(f.bic - 3.0 * ln(2.0 * 41.0 * 41.0)) < 1e-9"),
                "true",
            ),
            _ => (format!("{fx} round(f.condition * 1000.0) / 1000.0"), "1.0"),
        };
        r.getter(
            Doc::property("FitResult", name)
                .returns("float", doc)
                .summary(doc)
                .example(&ex, expect),
            move |f: &mut FitRef| -> f64 {
                let r = &f.0;
                match name {
                    "chi2" => r.chi2,
                    "rss" => r.rss,
                    "sigma" => r.sigma,
                    "bic" => r.bic,
                    "condition" => r.condition,
                    _ => r.total_weight(),
                }
            },
        );
    }
    for (name, doc) in [
        ("dof", "residuals minus parameters"),
        ("iterations", "Jacobian evaluations of the final fit"),
        ("evaluations", "residual evaluations of the final fit"),
        ("n_beads", "number of beads"),
    ] {
        r.getter(
            Doc::property("FitResult", name)
                .returns("int", doc)
                .summary(doc)
                .example(&format!("{fx} f.{name} > 0"), "true"),
            move |f: &mut FitRef| -> i64 {
                let r = &f.0;
                (match name {
                    "dof" => r.dof,
                    "iterations" => r.iterations,
                    "evaluations" => r.evaluations,
                    _ => r.beads.len(),
                }) as i64
            },
        );
    }
    r.getter(
        Doc::property("FitResult", "status")
            .returns("string", "\"converged\", \"max_evaluations\" or \"failed\"")
            .summary("how the optimiser stopped (see .reason)")
            .example(&format!("{fx} f.status"), "\"converged\""),
        |f: &mut FitRef| -> String { to_dyn(&f.0.status).into_string().unwrap_or_default() },
    );
    r.getter(
        Doc::property("FitResult", "reason")
            .returns("string", "the optimiser's termination reason in words")
            .summary("why the fit stopped")
            .example(&format!("{fx} type_of(f.reason)"), "\"string\""),
        |f: &mut FitRef| -> String { f.0.reason.clone() },
    );
    r.getter(
        Doc::property("FitResult", "degeneracies")
            .returns("array", "[#{kind: \"close_beads\" | \"unresolved\" | \"insignificant\" | \"bead_outside\" | \"ill_conditioned\", …}]")
            .summary("what the fit could not resolve (empty when well-posed)")
            .example(&format!("{fx} f.degeneracies.len()"), "0"),
        |f: &mut FitRef| -> Array { f.0.degeneracies.iter().map(to_dyn).collect() },
    );
    r.getter(
        Doc::property("FitResult", "history")
            .returns(
                "array",
                "[#{n_beads, rss, bic, accepted}] of the bead-adding steps",
            )
            .summary("bead-adding history (empty unless growing)")
            .example(
                &format!("{ONE_BEAD} fit_beads(sc, t).history.len() >= 2"),
                "true",
            ),
        |f: &mut FitRef| -> Array { f.0.history.iter().map(to_dyn).collect() },
    );
    for (name, doc) in [
        ("model_sx", "model Sx image"),
        ("model_sy", "model Sy image"),
        ("residual_sx", "data − model, Sx"),
        ("residual_sy", "data − model, Sy"),
    ] {
        r.getter(
            Doc::property("FitResult", name)
                .returns("Image", doc)
                .summary(doc)
                .example(&format!("{fx} f.{name}.cols"), "41"),
            move |f: &mut FitRef| -> ImageRef {
                let r = &f.0;
                ImageRef(Arc::new(
                    match name {
                        "model_sx" => &r.model_sx,
                        "model_sy" => &r.model_sy,
                        "residual_sx" => &r.residual_sx,
                        _ => &r.residual_sy,
                    }
                    .clone(),
                ))
            },
        );
    }
    r.bind(
        Doc::method("FitResult", "subtract")
            .arg("scan", "Scan", "", "the scan that was fitted")
            .returns(
                "Scan",
                "the scan minus the fitted model in Sx and Sy (Sz unchanged)",
            )
            .summary("remove the fitted beads from a scan")
            .example(
                &format!("{fx} let c = f.subtract(sc); abs(c.sx.max()) < 1e-3"),
                "true",
            ),
        |f: &mut FitRef, s: ScanRef| -> RResult<ScanRef> {
            let r = &f.0;
            let sx = s.scan.sx.sub(&r.model_sx).map_err(|e| err("subtract", e))?;
            let sy = s.scan.sy.sub(&r.model_sy).map_err(|e| err("subtract", e))?;
            let mut meta = s.scan.meta.clone();
            meta["subtracted_beads"] = serde_json::to_value(&r.beads).unwrap_or_default();
            Ok(scan_of(sx, sy, s.scan.sz.clone(), meta))
        },
    );
    r.bind(
        Doc::method("FitResult", "to_map")
            .returns("map", "everything but the images")
            .summary("the fit as a map (for printing and saving)")
            .example(&format!("{fx} f.to_map().status"), "\"converged\""),
        |f: &mut FitRef| -> Map {
            let mut v = serde_json::to_value(&*f.0).unwrap_or_default();
            if let Some(o) = v.as_object_mut() {
                for k in ["model_sx", "model_sy", "residual_sx", "residual_sy"] {
                    o.remove(k);
                }
            }
            json_to_dynamic(&v).try_cast::<Map>().unwrap_or_default()
        },
    );
}

// ------------------------------------------------------------------ filaments

fn register_filaments(r: &mut Registrar, ctx: &Arc<Ctx>) {
    let _ = ctx;
    let meas_keys: Vec<(&str, &str, &str, &str)> = vec![
        (
            "stencil",
            "string",
            "",
            "optional: derivative stencil (default central2)",
        ),
        (
            "window_um",
            "float",
            "µm",
            "optional: parabola window (default 0.4)",
        ),
        (
            "min_snr",
            "float",
            "",
            "optional: ignore line maxima below min_snr × line noise (default 0)",
        ),
        (
            "max_offset_um",
            "float",
            "µm",
            "optional: ignore maxima farther than this from the fitted line (default 0.15)",
        ),
        (
            "detect_snr",
            "float",
            "",
            "optional: candidate maxima above detect_snr × pixel noise (default 4)",
        ),
    ];
    let mut curve_keys = vec![
        (
            "n_angles",
            "int",
            "",
            "optional: angles spanning 180° (default 19, Fig. 4d)",
        ),
        (
            "pixel_um",
            "float",
            "µm",
            "optional: pixel size of the scans it will be applied to (default 0.05)",
        ),
        (
            "d_nm",
            "float",
            "nm",
            "optional: bead-model filament diameter (default: the reference bead's)",
        ),
        (
            "n",
            "float",
            "",
            "optional: its index (default: the reference bead's)",
        ),
        (
            "spacing_nm",
            "float",
            "nm",
            "optional: bead-model spacing (default 50)",
        ),
    ];
    curve_keys.extend(meas_keys.iter().copied());
    const CURVE: &str =
        "let t = template_model(#{h_um: 0.025}); let c = angle_curve(t, #{n_angles: 7});";
    let d = Doc::func("angle_curve", "filaments")
        .arg("tpl", "Template", "", "the point-particle template")
        .map("opts", "optional", &curve_keys)
        .form("angle_curve(tpl) -> AngleCurve")
        .returns("AngleCurve", "max Sx and Sy sensitivity vs filament angle, normalised to Sx at 0° (interpolated, period 180°)")
        .summary("orientation calibration curve from the bead model (Sec. 4.2 step 2, Fig. 4d)")
        .help("Each angle: a long straight bead-model filament rendered on pixels of pixel_um, measured by the same pipeline as data (stencil, parabola window), averaged over sub-pixel offsets. The default 19 angles over 180° follow the paper's rotation series.")
        .example(&format!("{CURVE} round(c.at(0.0).sx * 1000.0)"), "1000.0")
        .example(&format!("{CURVE} c.at(90.0).sy > 0.5"), "true")
        .example("let t = template_model(#{h_um: 0.025}); angle_curve(t, #{n_angles: 2})", "error: n_angles = 2");
    let spec = d.spec();
    let f = move |t: TemplateRef, m: Map| -> RResult<CurveRef> {
        let who = "angle_curve";
        let o = Opts::new(&spec, &m)?;
        let d = AngleCurveOptions::default();
        let co = AngleCurveOptions {
            n_angles: o
                .int("n_angles")?
                .map_or(d.n_angles, |v| v.clamp(0, 100_000) as usize),
            pixel_um: o.f64_or("pixel_um", d.pixel_um)?,
            d_nm: o.f64("d_nm")?,
            n: o.f64("n")?,
            bead_model: BeadModelOptions {
                spacing_nm: o.f64_or("spacing_nm", d.bead_model.spacing_nm)?,
            },
            measure: measure_opts(who, &o, d.measure)?,
        };
        let c = AngleCurve::compute(&t.0, &co).map_err(|e| err(who, e))?;
        Ok(CurveRef(Arc::new(c)))
    };
    let f2 = f.clone();
    r.bind(d, f);
    r.overload("angle_curve", move |t: TemplateRef| f2(t, Map::new()));

    r.bind(
        Doc::method("AngleCurve", "at")
            .arg(
                "angle_deg",
                "float",
                "°",
                "filament angle from the QPD y-axis towards +x",
            )
            .returns(
                "map",
                "#{sx, sy} normalised maximum sensitivities (interpolated)",
            )
            .summary("the calibration curve at an angle")
            .example(
                &format!(
                    "{CURVE} let a = c.at(30.0); let b = c.at(-150.0); round((a.sx - b.sx) * 1e9)"
                ),
                "0.0",
            ),
        |c: &mut CurveRef, a: f64| -> Map {
            let (sx, sy) = c.0.eval(a);
            let mut m = Map::new();
            m.insert("sx".into(), sx.into());
            m.insert("sy".into(), sy.into());
            m
        },
    );
    r.bind(
        Doc::method("AngleCurve", "correction")
            .arg("angle_deg", "float", "°", "filament angle")
            .arg(
                "channel",
                "string",
                "",
                "\"sx\" (row maxima) or \"sy\" (column maxima)",
            )
            .returns(
                "float",
                "factor that maps the measured maximum to the QPD y-axis orientation (step 5)",
            )
            .summary("orientation correction factor")
            .example(
                &format!("{CURVE} round(c.correction(0.0, \"sx\") * 1000.0)"),
                "1000.0",
            )
            .example(
                &format!("{CURVE} c.correction(0.0, \"sz\")"),
                "error: channel = \"sz\"",
            ),
        |c: &mut CurveRef, a: f64, ch: &str| -> RResult<f64> {
            let channel = match ch {
                "sx" | "x" => Channel::SxRows,
                "sy" | "y" => Channel::SyCols,
                _ => {
                    return fail(format!(
                        "correction: channel = \"{ch}\" is not one of \"sx\", \"sy\""
                    ))
                }
            };
            c.0.correction(a, channel).map_err(|e| err("correction", e))
        },
    );
    r.getter(
        Doc::property("AngleCurve", "nodes")
            .returns(
                "map",
                "#{angle_deg: [..], sx: [..], sy: [..], sx0, pixel_um}",
            )
            .summary("the computed nodes of the curve (for plots and tables)")
            .example(&format!("{CURVE} c.nodes.angle_deg.len()"), "6"),
        |c: &mut CurveRef| -> Map {
            let c = &c.0;
            let mut m = Map::new();
            m.insert("angle_deg".into(), floats(&c.angles_deg).into());
            m.insert("sx".into(), floats(&c.sx).into());
            m.insert("sy".into(), floats(&c.sy).into());
            m.insert("sx0".into(), c.sx0.into());
            m.insert("pixel_um".into(), c.options.pixel_um.into());
            m
        },
    );

    let d = Doc::func("measure_filament", "filaments")
        .arg("scan", "Scan", "", "XY scan of a filament")
        .arg("curve", "AngleCurve", "", "orientation calibration for the scan's pixel size")
        .map("opts", "optional (default: the curve's measurement options)", &meas_keys)
        .form("measure_filament(scan, curve) -> FilamentMeasurement")
        .returns("FilamentMeasurement", "angle, per-line maxima along the filament, corrected sensitivities")
        .summary("orientation from the row/column maxima and orientation-corrected sensitivities (Sec. 4.2 steps 4–5)")
        .help("Row maxima of ∂Sx/∂x are used for filaments within 45° of the QPD y-axis, column maxima of ∂Sy/∂y otherwise (the paper's step 4); a robust straight-line fit through the maxima gives the angle, the curve's correction maps every maximum to the y-axis orientation.");
    let fil_ex = "let t = template_model(#{h_um: 0.025}); let c = angle_curve(t, #{n_angles: 7}); let sc = render_beads(t, #{filaments: [#{points: [[-0.5, -2.0], [0.5, 2.0]], d_nm: 110.0, n: 1.572}], x: [-1.5, 1.5], y: [-1.5, 1.5], nx: 61, ny: 61}); let m = measure_filament(sc, c);";
    let spec = d.spec();
    let f = move |s: ScanRef, c: CurveRef, m: Map| -> RResult<FilamentRef> {
        let o = Opts::new(&spec, &m)?;
        let mo = measure_opts("measure_filament", &o, c.0.options.measure)?;
        let r = measure_filament(&s.scan.sx, &s.scan.sy, &c.0, &mo)
            .map_err(|e| err("measure_filament", e))?;
        Ok(FilamentRef(Arc::new(r)))
    };
    let f2 = f.clone();
    r.bind(
        d.example(&format!("{fil_ex} round(m.angle_deg)"), "14.0")
            .example(&format!("{fil_ex} m.channel"), "\"sx_rows\""),
        f,
    );
    r.overload("measure_filament", move |s: ScanRef, c: CurveRef| {
        f2(s, c, Map::new())
    });
    for (name, doc) in [
        (
            "angle_deg",
            "filament angle from the QPD y-axis towards +x, degrees",
        ),
        ("angle_err_deg", "1σ of the angle, degrees"),
        (
            "factor",
            "orientation correction applied (sens_corr = factor · sens)",
        ),
        (
            "mean_corr",
            "mean corrected max sensitivity (reference-bead units/µm)",
        ),
        ("std_corr", "std of the corrected maxima"),
        ("sem_corr", "standard error of mean_corr"),
    ] {
        r.getter(
            Doc::property("FilamentMeasurement", name)
                .returns("float", doc)
                .summary(doc)
                .example(&format!("{fil_ex} type_of(m.{name})"), "\"f64\""),
            move |m: &mut FilamentRef| -> f64 {
                let m = &m.0;
                match name {
                    "angle_deg" => m.angle_deg,
                    "angle_err_deg" => m.angle_err_deg,
                    "factor" => m.factor,
                    "mean_corr" => m.mean_corr,
                    "std_corr" => m.std_corr,
                    _ => m.sem_corr,
                }
            },
        );
    }
    r.getter(
        Doc::property("FilamentMeasurement", "channel")
            .returns("string", "\"sx_rows\" or \"sy_cols\"")
            .summary("which maxima were used")
            .example(&format!("{fil_ex} m.channel"), "\"sx_rows\""),
        |m: &mut FilamentRef| -> String { to_dyn(&m.0.channel).into_string().unwrap_or_default() },
    );
    r.getter(
        Doc::property("FilamentMeasurement", "points")
            .returns(
                "array",
                "[#{line, x, y, arc_um, sens, sens_err, sens_corr}] along the filament",
            )
            .summary("the maxima along the filament")
            .example(&format!("{fil_ex} m.points.len() > 40"), "true"),
        |m: &mut FilamentRef| -> Array { m.0.points.iter().map(to_dyn).collect() },
    );
    r.getter(
        Doc::property("FilamentMeasurement", "sens")
            .returns(
                "Image",
                "the sensitivity image used (reference-bead units/µm)",
            )
            .summary("sensitivity image of the chosen channel")
            .example(&format!("{fil_ex} m.sens.cols"), "61"),
        |m: &mut FilamentRef| -> ImageRef { ImageRef(Arc::new(m.0.sens.clone())) },
    );
    r.bind(
        Doc::method("FilamentMeasurement", "profile")
            .arg(
                "key",
                "string",
                "",
                "\"sens_corr\", \"sens\" or \"diameter\" (with the second argument)",
            )
            .returns("Profile", "the value vs arc length along the filament (µm)")
            .summary("a quantity along the filament as a Profile (for plot_profile and CSV)")
            .example(
                &format!("{fil_ex} m.profile(\"sens_corr\").len > 40"),
                "true",
            )
            .example(
                &format!("{fil_ex} m.profile(\"mass\")"),
                "error: key = \"mass\"",
            ),
        |m: &mut FilamentRef, key: &str| -> RResult<ProfileRef> {
            let pts = &m.0.points;
            let v: Vec<f64> = match key {
                "sens_corr" => pts.iter().map(|p| p.sens_corr).collect(),
                "sens" => pts.iter().map(|p| p.sens).collect(),
                _ => {
                    return fail(format!(
                        "profile: key = \"{key}\" is not one of \"sens_corr\", \"sens\""
                    ))
                }
            };
            let t: Vec<f64> = pts.iter().map(|p| p.arc_um).collect();
            let p = crate::data::Profile::try_new(t, v)
                .map_err(|e| err("profile", e))?
                .with_t_name("arc length");
            Ok(ProfileRef(Arc::new(p)))
        },
    );

    let d = Doc::func("sbr", "filaments")
        .arg("m", "FilamentMeasurement", "", "a measured filament")
        .map(
            "opts",
            "optional",
            &[
                ("skip_um", "float", "µm", "optional: arc skipped from the first non-zero maximum (default 1.2, Sec. 6)"),
                ("both_ends", "bool", "", "optional: also skip at the far end (default true)"),
                ("exclusion_um", "float", "µm", "optional: background pixels farther than this from the line (default 1.0)"),
                ("nonzero_snr", "float", "", "optional: a maximum is non-zero above this × background std (default 0)"),
                ("min_run", "int", "", "optional: consecutive lines that start the filament (default 3)"),
            ],
        )
        .form("sbr(m) -> map")
        .returns("map", "#{sbr_background, sbr_uniformity, mean_sens, mean_corr, std_sens, background_std, arc_start, arc_end, n_points, n_background}")
        .summary("signal-to-background ratio both ways the paper defines (Sec. 6)")
        .example(&format!("{fil_ex} sbr(m, #{{skip_um: 0.2}}).n_points > 10"), "true")
        .example(&format!("{fil_ex} sbr(m, #{{skip_um: -1.0}})"), "error: skip_um = -1");
    let spec = d.spec();
    let f = move |m: FilamentRef, mm: Map| -> RResult<Map> {
        let o = Opts::new(&spec, &mm)?;
        let d = SbrOptions::default();
        let so = SbrOptions {
            skip_um: o.f64_or("skip_um", d.skip_um)?,
            both_ends: o.bool_or("both_ends", d.both_ends)?,
            exclusion_um: o.f64_or("exclusion_um", d.exclusion_um)?,
            nonzero_snr: o.f64_or("nonzero_snr", d.nonzero_snr)?,
            min_run: count("sbr", &o, "min_run", 1, 100_000)?.unwrap_or(d.min_run),
        };
        let r = sbr(&m.0, &so).map_err(|e| err("sbr", e))?;
        Ok(to_map(&r))
    };
    let f2 = f.clone();
    r.bind(d, f);
    r.overload("sbr", move |m: FilamentRef| f2(m, Map::new()));

    let d = Doc::func("remove_background", "filaments")
        .arg("scan", "Scan", "", "XY scan of a filament with point-like aggregates")
        .arg("tpl", "Template", "", "the point-particle template")
        .map(
            "opts",
            "optional",
            &[
                ("axis", "string", "", "optional: the filament's closer QPD axis, \"y\" (default: fit Sy, subtract from Sx, Fig. 6) or \"x\""),
                ("angle_deg", "float", "°", "optional: the filament's angle (chooses axis: |angle| ≤ 45° → \"y\")"),
                ("detect_snr", "float", "", "optional: detections above detect_snr × robust noise (default 6)"),
                ("max_objects", "int", "", "optional: most point objects fitted (default 60)"),
            ],
        )
        .form("remove_background(scan, tpl) -> map")
        .returns("map", "#{scan: the cleaned Scan, fit: FitResult or (), n_objects}")
        .summary("remove point-like aggregates using the channel the filament barely shows in (Sec. 6)")
        .example(&format!("{TPL} let s = scene(); s.add_filament(#{{points: [[0.0, -3.0], [0.0, 3.0]], d_nm: 50.0, n: 1.41}}); s.add_bead(#{{x: 0.8, y: 0.5, d_nm: 90.0, n: 1.45}}); s.effects([\"detector_noise\"]); let sc = simulate(s, #{{x: [-1.5, 1.5], y: [-1.5, 1.5], nx: 61, ny: 61}}); remove_background(sc, t).n_objects"), "1")
        .example(&format!("{TPL} let sc = render_beads(t, #{{beads: [#{{x: 0.0, y: 0.0}}], x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 21, ny: 21}}); remove_background(sc, t, #{{axis: \"z\"}})"), "error: axis = \"z\"");
    let spec = d.spec();
    let f = move |s: ScanRef, t: TemplateRef, m: Map| -> RResult<Map> {
        let who = "remove_background";
        let o = Opts::new(&spec, &m)?;
        let d = BackgroundOptions::default();
        let axis = match (o.string("axis")?.as_deref(), o.f64("angle_deg")?) {
            (Some("y"), _) => FilamentAxis::Y,
            (Some("x"), _) => FilamentAxis::X,
            (Some(a), _) => {
                return fail(format!("{who}: axis = \"{a}\" is not one of \"x\", \"y\""))
            }
            (None, Some(a)) => FilamentAxis::from_angle(a),
            (None, None) => d.axis,
        };
        let bo = BackgroundOptions {
            axis,
            detect_snr: o.f64_or("detect_snr", d.detect_snr)?,
            max_objects: count(who, &o, "max_objects", 1, 10_000)?.unwrap_or(d.max_objects),
            fit: d.fit.clone(),
        };
        let r =
            remove_point_background(&s.scan.sx, &s.scan.sy, &t.0, &bo).map_err(|e| err(who, e))?;
        let mut out = Map::new();
        let n = r.fit.as_ref().map_or(0, |f| f.beads.len());
        let mut meta = s.scan.meta.clone();
        meta["background_removed"] = serde_json::json!({
            "axis": format!("{:?}", bo.axis),
            "n_objects": n,
        });
        out.insert(
            "scan".into(),
            Dynamic::from(scan_of(r.sx, r.sy, s.scan.sz.clone(), meta)),
        );
        out.insert(
            "fit".into(),
            r.fit
                .map_or(Dynamic::UNIT, |f| Dynamic::from(FitRef(Arc::new(f)))),
        );
        out.insert("n_objects".into(), (n as i64).into());
        Ok(out)
    };
    let f2 = f.clone();
    r.bind(d, f);
    r.overload("remove_background", move |s: ScanRef, t: TemplateRef| {
        f2(s, t, Map::new())
    });

    // quantities
    let calib_keys = [
        &[
            (
                "n_obj",
                "float",
                "",
                "refractive index of the filament (collagen 1.41 in the paper)",
            ),
            (
                "d_bm_nm",
                "float",
                "nm",
                "optional: bead-model cylinder diameter (default: the reference bead's)",
            ),
            (
                "n_bm",
                "float",
                "",
                "optional: bead-model index (default: the reference bead's)",
            ),
        ][..],
        PIPELINE_KEYS,
    ]
    .concat();
    let d = Doc::func("diameter_calib", "filaments")
        .arg("tpl", "Template", "", "the point-particle template")
        .map("opts", "", &calib_keys)
        .returns("map", "#{a_nm, d_bm_nm, n_bm, sens_bm, n_obj, n_corr}: d = A·√(sens_corr) (eqs. colDiam, OurColD)")
        .summary("the constant A of fibril diameters, derived from the bead model and n_corr for the current optics")
        .help("A = d_bm / √(sens_bm · n_corr): sens_bm is the max sensitivity of a bead-model cylinder along the QPD y-axis measured by the pixel pipeline; not hard-coded (the paper's 58.6 nm is for its own optics).")
        .example(&format!("{TPL} let a = diameter_calib(t, #{{n_obj: 1.41}}).a_nm; a > 40.0 && a < 90.0"), "true")
        .example(&format!("{TPL} diameter_calib(t, #{{n_obj: 1.2}})"), "error: n_obj");
    let spec = d.spec();
    r.bind(d, move |t: TemplateRef, m: Map| -> RResult<Map> {
        let who = "diameter_calib";
        let o = Opts::new(&spec, &m)?;
        let (px, mo, bm) = pipeline_opts(who, &o)?;
        let rb = t.0.reference;
        let c = DiameterCalib::from_template(
            &t.0,
            o.req_f64("n_obj")?,
            o.f64_or("d_bm_nm", rb.d_nm)?,
            o.f64_or("n_bm", rb.n)?,
            px,
            &mo,
            &bm,
        )
        .map_err(|e| err(who, e))?;
        Ok(to_map(&c))
    });
    r.bind(
        Doc::func("fibril_diameter", "filaments")
            .arg(
                "sens_corr",
                "float",
                "",
                "orientation-corrected max sensitivity (reference-bead units/µm)",
            )
            .arg("a_nm", "float", "nm", "the constant A from diameter_calib")
            .returns("float", "diameter, nm: d = A·√(sens_corr) (eq. OurColD)")
            .summary("fibril diameter from its corrected sensitivity")
            .example("fibril_diameter(0.25, 60.0)", "30.0")
            .example("fibril_diameter(-0.1, 60.0)", "error: sens_corr = -0.1"),
        |s: f64, a: f64| -> RResult<f64> {
            fibril_diameter_nm(s, a).map_err(|e| err("fibril_diameter", e))
        },
    );
    let d = Doc::func("lin_dens_calib", "filaments")
        .arg(
            "tpl",
            "Template",
            "",
            "the point-particle template (its reference bead is the bead-model material)",
        )
        .map(
            "opts",
            "",
            &[
                &[
                (
                    "n_obj",
                    "float",
                    "",
                    "optional: index of the filament (default 1.587, dry globular protein as Sec. 6)",
                ),
                (
                    "density_obj",
                    "float",
                    "g/cm³",
                    "optional: its density (default 1.35, protein)",
                ),
                ][..],
                PIPELINE_KEYS,
            ]
            .concat(),
        )
        .returns(
            "map",
            "#{mu_bm_mda_um, d_bm_nm, density_bm, sens_bm, n_obj, density_obj, n_corr}",
        )
        .summary("calibration of linear densities (eq. mtLinDens) from the template's bead model")
        .example(
            &format!("{TPL} lin_dens_calib(t, #{{}}).mu_bm_mda_um > 0.0"),
            "true",
        );
    let spec = d.spec();
    r.bind(d, move |t: TemplateRef, m: Map| -> RResult<Map> {
        let who = "lin_dens_calib";
        let o = Opts::new(&spec, &m)?;
        let (px, mo, bm) = pipeline_opts(who, &o)?;
        let c = LinDensCalib::from_template(
            &t.0,
            o.f64_or("n_obj", 1.587)?,
            o.f64_or("density_obj", 1.35)?,
            px,
            &mo,
            &bm,
        )
        .map_err(|e| err(who, e))?;
        Ok(to_map(&c))
    });
    let d = Doc::func("linear_density", "filaments")
        .arg("sens_corr", "float", "", "orientation-corrected max sensitivity (reference-bead units/µm)")
        .arg("calib", "map", "", "from lin_dens_calib")
        .returns("map", "#{mu_mda_um, protofilaments, protofilaments_exact} (13.75 MDa/µm per protofilament: 110 kDa per 8 nm dimer)")
        .summary("microtubule linear density and the protofilament number it implies (eq. mtLinDens, Sec. 6)")
        .example("linear_density(1.0, #{mu_bm_mda_um: 6.0, d_bm_nm: 110.0, density_bm: 1.05, sens_bm: 1.0, n_obj: 1.55, density_obj: 1.35, n_corr: 0.5}).mu_mda_um", "15.428571428571429")
        .example("linear_density(1.0, #{})", "error: calib");
    r.bind(d, |s: f64, c: Map| -> RResult<Map> {
        let who = "linear_density";
        let get = |k: &str| -> RResult<f64> {
            match c.get(k) {
                Some(v) => num(who, &format!("calib.{k}"), v),
                None => fail(format!(
                    "{who}: calib lacks `{k}`: pass the map lin_dens_calib returns"
                )),
            }
        };
        let cal = LinDensCalib {
            mu_bm_mda_um: get("mu_bm_mda_um")?,
            d_bm_nm: get("d_bm_nm")?,
            density_bm: get("density_bm")?,
            sens_bm: get("sens_bm")?,
            n_obj: get("n_obj")?,
            density_obj: get("density_obj")?,
            n_corr: get("n_corr")?,
        };
        let mu = cal.linear_density(s).map_err(|e| err(who, e))?;
        let (x, n) = protofilaments(mu).map_err(|e| err(who, e))?;
        let mut m = Map::new();
        m.insert("mu_mda_um".into(), mu.into());
        m.insert("protofilaments".into(), (n as i64).into());
        m.insert("protofilaments_exact".into(), x.into());
        Ok(m)
    });
    let d = Doc::func("point_mass", "filaments")
        .map(
            "obj",
            "the measured object",
            &[
                ("sens", "float", "", "its max sensitivity (same units as sens_rb)"),
                ("sens_err", "float", "", "optional: 1σ of sens"),
                ("sens_rb", "float", "", "optional: the reference bead's max sensitivity in the same pipeline (default 1: reference-bead units)"),
                ("n_obj", "float", "", "optional: index of the object (default: the reference bead's)"),
                ("density", "float", "g/cm³", "optional: density of the object (default: the reference bead's)"),
            ],
        )
        .returns("map", "#{volume_ratio, volume_nm3, sphere_d_nm, mass_kda, mass_err_kda, n_corr}")
        .summary("volume and mass of a point-like object from its max sensitivity (eqs. after nCor)")
        .example("round(point_mass(#{sens: 1.0}).sphere_d_nm * 1000.0) / 1000.0", "110.0")
        .example("point_mass(#{sens: -1.0})", "error: sens_obj = -1");
    let spec = d.spec();
    r.bind(d, move |m: Map| -> RResult<Map> {
        let who = "point_mass";
        let o = Opts::new(&spec, &m)?;
        let rb = RefBead::default();
        let p = point_object(
            o.req_f64("sens")?,
            o.f64("sens_err")?,
            o.f64_or("sens_rb", 1.0)?,
            o.f64_or("n_obj", rb.n)?,
            o.f64_or("density", rb.density_g_cm3)?,
            &rb,
        )
        .map_err(|e| err(who, e))?;
        Ok(to_map(&p))
    });
}

// ------------------------------------------------------------------ stats

fn register_stats(r: &mut Registrar) {
    r.bind(
        Doc::func("summary", "stats")
            .arg(
                "values",
                "array",
                "",
                "numbers (non-finite values are skipped and counted)",
            )
            .returns("map", "#{n, n_skipped, mean, std, sem, min, max}")
            .summary("mean, sample std, standard error, min, max")
            .example("summary([1.0, 2.0, 3.0]).std", "1.0")
            .example("summary([])", "error: "),
        |a: Array| -> RResult<Map> {
            let v = numbers("summary", "values", &Dynamic::from_array(a))?;
            let s = summary(&v).map_err(|e| err("summary", e))?;
            Ok(to_map(&s))
        },
    );
    let d = Doc::func("histogram", "stats")
        .arg("values", "array", "", "numbers")
        .arg(
            "bins",
            "int",
            "",
            &format!("number of bins, 1 ≤ bins ≤ {MAX_BINS}"),
        )
        .opt(
            "range",
            "array",
            "",
            "[lo, hi] (default: min and max of the values)",
        )
        .returns(
            "map",
            "#{edges, counts, centres, n_outside, n_skipped, all_equal}",
        )
        .summary("histogram with equal bins")
        .example("histogram([1.0, 2.0, 2.5, 4.0], 3).counts", "[1, 2, 1]")
        .example("histogram([1.0], 0)", "error: bins = 0");
    let f = |a: Array, bins: i64, range: Option<(f64, f64)>| -> RResult<Map> {
        if !(1..=MAX_BINS as i64).contains(&bins) {
            return fail(format!(
                "histogram: bins = {bins} is out of range: 1 ≤ bins ≤ {MAX_BINS}"
            ));
        }
        let v = numbers("histogram", "values", &Dynamic::from_array(a))?;
        let h = histogram(&v, bins as usize, range).map_err(|e| err("histogram", e))?;
        let mut m = to_map(&h);
        m.insert("centres".into(), floats(&h.centres()).into());
        Ok(m)
    };
    r.bind(d, move |a: Array, b: i64| f(a, b, None));
    r.overload("histogram", move |a: Array, b: i64, rg: Array| {
        let v = numbers("histogram", "range", &Dynamic::from_array(rg))?;
        if v.len() != 2 {
            return fail("histogram: range must be [lo, hi]");
        }
        f(a, b, Some((v[0], v[1])))
    });
    for (name, log) in [("linfit", false), ("loglog_fit", true)] {
        let d = Doc::func(name, "stats")
            .arg("x", "array", "", "abscissae")
            .arg("y", "array", "", "ordinates")
            .opt("sigma_y", "array", "", "1σ of each y (weighted fit)")
            .returns("map", "#{slope, intercept, slope_err, intercept_err, cov, chi2, r2, n}")
            .summary(if log {
                "straight line through (ln x, ln y): y = e^intercept · x^slope (e.g. the d^3.02±0.04 fit of Fig. 3c)"
            } else {
                "least-squares straight line y = intercept + slope·x with uncertainties"
            })
            .example(
                &format!("{name}([1.0, 2.0, 4.0], [{}]).slope", if log { "2.0, 16.0, 128.0" } else { "1.0, 3.0, 7.0" }),
                if log { "3.0" } else { "2.0" },
            )
            .example(&format!("{name}([1.0, 1.0], [1.0, 2.0])"), "error: ");
        let f = move |x: Array, y: Array, s: Option<Array>| -> RResult<Map> {
            let x = numbers(name, "x", &Dynamic::from_array(x))?;
            let y = numbers(name, "y", &Dynamic::from_array(y))?;
            let s = s
                .map(|s| numbers(name, "sigma_y", &Dynamic::from_array(s)))
                .transpose()?;
            if x.len() != y.len() || s.as_ref().is_some_and(|s| s.len() != x.len()) {
                return fail(format!(
                    "{name}: x, y (and sigma_y) must have the same length, got {} and {}",
                    x.len(),
                    y.len()
                ));
            }
            let r = if log {
                loglog_fit(&x, &y, s.as_deref())
            } else {
                linfit(&x, &y, s.as_deref())
            }
            .map_err(|e| err(name, e))?;
            Ok(to_map(&r))
        };
        r.bind(d, move |x: Array, y: Array| f(x, y, None));
        r.overload(name, move |x: Array, y: Array, s: Array| f(x, y, Some(s)));
    }
}
