//! Values and argument helpers shared by the analysis families (`sensitivity`, `templates`,
//! `filaments`, `stats`): the parsing of their common options (their script types
//! `Template`, `FitResult`, `AngleCurve`, `FilamentMeasurement` are in `types`).
//!
//! Units at the boundary: µm for positions, nm for diameters, kDa / MDa·µm⁻¹ for masses and
//! linear densities; sensitivities in the scan's units per µm, or reference-bead units per µm
//! after a template's normalisation (the reference bead's max ∂Sx/∂x = 1).

use super::keys::{DENSITY, DETECT_SNR, D_NM, N, POINTS, SIGMA, SPACING_NM, STENCIL};
use super::registry::{array_of, err, fail, num, numbers, Opt, Opts, RResult};
use super::types::{json_to_dynamic, ScanRef};
use crate::analysis::fit::Bead as FitBead;
use crate::analysis::{BeadModelOptions, LinePeak, MeasureOptions, PeakOptions, RefBead, Stencil};
use crate::data::{Image, Scan};
use rhai::{Array, Dynamic, Map};
use serde::Serialize;
use std::sync::Arc;

/// The options of this family's bindings, each key written once (`Opt`).
const END_MARGIN_UM: Opt = Opt::new("end_margin_um", "float", "µm");
const MAX_OFFSET_UM: Opt = Opt::new("max_offset_um", "float", "µm");
const MIN_SNR: Opt = Opt::new("min_snr", "float", "");
const MIN_VALUE: Opt = Opt::new("min_value", "float", "");
const PIXEL_UM: Opt = Opt::new("pixel_um", "float", "µm");
const SCAN: Opt = Opt::new("scan", "Scan | Image", "");
const WINDOW_UM: Opt = Opt::new("window_um", "float", "µm");

/// A reference template in a script (`Template`).
/// Any serialisable value as a Rhai map/array.
pub(crate) fn to_dyn<T: Serialize>(v: &T) -> Dynamic {
    json_to_dynamic(&serde_json::to_value(v).unwrap_or_default())
}

pub(crate) fn to_map<T: Serialize>(v: &T) -> Map {
    to_dyn(v).try_cast::<Map>().unwrap_or_default()
}

/// An answer map's domain: `warnings` (array of strings, empty inside the domain) and `status`
/// ("ok" when there is none, else "flagged"), said to the operator by `ctx` as `who: warning: …`.
pub(crate) fn with_warnings(ctx: &super::ctx::Ctx, who: &str, m: &mut Map, w: Vec<String>) {
    ctx.warn_all(who, &w);
    m.insert("status".into(), crate::analysis::domain::status(&w).into());
    m.insert(
        "warnings".into(),
        w.into_iter().map(Dynamic::from).collect::<Array>().into(),
    );
}

/// The warnings an input check (`data::clip`: clipped and dark pixels among those used) adds
/// to `who`'s answer, or `who`'s refusal when no answer can be read from those pixels.
pub(crate) fn input_gate(who: &str, check: crate::data::clip::InputCheck) -> RResult<Vec<String>> {
    check.gate(who).or_else(fail)
}

pub(crate) fn stencil_of(who: &str, o: &Opts, default: Stencil) -> RResult<Stencil> {
    match o.string(STENCIL)? {
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

pub(crate) fn pos_f64(
    who: &str,
    o: &Opts,
    key: impl super::doc::Key,
    default: f64,
    lo: f64,
    hi: f64,
) -> RResult<f64> {
    let key = key.key();
    let v = o.f64_or(key, default)?;
    if !(v >= lo && v <= hi) {
        return fail(format!(
            "{who}: {key} = {v} is out of range: {lo} ≤ {key} ≤ {hi}"
        ));
    }
    Ok(v)
}

pub(crate) fn count(
    who: &str,
    o: &Opts,
    key: impl super::doc::Key,
    lo: i64,
    hi: i64,
) -> RResult<Option<usize>> {
    let key = key.key();
    match o.int(key)? {
        None => Ok(None),
        Some(v) if (lo..=hi).contains(&v) => Ok(Some(v as usize)),
        Some(v) => fail(format!(
            "{who}: {key} = {v} is out of range: {lo} ≤ {key} ≤ {hi}"
        )),
    }
}

/// Peak options from the `peak_keys()`; defaults from `PeakOptions::default()` (the same values
/// the help texts print).
pub(crate) fn peak_opts(who: &str, o: &Opts) -> RResult<PeakOptions> {
    let d = PeakOptions::default();
    Ok(PeakOptions {
        window_um: pos_f64(who, o, WINDOW_UM, d.window_um, 1e-3, 100.0)?,
        min_value: o.f64(MIN_VALUE)?,
        min_snr: pos_f64(who, o, MIN_SNR, d.min_snr, 0.0, 1e6)?,
        sigma: o.f64(SIGMA)?,
        acf: [0.0; 4],
    })
}

/// Keys of the line-maximum options (`peak_opts`): help texts read their defaults from
/// `PeakOptions::default()`.
pub(crate) fn peak_keys() -> Vec<Key> {
    let d = PeakOptions::default();
    vec![
        WINDOW_UM.doc(format!(
            "optional: parabola window (default {}, Sec. 5)",
            d.window_um
        )),
        MIN_SNR.doc(format!(
            "optional: reject maxima below min_snr × line noise (default {})",
            d.min_snr
        )),
        MIN_VALUE.doc("optional: reject maxima below this value".into()),
        SIGMA.doc("optional: known pixel noise (default: from the fit residuals)".into()),
    ]
}

pub(crate) fn measure_opts(who: &str, o: &Opts, base: MeasureOptions) -> RResult<MeasureOptions> {
    Ok(MeasureOptions {
        stencil: stencil_of(who, o, base.stencil)?,
        window_um: pos_f64(who, o, WINDOW_UM, base.window_um, 1e-3, 100.0)?,
        min_snr: pos_f64(who, o, MIN_SNR, base.min_snr, 0.0, 1e6)?,
        max_offset_um: pos_f64(who, o, MAX_OFFSET_UM, base.max_offset_um, 0.0, 100.0)?,
        detect_snr: pos_f64(who, o, DETECT_SNR, base.detect_snr, 0.0, 1e6)?,
        end_margin_um: pos_f64(who, o, END_MARGIN_UM, base.end_margin_um, 0.0, 100.0)?,
    })
}

/// A map key's declaration: name, type, unit, help (owned, so that a default can be `format!`ed
/// into the help from the constant the code reads).
pub(crate) type Key = (&'static str, &'static str, &'static str, String);

/// Keys of the measurement pipeline (`measure_opts`): help texts read their defaults from
/// `MeasureOptions::default()`.
pub(crate) fn measure_keys() -> Vec<Key> {
    let d = MeasureOptions::default();
    vec![
        STENCIL.doc(format!(
                "optional: derivative stencil (default {})",
                d.stencil.name()
            )),
        WINDOW_UM.doc(format!("optional: parabola window (default {})", d.window_um)),
        MIN_SNR.doc(format!(
                "optional: ignore line maxima below min_snr × line noise (default {})",
                d.min_snr
            )),
        MAX_OFFSET_UM.doc(format!(
                "optional: ignore maxima farther than this from the fitted line (default {})",
                d.max_offset_um
            )),
        DETECT_SNR.doc(format!(
                "optional: candidate maxima above detect_snr × pixel noise (default {})",
                d.detect_snr
            )),
        END_MARGIN_UM.doc(format!(
                "optional: maxima closer than this to a filament end inside the scan are left out of the mean (the end lowers them) (default {})",
                d.end_margin_um
            )),
    ]
}

/// The two keys that give a calibration the pixel size of the data it will be applied to
/// (`pixel_of`): `scan` (the data itself) or `pixel_um`; one of them is required (no silent
/// 50 nm: every maximum sensitivity read through the pipeline depends on it, see docs/physics.md
/// "Calibrations and the measurement pipeline").
pub(crate) fn pixel_keys() -> Vec<Key> {
    vec![
        PIXEL_UM.doc(
            "pixel size of the scans it will be applied to (required unless scan is given)".into(),
        ),
        SCAN.doc(
            "optional: the scan (or image) it will be applied to; its pixel size |dx| is used"
                .into(),
        ),
    ]
}

/// The pixel size (µm) of the data a calibration is for: `scan`'s |dx| or `pixel_um` (one is
/// required; both must agree within 1 %). Range 1 nm – 10 µm.
pub(crate) fn pixel_of(who: &str, o: &Opts) -> RResult<f64> {
    let from_scan = match o.value(SCAN) {
        None => None,
        Some(v) => {
            let dx = if let Some(s) = v.read_lock::<ScanRef>() {
                s.scan.sx.dx()
            } else if let Some(i) = v.read_lock::<super::types::ImageRef>() {
                i.0.dx()
            } else {
                return fail(format!(
                    "{who}: scan must be a Scan or an Image (the data the calibration is for), got {}",
                    v.type_name()
                ));
            };
            Some(dx.abs())
        }
    };
    let given = o.f64(PIXEL_UM)?;
    let px = match (from_scan, given) {
        (Some(a), Some(b)) if ((a - b) / a).abs() > 0.01 => {
            return fail(format!(
                "{who}: pixel_um = {b} contradicts the scan's pixel size {a} µm; give one of them"
            ))
        }
        (Some(a), _) => a,
        (None, Some(b)) => b,
        (None, None) => {
            return fail(format!(
                "{who}: pixel_um is required: the pixel size (µm) of the scans this calibration is applied to (or pass scan: the scan itself); maximum sensitivities depend on it (the reference bead reads 0.948 at 0.05 µm, 0.881 at 0.1 µm)"
            ))
        }
    };
    if !(1e-3..=10.0).contains(&px) {
        return fail(format!(
            "{who}: pixel_um = {px} is out of range: 0.001 ≤ pixel_um ≤ 10 (µm)"
        ));
    }
    Ok(px)
}

/// Keys of the bead-model measurement pipeline shared by the calibrations (`pipeline_opts`):
/// the pixel size (`pixel_keys`, required), spacing from `BeadModelOptions::default()`, stencil
/// and window from `MeasureOptions::default()`.
pub(crate) fn pipeline_keys() -> Vec<Key> {
    let m = MeasureOptions::default();
    let mut v = pixel_keys();
    v.extend([
        SPACING_NM.doc(format!(
            "optional: bead-model spacing (default {})",
            BeadModelOptions::default().spacing_nm
        )),
        STENCIL.doc(format!(
            "optional: derivative stencil (default {})",
            m.stencil.name()
        )),
        WINDOW_UM.doc(format!(
            "optional: parabola window (default {})",
            m.window_um
        )),
    ]);
    v
}

/// Pixel size, measurement options and bead-model options from the `pipeline_keys()`.
pub(crate) fn pipeline_opts(
    who: &str,
    o: &Opts,
) -> RResult<(f64, MeasureOptions, BeadModelOptions)> {
    // only the declared keys: stencil and window; the rest of the measurement keeps its defaults
    let base = MeasureOptions::default();
    let mo = MeasureOptions {
        stencil: stencil_of(who, o, base.stencil)?,
        window_um: pos_f64(who, o, WINDOW_UM, base.window_um, 1e-3, 100.0)?,
        ..base
    };
    let bm = BeadModelOptions {
        spacing_nm: o.f64_or(SPACING_NM, BeadModelOptions::default().spacing_nm)?,
    };
    Ok((pixel_of(who, o)?, mo, bm))
}

pub(crate) fn line_peaks(v: &[LinePeak]) -> Array {
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

pub(crate) fn bead_map(b: &FitBead) -> Dynamic {
    let mut m = to_map(b);
    m.insert("found".into(), b.found().into());
    m.into()
}

/// `[#{x, y, weight}]` → (x, y, weight) triples.
pub(crate) fn bead_list(who: &str, v: &Dynamic) -> RResult<Vec<(f64, f64, f64)>> {
    let what = "#{x, y, weight} maps (µm, reference-bead units)";
    array_of(who, "beads", what, v, |i, b| {
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
}

/// `#{points: [[x, y], …], d_nm: 50.0 | [..], n: 1.41}` → a bead-model filament.
pub(crate) fn filament_arg(who: &str, v: &Dynamic) -> RResult<crate::analysis::Filament> {
    let Some(m) = v.read_lock::<Map>() else {
        return fail(format!(
            "{who}: a filament is #{{points: [[x, y], …], d_nm, n}}, got {}",
            v.type_name()
        ));
    };
    for k in m.keys() {
        if ![POINTS.name, D_NM.name, N.name].contains(&k.as_str()) {
            return fail(format!(
                "{who}: unknown filament key `{k}`; allowed keys: points, d_nm, n"
            ));
        }
    }
    let points = match m.get(POINTS.name) {
        Some(p) => super::registry::points(who, p)?,
        None => return fail(format!("{who}: filament lacks `points` ([[x, y], …] µm)")),
    };
    let d_nm = match m.get(D_NM.name) {
        None => return fail(format!("{who}: filament lacks `d_nm` (nm)")),
        Some(d) if d.is_array() => numbers(who, D_NM.name, d)?,
        Some(d) => vec![num(who, D_NM.name, d)?],
    };
    let n = match m.get(N.name) {
        None => return fail(format!("{who}: filament lacks `n` (refractive index)")),
        Some(v) => num(who, N.name, v)?,
    };
    let f = crate::analysis::Filament { points, d_nm, n };
    f.validate().map_err(|e| err(who, e))?;
    Ok(f)
}

pub(crate) fn ref_bead(who: &str, o: &Opts, n_medium: f64) -> RResult<RefBead> {
    let d = RefBead::default();
    let r = RefBead {
        d_nm: o.f64_or(D_NM, d.d_nm)?,
        n: o.f64_or(N, d.n)?,
        n_medium,
        density_g_cm3: o.f64_or(DENSITY, d.density_g_cm3)?,
    };
    r.validate().map_err(|e| err(who, e))?;
    Ok(r)
}

pub(crate) fn scans_arg(who: &str, v: &Array) -> RResult<Vec<Arc<Scan>>> {
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

pub(crate) fn scan_of(sx: Image, sy: Image, sz: Image, meta: serde_json::Value) -> ScanRef {
    scan_flagged(sx, sy, sz, meta, Default::default())
}

/// A scan computed pixel by pixel from another (a fit subtracted, aggregates removed): it keeps
/// the other's clipped and dark pixels (`flags`), so that analyses of it still flag them.
pub(crate) fn scan_flagged(
    sx: Image,
    sy: Image,
    sz: Image,
    meta: serde_json::Value,
    flags: crate::data::clip::InputFlags,
) -> ScanRef {
    ScanRef::new(
        Scan {
            flags,
            ..Scan::complete([sx, sy, sz], meta)
        },
        None,
    )
}

pub(crate) const TPL: &str = "let t = template_model(#{h_um: 0.025});";
pub(crate) const ONE_BEAD: &str = "let t = template_model(#{h_um: 0.025}); let sc = render_beads(t, #{beads: [#{x: 0.1, y: -0.05, weight: 1.0}], x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 41, ny: 41});";
