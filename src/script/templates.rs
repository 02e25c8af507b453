//! Binding family `templates`: reference-bead templates (from the model or from scans,
//! suppl. S5), the multi-bead fit (eq. multiBeadFit) and its `FitResult`, rendering beads and
//! filaments with a template (the bead model).

use super::ctx::Ctx;
use super::keys::{DENSITY, D_NM, N, PATIENCE, POLARIZATION, SIGMA, SPACING_NM};
use super::registry::{
    binding_list, err, fail, properties, Doc, Opt, Opts, RResult, Registrar, Spec,
};
use super::types::{json_to_dynamic, ImageRef, ScanRef};
use crate::analysis::bead_model::{filament_beads, render_scene};
use crate::analysis::template::{FromScansOptions, DEFAULT_MODEL_H_UM};
use crate::analysis::{
    fit_beads, BeadInit, BeadModelOptions, Channels, FitOptions, GrowCriterion, MeasureOptions,
    RefBead, Stencil, Template,
};
use crate::data::{Image, Scan};
use crate::optics::rayleigh::DetectorModel;
use rhai::{Array, Dynamic, Map};
use std::sync::Arc;

/// A reference template in a script (`Template`).
use super::analysis_values::*;
use super::registry::grid_axes;
use super::types::{FitRef, TemplateRef, TEMPLATE_ARG};

/// The options of this family's bindings, each key written once (`Opt`).
const BEADS_PER_SCAN: Opt = Opt::new("beads_per_scan", "int", "");
const CHANNELS: Opt = Opt::new("channels", "string", "");
const CRITERION: Opt = Opt::new("criterion", "string", "");
const FTOL: Opt = Opt::new("ftol", "float", "");
const GROW: Opt = Opt::new("grow", "bool", "");
const GTOL: Opt = Opt::new("gtol", "float", "");
const H_UM: Opt = Opt::new("h_um", "float", "µm");
const HALF_WIDTH_UM: Opt = Opt::new("half_width_um", "float", "µm");
const ITERATIONS: Opt = Opt::new("iterations", "int", "");
const MAX_BEADS: Opt = Opt::new("max_beads", "int", "");
const MERGE_DEGENERATE: Opt = Opt::new("merge_degenerate", "bool", "");
const MIN_DROP: Opt = Opt::new("min_drop", "float", "");
const MIN_SEPARATION: Opt = Opt::new("min_separation", "float", "");
const N_BEADS: Opt = Opt::new("n_beads", "int", "");
const THRESHOLD: Opt = Opt::new("threshold", "float", "");
const XTOL: Opt = Opt::new("xtol", "float", "");
const Z_UM: Opt = Opt::new("z_um", "float", "µm");
const BEADS: Opt = Opt::new("beads", "array", "");
const FILAMENTS: Opt = Opt::new("filaments", "array", "");
const INIT: Opt = Opt::new("init", "array", "");

binding_list! {
    pub fn register {
        bind_template_model, bind_template_from_scans, bind_render_beads,
        bind_fit_beads, bind_fit_numbers, bind_fit_verdict,
    }
}

// ------------------------------------------------------------------ templates

/// `template_model`: the point-particle template from the model.
fn bind_template_model(r: &mut Registrar) {
    let rb = RefBead::default();
    let d = Doc::func("template_model")
        .opts(&[
                H_UM.doc(format!("optional: node spacing (default {DEFAULT_MODEL_H_UM}; 0.001–0.2)")),
                Z_UM.doc("optional: axial offset of the bead from the focus (default 0)".to_string()),
                D_NM.doc(format!("optional: reference bead diameter (default {})", rb.d_nm)),
                N.doc(format!("optional: reference bead index (default {})", rb.n)),
                DENSITY.doc(format!("optional: reference bead density (default {})", rb.density_g_cm3)),
                POLARIZATION.doc("optional: vector dipole field (default false)".to_string()),
            ],
        )
        .form("template_model() -> Template")
        .returns(
            "Template",
            "normalised so the reference bead's max ∂Sx/∂x = 1",
        )
        .summary("reference template from the physics model in the current optics (Sec. 3.1)")
        .help("In the current optics' beam: with set_optics(#{beam: \"vector\"}) (e.g. set_optics(fit_beam(scan).optics), the beam fitted to your reference bead) the point dipole in the aplanatic vector focus of that pupil filling (always vectorial: polarization is then ignored), else the paper's paraxial model (suppl. S2/S3). angle_curve, diameter_calib, lin_dens_calib and point_mass(#{tpl}) follow the template.")
        .example(&format!("{TPL} t.norm_factor > 0.0"), "true")
        .example("template_model(#{h_um: 5.0})", "error: h_um = 5");
    r.bind_ctx_opts0(d, template_model);
}

/// `template_from_scans` and what a Template shows of itself.
fn bind_template_from_scans(r: &mut Registrar) {
    let rb = RefBead::default();
    let fs = FromScansOptions::default();
    let d = Doc::func("template_from_scans")
        .arg("scans", "array", "", "XY scans of reference beads [Scan, …]")
        .opts(&[
                HALF_WIDTH_UM.doc(format!("optional: half-width of the template (default {})", fs.half_width_um)),
                H_UM.doc("optional: node spacing (default: the finest pixel)".into()),
                BEADS_PER_SCAN.doc("optional: beads per scan (default: all isolated maxima)".into()),
                THRESHOLD.doc(format!("optional: detection threshold, fraction of the largest peak (default {})", fs.threshold)),
                ITERATIONS.doc(format!("optional: alignment iterations (default {})", fs.iterations)),
                D_NM.doc(format!("optional: reference bead diameter (default {})", rb.d_nm)),
                N.doc(format!("optional: reference bead index (default {})", rb.n)),
                DENSITY.doc(format!("optional: density (default {})", rb.density_g_cm3)),
            ],
        )
        .form("template_from_scans(scans) -> Template")
        .returns("Template", "aligned average of the beads, normalised so max ∂Sx/∂x = 1; .source tells the beads used and the misfit")
        .summary("reference template from measured scans of several reference beads: locate, align sub-pixel, average, normalise")
        .example(&format!("{TPL} let a = render_beads(t, #{{beads: [#{{x: 0.03, y: 0.0}}], x: [-2.0, 2.0], y: [-2.0, 2.0], nx: 81, ny: 81}}); let b = render_beads(t, #{{beads: [#{{x: -0.02, y: 0.04}}], x: [-2.0, 2.0], y: [-2.0, 2.0], nx: 81, ny: 81}}); template_from_scans([a, b]).source.n_beads"), "2")
        .example("template_from_scans([])", "error: no scans");
    r.bind_ctx_opts(d, template_from_scans);

    // properties and methods
    properties!(r, "Template", TemplateRef, TPL, [
        norm_factor: "float", "factor applied to the source data so that max ∂Sx/∂x = 1 (reference-bead units per scan unit)"; "normalisation of the template"; "t.norm_factor > 1.0" => "true"; |t| t.0.norm_factor,
        reference: "map", "#{d_nm, n, n_medium, density_g_cm3}"; "the reference bead the template represents"; "t.reference.d_nm" => "110.0"; |t| to_map(&t.0.reference),
        source: "map", "#{kind: \"model\" | \"scans\" | \"analytic\", …} (beads used, misfit)"; "where the template came from"; "t.source.kind" => "\"model\""; |t| to_map(&t.0.source),
        h_um: "float", "node spacing, µm"; "grid spacing of the template"; "t.h_um" => "0.025"; |t| t.0.grid.h,
    ]);
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
        |t: &mut TemplateRef, u: f64, v: f64| template_at(t, u, v),
    );
    r.bind(
        Doc::method("Template", "max_sens")
            .arg("pixel_um", "float", "µm", "pixel size of the scans to be measured")
            .opt("stencil", "string", "", &format!("derivative stencil (default {})", MeasureOptions::default().stencil.name()))
            .returns("float", "max ∂Sx/∂x of the reference bead as the pixel pipeline measures it (≈ 1)")
            .summary("the reference bead's max sensitivity through the measurement pipeline (denominator of masses)")
            .example(&format!("{TPL} let m = t.max_sens(0.05); m > 0.9 && m < 1.0"), "true"),
        |t: &mut TemplateRef, px: f64| template_max_sens(t, px, None),
    );
    r.overload("max_sens", |t: &mut TemplateRef, px: f64, st: &str| {
        template_max_sens(t, px, Some(st))
    });
    r.bind_ctx(
        Doc::method("Template", "save")
            .arg("path", "string", "", "file (JSON; relative: in the session folder; an existing file is kept and a numbered name used)")
            .returns("string", "the path written")
            .summary("save the template (JSON with grid, reference bead, source and the script's provenance)")
            .example(&format!("{TPL} let p = status().data_dir + \"/tpl_example.json\"; t.save(p); load_template(p).h_um"), "0.025"),
        |c| move |t: &mut TemplateRef, path: &str| -> RResult<String> {
            super::console::save_template(&c, t, path, false)
        },
    );
    r.bind(
        Doc::func("load_template")
            .arg("path", "string", "", "a file written by template.save")
            .returns("Template", "")
            .summary("load a saved template")
            .example(
                "load_template(\"no/such/template.json\")",
                "error: load_template: no/such/template.json",
            ),
        |path: &str| load_template(path),
    );
}

/// `render_beads` and `bead_model`: scans and bead models made from a template.
fn bind_render_beads(r: &mut Registrar) {
    let d = Doc::func("render_beads")
        .arg_of(TEMPLATE_ARG)
        .map(
            "what",
            "objects and the grid",
            &[
                BEADS.doc("optional: [#{x, y, weight}] point objects (µm; weight in reference-bead units, default 1)".into()),
                FILAMENTS.doc("optional: [#{points: [[x, y], …], d_nm, n}] bead-model filaments (d_nm: one value or one per vertex)".into()),
                SPACING_NM.doc(format!("optional: bead-model spacing (default {}, Sec. 4.2)", BeadModelOptions::default().spacing_nm)),
                ("x", "array", "µm", "[from, to]".into()),
                ("y", "array", "µm", "[from, to]".into()),
                ("nx", "int", "", "pixels along x".into()),
                ("ny", "int", "", "pixels along y".into()),
            ],
        )
        .returns("Scan", "noise-free scan in the template's instrument units (superposition, eq. ReEEpReEE; × norm_factor gives reference-bead units)")
        .summary("render point objects and filaments from a template (the bead model of Sec. 4.2)")
        .example(&format!("{ONE_BEAD} sc.sx.cols"), "41")
        .example(&format!("{TPL} render_beads(t, #{{filaments: [#{{points: [[0.0, -1.0], [0.0, 1.0]], d_nm: 50.0, n: 1.41}}], x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 21, ny: 21}}).rows"), "21")
        .example(&format!("{TPL} render_beads(t, #{{filaments: [#{{points: [[0.0, 0.0]], d_nm: 50.0, n: 1.41}}], x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 21, ny: 21}})"), "error: ");
    let spec = d.spec();
    r.bind(d, move |t: TemplateRef, m: Map| render_beads(&spec, &t, &m));

    let d = Doc::func("bead_model")
        .arg_of(TEMPLATE_ARG)
        .arg("filament", "map", "", "#{points: [[x, y], …] (µm), d_nm (one or per vertex), n}")
        .opt("spacing_nm", "float", "nm", &format!("bead spacing (default {})", BeadModelOptions::default().spacing_nm))
        .returns("array", "[#{x, y, weight}] the beads (weights in reference-bead units: (3/4)·h·d²·n_corr / d_ref³·… , Sec. 4.2)")
        .summary("the beads of a filament's bead model")
        .example(&format!("{TPL} bead_model(t, #{{points: [[0.0, 0.0], [0.0, 1.0]], d_nm: 110.0, n: 1.572}}, 50.0).len()"), "20");
    r.bind(d, |t: TemplateRef, fm: Map, sp: f64| bead_model(&t, fm, sp));
    r.overload("bead_model", |t: TemplateRef, fm: Map| {
        bead_model(&t, fm, BeadModelOptions::default().spacing_nm)
    });
}

// ------------------------------------------------------------------ fit

/// Default relative RSS drop of the `rel_drop` growth criterion.
const DEFAULT_MIN_DROP: f64 = 0.02;

/// `fit_beads(scan, tpl, [opts])`: its options, declared once with their defaults.
fn bind_fit_beads(r: &mut Registrar) {
    // the defaults in the help come from FitOptions::default(), never repeated here
    let fd = FitOptions::default();
    let keys: Vec<(&str, &str, &str, String)> = vec![
        CHANNELS.doc("optional: \"both\" (default, eq. multiBeadFit), \"sx\", \"sy\"".into()),
        N_BEADS.doc("optional: number of beads for automatic initial guesses from peaks".into()),
        INIT.doc("optional: initial guesses [#{x, y, weight}]".into()),
        GROW.doc("optional: add beads one at a time at the largest residual while the criterion improves (default when neither n_beads nor init)".into()),
        MAX_BEADS.doc(format!("optional: limit when growing (default {})", fd.max_beads)),
        CRITERION.doc("optional: \"bic\" (default) or \"rel_drop\"".into()),
        MIN_DROP.doc(format!("optional: RSS drop needed with criterion rel_drop (default {DEFAULT_MIN_DROP})")),
        SIGMA.doc("optional: pixel noise (default: from the residuals)".into()),
        FTOL.doc(format!("optional: relative tolerance on the objective (default {:e})", fd.ftol)),
        XTOL.doc(format!("optional: relative tolerance on the parameters (default {:e})", fd.xtol)),
        GTOL.doc(format!("optional: gradient tolerance (default {:e})", fd.gtol)),
        PATIENCE.doc(format!("optional: residual evaluations allowed = patience × (3n + 1) (default {})", fd.patience)),
        MIN_SEPARATION.doc(format!("optional: beads closer than this × w0 (set_optics) are degenerate (default {})", fd.min_separation)),
        MERGE_DEGENERATE.doc(format!("optional: merge degenerate pairs and refit (default {})", fd.merge_degenerate)),
        N.doc("optional: refractive index of the beads, for the diameter a weight implies in the size-domain check (default: the template reference's)".into()),
    ];
    let keys_ref: Vec<(&str, &str, &str, &str)> = keys
        .iter()
        .map(|(a, b, c, d)| (*a, *b, *c, d.as_str()))
        .collect();
    let d = Doc::func("fit_beads")
        .arg("scan", "Scan", "", "XY scan (Sx and Sy)")
        .arg_of(TEMPLATE_ARG)
        .opts(&keys_ref)
        .form("fit_beads(scan, tpl) -> FitResult")
        .returns("FitResult", "beads with uncertainties, residual images, χ², status and reason, degeneracies")
        .summary("multi-bead template fit (eq. multiBeadFit) with Levenberg–Marquardt and an analytic Jacobian")
        .example(&format!("{ONE_BEAD} let f = fit_beads(sc, t, #{{n_beads: 1}}); round(f.beads[0].x * 1000.0)"), "100.0")
        .example(&format!("{ONE_BEAD} fit_beads(sc, t, #{{channels: \"sz\"}})"), "error: channels = \"sz\"");
    r.bind_ctx_opts2(d, fit_beads_of);
}

/// The fit's beads and numbers: `FitResult`'s beads, χ², RSS, σ, BIC, condition, counts.
fn bind_fit_numbers(r: &mut Registrar) {
    let fx = format!("{ONE_BEAD} let f = fit_beads(sc, t, #{{n_beads: 1}});");
    properties!(r, "FitResult", FitRef, fx, [
        beads: "array", "[#{x, y, weight, x_err, y_err, weight_err, x_crlb, y_crlb, weight_crlb, found}] (µm, reference-bead units; errors 1σ or () when ill-conditioned; *_crlb: the Cramér–Rao bound of the scan's Sx and Sy pixels at the fit with its σ, or (); found: the weight is significantly positive, weight − 3σ > 0 — a bead not found is noise and its position means nothing)"; "the fitted beads"; "round(f.beads[0].weight * 1000.0)" => "1000.0"; |f| -> Array { f.0.beads.iter().map(bead_map).collect() },
    ]);
    // Noise-free one-bead fixture: σ estimated from the residuals gives χ² = N − p exactly
    // (N = 2·41² residuals, p = 3); with σ given, BIC = χ² + p·ln N with χ² ≈ 0; the scaled
    // columns of JᵀJ are orthogonal by symmetry, so the condition number is 1.
    let sig = format!("{ONE_BEAD} let f = fit_beads(sc, t, #{{n_beads: 1, sigma: 0.001}});");
    let float_rows = [
        ("chi2", "rss / σ²"),
        ("rss", "Σ (data − model)² over the fitted pixels"),
        ("sigma", "pixel noise used (given or estimated)"),
        ("bic", "Bayesian information criterion"),
        ("condition", "condition number of the column-scaled JᵀJ"),
        ("total_weight", "Σ weights (reference-bead units)"),
    ];
    r.named_getters(
        "FitResult",
        "float",
        &float_rows,
        |name| match name {
            "total_weight" => (format!("{fx} round(f.total_weight * 1000.0)"), "1000.0"),
            "chi2" => (format!("{fx} f.chi2"), "3359.0"),
            "rss" => (format!("{fx} f.rss < 1e-20"), "true"),
            "sigma" => (format!("{fx} f.sigma < 1e-15"), "true"),
            "bic" => (
                format!("{sig} abs(f.bic - 3.0 * ln(2.0 * 41.0 * 41.0)) < 1e-9"),
                "true",
            ),
            _ => (format!("{fx} round(f.condition * 1000.0) / 1000.0"), "1.0"),
        },
        fit_float,
    );
    properties!(r, "FitResult", FitRef, fx, [
        n_found: "int", "beads whose weight is significantly positive (weight − 3σ > 0)"; "how many of the fitted beads were found (the others are noise: see beads[i].found)"; "f.n_found" => "1"; |f| -> i64 { (f.0.beads.len() - f.0.not_found().len()) as i64 },
    ]);
    let count_rows = [
        ("dof", "residuals minus parameters"),
        ("iterations", "Jacobian evaluations of the final fit"),
        ("evaluations", "residual evaluations of the final fit"),
        ("n_beads", "number of beads"),
    ];
    let ex = |name: &str| (format!("{fx} f.{name} > 0"), "true");
    r.named_getters("FitResult", "int", &count_rows, ex, fit_count);
}

/// The fit's verdict and images: `FitResult`'s status, warnings, optimiser, history, model
/// and residual images, `subtract`, `to_map`.
fn bind_fit_verdict(r: &mut Registrar) {
    let fx = format!("{ONE_BEAD} let f = fit_beads(sc, t, #{{n_beads: 1}});");
    properties!(r, "FitResult", FitRef, fx, [
        status: "string", "\"ok\" when `warnings` is empty, else \"flagged\""; "whether the answer is inside its domain (docs/analysis.md, Domains)"; "f.status" => "\"ok\""; |f| -> String { crate::analysis::domain::status(&f.0.warnings).to_string() },
        warnings: "array", "[string]: where the answer leaves its domain (a bead not found, outside the template's size domain, near the scan's edge, a model that does not describe the data, degeneracies, clipped or dark pixels among those fitted); empty when positions, weights and σ hold"; "what the answer cannot vouch for"; "f.warnings.len()" => "0"; |f| -> Array { f.0.warnings.iter().map(|w| Dynamic::from(w.clone())).collect() },
        optimizer: "string", "\"converged\", \"max_evaluations\" or \"failed\""; "how the optimiser stopped (see .reason)"; "f.optimizer" => "\"converged\""; |f| -> String { to_dyn(&f.0.status).into_string().unwrap_or_default() },
        reason: "string", "the optimiser's termination reason in words"; "why the fit stopped"; "type_of(f.reason)" => "\"string\""; |f| -> String { f.0.reason.clone() },
        degeneracies: "array", "[#{kind: \"close_beads\" | \"unresolved\" | \"insignificant\" | \"bead_outside\" | \"ill_conditioned\", …}]"; "what the fit could not resolve (empty when well-posed)"; "f.degeneracies.len()" => "0"; |f| -> Array { f.0.degeneracies.iter().map(to_dyn).collect() },
    ]);
    properties!(r, "FitResult", FitRef, ONE_BEAD, [
        history: "array", "[#{n_beads, rss, bic, accepted}] of the bead-adding steps"; "bead-adding history (empty unless growing)"; "fit_beads(sc, t).history.len() >= 2" => "true"; |f| -> Array { f.0.history.iter().map(to_dyn).collect() },
    ]);
    let image_rows = [
        ("model_sx", "model Sx image"),
        ("model_sy", "model Sy image"),
        ("residual_sx", "data − model, Sx"),
        ("residual_sy", "data − model, Sy"),
    ];
    let ex = |name: &str| (format!("{fx} f.{name}.cols"), "41");
    r.named_getters("FitResult", "Image", &image_rows, ex, fit_image);
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
        |f: &mut FitRef, s: ScanRef| subtract(f, &s),
    );
    r.bind(
        Doc::method("FitResult", "to_map")
            .returns("map", "everything but the images")
            .summary("the fit as a map (for printing and saving)")
            .example(&format!("{fx} f.to_map().optimizer"), "\"converged\""),
        |f: &mut FitRef| fit_map(f),
    );
}

/// `template_model([opts])`: the reference bead's response on nodes every h_um (µm) from the
/// point-dipole model in the session's optics, normalised so its max ∂Sx/∂x = 1 (Sec. 3.1).
fn template_model(c: &Ctx, spec: &Spec, m: &Map) -> RResult<TemplateRef> {
    let o = Opts::new(spec, m)?;
    let optics = c.optics();
    let rb = ref_bead("template_model", &o, optics.n_medium)?;
    let det = DetectorModel {
        polarization: o.bool_or(POLARIZATION, false)?,
        ..Default::default()
    };
    let t = Template::from_optics(
        &optics,
        &det,
        rb,
        o.f64_or(H_UM, DEFAULT_MODEL_H_UM)?,
        o.f64_or(Z_UM, 0.0)?,
    )
    .map_err(|e| err("template_model", e))?;
    Ok(TemplateRef(Arc::new(t)))
}

/// `template_from_scans(scans[, opts])`: locate the isolated reference beads in XY scans, align
/// them sub-pixel, average and normalise so max ∂Sx/∂x = 1 (suppl. S5).
fn template_from_scans(c: &Ctx, spec: &Spec, a: &Array, m: &Map) -> RResult<TemplateRef> {
    let o = Opts::new(spec, m)?;
    let n_medium = c.optics().n_medium;
    let rb = ref_bead("template_from_scans", &o, n_medium)?;
    let d = FromScansOptions::default();
    let fo = FromScansOptions {
        half_width_um: o.f64_or(HALF_WIDTH_UM, d.half_width_um)?,
        h_um: o.f64(H_UM)?,
        beads_per_scan: count("template_from_scans", &o, BEADS_PER_SCAN, 1, 10_000)?,
        threshold: o.f64_or(THRESHOLD, d.threshold)?,
        iterations: count("template_from_scans", &o, ITERATIONS, 0, 100)?.unwrap_or(d.iterations),
    };
    let scans = scans_arg("template_from_scans", a)?;
    let refs: Vec<&Scan> = scans.iter().map(|s| s.as_ref()).collect();
    let t = Template::from_scans(&refs, rb, &fo).map_err(|e| err("template_from_scans", e))?;
    Ok(TemplateRef(Arc::new(t)))
}

/// `Template.at(u, v)`: the template's (Sx, Sy, Sz) in reference-bead units at a displacement
/// (u, v) µm from the bead (interpolated).
fn template_at(t: &TemplateRef, u: f64, v: f64) -> Map {
    let s = t.0.eval(u, v);
    let mut m = Map::new();
    m.insert("sx".into(), s[0].into());
    m.insert("sy".into(), s[1].into());
    m.insert("sz".into(), s[2].into());
    m
}

/// `Template.max_sens(pixel_um[, stencil])`: the reference bead's max ∂Sx/∂x as the pixel
/// pipeline measures it at pixel size `pixel_um` (µm), with the measurement's default stencil
/// and parabola window unless a stencil is given.
fn template_max_sens(t: &TemplateRef, px: f64, stencil: Option<&str>) -> RResult<f64> {
    let d = MeasureOptions::default();
    let s = match stencil {
        None => d.stencil,
        Some(st) => Stencil::parse(st).map_or_else(
            || fail(format!("max_sens: stencil = \"{st}\" is not one of \"central2\", \"central5\", \"sg5\", …")),
            Ok,
        )?,
    };
    t.0.pipeline_max_sens(px, s, d.window_um)
        .map_err(|e| err("max_sens", e))
}

/// `load_template(path)`: a template saved by `Template.save` (JSON).
fn load_template(path: &str) -> RResult<TemplateRef> {
    let bytes = std::fs::read(path).map_err(|e| err("load_template", format!("{path}: {e}")))?;
    // a scan file (npz is a zip archive: "PK") or another binary file is named as what it is
    if bytes.starts_with(b"PK") {
        return fail(format!(
            "load_template: {path} is a scan file (npz), not a template: load it with load_scan(path); a template is the JSON file written by template.save or calibrate"
        ));
    }
    let Ok(s) = String::from_utf8(bytes) else {
        return fail(format!(
            "load_template: {path} is not a template (a binary file; a template is the JSON file written by template.save or calibrate)"
        ));
    };
    let t = Template::from_json(&s).map_err(|e| err("load_template", format!("{path}: {e}")))?;
    Ok(TemplateRef(Arc::new(t)))
}

/// `render_beads(tpl, what)`: the noise-free scan of point beads and bead-model filaments by
/// superposition of the template (Sec. 4.2), in the instrument units of the template's source.
fn render_beads(spec: &Spec, t: &TemplateRef, m: &Map) -> RResult<ScanRef> {
    let o = Opts::new(spec, m)?;
    let who = "render_beads";
    let beads = match m.get(BEADS.name) {
        Some(b) => bead_list(who, b)?,
        None => vec![],
    };
    let fils = match m.get(FILAMENTS.name) {
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
        spacing_nm: o.f64_or(SPACING_NM, BeadModelOptions::default().spacing_nm)?,
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
}

/// `bead_model(tpl, filament[, spacing_nm])`: the beads (µm, reference-bead weights) that
/// represent a filament, one every `spacing_nm` nm along it (Sec. 4.2).
fn bead_model(t: &TemplateRef, fm: Map, sp: f64) -> RResult<Array> {
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
}

/// `fit_beads(scan, tpl[, opts])`: Levenberg–Marquardt fit of template copies (positions µm,
/// weights in reference-bead units) to a scan's Sx and Sy (eq. multiBeadFit); the degeneracy
/// and merge distances scale with the session's beam waist.
fn fit_beads_of(c: &Ctx, spec: &Spec, s: &ScanRef, t: &TemplateRef, m: &Map) -> RResult<FitRef> {
    let who = "fit_beads";
    let o = Opts::new(spec, m)?;
    // the degeneracy and merge distances scale with the session's beam waist (set_optics)
    let optics = c.optics();
    let d = FitOptions {
        w0_um: optics.w0_nm / 1000.0,
        wavelength_nm: optics.wavelength_nm,
        ..FitOptions::default()
    };
    let channels = match o.string(CHANNELS)? {
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
    let init = match m.get(INIT.name) {
        None => None,
        Some(v) => Some(
            bead_list(who, v)?
                .into_iter()
                .map(|(x, y, weight)| BeadInit { x, y, weight })
                .collect(),
        ),
    };
    let criterion = match o.string(CRITERION)?.as_deref() {
        None | Some("bic") => GrowCriterion::Bic,
        Some("rel_drop") => GrowCriterion::RelDrop {
            min_drop: o.f64_or(MIN_DROP, DEFAULT_MIN_DROP)?,
        },
        Some(c) => {
            return fail(format!(
                "{who}: criterion = \"{c}\" is not one of \"bic\", \"rel_drop\""
            ))
        }
    };
    let fo = FitOptions {
        channels,
        n_beads: count(who, &o, N_BEADS, 1, 10_000)?,
        init,
        grow: o.bool_or(GROW, d.grow)?,
        max_beads: count(who, &o, MAX_BEADS, 1, 10_000)?.unwrap_or(d.max_beads),
        criterion,
        sigma: o.f64(SIGMA)?,
        ftol: o.f64_or(FTOL, d.ftol)?,
        xtol: o.f64_or(XTOL, d.xtol)?,
        gtol: o.f64_or(GTOL, d.gtol)?,
        patience: count(who, &o, PATIENCE, 1, 1_000_000)?.unwrap_or(d.patience),
        min_separation: o.f64_or(MIN_SEPARATION, d.min_separation)?,
        merge_degenerate: o.bool_or(MERGE_DEGENERATE, d.merge_degenerate)?,
        bead_n: match o.f64(N)? {
            Some(n) => Some(pos_f64(who, &o, N, n, 1.0, 4.0)?),
            None => None,
        },
        ..d
    };
    // clipped or dark pixels among those fitted (`data::clip`): attached to the answer, or
    // a refusal when every pixel of a fitted channel is at the rail (or dark)
    let used: &[&str] = match fo.channels {
        Channels::Both => &["sx", "sy"],
        Channels::Sx => &["sx"],
        Channels::Sy => &["sy"],
    };
    let inputs = input_gate(who, crate::data::clip::input_check(&s.scan, used, None))?;
    let mut r = fit_beads(&s.scan.sx, &s.scan.sy, &t.0, &fo).map_err(|e| err(who, e))?;
    r.warnings.extend(inputs);
    c.warn_all(who, &r.warnings);
    Ok(FitRef(Arc::new(r)))
}

/// `FitResult.subtract(scan)`: the scan minus the fitted model in Sx and Sy (Sz unchanged),
/// the subtracted beads noted in its metadata.
fn subtract(f: &FitRef, s: &ScanRef) -> RResult<ScanRef> {
    let r = &f.0;
    let sx = s.scan.sx.sub(&r.model_sx).map_err(|e| err("subtract", e))?;
    let sy = s.scan.sy.sub(&r.model_sy).map_err(|e| err("subtract", e))?;
    let mut meta = s.scan.meta.clone();
    meta["subtracted_beads"] = serde_json::to_value(&r.beads).unwrap_or_default();
    Ok(scan_flagged(
        sx,
        sy,
        s.scan.sz.clone(),
        meta,
        s.scan.flags.clone(),
    ))
}

/// `FitResult.to_map()`: the fit as a map, without its four images.
fn fit_map(f: &FitRef) -> Map {
    let mut v = serde_json::to_value(&*f.0).unwrap_or_default();
    if let Some(o) = v.as_object_mut() {
        for k in ["model_sx", "model_sy", "residual_sx", "residual_sy"] {
            o.remove(k);
        }
        if let Some(serde_json::Value::Array(bs)) = o.get_mut("beads") {
            for (b, fb) in bs.iter_mut().zip(&f.0.beads) {
                b["found"] = fb.found().into();
            }
        }
        o.insert(
            "n_found".into(),
            (f.0.beads.len() - f.0.not_found().len()).into(),
        );
        o.insert("optimizer".into(), o["status"].clone());
        o.insert(
            "status".into(),
            crate::analysis::domain::status(&f.0.warnings).into(),
        );
    }
    json_to_dynamic(&v).try_cast::<Map>().unwrap_or_default()
}

/// The float properties of a `FitResult`: chi2 = rss/σ², rss, sigma, bic, condition and (any
/// other name) total_weight in reference-bead units.
fn fit_float(f: &FitRef, name: &str) -> f64 {
    let r = &f.0;
    match name {
        "chi2" => r.chi2,
        "rss" => r.rss,
        "sigma" => r.sigma,
        "bic" => r.bic,
        "condition" => r.condition,
        _ => r.total_weight(),
    }
}

/// The integer properties of a `FitResult`: dof, iterations, evaluations and (any other name)
/// the number of beads.
fn fit_count(f: &FitRef, name: &str) -> i64 {
    let r = &f.0;
    (match name {
        "dof" => r.dof,
        "iterations" => r.iterations,
        "evaluations" => r.evaluations,
        _ => r.beads.len(),
    }) as i64
}

/// The image properties of a `FitResult`: model_sx, model_sy, residual_sx and (any other name)
/// residual_sy = data − model.
fn fit_image(f: &FitRef, name: &str) -> ImageRef {
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
}
