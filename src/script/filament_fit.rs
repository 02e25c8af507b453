//! Binding family `filament_fit`: the whole-image fit of a straight bead-model filament
//! (`analysis::filament_fit`), beside the paper's per-row maxima (`measure_filament`).

use super::analysis_values::{count, pos_f64, Key};
use super::ctx::Ctx;
use super::keys::{DENSITY_G_CM3, N, PATIENCE, SIGMA, SPACING_NM};
use super::registry::{err, fail, Doc, Opt, Opts, RResult, Registrar, Spec};
use super::types::{ScanRef, TemplateRef, TEMPLATE_ARG};
use crate::analysis::domain::{dipole_d_max_nm, status};
use crate::analysis::filament_fit::{
    fit_line_filament, volume_per_um, LineFitOptions, LineFitResult,
};
use crate::analysis::quantities::{PROTEIN_DENSITY_G_CM3, PROTEIN_N};
use crate::analysis::scaling::mass_kda;
use crate::analysis::template::Template;
use rhai::{Array, Dynamic, Map};

/// The options of this family's bindings, each key written once (`Opt`).
const SEARCH_STEP_DEG: Opt = Opt::new("search_step_deg", "float", "°");
const TOL: Opt = Opt::new("tol", "float", "");

/// A noisy microtubule-like filament (110 nm polystyrene-like rod, n = 1.572) at 10 ms per pixel.
const FIL_EX: &str = "let t = template_model(#{h_um: 0.025}); let s = scene(); s.add_filament(#{points: [[-0.5, -3.0], [0.5, 3.0]], d_nm: 110.0, n: 1.572}); s.effects([\"detector_noise\"]); let sc = simulate(s, #{x: [-1.5, 1.5], y: [-1.5, 1.5], nx: 41, ny: 41, n_samples: 1000}); let f = fit_filament(sc, t, #{n: 1.572});";

fn keys() -> Vec<Key> {
    let d = LineFitOptions::default();
    vec![
        N.doc(format!("optional: the filament's refractive index, for μ and the diameter (default {PROTEIN_N}, protein)")),
        DENSITY_G_CM3.doc(format!("optional: its density, for μ (default {:.3}, protein 1/0.745)", PROTEIN_DENSITY_G_CM3)),
        SIGMA.doc("optional: pixel noise σ in the scan's units (default: estimated from the residuals)".into()),
        SPACING_NM.doc(format!("optional: bead-model section spacing (default {}, the paper's)", d.spacing_um * 1000.0)),
        SEARCH_STEP_DEG.doc(format!("optional: angle step of the start search (default {})", d.search_step_deg)),
        TOL.doc(format!("optional: solver tolerance on the cost, step and gradient (default {:e})", d.tol)),
        PATIENCE.doc(format!("optional: solver evaluation budget (default {})", d.patience)),
    ]
}

pub fn register(r: &mut Registrar) {
    let keys = keys();
    let d = Doc::func("fit_filament")
        .arg("scan", "Scan", "", "XY scan of one straight filament crossing it (Sx and Sy)")
        .arg_of(TEMPLATE_ARG)
        .opts(&keys)
        .form("fit_filament(scan, tpl) -> map")
        .returns("map", "#{angle_deg, angle_err_deg, angle_crlb_deg, offset_um, offset_err_um, offset_crlb_um, foot: [x, y], lambda_per_um, lambda_err_per_um, lambda_crlb_per_um, mu_mda_um, mu_err_mda_um, mu_crlb_mda_um, diameter_nm, diameter_err_nm, diameter_crlb_nm, background: [sx, sy], sigma, sigma_estimated, pixel_noise, chi2, n_residuals, iterations, optimizer, reason, warnings, status} — angles in degrees from the QPD +y axis towards +x, offset and foot in µm (the axis passes through foot, offset from the scan's centre along (cos θ, −sin θ)), λ in reference-bead units per µm, μ in MDa/µm, diameter in nm; *_err: 1σ from the fit's covariance; *_crlb: the Cramér–Rao bound of the scan's pixels at the fit with its σ")
        .summary("whole-image fit of a straight bead-model filament: angle, offset, linear density and diameter with σ and their Cramér–Rao bounds")
        .help(&format!("The bead-model filament (Sec. 4.2: sections every spacing_nm along the axis, each the template's reference bead times λ·h) plus a background per channel, fitted to every pixel of Sx and Sy by the project's Levenberg–Marquardt from a matched-filter search over angle and offset. Beside measure_filament (the paper's per-row maxima), not instead of it: it uses all the pixels, so its σ sits at the Cramér–Rao bound (200 simulated microtubules at 10 ms: scatter/CRLB 1.01 for λ) and it finds filaments the per-row maxima miss at short dwells. μ = ρ·λ·V_ref/n_corr (eq. mtLinDens), diameter √(4V/π) of a cylinder (eq. colDiam). Domain (warnings, status \"flagged\"): one straight filament of uniform diameter whose ends lie outside the scan, residuals within {}× the residuals' own pixel noise (from their first differences; 5 standard errors of that ratio for small images, e.g. 1.3× for a 25×10 strip), λ at least {}σ above zero, the diameter inside the point dipole's domain, a converged fit. Refused: a scan that is not XY, no line correlating positively with the data, a fitted λ ≤ 0.", crate::analysis::filament_fit::MISFIT_RATIO, crate::analysis::filament_fit::DETECT_SIGMAS))
        .example(&format!("{FIL_EX} round(f.angle_deg)"), "9.0")
        .example(&format!("{FIL_EX} round(f.diameter_nm / 10.0)"), "11.0")
        .example(&format!("{FIL_EX} f.status"), "\"ok\"")
        .example(&format!("{FIL_EX} f.lambda_err_per_um / f.lambda_crlb_per_um < 1.05 && f.lambda_crlb_per_um > 0.0"), "true")
        .example("let t = template_model(#{h_um: 0.025}); let s = scene(); s.add_filament(#{points: [[-0.5, -3.0], [0.5, 3.0]], d_nm: 110.0, n: 1.572}); s.add_bead(#{x: 0.8, y: -0.6, d_nm: 110.0}); let sc = simulate(s, #{x: [-1.5, 1.5], y: [-1.5, 1.5], nx: 41, ny: 41}); let f = fit_filament(sc, t); f.warnings[0].starts_with(\"misfit\")", "true")
        .example(&format!("{FIL_EX} fit_filament(sc, t, #{{spacing_nm: 0.0}})"), "error: fit_filament: spacing_nm = 0")
        .example(&format!("{FIL_EX} fit_filament(sc, t, #{{n: 1.2}})"), "error: fit_filament: n = 1.2");
    r.bind_ctx_opts2(d, fit_filament_of);
}

/// `fit_filament(scan, tpl[, opts])`: see the declaration's help.
fn fit_filament_of(c: &Ctx, spec: &Spec, s: &ScanRef, t: &TemplateRef, m: &Map) -> RResult<Map> {
    let who = "fit_filament";
    let o = Opts::new(spec, m)?;
    let d = LineFitOptions::default();
    let n_medium = t.0.reference.n_medium;
    let n = o.f64_or(N, PROTEIN_N)?;
    if !(n > n_medium && n <= 4.0) {
        return fail(format!(
            "{who}: n = {n} is out of range: the medium's {n_medium} < n ≤ 4 (a filament without contrast has no linear density)"
        ));
    }
    let rho = pos_f64(who, &o, DENSITY_G_CM3, PROTEIN_DENSITY_G_CM3, 0.1, 25.0)?;
    let sigma = match o.f64(SIGMA)? {
        None => None,
        Some(v) if v > 0.0 && v.is_finite() => Some(v),
        Some(v) => return fail(format!("{who}: sigma = {v} is out of range: σ > 0")),
    };
    let spacing_nm = o.f64_or(SPACING_NM, d.spacing_um * 1000.0)?;
    if !(1.0..=500.0).contains(&spacing_nm) {
        return fail(format!(
            "{who}: spacing_nm = {spacing_nm} is out of range: 1 ≤ spacing_nm ≤ 500"
        ));
    }
    let opts = LineFitOptions {
        sigma,
        spacing_um: spacing_nm / 1000.0,
        search_step_deg: pos_f64(who, &o, SEARCH_STEP_DEG, d.search_step_deg, 0.1, 45.0)?,
        tol: pos_f64(who, &o, TOL, d.tol, 0.0, 1e-2)?,
        patience: count(who, &o, PATIENCE, 1, 1_000_000)?.unwrap_or(d.patience),
    };
    let r =
        fit_line_filament(&s.scan.sx, &s.scan.sy, &t.0, None, &opts).map_err(|e| err(who, e))?;
    if r.filament.lambda.is_nan() || r.filament.lambda <= 0.0 {
        return fail(format!(
            "{who}: no filament: the fitted weight per length λ = {} is not positive",
            r.filament.lambda
        ));
    }
    let mut warnings = r.warnings.clone();
    warnings.extend(crate::data::clip::input_check(&s.scan, &["sx", "sy"], None).warnings);
    let out = result_map(&t.0, &r, n, rho, c, &mut warnings).map_err(|e| err(who, e))?;
    c.warn_all(who, &warnings);
    Ok(finish(out, warnings))
}

fn finish(mut out: Map, warnings: Vec<String>) -> Map {
    out.insert("status".into(), status(&warnings).into());
    out.insert(
        "warnings".into(),
        Dynamic::from_array(warnings.into_iter().map(Dynamic::from).collect::<Array>()),
    );
    out
}

/// The script's map of a line fit: values, 1σ, bounds, μ and diameter at index `n` and
/// density `rho`; the diameter's dipole domain appended to `warnings`.
fn result_map(
    tpl: &Template,
    r: &LineFitResult,
    n: f64,
    rho: f64,
    c: &Ctx,
    warnings: &mut Vec<String>,
) -> crate::analysis::Result<Map> {
    let f = &r.filament;
    let v = volume_per_um(tpl, f.lambda, n)?; // nm³ per µm
    let mu = mass_kda(v, rho) / 1000.0;
    let dia = (4.0 * v / (std::f64::consts::PI * 1000.0)).sqrt();
    let optics = c.optics();
    let dmax = dipole_d_max_nm(n, optics.wavelength_nm, optics.n_medium);
    if dia > dmax {
        warnings.push(format!(
            "diameter {dia:.0} nm is beyond the point-dipole sections' domain (≤ {dmax:.0} nm at n = {n}): λ and μ are biased"
        ));
    }
    let mut m = Map::new();
    let mut put = |k: &str, v: f64| {
        m.insert(k.into(), v.into());
    };
    put("angle_deg", f.angle_deg);
    put("angle_err_deg", r.err.angle_deg);
    put("angle_crlb_deg", r.crlb.angle_deg);
    put("offset_um", f.offset_um);
    put("offset_err_um", r.err.offset_um);
    put("offset_crlb_um", r.crlb.offset_um);
    put("lambda_per_um", f.lambda);
    put("lambda_err_per_um", r.err.lambda);
    put("lambda_crlb_per_um", r.crlb.lambda);
    put("mu_mda_um", mu);
    put("mu_err_mda_um", mu * r.err.lambda_rel);
    put("mu_crlb_mda_um", mu * r.crlb.lambda_rel);
    put("diameter_nm", dia);
    put("diameter_err_nm", dia * r.err.diameter_rel);
    put("diameter_crlb_nm", dia * r.crlb.diameter_rel);
    put("sigma", r.sigma);
    put("pixel_noise", r.pixel_noise);
    put("chi2", r.rss / (r.sigma * r.sigma));
    let foot = f.foot();
    let arr = |a: [f64; 2]| Dynamic::from_array(vec![a[0].into(), a[1].into()]);
    m.insert("foot".into(), arr(foot));
    m.insert("background".into(), arr(f.background));
    m.insert("sigma_estimated".into(), r.sigma_estimated.into());
    m.insert("n_residuals".into(), (r.n_residuals as i64).into());
    m.insert("iterations".into(), (r.iterations as i64).into());
    let opt = serde_json::to_value(r.status)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_default();
    m.insert("optimizer".into(), opt.into());
    m.insert("reason".into(), r.reason.clone().into());
    Ok(m)
}
