//! Binding family `focus_crlb`: the Cramér–Rao bound of the best focus of an XZ/YZ scan
//! (`analysis::focus_crlb`), with the unit response rendered by the simulator's renderer in the
//! session's beam.

use super::ctx::Ctx;
use super::keys::{SIGMA, WEIGHT};
use super::registry::{err, fail, Doc, Opt, Opts, RResult, Registrar, Spec};
use super::types::ScanRef;
use crate::analysis::focus::{focus_search, FocusOptions};
use crate::analysis::focus_crlb::{focus_crlb, focus_weight};
use crate::analysis::template::RefBead;
use crate::data::Image;
use crate::instrument::sim::render::Renderer;
use crate::instrument::sim::scene::{Bead, Scene};
use crate::optics::template::TemplateSpec;
use rhai::{Dynamic, Map};

/// The options of this family's bindings, each key written once (`Opt`).
const U0: Opt = Opt::new("u0", "float", "µm");
const Z_BEST: Opt = Opt::new("z_best", "float", "µm");

const FOCUS_EX: &str = "let s = scene(); s.add_bead(#{x: 0.0, y: 0.0, z: 0.1, d_nm: 110.0, n: 1.572}); s.effects([\"detector_noise\"]); simulate(s); let sc = scan_xz(#{x: [-1.0, 1.0], z: [-1.0, 1.0], nx: 41, nz: 41, dwell: 0.001}); let b = focus_crlb(sc);";

pub fn register(r: &mut Registrar) {
    let keys: &[(&str, &str, &str, &str)] = &[
        Z_BEST.doc("optional: the object's height (default: focus_search's z_best of the image)"),
        U0.doc("optional: its lateral position (default: the sensitivity maximum of the row nearest z_best)"),
        WEIGHT.doc("optional: its weight in reference-bead units (default: least squares of the model at u0, z_best)"),
        SIGMA.doc("optional: pixel noise in the image's units (default: the image's robust pixel noise)"),
    ];
    let d = Doc::func("focus_crlb")
        .arg("img", "Scan | Image", "", "an XZ scan (its Sx), or the Sx of an XZ / Sy of a YZ scan")
        .opts(keys)
        .form("focus_crlb(img) -> map")
        .returns("map", "#{z_crlb, u_crlb, weight_crlb, z_best, u0, weight, sigma, channel} — z_crlb: the Cramér–Rao bound (1σ floor, µm) of the object's height, i.e. of the best focus; u_crlb its lateral position's (µm); weight in reference-bead units")
        .summary("the best 1σ an XZ/YZ focus scan can give for the best focus z: the Cramér–Rao bound of the object's height")
        .help("The model: one small object of weight w (reference-bead units: a 110 nm polystyrene bead is 1) at lateral position u0 and height z0 in the session's beam (the simulator's point-dipole response, rendered per z row), plus a background; the Fisher information of the image's pixels, each with noise σ, about (u0, z0, w, background) (analysis::focus_crlb). The best focus of focus_search is z0, so z_crlb is the floor under its z_err; focus::search reports it. The bound holds for an object that is a point dipole on the beam's scale; a filament or a large bead is not that object.")
        .example(&format!("{FOCUS_EX} b.z_crlb > 0.0 && b.z_crlb < 0.05"), "true")
        .example(&format!("{FOCUS_EX} round(b.weight * 10.0)"), "10.0")
        .example(&format!("{FOCUS_EX} let b2 = focus_crlb(sc, #{{sigma: b.sigma * 2.0}}); round(b2.z_crlb / b.z_crlb * 100.0)"), "200.0")
        .example(&format!("{FOCUS_EX} focus_crlb(sc, #{{sigma: -1.0}})"), "error: focus_crlb: sigma = -1");
    r.bind_ctx_opts(d, focus_crlb_of);
}

/// The channel image of an XZ (Sx) or YZ (Sy) scan, or the image itself.
fn channel_image(who: &str, v: &Dynamic) -> RResult<Image> {
    if let Some(s) = v.read_lock::<ScanRef>() {
        return Ok(if s.scan.sx.x_name == "y" {
            s.scan.sy.clone()
        } else {
            s.scan.sx.clone()
        });
    }
    if let Some(i) = v.read_lock::<super::types::ImageRef>() {
        return Ok((*i.0).clone());
    }
    fail(format!(
        "{who}: img is a {}; give a Scan or an Image",
        v.type_name()
    ))
}

/// `focus_crlb(img[, opts])`: see the declaration's help.
fn focus_crlb_of(c: &Ctx, spec: &Spec, v: &Dynamic, m: &Map) -> RResult<Map> {
    let who = "focus_crlb";
    let o = Opts::new(spec, m)?;
    let img = channel_image(who, v)?;
    crate::analysis::kind::require_plane(who, &img, &["XZ", "YZ"]).map_err(|e| err(who, e))?;
    let lateral_y = img.x_name == "y";
    let (us, zs) = (img.x.clone(), img.y.clone());
    let z_best = match o.f64(Z_BEST)? {
        Some(z) => z,
        None => {
            focus_search(&img, &FocusOptions::default())
                .map_err(|e| err(who, e))?
                .z_best
        }
    };
    let u0 = match o.f64(U0)? {
        Some(u) => u,
        None => {
            // the sensitivity maximum of the row nearest z_best
            let f = focus_search(&img, &FocusOptions::default()).map_err(|e| err(who, e))?;
            f.rows
                .iter()
                .filter_map(|r| r.peak().map(|p| (r.coord, p.pos)))
                .min_by(|a, b| (a.0 - z_best).abs().total_cmp(&(b.0 - z_best).abs()))
                .map(|(_, p)| p)
                .unwrap_or(0.5 * (us[0] + us[us.len() - 1]))
        }
    };
    for (name, val) in [("z_best", z_best), ("u0", u0)] {
        if !val.is_finite() {
            return fail(format!("{who}: {name} = {val} is not finite"));
        }
    }
    // the unit object (the reference bead) in the session's beam, rendered by the simulator
    let optics = c.optics();
    let rb = RefBead::default();
    let mut scene = Scene::default();
    scene
        .add_bead(Bead {
            pos: [0.0, 0.0, 0.0],
            d_nm: rb.d_nm,
            n: rb.n,
        })
        .map_err(|e| err(who, e))?;
    let rend =
        Renderer::checked(&optics, &scene, TemplateSpec::default()).map_err(|e| err(who, e))?;
    let ch = if lateral_y { 1 } else { 0 };
    let row = |u: &[f64], dz: f64| -> crate::analysis::Result<Vec<f64>> {
        let out = if lateral_y {
            rend.render_grid_ideal(&[0.0], u, dz)
        } else {
            rend.render_grid_ideal(u, &[0.0], dz)
        };
        Ok(out[ch].clone())
    };
    let weight = match o.f64(WEIGHT)? {
        Some(w) => w,
        None => {
            focus_weight(&us, &zs, &img.data, u0, z_best, &row)
                .map_err(|e| err(who, e))?
                .0
        }
    };
    let sigma = match o.f64(SIGMA)? {
        Some(s) if s > 0.0 && s.is_finite() => s,
        Some(s) => return fail(format!("{who}: sigma = {s} is out of range: σ > 0")),
        None => {
            let a = crate::analysis::domain::pixel_noise(&img, true);
            let b = crate::analysis::domain::pixel_noise(&img, false);
            let s = if a > 0.0 && b > 0.0 {
                a.min(b)
            } else {
                a.max(b)
            };
            if s.is_nan() || s <= 0.0 {
                return fail(format!(
                    "{who}: the image has no pixel noise (noise-free data have no bound); give sigma"
                ));
            }
            s
        }
    };
    let b = focus_crlb(&us, &zs, u0, z_best, weight, sigma, &row).map_err(|e| err(who, e))?;
    let mut out = Map::new();
    out.insert("z_crlb".into(), b.z.into());
    out.insert("u_crlb".into(), b.u.into());
    out.insert("weight_crlb".into(), b.weight.into());
    out.insert("z_best".into(), z_best.into());
    out.insert("u0".into(), u0.into());
    out.insert("weight".into(), weight.into());
    out.insert("sigma".into(), sigma.into());
    out.insert(
        "channel".into(),
        (if lateral_y { "sy" } else { "sx" }).into(),
    );
    Ok(out)
}
