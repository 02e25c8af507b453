//! Binding family `sensitivity`: derivatives of scans (∂S/∂x, eq. sens), their maxima (eq.
//! maxSens, parabola fits), focus search (suppl. S5), profiles along a line.

use super::ctx::Ctx;
use super::keys::{AXIS, STENCIL};
use super::registry::{binding_list, err, fail, Doc, Opts, RResult, Registrar, Spec};
use super::types::{ImageRef, ProfileRef, ScanRef};
use crate::analysis::focus::{focus_search, FocusOptions};
use crate::analysis::peaks::{col_peaks, row_peaks};
use crate::analysis::profile::profile_polyline;
use crate::analysis::{sensitivity, Stencil};
use crate::data::Image;
use crate::optics::grid::Interp;
use rhai::{Array, Dynamic, Map};
use std::sync::Arc;

/// A reference template in a script (`Template`).
use super::analysis_values::*;

// ------------------------------------------------------------------ sensitivity

binding_list! {
    pub fn register {
        bind_sensitivity, bind_peaks, bind_max_sens, bind_focus_search, bind_profile_along
    }
}

/// `sensitivity(img | scan, [opts])`: the sensitivity image (eq. sensitivity).
fn bind_sensitivity(r: &mut Registrar) {
    let d = Doc::func("sensitivity")
        .arg("img", "Image | Scan", "", "an image (or a scan: Sx for axis x, Sy for axis y)")
        .opts(&[
                AXIS.doc("\"x\" (∂/∂x, default) or \"y\" (∂/∂y)"),
                STENCIL.doc("\"central2\" (default), \"central5\", \"sg5\", \"sg7\", … (Savitzky–Golay)"),
            ],
        )
        .returns("Image", "the derivative, signal units per µm")
        .summary("sensitivity image ∂S/∂x or ∂S/∂y (Sec. 3.2)")
        .help("Central differences inside, one-sided at the edges (documented in docs/analysis.md). The noise gain of each stencil: σ(derivative) = gain·σ(pixel)/h with gain 0.707 (central2), 0.950 (central5), 0.316 (sg5). NaN pixels propagate only to the derivatives that use them.")
        .form("sensitivity(img) -> Image")
        .example(&format!("{ONE_BEAD} let s = sensitivity(sc); round(s.max() * t.norm_factor * 10.0) / 10.0"), "1.0")
        .example(&format!("{ONE_BEAD} sensitivity(sc.sx, #{{axis: \"z\"}})"), "error: axis = \"z\"");
    r.bind_opts(d, |spec, v: Dynamic, m| sensitivity_of(spec, v, m));
}

/// `row_peaks`, `col_peaks`: peaks along rows or columns.
fn bind_peaks(r: &mut Registrar) {
    let keys = peak_keys();
    for (name, rows) in [("row_peaks", true), ("col_peaks", false)] {
        let d = Doc::func(name)
            .arg("img", "Image", "", "usually a sensitivity image")
            .opts(&keys)
            .form(&format!("{name}(img) -> array"))
            .returns("array", "per line: #{line, coord, ok, pos, value, pos_err, value_err, curvature, curvature_err, n_points, truncated} or #{line, coord, ok: false, miss}")
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
        r.bind_opts(d, move |spec, i: ImageRef, m| {
            line_maxima(spec, name, rows, &i, m)
        });
    }
}

/// `max_sens`: the largest sensitivity around one point object.
fn bind_max_sens(r: &mut Registrar) {
    let keys = peak_keys();
    let d = Doc::func("max_sens")
        .arg("img", "Image", "", "a sensitivity image around one point object")
        .opts(&keys)
        .form("max_sens(img) -> map")
        .returns("map", "#{x, y, value, x_err, y_err, value_err, n_points, warnings, status} (µm; value in the image's units; warnings: the maximum within half a window and half a pixel of the edge of the image's data, the best row's maximum below 10σ of its noise, a second maximum across the rows that rivals the best (within 2σ) or stands above 20 % of it (a bead ≳0.8 µm off the focus spreads into lobes; or a second object), clipped or dark pixels in the window)")
        .summary("maximum sensitivity of a point object: row parabolas, refined across rows (Sec. 5)")
        .example(&format!("{ONE_BEAD} let m = max_sens(sensitivity(sc)); round(m.value * t.norm_factor / t.max_sens(0.05) * 100.0) / 100.0"), "1.0");
    r.bind_ctx_opts(d, max_sens);
}

/// `focus_search`: the focus from a z series.
fn bind_focus_search(r: &mut Registrar) {
    let fd = FocusOptions::default();
    let d = Doc::func("focus_search")
        .arg("img", "Image | Scan", "", "an XZ (or YZ) scan channel: rows are z (a Scan: its Sx)")
        .opts(&[
                STENCIL.doc(format!("optional: derivative stencil (default {})", fd.stencil.name())),
                ("window_um", "float", "µm", format!("optional: lateral parabola window (default {})", fd.window_um)),
                ("z_window_um", "float", "µm", format!("optional: window of the parabola over z (default {})", fd.z_window_um)),
                ("level", "float", "", format!("optional: fraction of the peak that defines the tolerated z range (default {})", fd.level)),
            ],
        )
        .form("focus_search(img) -> map")
        .returns("map", "#{z_best, z_err, max_sens, max_sens_err, z_lo, z_hi, rows, warnings, status} (µm; rows: per-z maxima; warnings: best z at the end of the z range, object at the lateral edge)")
        .summary("best focus: max sensitivity per z row, parabola over z (suppl. S5)")
        .help("z_lo/z_hi: where the row maxima fall to level × max (paper: within 2 % over ±200 nm); () on a side where the scan ends first.");
    let c = r.ctx();
    r.bind_opts(
        d.example(
            "let s = scene(); s.add_bead(#{x: 0.0, y: 0.0, z: 0.0, d_nm: 110.0, n: 1.572}); let t = template_model(#{h_um: 0.025}); let xs = []; let sc = simulate(s, #{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 5, ny: 5}); focus_search(sc.sx, #{level: 2.0})",
            "error: level = 2",
        ),
        move |spec, v: Dynamic, m| focus_search_of(&c, spec, v, m),
    );
}

/// `profile_along`: an image sampled along a polyline.
fn bind_profile_along(r: &mut Registrar) {
    let d = Doc::func("profile_along")
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
    r.bind(d, |i: ImageRef, p: Array, step: f64| {
        profile_along(&i, p, step)
    });
    r.overload("profile_along", |i: ImageRef, p: Array| {
        let step = pixel_step(&i);
        profile_along(&i, p, step)
    });
}

/// The `img` argument of `who`: an Image, or a Scan's Sx (`axis` x) or Sy (`axis` y) channel.
fn image_or_scan(who: &str, v: &Dynamic, axis: crate::analysis::Axis) -> RResult<Arc<Image>> {
    if let Some(s) = v.read_lock::<ScanRef>() {
        let ch = match axis {
            crate::analysis::Axis::X => "sx",
            crate::analysis::Axis::Y => "sy",
        };
        Ok(Arc::new(
            super::types::flagged_channel(&s.scan, ch).unwrap_or_else(|| s.scan.sx.clone()),
        ))
    } else if let Some(i) = v.read_lock::<ImageRef>() {
        Ok(i.0.clone())
    } else {
        fail(format!(
            "{who}: img must be an Image or a Scan, got {}",
            v.type_name()
        ))
    }
}

/// `sensitivity(img[, opts])`: the derivative ∂S/∂x or ∂S/∂y (signal units per µm) of an image,
/// or of a scan's Sx (axis x) / Sy (axis y), by the chosen stencil (Sec. 3.2).
fn sensitivity_of(spec: &Spec, v: Dynamic, m: &Map) -> RResult<ImageRef> {
    let o = Opts::new(spec, m)?;
    let ax = o.string(AXIS)?.unwrap_or_else(|| "x".into());
    let axis = crate::analysis::Axis::parse(&ax).map_or_else(
        || {
            fail(format!(
                "sensitivity: axis = \"{ax}\" is not one of \"x\", \"y\""
            ))
        },
        Ok,
    )?;
    let st = stencil_of("sensitivity", &o, Stencil::Central2)?;
    let im = image_or_scan("sensitivity", &v, axis)?;
    // (with the clipped and dark pixels its stencil reached, `derived_flags`)
    let out = sensitivity(&im, axis, st).map_err(|e| err("sensitivity", e))?;
    Ok(ImageRef(Arc::new(out)))
}

/// `row_peaks(img[, opts])` (`rows` true) / `col_peaks` (false): the sub-pixel maximum of every
/// row (x position, µm) or column (y position, µm) by a least-squares parabola over the window.
fn line_maxima(spec: &Spec, name: &str, rows: bool, i: &ImageRef, m: &Map) -> RResult<Array> {
    let o = Opts::new(spec, m)?;
    let po = peak_opts(name, &o)?;
    let v = if rows {
        row_peaks(&i.0, &po)
    } else {
        col_peaks(&i.0, &po)
    }
    .map_err(|e| err(name, e))?;
    Ok(line_peaks(&v))
}

/// `max_sens(img[, opts])`: the maximum of a point object's sensitivity image, row parabolas
/// refined across rows (Sec. 5); position in µm, value in the image's units.
fn max_sens(c: &Ctx, spec: &Spec, i: &ImageRef, m: &Map) -> RResult<Map> {
    let o = Opts::new(spec, m)?;
    let po = peak_opts("max_sens", &o)?;
    // with the clipped or dark pixels of the window it is read from (`data::clip`)
    let (p, w) = crate::analysis::peaks::max_sens(&i.0, &po).map_err(|e| err("max_sens", e))?;
    let mut out = to_map(&p);
    with_warnings(c, "max_sens", &mut out, w);
    Ok(out)
}

/// `focus_search(img[, opts])`: best focus z (µm) of an XZ/YZ scan: the maximum sensitivity of
/// each z row, then a parabola over z (suppl. S5).
fn focus_search_of(c: &Ctx, spec: &Spec, v: Dynamic, m: &Map) -> RResult<Map> {
    let o = Opts::new(spec, m)?;
    let d = FocusOptions::default();
    let fo = FocusOptions {
        stencil: stencil_of("focus_search", &o, d.stencil)?,
        window_um: pos_f64("focus_search", &o, "window_um", d.window_um, 1e-3, 100.0)?,
        z_window_um: pos_f64("focus_search", &o, "z_window_um", d.z_window_um, 1e-3, 1e3)?,
        level: pos_f64("focus_search", &o, "level", d.level, 0.0, 1.0)?,
    };
    let im = image_or_scan("focus_search", &v, crate::analysis::Axis::X)?;
    let mut res = focus_search(&im, &fo).map_err(|e| err("focus_search", e))?;
    // clipped or dark pixels among those the row maxima are read from: the parabola window
    // around each row's maximum, widened by the stencil (`data::clip`)
    let sflags =
        crate::analysis::sensitivity::derived_flags(&im, crate::analysis::Axis::X, fo.stencil);
    let half = 0.5 * fo.window_um * (1.0 + 1e-9);
    let centres: Vec<Option<f64>> = res.rows.iter().map(|r| r.peak().map(|p| p.pos)).collect();
    let used = |r: usize, c: usize| {
        centres
            .get(r)
            .copied()
            .flatten()
            .is_some_and(|x| (im.x[c] - x).abs() <= half)
    };
    let check = crate::data::clip::flags_check(sflags.as_deref(), used);
    res.warnings.extend(input_gate("focus_search", check)?);
    let mut out = Map::new();
    out.insert("z_best".into(), res.z_best.into());
    out.insert("z_err".into(), to_dyn(&res.z_err));
    out.insert("max_sens".into(), res.max_sens.into());
    out.insert("max_sens_err".into(), to_dyn(&res.max_sens_err));
    out.insert("z_lo".into(), to_dyn(&res.z_lo));
    out.insert("z_hi".into(), to_dyn(&res.z_hi));
    out.insert("rows".into(), line_peaks(&res.rows).into());
    with_warnings(c, "focus_search", &mut out, res.warnings);
    Ok(out)
}

/// `profile_along(img, points[, step_um])`: bicubic profile of an image along a polyline (µm),
/// sampled every `step_um` of arc length (Fig. 5c).
fn profile_along(i: &ImageRef, p: Array, step: f64) -> RResult<ProfileRef> {
    let pts = super::registry::points("profile_along", &Dynamic::from_array(p))?;
    let pr =
        profile_polyline(&i.0, &pts, step, Interp::Cubic).map_err(|e| err("profile_along", e))?;
    Ok(ProfileRef(Arc::new(pr)))
}

/// The default step of `profile_along`: the smaller pixel size of the image (µm), 0.01 µm for a
/// degenerate image.
fn pixel_step(i: &ImageRef) -> f64 {
    let h = i.0.dx().abs().min(i.0.dy().abs());
    if h > 0.0 {
        h
    } else {
        0.01
    }
}
