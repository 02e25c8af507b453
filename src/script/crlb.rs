//! Binding family `crlb`: the information limit of a scan before it is taken — the Cramér–Rao
//! bounds of a planned XY raster of a scene (`analysis::crlb`, `analysis::filament_fit`).

use super::ctx::Ctx;
use super::keys::DWELL;
use super::registry::{err, fail, fields_map, Doc, Opts, RResult, Registrar, Spec};
use super::scene::SceneRef;
use crate::analysis::crlb::{beads_crlb, pixel_sigma};
use crate::analysis::filament_fit::{lambda_of_diameter, line_crlb, volume_per_um, LineFilament};
use crate::analysis::fit::BeadInit;
use crate::analysis::quantities::{mass_resolution_kda, PROTEIN_DENSITY_G_CM3};
use crate::analysis::scaling::mass_kda;
use crate::analysis::template::{RefBead, Template, DEFAULT_MODEL_H_UM};
use crate::instrument::sim::scene::DiameterProfile;
use crate::optics::rayleigh::{alpha_um3, DetectorModel};
use rhai::{Array, Dynamic, Map};

pub fn register(r: &mut Registrar) {
    let keys: &[(&str, &str, &str, &str)] = &[
        ("x", "array", "µm", "[from, to] (stage = scene coordinates)"),
        ("y", "array", "µm", "[from, to]"),
        ("nx", "int", "", "pixels along x"),
        ("ny", "int", "", "pixels along y"),
        DWELL.doc("optional: dwell per pixel (default 0.01, as scan_xy)"),
    ];
    const SC: &str = "let s = scene(); s.add_bead(#{x: 0.0, y: 0.0, d_nm: 110.0}); s.effects([\"detector_noise\"]);";
    const PLAN: &str = "#{x: [-1.6, 1.55], y: [-1.6, 1.55], nx: 64, ny: 64, dwell: 0.01}";
    let d = Doc::func("crlb")
        .map("plan", "the XY raster as scan_xy takes it", keys)
        .arg("scene", "Scene", "", "what the scan will see; its detector_noise sets the noise")
        .form("crlb(plan, scene) -> map")
        .returns("map", "#{sigma_pixel, beads: [#{x, y, weight, x_crlb, y_crlb, weight_crlb, mass_crlb_kda}], filaments: [#{angle_deg, angle_crlb_deg, offset_crlb_um, lin_dens_rel, mu_crlb_mda_um, diameter_crlb_nm}], notes}")
        .summary("the best 1σ a planned XY scan can give: Cramér–Rao bounds of the scene's beads and straight filaments")
        .help("Before spending the scan time: the Fisher information of the plan's pixels (Sx and Sy, white detector noise σ_s/√(dwell·100 kHz) from the scene's detector_noise) about each estimator that applies — beads: x, y and weight of the template model (all beads jointly; mass_crlb_kda at the reference bead's density 1.05 g/cm³ and the bead's index), straight filaments: angle, offset and weight per length of the bead model (lin_dens_rel = σ_μ/μ, mu at protein density 1/0.745 g/cm³, diameter half as relative). The model is the session optics' point-dipole template (110 nm polystyrene reference, 20 nm grid, z = 0). No estimator does better; a good one reaches it (fit_beads: beads[i].weight_crlb; measure_filament: m.crlb). Other noise effects (laser power, pointing, drift) are not in the bound: notes says so.")
        .example(&format!("{SC} let b = crlb({PLAN}, s); b.beads[0].mass_crlb_kda > 600.0 && b.beads[0].mass_crlb_kda < 950.0"), "true")
        .example(&format!("{SC} let a = crlb({PLAN}, s).beads[0].weight_crlb; let b = crlb(#{{x: [-1.6, 1.55], y: [-1.6, 1.55], nx: 64, ny: 64, dwell: 0.04}}, s).beads[0].weight_crlb; round(a / b * 100.0)"), "200.0")
        .example("let s = scene(); s.add_bead(#{x: 0.0, y: 0.0, d_nm: 110.0}); crlb(#{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 21, ny: 21}, s)", "error: crlb: the scene has no detector_noise")
        .example(&format!("{SC} crlb(#{{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 21, ny: 21, dwell: -1.0}}, s)"), "error: crlb: dwell = -1");
    let spec = d.spec();
    r.bind_ctx(d, move |c| {
        let spec = spec.clone();
        move |m: Map, s: SceneRef| crlb_of(&c, &spec, &m, &s)
    });
}

/// `crlb(plan, scene)`: see the declaration's help.
fn crlb_of(c: &Ctx, spec: &Spec, m: &Map, s: &SceneRef) -> RResult<Map> {
    let who = "crlb";
    let o = Opts::new(spec, m)?;
    let (xs, ys) = super::registry::grid_axes(who, &o)?;
    let dwell = o.f64_or(DWELL, crate::acquire::plan::DEFAULT_DWELL_S)?;
    if !(dwell.is_finite() && dwell > 0.0 && dwell <= crate::acquire::plan::MAX_DWELL_S) {
        return fail(format!(
            "{who}: dwell = {dwell} is out of range: 0 < dwell ≤ {} s",
            crate::acquire::plan::MAX_DWELL_S
        ));
    }
    let scene = &s.0;
    let Some(noise) = scene.effects.detector_noise else {
        return fail(format!("{who}: the scene has no detector_noise: without noise there is no bound (s.effects([\"detector_noise\"]))"));
    };
    let rate = crate::instrument::sim::SimConfig::default().sample_rate;
    let sigma = pixel_sigma(noise.sigma_sample, dwell, rate).map_err(|e| err(who, e))?;
    if sigma == 0.0 {
        return fail(format!(
            "{who}: detector_noise sigma_sample = 0: noise-free data have no bound"
        ));
    }
    let optics = c.optics();
    let rb = RefBead {
        n_medium: optics.n_medium,
        ..RefBead::default()
    };
    let det = DetectorModel {
        polarization: scene.effects.polarization == Some(true),
        misalignment: scene.effects.misalignment,
    };
    let tpl = Template::from_optics(&optics, &det, rb, DEFAULT_MODEL_H_UM, 0.0)
        .map_err(|e| err(who, e))?;
    let sig = |_: usize, _: usize, _: usize| Some(sigma);
    let mut notes = Array::new();
    for (name, on) in [
        (
            "laser_power_noise",
            scene.effects.laser_power_noise.is_some(),
        ),
        ("pointing_noise", scene.effects.pointing_noise.is_some()),
        ("drift", scene.effects.drift.is_some()),
        ("thermal_motion", scene.effects.thermal_motion.is_some()),
    ] {
        if on {
            notes.push(format!("{name} is not in the bound (white detector noise only): the bound is lower than what the scan can reach").into());
        }
    }
    if !scene.aggregates.is_empty() {
        notes.push("aggregates are not estimated (their signal is ignored)".into());
    }
    // beads: the template model, all beads jointly
    let alpha_ref = alpha_um3(rb.d_nm, rb.n, rb.n_medium);
    let init: Vec<BeadInit> = scene
        .beads
        .iter()
        .map(|b| BeadInit {
            x: b.pos[0],
            y: b.pos[1],
            weight: alpha_um3(b.d_nm, b.n, optics.n_medium) / alpha_ref,
        })
        .collect();
    let mut beads = Array::new();
    if !init.is_empty() {
        if scene.beads.iter().any(|b| b.pos[2] != 0.0) {
            notes.push("beads off the focal plane are bounded with the in-focus template".into());
        }
        let b = beads_crlb(&tpl, &init, &xs, &ys, &[0, 1], &sig).map_err(|e| err(who, e))?;
        for ((bi, bd), sb) in init.iter().zip(b).zip(&scene.beads) {
            let mut m = fields_map!(bi; x, y, weight);
            m.insert("x_crlb".into(), bd.x.into());
            m.insert("y_crlb".into(), bd.y.into());
            m.insert("weight_crlb".into(), bd.weight.into());
            let mass = mass_resolution_kda(bd.weight, sb.n, rb.density_g_cm3, &rb)
                .map_err(|e| err(who, e))?;
            m.insert("mass_crlb_kda".into(), mass.into());
            beads.push(m.into());
        }
    }
    // straight uniform filaments: the bead-model line
    let mut fils = Array::new();
    for (i, f) in scene.filaments.iter().enumerate() {
        let DiameterProfile::Constant { d_nm } = f.profile else {
            notes.push(format!("filament {i}: not of constant diameter; not bounded").into());
            continue;
        };
        if f.points.len() != 2 {
            notes.push(format!("filament {i}: not straight (2 points); not bounded").into());
            continue;
        }
        let (a, b) = (f.points[0], f.points[1]);
        let angle = (b[0] - a[0]).atan2(b[1] - a[1]).to_degrees();
        let angle = if angle > 90.0 {
            angle - 180.0
        } else if angle <= -90.0 {
            angle + 180.0
        } else {
            angle
        };
        let lambda = lambda_of_diameter(&tpl, d_nm, f.n).map_err(|e| err(who, e))?;
        let line = LineFilament {
            centre: [0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1])],
            offset_um: 0.0,
            angle_deg: angle,
            lambda,
            background: [0.0, 0.0],
            spacing_um: 0.05,
        };
        let bd = line_crlb(&tpl, &line, &xs, &ys, &[0, 1], &sig).map_err(|e| err(who, e))?;
        let v = volume_per_um(&tpl, lambda, f.n).map_err(|e| err(who, e))?;
        let mu = mass_kda(v, PROTEIN_DENSITY_G_CM3) / 1000.0;
        let mut m = Map::new();
        m.insert("angle_deg".into(), angle.into());
        m.insert("angle_crlb_deg".into(), bd.angle_deg.into());
        m.insert("offset_crlb_um".into(), bd.offset_um.into());
        m.insert("lin_dens_rel".into(), bd.lambda_rel.into());
        m.insert("mu_mda_um".into(), mu.into());
        m.insert("mu_crlb_mda_um".into(), (bd.lambda_rel * mu).into());
        m.insert("diameter_crlb_nm".into(), (bd.diameter_rel * d_nm).into());
        fils.push(m.into());
    }
    let mut out = Map::new();
    out.insert("sigma_pixel".into(), sigma.into());
    out.insert("dwell_s".into(), dwell.into());
    out.insert("beads".into(), Dynamic::from_array(beads));
    out.insert("filaments".into(), Dynamic::from_array(fils));
    out.insert("notes".into(), Dynamic::from_array(notes));
    Ok(out)
}
