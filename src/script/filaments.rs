//! Binding family `filaments`: the orientation calibration (19-angle curve), filament
//! measurement, SBR and aggregate removal with the Sy channel, fibril diameters, microtubule
//! linear density, masses.

use super::ctx::Ctx;
use super::keys::{AXIS, DENSITY, DETECT_SNR, D_NM, N, SPACING_NM};
use super::registry::{
    binding_list, err, fail, fields_map, num, properties, Doc, Opt, Opts, RResult, Registrar, Spec,
};
use super::types::{floats, ImageRef, ProfileRef, ScanRef};
use crate::analysis::background::Remaining;
use crate::analysis::checked::{measure_filament_scan, remove_background_scan, Cleaned};
use crate::analysis::microtubule::{density, remove_aggregates, AggregateOptions};
use crate::analysis::orientation::Channel;
use crate::analysis::quantities::{
    fibril_diameter_nm, point_object, protofilaments, DiameterCalib, LinDensCalib, PROTEIN_N,
};
use crate::analysis::sbr::{sbr, SbrOptions};
use crate::analysis::{
    AngleCurve, AngleCurveOptions, BackgroundOptions, BeadModelOptions, FilamentAxis, FitResult,
    RefBead,
};
use rhai::{Array, Dynamic, Map};
use std::sync::Arc;

/// A reference template in a script (`Template`).
use super::analysis_values::*;
use super::types::{CurveRef, FilamentRef, FitRef, TemplateRef, TEMPLATE_ARG};

/// The options of this family's bindings, each key written once (`Opt`).
const ANGLE_DEG: Opt = Opt::new("angle_deg", "float", "°");
const BOTH_ENDS: Opt = Opt::new("both_ends", "bool", "");
const D_BM_NM: Opt = Opt::new("d_bm_nm", "float", "nm");
const DENSITY_OBJ: Opt = Opt::new("density_obj", "float", "g/cm³");
const EXCLUSION_UM: Opt = Opt::new("exclusion_um", "float", "µm");
const FIT_WEIGHT: Opt = Opt::new("fit_weight", "bool", "");
const MAX_OBJECTS: Opt = Opt::new("max_objects", "int", "");
const MIN_WEIGHT: Opt = Opt::new("min_weight", "float", "");
const N_ANGLES: Opt = Opt::new("n_angles", "int", "");
const N_BM: Opt = Opt::new("n_bm", "float", "");
const N_OBJ: Opt = Opt::new("n_obj", "float", "");
const NONZERO_SNR: Opt = Opt::new("nonzero_snr", "float", "");
const SENS: Opt = Opt::new("sens", "float", "");
const SENS_ERR: Opt = Opt::new("sens_err", "float", "");
const SENS_RB: Opt = Opt::new("sens_rb", "float", "");
const SKIP_UM: Opt = Opt::new("skip_um", "float", "µm");
const TPL_KEY: Opt = Opt::new("tpl", "Template", "");

/// `lin_dens_calib`'s default density of the filament, g/cm³ (protein; kept as it was: the
/// globular-protein value of Sec. 3.2, `quantities::PROTEIN_DENSITY_G_CM3` = 1/0.745, is 1.342).
const LIN_DENS_DENSITY_OBJ_G_CM3: f64 = 1.35;

// ------------------------------------------------------------------ filaments

/// A filament measured from a scan, for the examples.
const FIL_EX: &str = "let t = template_model(#{h_um: 0.025}); let c = angle_curve(t, #{n_angles: 7, pixel_um: 0.05}); let sc = render_beads(t, #{filaments: [#{points: [[-0.5, -2.0], [0.5, 2.0]], d_nm: 110.0, n: 1.572}], x: [-1.5, 1.5], y: [-1.5, 1.5], nx: 61, ny: 61}); let m = measure_filament(sc, c);";

binding_list! {
    pub fn register {
        bind_angle_curve, bind_measure_filament, bind_background, bind_microtubule, bind_quantities
    }
}

/// `angle_curve` and the `AngleCurve` it returns (Sec. 4.2 step 2, Fig. 4d).
fn bind_angle_curve(r: &mut Registrar) {
    let meas_keys = measure_keys();
    let c = AngleCurveOptions::default();
    let mut curve_keys: Vec<Key> = vec![
        N_ANGLES.doc(format!(
            "optional: angles spanning 180° (default {}, Fig. 4d)",
            c.n_angles
        )),
        D_NM.doc("optional: bead-model filament diameter (default: the reference bead's)".into()),
        N.doc("optional: its index (default: the reference bead's)".into()),
        SPACING_NM.doc(format!(
            "optional: bead-model spacing (default {})",
            c.bead_model.spacing_nm
        )),
    ];
    curve_keys.extend(pixel_keys());
    curve_keys.extend(meas_keys.iter().cloned());
    const CURVE: &str =
        "let t = template_model(#{h_um: 0.025}); let c = angle_curve(t, #{n_angles: 7, pixel_um: 0.05});";
    let d = Doc::func("angle_curve")
        .arg_of(TEMPLATE_ARG)
        .opts(&curve_keys)
        .form("angle_curve(tpl, #{pixel_um}) -> AngleCurve")
        .returns("AngleCurve", "max Sx and Sy sensitivity vs filament angle, normalised to Sx at 0° (interpolated, period 180°)")
        .summary("orientation calibration curve from the bead model (Sec. 4.2 step 2, Fig. 4d)")
        .help(&format!("Each angle: a long straight bead-model filament rendered on pixels of pixel_um (required, or taken from scan), measured by the same pipeline as data (stencil, parabola window), averaged over sub-pixel offsets; measure_filament refuses a curve made for another pixel size. The default {} angles over 180° follow the paper's rotation series.", c.n_angles))
        .example(&format!("{CURVE} round(c.at(0.0).sx * 1000.0)"), "1000.0")
        .example(&format!("{CURVE} c.at(90.0).sy > 0.5"), "true")
        .example("let t = template_model(#{h_um: 0.025}); angle_curve(t, #{n_angles: 2, pixel_um: 0.05})", "error: n_angles = 2")
        .example("let t = template_model(#{h_um: 0.025}); angle_curve(t, #{n_angles: 7})", "error: angle_curve: pixel_um is required");
    r.bind_opts(d, |spec, t: TemplateRef, m| angle_curve(spec, &t, m));

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
        |c: &mut CurveRef, a: f64| curve_at(c, a),
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
        |c: &mut CurveRef, a: f64, ch: &str| curve_correction(c, a, ch),
    );
    properties!(r, "AngleCurve", CurveRef, CURVE, [
        nodes: "map", "#{angle_deg: [..], sx: [..], sy: [..], sx0, pixel_um}"; "the computed nodes of the curve (for plots and tables)"; "c.nodes.angle_deg.len()" => "6"; |c| curve_nodes(c),
    ]);
}

/// `measure_filament` and the `FilamentMeasurement` it returns.
fn bind_measure_filament(r: &mut Registrar) {
    let meas_keys = measure_keys();
    let d = Doc::func("measure_filament")
        .arg("scan", "Scan", "", "XY scan of a filament")
        .arg("curve", "AngleCurve", "", "orientation calibration for the scan's pixel size")
        .map("opts", "optional (default: the curve's measurement options)", &meas_keys)
        .form("measure_filament(scan, curve) -> FilamentMeasurement")
        .returns("FilamentMeasurement", "angle, per-line maxima along the filament, corrected sensitivities")
        .summary("orientation from the row/column maxima and orientation-corrected sensitivities (Sec. 4.2 steps 4–5)")
        .help("Row maxima of ∂Sx/∂x are used for filaments within 45° of the QPD y-axis, column maxima of ∂Sy/∂y otherwise (the paper's step 4); a robust straight-line fit through the maxima gives the angle, the curve's correction maps every maximum to the y-axis orientation. Refused, with the reason: a single point object, or point objects in a row with no filament signal between them (if the preferred channel's line is such, the other channel's line is tried, then the search is repeated with candidates above 3/4 and 5/8 of detect_snr).");
    r.bind_ctx_opts2(
        d.example(&format!("{FIL_EX} round(m.angle_deg)"), "14.0")
            .example(&format!("{FIL_EX} m.channel"), "\"sx_rows\""),
        measure_filament_of,
    );
    let float_rows = [
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
    ];
    let ex = |name: &str| (format!("{FIL_EX} type_of(m.{name})"), "\"f64\"");
    r.named_getters(
        "FilamentMeasurement",
        "float",
        &float_rows,
        ex,
        filament_float,
    );
    properties!(r, "FilamentMeasurement", FilamentRef, FIL_EX, [
        channel: "string", "\"sx_rows\" or \"sy_cols\""; "which maxima were used"; "m.channel" => "\"sx_rows\""; |m| -> String { to_dyn(&m.0.channel).into_string().unwrap_or_default() },
        points: "array", "[#{line, x, y, arc_um, sens, sens_err, sens_corr, interior}] along the filament (interior: at least end_margin_um from every end inside the scan; only these enter mean_corr)"; "the maxima along the filament"; "m.points.len() > 40" => "true"; |m| -> Array { m.0.points.iter().map(to_dyn).collect() },
        ends_um: "array", "[lo, hi]: arc positions (µm, the points' arc axis) of the filament's ends inside the scan, where its maxima fall to half their plateau; () where it runs out of the scan"; "where the filament ends"; "m.ends_um" => "[(), ()]"; |m| -> Array { m.0.ends_um.iter().map(to_dyn).collect() },
        n_interior: "int", "maxima at least end_margin_um from every end"; "how many maxima the mean is over"; "m.n_interior > 40" => "true"; |m| -> i64 { m.0.points.iter().filter(|p| p.interior).count() as i64 },
        warnings: "array", "[string]: where the answer leaves its domain; empty when the mean and its σ hold"; "what the answer cannot vouch for"; "m.warnings.len()" => "0"; |m| -> Array { m.0.warnings.iter().map(|w| Dynamic::from(w.clone())).collect() },
        status: "string", "\"ok\" when `warnings` is empty, else \"flagged\""; "whether the answer is inside its domain (docs/analysis.md, Domains)"; "m.status" => "\"ok\""; |m| -> String { crate::analysis::domain::status(&m.0.warnings).to_string() },
        sens: "Image", "the sensitivity image used (reference-bead units/µm)"; "sensitivity image of the chosen channel"; "m.sens.cols" => "61"; |m| -> ImageRef { ImageRef(Arc::new(m.0.sens.clone())) },
    ]);
    // a noisy scan (1 ms per pixel): the per-row method's sem sits above the bound
    let noisy_ex = "let t = template_model(#{h_um: 0.025}); let c = angle_curve(t, #{n_angles: 7, pixel_um: 0.05}); let s = scene(); s.add_filament(#{points: [[-0.5, -3.0], [0.5, 3.0]], d_nm: 110.0, n: 1.572}); s.effects([\"detector_noise\"]); let sc = simulate(s, #{x: [-1.5, 1.5], y: [-1.5, 1.5], nx: 61, ny: 61, n_samples: 100}); let m = measure_filament(sc, c);";
    properties!(r, "FilamentMeasurement", FilamentRef, noisy_ex, [
        crlb: "map", "#{angle_deg, offset_um, mean_corr, lin_dens_rel, diameter_rel, sigma: [sx, sy]} or () (noise-free data, a curve loaded from a file)"; "Cramér–Rao bounds (1σ floors) of the whole-image bead-model filament at the measured line and sensitivity, from the scan's Sx and Sy pixels with their robust pixel noise: compare angle_err_deg and sem_corr with them"; "m.crlb.lin_dens_rel < m.sem_corr / m.mean_corr" => "true"; |m| -> Dynamic { m.0.crlb.as_ref().map_or(Dynamic::UNIT, |c| to_map(c).into()) },
    ]);
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
                &format!("{FIL_EX} m.profile(\"sens_corr\").len > 40"),
                "true",
            )
            .example(
                &format!("{FIL_EX} m.profile(\"mass\")"),
                "error: key = \"mass\"",
            ),
        |m: &mut FilamentRef, key: &str| filament_profile(m, key),
    );
}

/// `sbr` and `remove_background`: the signal over the background of a filament.
fn bind_background(r: &mut Registrar) {
    let sd = SbrOptions::default();
    let d = Doc::func("sbr")
        .arg("m", "FilamentMeasurement", "", "a measured filament")
        .opts(&[
                SKIP_UM.doc(format!("optional: arc skipped from the first non-zero maximum (default {}, Sec. 6)", sd.skip_um)),
                BOTH_ENDS.doc(format!("optional: also skip at the far end (default {})", sd.both_ends)),
                EXCLUSION_UM.doc(format!("optional: background pixels farther than this from the line (default {:?})", sd.exclusion_um)),
                NONZERO_SNR.doc(format!("optional: a maximum is non-zero above this × background std (default {})", sd.nonzero_snr)),
                ("min_run", "int", "", format!("optional: consecutive lines that start the filament (default {})", sd.min_run)),
            ],
        )
        .form("sbr(m) -> map")
        .returns("map", "#{sbr_background, sbr_uniformity, mean_sens, mean_corr, std_sens, background_std, arc_start, arc_end, n_points, n_background}")
        .summary("signal-to-background ratio both ways the paper defines (Sec. 6)")
        .example(&format!("{FIL_EX} sbr(m, #{{skip_um: 0.2}}).n_points > 10"), "true")
        .example(&format!("{FIL_EX} sbr(m, #{{skip_um: -1.0}})"), "error: skip_um = -1");
    r.bind_opts(d, |spec, m: FilamentRef, mm| sbr_of(spec, &m, mm));

    let bd = BackgroundOptions::default();
    let d = Doc::func("remove_background")
        .arg("scan", "Scan", "", "XY scan of a filament with point-like aggregates")
        .arg_of(TEMPLATE_ARG)
        .opts(&point_object_keys(
            vec![
                AXIS.doc("optional: the filament's closer QPD axis, \"y\" (default: fit Sy, subtract from Sx, Fig. 6) or \"x\"".to_string()),
                ANGLE_DEG.doc("optional: the filament's angle (chooses axis: |angle| ≤ 45° → \"y\")".to_string()),
            ],
            format!("optional: smallest object detected, reference-bead units (a 110 nm polystyrene bead is 1; default {}: the floor that keeps noise-free data from turning the filament's faint residue into objects)", bd.min_weight),
        ))
        .form("remove_background(scan, tpl) -> map")
        .returns("map", "#{scan: the cleaned Scan, fit: FitResult or (), n_objects, remaining: [#{x, y, weight, snr}] (point-like features still in the fitted channel at ≥ 5 × the detection map's robust noise after the removal: µm, reference-bead units; snr () on noise-free data), warning: the text saying so, or () when none, warnings: [string] (that text and clipped or dark pixels of Sx, Sy), status: \"ok\" when warnings is empty}")
        .summary("remove point-like aggregates using the channel the filament barely shows in (Sec. 6)")
        .example(&format!("{TPL} let s = scene(); s.add_filament(#{{points: [[0.0, -3.0], [0.0, 3.0]], d_nm: 50.0, n: 1.41}}); s.add_bead(#{{x: 0.8, y: 0.5, d_nm: 90.0, n: 1.45}}); s.effects([\"detector_noise\"]); let sc = simulate(s, #{{x: [-1.5, 1.5], y: [-1.5, 1.5], nx: 61, ny: 61}}); remove_background(sc, t).n_objects"), "1")
        .example(&format!("{TPL} let sc = render_beads(t, #{{beads: [#{{x: 0.0, y: 0.0}}], x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 21, ny: 21}}); remove_background(sc, t, #{{axis: \"z\"}})"), "error: axis = \"z\"");
    r.bind_ctx_opts2(d, remove_background);
}

/// `remove_aggregates` and `microtubule_density`: the arithmetic of the `aggregates::remove`
/// and `microtubule::density` protocols (`analysis::microtubule`), which call them.
fn bind_microtubule(r: &mut Registrar) {
    let ad = AggregateOptions::default();
    const CURVE_DOC: &str = "orientation calibration for the scan's pixel size";
    let d = Doc::func("remove_aggregates")
        .arg("scan", "Scan", "", "XY scan of a filament with point-like aggregates")
        .arg_of(TEMPLATE_ARG)
        .arg("curve", "AngleCurve", "", CURVE_DOC)
        .opts(&point_object_keys(
            vec![SKIP_UM.doc(format!("optional: arc skipped from the first non-zero maximum (default {}, Sec. 6)", ad.skip_um))],
            format!("optional: smallest object removed, reference-bead units (default {})", ad.min_weight),
        ))
        .form("remove_aggregates(scan, tpl, curve) -> map")
        .returns("map", "#{scan (cleaned), n_objects, angle_deg, sbr_before, sbr_after, uniformity_before, uniformity_after, mean_corr_after, improvement, detection_limit (the faintest point object the removal detects, reference-bead units), undetected_rel (what one object just below it, on the filament, adds to its mean corrected maximum, relative), faint: [#{x, y, weight, weight_err, snr}] (objects below that limit a matched filter finds on the filament's line, at ≥ 5σ), faint_rise_rel (what they add to the mean corrected maximum, relative; () when none), remaining: [#{x, y, weight, snr}], warning (() when none), warnings (both measurements' and the removal's, once each), status}")
        .summary("aggregates::remove's arithmetic: measure the filament, remove the point objects fitted in the channel it barely shows in, measure again; SBR before and after (Sec. 6)")
        .help("The protocol aggregates::remove calls it (and adds figures); the truth sweep runs the same Rust function (analysis::microtubule::remove_aggregates). Warnings are said as each step says them: measure_filament before, remove_background, measure_filament after.")
        .example(&format!("{FIL_EX} remove_aggregates(sc, t, c, #{{skip_um: 0.2}}).n_objects"), "0")
        .example(&format!("{FIL_EX} remove_aggregates(sc, t, c, #{{skip_um: -1.0}})"), "error: skip_um = -1");
    r.bind_ctx_opts3(d, remove_aggregates_of);
    let d = Doc::func("microtubule_density")
        .arg("scan", "Scan", "", "XY scan of the microtubule, aggregates removed")
        .arg("curve", "AngleCurve", "", CURVE_DOC)
        .arg("calib", "map", "", "from lin_dens_calib (at the scan's pixel size)")
        .opts(&[SKIP_UM.doc(format!("optional: arc skipped from the first non-zero maximum (default {}, Sec. 6)", ad.skip_um))])
        .form("microtubule_density(scan, curve, calib) -> map")
        .returns("map", "#{mu_mda_um (MDa/µm), mu_err_mda_um, protofilaments, protofilaments_exact, mean_corr, sbr, uniformity, n_points (maxima used), n_excluded (left out: within a removed object's footprint), undetected_mda_um (what one point object just below the removal's detection limit, on the filament, would add to μ; () on a scan not cleaned by aggregates::remove), faint_mda_um (what the objects below that limit found on the filament's line add to μ; () when none), warnings, status}")
        .summary("microtubule::density's arithmetic: the linear density over the uniform region, its σ and the protofilament number (eq. mtLinDens, Sec. 6)")
        .help("The protocol microtubule::density calls it; the truth sweep runs the same Rust function (analysis::microtubule::density). On a scan cleaned by remove_aggregates or remove_background, the maxima where a removed object's subtraction can move them (its template's derivative at ≥ 10 % of its peak; the footprint in the scan's meta.background_removed) are left out. σ(μ) is the standard error of the region's maxima through the orientation correction. Warnings: measure_filament's (said as it says them), fewer than 10 maxima in the uniform region outside the removed objects' footprints, maxima that do not scatter about one level (a slope or a slow structure along the region), σ(μ) above half a protofilament, and (on a scan cleaned by remove_aggregates) one point object just below the removal's detection limit that would add more than a protofilament to μ (undetected_mda_um), and point objects below that limit found on the filament's line by a matched filter (remove_aggregates' faint) that together add more than half σ(μ) (faint_mda_um).")
        .example(&format!("{FIL_EX} microtubule_density(sc, c, lin_dens_calib(t, #{{pixel_um: 0.05}}), #{{skip_um: 0.2}}).n_points > 10"), "true")
        .example(&format!("{FIL_EX} microtubule_density(sc, c, #{{}})"), "error: microtubule_density: calib lacks");
    r.bind_ctx_opts3(d, microtubule_density_of);
}

/// The quantities: `diameter_calib`, `lin_dens_calib`, `linear_density`, `point_mass` and what follows.
fn bind_quantities(r: &mut Registrar) {
    // quantities
    let mut calib_keys: Vec<Key> = vec![
        N_OBJ.doc("refractive index of the filament (collagen 1.41 in the paper)".into()),
        D_BM_NM
            .doc("optional: bead-model cylinder diameter (default: the reference bead's)".into()),
        N_BM.doc("optional: bead-model index (default: the reference bead's)".into()),
    ];
    calib_keys.extend(pipeline_keys());
    let d = Doc::func("diameter_calib")
        .arg_of(TEMPLATE_ARG)
        .map("opts", "", &calib_keys)
        .returns("map", "#{a_nm, d_bm_nm, n_bm, sens_bm, n_obj, n_corr, d_max_nm}: d = A·√(sens_corr) (eqs. colDiam, OurColD), which holds up to d_max_nm (nm: the point-dipole sections' domain at n_obj in the session's optics)")
        .summary("the constant A of fibril diameters, derived from the bead model and n_corr for the current optics")
        .help("A = d_bm / √(sens_bm · n_corr): sens_bm is the max sensitivity of a bead-model cylinder along the QPD y-axis measured by the pixel pipeline of the data (pixel_um or scan: required; stencil, window), so A belongs to that pixel size (default optics: 71.1 nm at 0.05 µm, 73.3 nm at 0.1 µm, 70.4 nm as the pixel → 0; docs/physics.md); not hard-coded (the paper's 58.6 nm is for its own optics).")
        .example(&format!("{TPL} let a = diameter_calib(t, #{{n_obj: 1.41, pixel_um: 0.05}}).a_nm; a > 40.0 && a < 90.0"), "true")
        .example(&format!("{TPL} diameter_calib(t, #{{n_obj: 1.2, pixel_um: 0.05}})"), "error: n_obj")
        .example(&format!("{TPL} diameter_calib(t, #{{n_obj: 1.41}})"), "error: diameter_calib: pixel_um is required");
    let spec = d.spec();
    let c = r.ctx();
    r.bind(d, move |t: TemplateRef, m: Map| {
        diameter_calib(&c, &spec, &t, &m)
    });
    r.bind(
        Doc::func("fibril_diameter")
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
    let mut lin_keys: Vec<Key> = vec![
        N_OBJ.doc(format!(
            "optional: index of the filament (default {PROTEIN_N}, dry globular protein as Sec. 6)"
        )),
        DENSITY_OBJ.doc(format!(
            "optional: its density (default {LIN_DENS_DENSITY_OBJ_G_CM3}, protein)"
        )),
    ];
    lin_keys.extend(pipeline_keys());
    let d = Doc::func("lin_dens_calib")
        .arg(
            "tpl",
            "Template",
            "",
            "the point-particle template (its reference bead is the bead-model material)",
        )
        .map("opts", "", &lin_keys)
        .returns(
            "map",
            "#{mu_bm_mda_um, d_bm_nm, density_bm, sens_bm, n_obj, density_obj, n_corr}",
        )
        .summary("calibration of linear densities (eq. mtLinDens) from the template's bead model")
        .example(
            &format!("{TPL} lin_dens_calib(t, #{{pixel_um: 0.05}}).mu_bm_mda_um > 0.0"),
            "true",
        );
    let spec = d.spec();
    r.bind(d, move |t: TemplateRef, m: Map| {
        lin_dens_calib(&spec, &t, &m)
    });
    let d = Doc::func("linear_density")
        .arg("sens_corr", "float", "", "orientation-corrected max sensitivity (reference-bead units/µm)")
        .arg("calib", "map", "", "from lin_dens_calib")
        .returns("map", "#{mu_mda_um, protofilaments, protofilaments_exact} (13.75 MDa/µm per protofilament: 110 kDa per 8 nm dimer)")
        .summary("microtubule linear density and the protofilament number it implies (eq. mtLinDens, Sec. 6)")
        .example("linear_density(1.0, #{mu_bm_mda_um: 6.0, d_bm_nm: 110.0, density_bm: 1.05, sens_bm: 1.0, n_obj: 1.55, density_obj: 1.35, n_corr: 0.5}).mu_mda_um", "15.428571428571429")
        .example("linear_density(1.0, #{})", "error: calib");
    r.bind(d, |s: f64, c: Map| linear_density(s, &c));
    let mut pm_keys: Vec<Key> = vec![
        SENS.doc("its max sensitivity (reference-bead units: scan values × tpl.norm_factor; or a fit weight with fit_weight: true)".into()),
        SENS_ERR.doc("optional: 1σ of sens".into()),
        SENS_RB.doc("the reference bead's max sensitivity through the same pipeline (e.g. tpl.max_sens(pixel_um)); or give tpl and the pixel size, or fit_weight: true".into()),
        TPL_KEY.doc("the template: sens_rb = its reference bead read through the pipeline of the data (pixel_um or scan required; stencil, window_um)".into()),
        FIT_WEIGHT.doc("optional: sens is a template-fit weight (reference-bead units by construction: sens_rb = 1)".into()),
        N_OBJ.doc("optional: index of the object (default: the reference bead's)".into()),
        DENSITY.doc("optional: density of the object (default: the reference bead's)".into()),
    ];
    pm_keys.extend(pixel_keys());
    let m_def = crate::analysis::MeasureOptions::default();
    pm_keys.push((
        "stencil",
        "string",
        "",
        format!(
            "optional: derivative stencil of the data (default {})",
            m_def.stencil.name()
        ),
    ));
    pm_keys.push((
        "window_um",
        "float",
        "µm",
        format!(
            "optional: parabola window of the data (default {})",
            m_def.window_um
        ),
    ));
    let d = Doc::func("point_mass")
        .map("obj", "the measured object", &pm_keys)
        .returns("map", "#{volume_ratio, volume_nm3, sphere_d_nm, mass_kda, mass_err_kda, n_corr, sens_rb}")
        .summary("volume and mass of a point-like object from its max sensitivity (eqs. after nCor)")
        .help("V/V_rb = sens/(n_corr·sens_rb). A maximum read off a sensitivity image (max_sens) depends on the pixel size, stencil and window; so does the reference bead's, and the two must come from the same pipeline: at 0.05 µm pixels the reference bead itself reads 0.948 (not 1), so dividing by 1 would make every mass 5 % low. Give exactly one of: sens_rb; tpl with pixel_um or scan (sens_rb computed as tpl.max_sens does, 4×4 sub-pixel offsets); fit_weight: true (template-fit weights are already in reference-bead units).")
        .example(&format!("{TPL} round(point_mass(#{{sens: t.max_sens(0.05), tpl: t, pixel_um: 0.05}}).sphere_d_nm * 1000.0) / 1000.0"), "110.0")
        .example("round(point_mass(#{sens: 1.0, fit_weight: true}).sphere_d_nm * 1000.0) / 1000.0", "110.0")
        .example("point_mass(#{sens: 1.0})", "error: point_mass: the reference bead's sensitivity is missing")
        .example("point_mass(#{sens: -1.0, fit_weight: true})", "error: sens_obj = -1");
    let spec = d.spec();
    r.bind(d, move |m: Map| point_mass(&spec, &m));
}

/// `angle_curve(tpl, opts)`: maximum Sx and Sy sensitivity of a long straight bead-model
/// filament vs its angle, measured on pixels of pixel_um by the data's pipeline and normalised
/// to Sx at 0° (Sec. 4.2 step 2, Fig. 4d).
fn angle_curve(spec: &Spec, t: &TemplateRef, m: &Map) -> RResult<CurveRef> {
    let who = "angle_curve";
    let o = Opts::new(spec, m)?;
    let d = AngleCurveOptions::default();
    let co = AngleCurveOptions {
        n_angles: o
            .int(N_ANGLES)?
            .map_or(d.n_angles, |v| v.clamp(0, 100_000) as usize),
        pixel_um: pixel_of(who, &o)?,
        d_nm: o.f64(D_NM)?,
        n: o.f64(N)?,
        bead_model: BeadModelOptions {
            spacing_nm: o.f64_or(SPACING_NM, d.bead_model.spacing_nm)?,
        },
        measure: measure_opts(who, &o, d.measure)?,
    };
    let c = AngleCurve::compute(&t.0, &co).map_err(|e| err(who, e))?;
    Ok(CurveRef(Arc::new(c)))
}

/// `AngleCurve.at(angle_deg)`: the normalised maximum sensitivities (Sx, Sy) at an angle (°),
/// interpolated with period 180°.
fn curve_at(c: &CurveRef, a: f64) -> Map {
    let (sx, sy) = c.0.eval(a);
    let mut m = Map::new();
    m.insert("sx".into(), sx.into());
    m.insert("sy".into(), sy.into());
    m
}

/// `AngleCurve.correction(angle_deg, channel)`: the factor that maps a maximum measured in
/// `channel` at the angle (°) to the QPD y-axis orientation (Sec. 4.2 step 5).
fn curve_correction(c: &CurveRef, a: f64, ch: &str) -> RResult<f64> {
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
}

/// `AngleCurve.nodes`: the computed nodes (angles °, Sx, Sy), Sx at 0° and the pixel size (µm).
fn curve_nodes(c: &CurveRef) -> Map {
    let c = &c.0;
    let mut m = Map::new();
    m.insert("angle_deg".into(), floats(&c.angles_deg).into());
    m.insert("sx".into(), floats(&c.sx).into());
    m.insert("sy".into(), floats(&c.sy).into());
    m.insert("sx0".into(), c.sx0.into());
    m.insert("pixel_um".into(), c.options.pixel_um.into());
    m
}

/// `measure_filament(scan, curve[, opts])`: the filament's angle from its row (or column)
/// maxima and the orientation-corrected sensitivities along it (Sec. 4.2 steps 4–5).
fn measure_filament_of(
    c0: &Ctx,
    spec: &Spec,
    s: &ScanRef,
    c: &CurveRef,
    m: &Map,
) -> RResult<FilamentRef> {
    let o = Opts::new(spec, m)?;
    let mo = measure_opts("measure_filament", &o, c.0.options.measure)?;
    let r = measure_filament_scan(&s.scan, &c.0, &mo).or_else(fail)?;
    c0.warn_all("measure_filament", &r.warnings);
    Ok(FilamentRef(Arc::new(r)))
}

/// `FilamentMeasurement.profile(key)`: `sens_corr` or `sens` vs arc length (µm) along the
/// filament.
fn filament_profile(m: &FilamentRef, key: &str) -> RResult<ProfileRef> {
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
}

/// `sbr(m[, opts])`: the signal-to-background ratio of a measured filament both ways the paper
/// defines it (Sec. 6).
fn sbr_of(spec: &Spec, m: &FilamentRef, mm: &Map) -> RResult<Map> {
    let o = Opts::new(spec, mm)?;
    let d = SbrOptions::default();
    let so = SbrOptions {
        skip_um: o.f64_or(SKIP_UM, d.skip_um)?,
        both_ends: o.bool_or(BOTH_ENDS, d.both_ends)?,
        exclusion_um: o.f64_or(EXCLUSION_UM, d.exclusion_um)?,
        nonzero_snr: o.f64_or(NONZERO_SNR, d.nonzero_snr)?,
        min_run: count("sbr", &o, "min_run", 1, 100_000)?.unwrap_or(d.min_run),
    };
    let r = sbr(&m.0, &so).map_err(|e| err("sbr", e))?;
    Ok(to_map(&r))
}

/// `remove_background(scan, tpl[, opts])`: fit the point-like aggregates in the channel the
/// filament barely shows in and subtract them from both channels (Sec. 6, Fig. 6).
fn remove_background(c: &Ctx, spec: &Spec, s: &ScanRef, t: &TemplateRef, m: &Map) -> RResult<Map> {
    let who = "remove_background";
    let o = Opts::new(spec, m)?;
    let d = BackgroundOptions::default();
    let axis = match (o.string(AXIS)?.as_deref(), o.f64(ANGLE_DEG)?) {
        (Some("y"), _) => FilamentAxis::Y,
        (Some("x"), _) => FilamentAxis::X,
        (Some(a), _) => return fail(format!("{who}: axis = \"{a}\" is not one of \"x\", \"y\"")),
        (None, Some(a)) => FilamentAxis::from_angle(a),
        (None, None) => d.axis,
    };
    let bo = point_object_opts(who, &o, BackgroundOptions { axis, ..d })?;
    let r = remove_background_scan(&s.scan, &t.0, &bo).or_else(fail)?;
    let (mut out, fit, warnings) = cleaned_map(r);
    let fit = fit.map_or(Dynamic::UNIT, |f| Dynamic::from(FitRef(Arc::new(f))));
    out.insert("fit".into(), fit);
    with_warnings(c, who, &mut out, warnings);
    Ok(out)
}

/// The keys `remove_background` and `remove_aggregates` answer alike: the cleaned scan, the
/// objects removed, the features left and the sentence about them; the fit and the removal's
/// warnings handed back.
fn cleaned_map(cl: Cleaned) -> (Map, Option<FitResult>, Vec<String>) {
    let mut out = Map::new();
    out.insert("n_objects".into(), (cl.n_objects() as i64).into());
    out.insert("remaining".into(), remaining_array(&cl.remaining).into());
    let warning = cl.warning.map_or(Dynamic::UNIT, |w| w.into());
    out.insert("warning".into(), warning);
    out.insert("scan".into(), Dynamic::from(ScanRef::new(cl.scan, None)));
    (out, cl.fit, cl.warnings)
}

/// A key of an options map as `Doc::opts` declares it, its help built at run time.
type KeyDoc = (&'static str, &'static str, &'static str, String);

/// `remove_background`'s and `remove_aggregates`' keys: their own (`first`), then those of
/// the point-object detection and fit they share with its defaults; `min_weight` says what
/// the smallest object is to each.
fn point_object_keys(first: Vec<KeyDoc>, min_weight: String) -> Vec<KeyDoc> {
    let d = BackgroundOptions::default();
    let mut keys = first;
    keys.push(DETECT_SNR.doc(format!(
        "optional: detections above detect_snr × robust noise (default {})",
        d.detect_snr
    )));
    keys.push(MAX_OBJECTS.doc(format!(
        "optional: most point objects fitted (default {})",
        d.max_objects
    )));
    keys.push(MIN_WEIGHT.doc(min_weight));
    keys
}

/// The point-object keys of `o` ([`point_object_keys`]) over `d`'s.
fn point_object_opts(who: &str, o: &Opts, d: BackgroundOptions) -> RResult<BackgroundOptions> {
    Ok(BackgroundOptions {
        detect_snr: o.f64_or(DETECT_SNR, d.detect_snr)?,
        max_objects: count(who, o, MAX_OBJECTS, 1, 10_000)?.unwrap_or(d.max_objects),
        min_weight: o.f64_or(MIN_WEIGHT, d.min_weight)?,
        ..d
    })
}

/// The point-like features left after a removal, as maps `#{x, y, weight, snr}`.
fn remaining_array(rem: &[Remaining]) -> Array {
    rem.iter()
        .map(|f| {
            let mut m = fields_map!(f; x, y, weight);
            m.insert("snr".into(), f.snr.map_or(Dynamic::UNIT, Dynamic::from));
            Dynamic::from(m)
        })
        .collect()
}

/// `remove_aggregates(scan, tpl, curve[, opts])`: the arithmetic of `aggregates::remove`
/// (`analysis::microtubule::remove_aggregates`): measured, cleaned, measured again; each step's
/// warnings said as that step says them.
fn remove_aggregates_of(
    c: &Ctx,
    spec: &Spec,
    (s, t, curve): (&ScanRef, &TemplateRef, &CurveRef),
    m: &Map,
) -> RResult<Map> {
    let who = "remove_aggregates";
    let o = Opts::new(spec, m)?;
    let skip_um = o.f64_or(SKIP_UM, AggregateOptions::default().skip_um)?;
    let b = point_object_opts(who, &o, BackgroundOptions::default())?;
    let ao = AggregateOptions {
        skip_um,
        detect_snr: b.detect_snr,
        max_objects: b.max_objects,
        min_weight: b.min_weight,
    };
    let r = remove_aggregates(&s.scan, &t.0, &curve.0, &ao).or_else(fail)?;
    for (step, w) in &r.said {
        c.warn_all(step, w);
    }
    let improvement = r.improvement();
    let (sb, sa) = (r.before, r.after);
    let limit = r.cleaned.detection_limit;
    let faint: Array = r
        .faint
        .iter()
        .map(|f| Dynamic::from(fields_map!(f; x, y, weight, weight_err, snr)))
        .collect();
    let (mut out, _, _) = cleaned_map(r.cleaned);
    out.insert("faint".into(), faint.into());
    for (k, v) in [
        ("detection_limit", limit),
        ("undetected_rel", r.undetected_rel),
        ("faint_rise_rel", r.faint_rise_rel),
    ] {
        out.insert(k.into(), v.map_or(Dynamic::UNIT, Dynamic::from_float));
    }
    for (k, v) in [
        ("angle_deg", r.angle_deg),
        ("sbr_before", sb.sbr_background),
        ("sbr_after", sa.sbr_background),
        ("uniformity_before", sb.sbr_uniformity),
        ("uniformity_after", sa.sbr_uniformity),
        ("mean_corr_after", sa.mean_corr),
        ("improvement", improvement),
    ] {
        out.insert(k.into(), v.into());
    }
    domain_of(&mut out, r.warnings);
    Ok(out)
}

/// `warnings` and `status` of an answer whose warnings were already said step by step.
fn domain_of(out: &mut Map, w: Vec<String>) {
    out.insert("status".into(), crate::analysis::domain::status(&w).into());
    out.insert(
        "warnings".into(),
        w.into_iter().map(Dynamic::from).collect::<Array>().into(),
    );
}

/// `microtubule_density(scan, curve, calib[, opts])`: the arithmetic of `microtubule::density`
/// (`analysis::microtubule::density`); the measurement's warnings said as `measure_filament`
/// says them.
fn microtubule_density_of(
    c: &Ctx,
    spec: &Spec,
    (s, curve, cal): (&ScanRef, &CurveRef, &Map),
    m: &Map,
) -> RResult<Map> {
    let o = Opts::new(spec, m)?;
    let cal = lin_dens_calib_of("microtubule_density", cal)?;
    let skip = o.f64_or(SKIP_UM, SbrOptions::default().skip_um)?;
    let r = density(&s.scan, &curve.0, &cal, skip).or_else(fail)?;
    c.warn_all("measure_filament", &r.measure_warnings);
    let mut out = fields_map!(r; mu_mda_um, mu_err_mda_um, protofilaments_exact);
    for (k, v) in [
        ("mean_corr", r.region.mean_corr),
        ("sbr", r.region.sbr_background),
        ("uniformity", r.region.sbr_uniformity),
    ] {
        out.insert(k.into(), v.into());
    }
    out.insert("protofilaments".into(), (r.protofilaments as i64).into());
    out.insert("n_points".into(), (r.region.n_points as i64).into());
    out.insert("n_excluded".into(), (r.n_excluded as i64).into());
    for (k, v) in [
        ("undetected_mda_um", r.undetected_mda_um),
        ("faint_mda_um", r.faint_mda_um),
    ] {
        out.insert(k.into(), v.map_or(Dynamic::UNIT, Dynamic::from_float));
    }
    domain_of(&mut out, r.warnings);
    Ok(out)
}

/// `diameter_calib(tpl, opts)`: the constant A (nm) of fibril diameters d = A·√(sens_corr)
/// from a bead-model cylinder measured by the data's pixel pipeline and n_corr (eqs. colDiam,
/// OurColD).
fn diameter_calib(ctx: &Ctx, spec: &Spec, t: &TemplateRef, m: &Map) -> RResult<Map> {
    let who = "diameter_calib";
    let o = Opts::new(spec, m)?;
    let (px, mo, bm) = pipeline_opts(who, &o)?;
    let rb = t.0.reference;
    let c = DiameterCalib::from_template(
        &t.0,
        o.req_f64(N_OBJ)?,
        o.f64_or(D_BM_NM, rb.d_nm)?,
        o.f64_or(N_BM, rb.n)?,
        px,
        &mo,
        &bm,
    )
    .map_err(|e| err(who, e))?;
    let mut out = to_map(&c);
    // the largest diameter d = A·√(sens_corr) holds for: the point-dipole sections' domain
    let o = ctx.optics();
    let d_max = crate::analysis::domain::dipole_d_max_nm(c.n_obj, o.wavelength_nm, o.n_medium);
    out.insert("d_max_nm".into(), d_max.into());
    Ok(out)
}

/// `lin_dens_calib(tpl, opts)`: the calibration of linear densities (MDa/µm) from the
/// template's bead model, measured by the data's pixel pipeline (eq. mtLinDens).
fn lin_dens_calib(spec: &Spec, t: &TemplateRef, m: &Map) -> RResult<Map> {
    let who = "lin_dens_calib";
    let o = Opts::new(spec, m)?;
    let (px, mo, bm) = pipeline_opts(who, &o)?;
    let c = LinDensCalib::from_template(
        &t.0,
        o.f64_or(N_OBJ, PROTEIN_N)?,
        o.f64_or(DENSITY_OBJ, LIN_DENS_DENSITY_OBJ_G_CM3)?,
        px,
        &mo,
        &bm,
    )
    .map_err(|e| err(who, e))?;
    Ok(to_map(&c))
}

/// `linear_density(sens_corr, calib)`: a microtubule's linear density (MDa/µm) and the
/// protofilament number it implies (13.75 MDa/µm each; eq. mtLinDens, Sec. 6).
fn linear_density(s: f64, c: &Map) -> RResult<Map> {
    let who = "linear_density";
    let cal = lin_dens_calib_of(who, c)?;
    let mu = cal.linear_density(s).map_err(|e| err(who, e))?;
    let (x, n) = protofilaments(mu).map_err(|e| err(who, e))?;
    let mut m = Map::new();
    m.insert("mu_mda_um".into(), mu.into());
    m.insert("protofilaments".into(), (n as i64).into());
    m.insert("protofilaments_exact".into(), x.into());
    Ok(m)
}

/// The linear-density calibration of the map `lin_dens_calib` returns (`who` names the binding
/// in the error when a key is missing).
fn lin_dens_calib_of(who: &str, c: &Map) -> RResult<LinDensCalib> {
    let get = |k: &str| -> RResult<f64> {
        match c.get(k) {
            Some(v) => num(who, &format!("calib.{k}"), v),
            None => fail(format!(
                "{who}: calib lacks `{k}`: pass the map lin_dens_calib returns"
            )),
        }
    };
    Ok(LinDensCalib {
        mu_bm_mda_um: get("mu_bm_mda_um")?,
        d_bm_nm: get("d_bm_nm")?,
        density_bm: get("density_bm")?,
        sens_bm: get("sens_bm")?,
        n_obj: get("n_obj")?,
        density_obj: get("density_obj")?,
        n_corr: get("n_corr")?,
    })
}

/// `point_mass(obj)`: volume (nm³) and mass (kDa) of a point-like object from its maximum
/// sensitivity, V/V_rb = sens/(n_corr·sens_rb), the reference bead's sensitivity read through
/// the same pipeline (eqs. after nCor).
fn point_mass(spec: &Spec, m: &Map) -> RResult<Map> {
    let who = "point_mass";
    let o = Opts::new(spec, m)?;
    let rb = RefBead::default();
    let tpl = match o.value(TPL_KEY) {
        None => None,
        Some(v) => match v.read_lock::<TemplateRef>() {
            Some(t) => Some(t.clone()),
            None => {
                return fail(format!(
                    "{who}: tpl must be a Template, got {}",
                    v.type_name()
                ))
            }
        },
    };
    let fit = o.bool_or(FIT_WEIGHT, false)?;
    let given = o.f64(SENS_RB)?;
    let n_ways = usize::from(given.is_some()) + usize::from(tpl.is_some()) + usize::from(fit);
    if n_ways > 1 {
        return fail(format!(
            "{who}: give only one of sens_rb, tpl (with the pixel size) and fit_weight: true"
        ));
    }
    let sens_rb = match (given, tpl) {
        (Some(v), _) => v,
        (None, Some(t)) => {
            let px = pixel_of(who, &o)?;
            let base = crate::analysis::MeasureOptions::default();
            let st = stencil_of(who, &o, base.stencil)?;
            let win = pos_f64(who, &o, "window_um", base.window_um, 1e-3, 100.0)?;
            t.0.pipeline_max_sens(px, st, win)
                .map_err(|e| err(who, e))?
        }
        (None, None) if fit => 1.0,
        (None, None) => {
            return fail(format!("{who}: the reference bead's sensitivity is missing: give sens_rb (its max sensitivity through the same pipeline, e.g. tpl.max_sens(pixel_um)), or tpl with pixel_um (or scan), or fit_weight: true for a template-fit weight"));
        }
    };
    let p = point_object(
        o.req_f64(SENS)?,
        o.f64(SENS_ERR)?,
        sens_rb,
        o.f64_or(N_OBJ, rb.n)?,
        o.f64_or(DENSITY, rb.density_g_cm3)?,
        &rb,
    )
    .map_err(|e| err(who, e))?;
    let mut out = to_map(&p);
    out.insert("sens_rb".into(), sens_rb.into());
    Ok(out)
}

/// The float properties of a `FilamentMeasurement`: angle_deg and angle_err_deg (°), factor,
/// mean_corr and std_corr (reference-bead units/µm) and (any other name) sem_corr.
fn filament_float(m: &FilamentRef, name: &str) -> f64 {
    let m = &m.0;
    match name {
        "angle_deg" => m.angle_deg,
        "angle_err_deg" => m.angle_err_deg,
        "factor" => m.factor,
        "mean_corr" => m.mean_corr,
        "std_corr" => m.std_corr,
        _ => m.sem_corr,
    }
}
