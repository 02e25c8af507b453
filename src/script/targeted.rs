//! Binding family `targeted`: the Rust helpers of the targeted protocols (`stdlib/targeted.rhai`)
//! — one bead fitted to readings at arbitrary points, and the pattern of points where one
//! reading carries the most information about it (`analysis::point_fit`).

use super::analysis_values::pos_f64;
use super::keys::{DENSITY_G_CM3, N, SIGMA, WEIGHT, X, Y};
use super::registry::{err, fail, num, Doc, Opt, Opts, RResult, Registrar, Spec};
use super::types::{TemplateRef, TEMPLATE_ARG};
use crate::analysis::point_fit::{design_points, fit_bead_points, PointReading};
use crate::analysis::quantities::{mass_resolution_kda, point_object};
use crate::analysis::template::RefBead;
use rhai::{Array, Dynamic, Map};

/// The options of this family's bindings, each key written once (`Opt`).
const BACKGROUND: Opt = Opt::new("background", "bool", "");

const PTS_EX: &str = "let t = template_model(#{h_um: 0.025}); let k = 1.2 / t.norm_factor; let pts = []; for p in bead_design(t, #{x: 0.0, y: 0.0}) { for d in [[0.0, 0.0], [0.05, -0.05]] { let r = t.at(p[0] + d[0] - 0.02, p[1] + d[1] + 0.01); pts.push(#{x: p[0] + d[0], y: p[1] + d[1], sx: k * r.sx, sy: k * r.sy}); } }";

pub fn register(r: &mut Registrar) {
    let d = Doc::func("bead_design")
        .arg_of(TEMPLATE_ARG)
        .map(
            "at",
            "where the bead is",
            &[
                X.doc("the bead's x (stage)"),
                Y.doc("the bead's y (stage)"),
            ],
        )
        .form("bead_design(tpl, #{x, y}) -> array")
        .returns("array", "[[x, y], ...] µm: the four stage points of the cross (x ± r_x, y), (x, y ± r_y)")
        .summary("where to read a located bead: the points at which one reading tells most about its weight")
        .help("r_x is where |Sx| of the template peaks along x, r_y where |Sy| peaks along y (analysis::point_fit::design_radius). On the x arm Sx carries the weight and Sy the y position (∂Sy/∂y); on the y arm Sy carries the weight and Sx the x position; the two ends of each arm cancel a constant background. targeted::bead reads these points and re-centres them on its estimate.")
        .example("let t = template_model(#{h_um: 0.025}); let p = bead_design(t, #{x: 1.0, y: 2.0}); [p.len(), p[0][1], p[2][0]]", "[4, 2.0, 1.0]")
        .example("let t = template_model(#{h_um: 0.025}); let p = bead_design(t, #{x: 0.0, y: 0.0}); p[1][0] > 0.1 && p[1][0] < 0.4", "true")
        .example("let t = template_model(#{h_um: 0.025}); bead_design(t, #{x: 0.0})", "error: bead_design: missing key `y`");
    let spec = d.spec();
    r.bind(d, move |t: TemplateRef, m: Map| {
        bead_design_of(&spec, &t, &m)
    });

    let keys: &[(&str, &str, &str, &str)] = &[
        X.doc("start: the bead's x"),
        Y.doc("start: the bead's y"),
        WEIGHT.doc("optional start weight, reference-bead units (default 1)"),
        SIGMA
            .doc("optional: the readings' noise in the scan's units (default: from the residuals)"),
        BACKGROUND.doc("optional: fit a constant per channel (default true)"),
        N.doc("optional: the bead's refractive index, for the mass (default 1.572, polystyrene)"),
        DENSITY_G_CM3.doc("optional: its density, for the mass (default 1.05)"),
    ];
    let d = Doc::func("fit_bead_points")
        .arg("points", "array", "", "readings: [#{x, y, sx, sy}] — stage position (µm) and the Sx, Sy read there")
        .arg_of(TEMPLATE_ARG)
        .map("opts", "start and options", keys)
        .form("fit_bead_points(points, tpl, #{x, y}) -> map")
        .returns("map", "#{x, y, weight, x_err, y_err, weight_err, x_crlb, y_crlb, weight_crlb, mass_kda, mass_err_kda, mass_crlb_kda, background: [sx, sy], sigma, sigma_estimated, n_points, optimizer, warnings, status} — µm, reference-bead units, kDa; *_crlb: the Cramér–Rao bound of these readings at the fit with σ")
        .summary("one bead's position and weight from readings at arbitrary stage points (the template model of fit_beads)")
        .help("Least squares of (w/f)·T(p − b) + background over the Sx and Sy readings (the project's Levenberg–Marquardt); 1σ from the covariance, the Cramér–Rao bound of the same points beside it. Mass: w/n_corr times the reference bead's mass (Sec. 3.2). Warnings: a fit that did not converge; a weight not 3σ above zero; σ estimated from fewer than 10 residual degrees of freedom (give sigma).")
        .example(&format!("{PTS_EX} let f = fit_bead_points(pts, t, #{{x: 0.0, y: 0.0, sigma: 1e-4}}); [round(f.x * 1000.0), round(f.y * 1000.0), round(f.weight * 100.0)]"), "[20.0, -10.0, 120.0]")
        .example(&format!("{PTS_EX} let f = fit_bead_points(pts, t, #{{x: 0.0, y: 0.0, sigma: 1e-4}}); round(f.weight_err / f.weight_crlb * 1000.0) / 1000.0"), "1.0")
        .example(&format!("{PTS_EX} fit_bead_points(pts, t, #{{x: 0.0, y: 0.0, sigma: 0.0}})"), "error: fit_bead_points: sigma = 0")
        .example(&format!("{PTS_EX} fit_bead_points([#{{x: 0.0, y: 0.0, sx: 1.0}}], t, #{{x: 0.0, y: 0.0}})"), "error: fit_bead_points: points[0] has no `sy`");
    let spec = d.spec();
    r.bind(d, move |p: Array, t: TemplateRef, m: Map| {
        fit_bead_points_of(&spec, &p, &t, &m)
    });
}

/// `bead_design(tpl, #{x, y})`: see the declaration's help.
fn bead_design_of(spec: &Spec, t: &TemplateRef, m: &Map) -> RResult<Array> {
    let who = "bead_design";
    let o = Opts::new(spec, m)?;
    let (x, y) = (o.req_f64(X)?, o.req_f64(Y)?);
    let pts = design_points(&t.0, x, y).map_err(|e| err(who, e))?;
    Ok(pts
        .into_iter()
        .map(|p| Dynamic::from_array(vec![p[0].into(), p[1].into()]))
        .collect())
}

/// The readings of a points array: each a map with x, y, sx, sy.
fn readings(who: &str, pts: &Array) -> RResult<Vec<PointReading>> {
    let mut out = Vec::with_capacity(pts.len());
    for (i, p) in pts.iter().enumerate() {
        let Some(m) = p.read_lock::<Map>() else {
            return fail(format!(
                "{who}: points[{i}] is a {}; each reading is #{{x, y, sx, sy}}",
                p.type_name()
            ));
        };
        let mut v = [0.0; 4];
        for (k, key) in ["x", "y", "sx", "sy"].iter().enumerate() {
            let Some(d) = m.get(*key) else {
                return fail(format!(
                    "{who}: points[{i}] has no `{key}`; each reading is #{{x, y, sx, sy}}"
                ));
            };
            v[k] = num(who, &format!("points[{i}].{key}"), d)?;
        }
        out.push(PointReading {
            x: v[0],
            y: v[1],
            sx: v[2],
            sy: v[3],
        });
    }
    Ok(out)
}

/// `fit_bead_points(points, tpl, #{x, y, ...})`: see the declaration's help.
fn fit_bead_points_of(spec: &Spec, pts: &Array, t: &TemplateRef, m: &Map) -> RResult<Map> {
    let who = "fit_bead_points";
    let o = Opts::new(spec, m)?;
    let rd = readings(who, pts)?;
    let start = [o.req_f64(X)?, o.req_f64(Y)?, o.f64_or(WEIGHT, 1.0)?];
    let sigma = match o.f64(SIGMA)? {
        None => None,
        Some(s) if s > 0.0 && s.is_finite() => Some(s),
        Some(s) => return fail(format!("{who}: sigma = {s} is out of range: σ > 0")),
    };
    let background = o.bool_or(BACKGROUND, true)?;
    let rb = RefBead {
        n_medium: t.0.reference.n_medium,
        ..RefBead::default()
    };
    let n = o.f64_or(N, rb.n)?;
    if !(1.0..=4.0).contains(&n) || (n - rb.n_medium).abs() < 1e-9 {
        return fail(format!(
            "{who}: n = {n} is out of range: 1 ≤ n ≤ 4, n ≠ the medium's {}",
            rb.n_medium
        ));
    }
    let rho = pos_f64(who, &o, DENSITY_G_CM3, rb.density_g_cm3, 0.1, 25.0)?;
    let f = fit_bead_points(&t.0, &rd, start, sigma, background).map_err(|e| err(who, e))?;
    let mut warnings: Vec<String> = vec![];
    if f.status != crate::analysis::fit::FitStatus::Converged {
        warnings.push(format!("the fit did not converge: {}", f.reason));
    }
    if f.weight.is_nan() || f.weight <= 3.0 * f.err[2] {
        warnings.push(format!(
            "no bead: the weight {:.4} is not 3σ ({:.4}) above zero",
            f.weight, f.err[2]
        ));
    }
    let np = if background { 5 } else { 3 };
    if f.sigma_estimated && f.n_residuals < np + 10 {
        warnings.push(format!(
            "σ estimated from {} residual degrees of freedom: its error bars are rough (give sigma)",
            f.n_residuals.saturating_sub(np)
        ));
    }
    let po = point_object(f.weight, None, 1.0, n, rho, &rb).map_err(|e| err(who, e))?;
    let mass_crlb = mass_resolution_kda(f.crlb[2], n, rho, &rb).map_err(|e| err(who, e))?;
    let mut out = Map::new();
    let mut put = |k: &str, v: f64| {
        out.insert(k.into(), v.into());
    };
    put("x", f.x);
    put("y", f.y);
    put("weight", f.weight);
    put("x_err", f.err[0]);
    put("y_err", f.err[1]);
    put("weight_err", f.err[2]);
    put("x_crlb", f.crlb[0]);
    put("y_crlb", f.crlb[1]);
    put("weight_crlb", f.crlb[2]);
    put("mass_kda", po.mass_kda);
    put(
        "mass_err_kda",
        mass_resolution_kda(f.err[2], n, rho, &rb).map_err(|e| err(who, e))?,
    );
    put("mass_crlb_kda", mass_crlb);
    put("sigma", f.sigma);
    out.insert(
        "background".into(),
        Dynamic::from_array(vec![f.background[0].into(), f.background[1].into()]),
    );
    out.insert("sigma_estimated".into(), f.sigma_estimated.into());
    out.insert("n_points".into(), (rd.len() as i64).into());
    let opt = serde_json::to_value(f.status)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_default();
    out.insert("optimizer".into(), opt.into());
    out.insert(
        "status".into(),
        crate::analysis::domain::status(&warnings).into(),
    );
    out.insert(
        "warnings".into(),
        Dynamic::from_array(warnings.into_iter().map(Dynamic::from).collect()),
    );
    Ok(out)
}
