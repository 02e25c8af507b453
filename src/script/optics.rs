//! Binding family `optics`: the set-up's optics (`optics`, `set_optics`), the Rayleigh
//! response of a point scatterer and the paper's calculators (scattered power, trap depth,
//! index correction, mass, maximum sensitivity; suppl. S1–S3).

use super::ctx::Ctx;
use super::keys::{D_NM, N, POLARIZATION, X, Y, Z};
use super::registry::{err, fail, fields_map, num, Doc, Opt, Opts, RResult, Registrar, Spec};
use super::scene::{BEAD_D_NM, BEAD_N};
use super::types::ScanRef;
use crate::analysis::beam_fit::{fit_beam, BeamFit, BeamFitOptions, D_RANGE_NM, V_MAX};
use crate::optics::calc::{
    n_corr, p_scat_ratio, sphere_mass_kda, trap_depth_kt, TrapShape, ROOM_T_K,
};
use crate::optics::finite_size::DEFAULT_N_R;
use crate::optics::mie_beam::dipole_response_in_beam;
use crate::optics::params::{Beam, Optics};
use crate::optics::rayleigh::DetectorModel;
use crate::optics::ValidOptics;
use rhai::{Array, Dynamic, Map, INT};

/// The options of this family's bindings, each key written once (`Opt`).
const BEAM: Opt = Opt::new("beam", "string", "");
const N_MEDIUM: Opt = Opt::new("n_medium", "float", "");
const NA: Opt = Opt::new("na", "float", "");
const POWER_MW: Opt = Opt::new("power_mw", "float", "mW");
const PUPIL_FILLING: Opt = Opt::new("pupil_filling", "float", "");
const QPD_NA: Opt = Opt::new("qpd_na", "float", "");
const W0_NM: Opt = Opt::new("w0_nm", "float", "nm");
const WAVELENGTH_NM: Opt = Opt::new("wavelength_nm", "float", "nm");
const MODEL: Opt = Opt::new("model", "string", "");
const N_PHI: Opt = Opt::new("n_phi", "int", "");
const N_THETA: Opt = Opt::new("n_theta", "int", "");
const SHAPE: Opt = Opt::new("shape", "string", "");
const TEMPERATURE_K: Opt = Opt::new("temperature_k", "float", "K");

/// `optics()` as a map (the keys `set_optics` takes).
fn optics_map(o: &Optics) -> Map {
    let mut m = fields_map!(o; wavelength_nm, n_medium, w0_nm, na, qpd_na, power_mw, pupil_filling);
    m.insert("n_theta".into(), (o.n_theta as INT).into());
    m.insert("n_phi".into(), (o.n_phi as INT).into());
    m.insert("beam".into(), o.beam.name().into());
    m
}

pub fn register(r: &mut Registrar) {
    r.bind_ctx(
        Doc::func("optics")
            .returns("map", "#{wavelength_nm, n_medium, w0_nm, na, qpd_na, power_mw, n_theta, n_phi, beam, pupil_filling}")
            .summary("the current optical parameters (nm, mW)")
            .help("Defaults are the paper's: λ = 1064 nm, water n = 1.333, w0 = 400 nm (1/e² radius), detection NA 1.2, 0.13 mW at the focus; n_theta × n_phi is the cone quadrature (accuracy knob, docs/accuracy.md).")
            .example("optics().wavelength_nm", "1064.0")
            .example("optics().w0_nm", "400.0"),
        |c| move || optics(&c),
    );
    bind_set_optics(r);
    bind_response(r);
    bind_model_sensitivity(r);
}

/// `set_optics`: the session optics.
fn bind_set_optics(r: &mut Registrar) {
    let d = Doc::func("set_optics")
        .map(
            "changes",
            "any subset of the optical parameters",
            &[
                WAVELENGTH_NM.doc("optional: vacuum wavelength"),
                N_MEDIUM.doc("optional: refractive index of the medium"),
                W0_NM.doc("optional: beam waist (1/e² intensity radius)"),
                NA.doc("optional: detection (condenser) NA"),
                QPD_NA.doc("optional: NA subtended by the QPD (inf: not limiting)"),
                POWER_MW.doc("optional: laser power at the focus"),
                N_THETA.doc("optional: cone quadrature nodes in θ"),
                N_PHI.doc("optional: cone quadrature nodes in φ per quadrant"),
                BEAM.doc("optional: \"vector\" (aplanatic vectorial focus of the objective NA, Richards–Wolf; every tier in one beam) or \"paraxial\" (the paper's scalar Gaussian of waist w0, suppl. S3)"),
                PUPIL_FILLING.doc("optional: vector beam's Gaussian pupil filling f0 = pupil 1/e field radius / aperture radius (Novotny & Hecht eq. 3.52); default inf = uniformly filled (the prompt takes finite numbers: 1e6 is uniform to 1e-13)"),
            ],
        )
        .returns("map", "the new optics")
        .summary("change optical parameters (validated; the simulator re-renders with them)")
        .example("set_optics(#{w0_nm: 450.0}).w0_nm", "450.0")
        .example("set_optics(#{na: -1.0})", "error: na = -1 is out of range")
        .example("set_optics(#{beam: \"vector\"}).beam", "\"vector\"")
        .example("set_optics(#{beam: \"gauss\"})", "error: beam = \"gauss\" is not a beam model");
    r.bind_map(d, set_optics);
}

/// `response` and the trap depth: what a particle gives in this beam.
fn bind_response(r: &mut Registrar) {
    let d = Doc::func("response")
        .map(
            "at",
            "particle displacement from the focus and the particle",
            &[
                X.doc("optional: displacement (default 0)"),
                Y.doc("optional: displacement (default 0)"),
                Z.doc("optional: displacement, + downstream (default 0)"),
                D_NM.doc(format!("optional: diameter (default {BEAD_D_NM})").as_str()),
                N.doc(format!("optional: refractive index (default {BEAD_N}, polystyrene)").as_str()),
                POLARIZATION.doc("optional: vector dipole field in the paraxial beam (default false; the vector beam is always vectorial)"),
            ],
        )
        .returns("map", "#{sx, sy, sz}: QPD signals normalised to the beam power")
        .summary("point-dipole QPD response of one sphere in the session's beam")
        .help("Dipole scattering of the sphere's static polarisability, interference with the beam integrated over the detection cone per quadrant; Sx = right − left, Sy = top − bottom. In the session's beam: the aplanatic vector focus (default, docs/physics.md §10) or, with set_optics(#{beam: \"paraxial\"}), the paper's Gaussian model (suppl. S2).")
        .example("response(#{x: 0.0}).sx", "0.0")
        .example("response(#{x: 0.2}).sx > 0.0 && response(#{x: -0.2}).sx < 0.0", "true")
        .example("response(#{x: 0.2, n: 1.333}).sx", "0.0")
        .example("response(#{d_nm: -5.0})", "error: d_nm = -5 is out of range");
    r.bind_map(d, response_of);

    r.bind_ctx(
        Doc::func("p_scat_ratio")
            .arg("d_nm", "float", "nm", "sphere diameter")
            .arg("n", "float", "", "refractive index of the sphere")
            .returns("float", "P_scat / P_beam, w0 read as the 1/e² intensity radius")
            .summary(
                "fraction of the beam power a Rayleigh sphere at the focus scatters (suppl. S1)",
            )
            .help("P_scat/P_beam = (16/3)·k⁴·CM²·r⁶/w0² with k = 2π n_s/λ, CM = (m²−1)/(m²+2), m = n/n_s and w0 the 1/e² intensity radius of set_optics (peak intensity 2P/(π w0²)). The supplement (S1) integrates the beam as I0·e^(−r²/w0²), i.e. reads w0 as a 1/e radius, and gets half this value: the paper's convention gives 2.35e-5 for the 110 nm reference bead (its \"≈ 2×10⁻⁵\") where this gives 4.70e-5, and 1 % at 302 nm (paper: \"exceed 300 nm\") where this gives 269 nm. See docs/physics.md §6.")
            .example("round(p_scat_ratio(110.0, 1.572) * 1e7) / 1e7", "4.7e-5")
            .example("p_scat_ratio(110.0, 0.5)", "error: n = 0.5 is out of range"),
        |c| move |d: Dynamic, n: Dynamic| p_scat(&c, &d, &n),
    );

    let d = Doc::func("trap_depth_kt")
        .map(
            "object",
            "the trapped object",
            &[
                SHAPE.doc("\"sphere\" or \"cylinder\" (a fibril in the focal plane)"),
                D_NM.doc("diameter"),
                N.doc("refractive index"),
                TEMPERATURE_K.doc("optional: temperature (default 295.15)"),
            ],
        )
        .returns("float", "depth of the gradient-force potential in kT")
        .summary("trap depth of a bead or fibril at the laser power of optics() (suppl. S3)")
        .example(
            "trap_depth_kt(#{shape: \"cylinder\", d_nm: 150.0, n: 1.414}) < 1.0",
            "true",
        )
        .example(
            "trap_depth_kt(#{shape: \"cube\", d_nm: 10.0, n: 1.5})",
            "error: shape = \"cube\"",
        );
    r.bind_map(d, trap_depth);

    r.bind_ctx(
        Doc::func("n_corr")
            .arg("n_obj", "float", "", "index of the measured object")
            .arg("n_ref", "float", "", "index of the reference bead")
            .returns("float", "sensitivity ratio at equal volume")
            .summary("refractive-index correction (eq. nCor) in the medium of optics()")
            .example("n_corr(1.572, 1.572)", "1.0")
            .example("round(n_corr(1.414, 1.57) * 1e4) / 1e4", "0.3505"),
        |c| move |a: Dynamic, b: Dynamic| index_correction(&c, &a, &b),
    );
}

/// `max_sensitivity_model` and `fit_beam`.
fn bind_model_sensitivity(r: &mut Registrar) {
    r.bind(
        Doc::func("sphere_mass_kda")
            .arg("d_nm", "float", "nm", "diameter")
            .arg(
                "density_g_cm3",
                "float",
                "g/cm³",
                "density (polystyrene 1.05)",
            )
            .returns("float", "mass in kDa")
            .summary("mass of a sphere")
            .example("round(sphere_mass_kda(110.0, 1.05) / 1e3)", "441.0"),
        |d: Dynamic, rho: Dynamic| sphere_mass(&d, &rho),
    );

    let d = Doc::func("max_sensitivity_model")
        .map(
            "bead",
            "the sphere and the model tier",
            &[
                D_NM.doc("diameter"),
                N.doc(format!("optional: index (default {BEAD_N})").as_str()),
                MODEL.doc("optional: \"rayleigh\" (point dipole, default) or \"finite_size\" (suppl. S6)"),
            ],
        )
        .returns("map", "#{sens: (∂Sx/∂x)max in 1/µm, z: best focus in µm}")
        .summary("model maximum Sx sensitivity of a sphere at its best focus (Fig. 3c)")
        .example("let a = max_sensitivity_model(#{d_nm: 110.0}); let b = max_sensitivity_model(#{d_nm: 220.0}); round(b.sens / a.sens)", "8.0")
        .example("max_sensitivity_model(#{d_nm: 110.0, model: \"qed\"})", "error: model = \"qed\"");
    r.bind_map(d, max_sensitivity_model);
    register_fit_beam(r);
}

/// `f0` as `set_optics` takes it: finite (the prompt refuses ∞); 1e6 is a uniformly filled
/// pupil to 1e-12 (spectral waist 2/(k f0 sinΘ) ≈ 4e-8 µm).
pub const UNIFORM_F0: f64 = 1e6;

fn register_fit_beam(r: &mut Registrar) {
    let d = Doc::func("fit_beam")
        .arg("scan", "Scan", "", "an xy scan of one reference bead at the focus (Sx, Sy, Sz; pixels ≤ 0.1 µm over ≥ 1.2 µm)")
        .opts(&[
                D_NM.doc(format!("optional: reference bead diameter (default {BEAD_D_NM}; {}–{})", D_RANGE_NM.0, D_RANGE_NM.1)),
                N.doc(format!("optional: reference bead index (default {BEAD_N})")),
            ],
        )
        .form("fit_beam(scan) -> map")
        .returns(
            "map",
            "#{pupil_filling, inv_f0_sq, polarization_deg, qpd_rotation_deg, offset_x, offset_y (magnitudes: a scan at the focus does not measure an offset's sign, which enters at second order), offset_x_sq, offset_y_sq (their squares, whose σ holds near zero too), defocus_sq_um2 (the bead's height off the focus, squared, µm²: fitted with the rest, it widens σ of inv_f0_sq, with which it trades), gain_x, gain_y, gain_z, gain_ratio, x0, y0 (each with its 1σ as <key>_sd; gain_z () with gain_z_note when the scan does not determine it: at the focus Sz carries no bead signal), background, residual_rms, noise ([sx, sy, sz]), chi2_red, corr_polarization_rotation, builds, seconds, optics: #{beam, pupil_filling} (for set_optics), misalignment: #{offset_x, offset_y, rotation_deg, gain_y} (the scene effect's keys), warnings: [string] (clipped or dark pixels, the bead near the scan's edge, the bead off the focus, v at the search's bound), status: \"ok\" when warnings is empty}",
        )
        .summary("fit the focused beam (pupil filling, polarisation axis) and the QPD (gains, rotation, offsets) to a reference-bead scan")
        .help("Least-squares fit of the aplanatic vector focus to one xy scan of a reference bead (default 110 nm polystyrene) at the focus, in the session's λ, n_medium and NA: v = 1/f0² (0 = uniformly filled pupil; pupil_filling = 1/√v, inf when v = 0 — then optics.pupil_filling is 1e6, uniform to 1e-12), the polarisation axis ψ from the stage x axis, the QPD rotation δ relative to the polarisation (correlated with ψ: only the focus's ellipticity separates them; corr_polarization_rotation says how much), QPD offsets in cone radii, channel gains (gain_ratio = gain_y/gain_x, the misalignment effect's gain_y) and offsets, and the bead position (µm). Uncertainties (*_sd) are 1σ from the covariance of all 13 parameters scaled by the residual variance, with each channel weighted by its noise (estimated from the image's second differences). Refuses scans that are not xy, have no bead (Sx gain < 10σ), or that the model does not explain (residual rms > 2× the noise: wrong bead size or index, far out of focus). The QPD offsets enter at second order at the focus: their squares are measured, their sign is not (offset_x, offset_y are magnitudes). A bead off the focus reads as a smaller pupil filling: a defocus test refits the model 0.04–0.9 µm above and below and warns when that explains the scan better (Δχ² > 9). About 70–100 template-plane builds: 1–5 s. Use the beam: set_optics(f.optics); then template_model, angle_curve, diameter_calib, lin_dens_calib and point_mass describe the fitted instrument. docs/physics.md §10.4.")
        .example("let t = template_model(#{h_um: 0.025}); let sc = render_beads(t, #{beads: [#{x: 0.0, y: 0.0, weight: 1.0}], x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 41, ny: 41}); fit_beam(sc, #{d_nm: 500.0})", "error: d_nm = 500")
        .example("let t = template_model(#{h_um: 0.025}); let sc = render_beads(t, #{beads: [#{x: 0.0, y: 0.0, weight: 1.0}], x: [-2.0, 2.0], y: [-2.0, 2.0], nx: 21, ny: 21}); fit_beam(sc)", "error: the fit needs pixels ≤ 0.1 µm");
    r.bind_ctx_opts(d, fit_beam_of);
}

/// `fit_beam(scan[, opts])`: the beam and QPD fitted to a reference-bead scan (module
/// `analysis::beam_fit`), as a map with 1σ uncertainties.
fn fit_beam_of(c: &Ctx, spec: &Spec, s: &ScanRef, m: &Map) -> RResult<Map> {
    let o = Opts::new(spec, m)?;
    let opts = BeamFitOptions {
        d_nm: o.f64_or(D_NM, BEAD_D_NM)?,
        n: o.f64_or(N, BEAD_N)?,
        ..BeamFitOptions::default()
    };
    let sc = &s.scan;
    // its domain (docs/analysis.md, Domains): no clipped or dark pixel among the three
    // channels it fits, the bead whole inside the 1.2 µm field it needs, v not at the search's
    // upper bound
    let check = crate::data::clip::input_check(sc, &["sx", "sy", "sz"], None);
    let mut warnings = super::analysis_values::input_gate("fit_beam", check)?;
    let f = fit_beam(&c.optics(), &sc.sx, &sc.sy, &sc.sz, &opts).map_err(|e| err("fit_beam", e))?;
    warnings.extend(crate::analysis::domain::margin_warning(
        "the bead",
        &sc.sx,
        f.x0.value,
        f.y0.value,
        BEAD_FIELD_HALF_UM,
    ));
    if f.inv_f0_sq.value >= V_MAX * (1.0 - 1e-9) {
        warnings.push(format!(
            "the pupil filling is at the search's bound v = 1/f0² = {V_MAX} (a beam much narrower than the pupil): its value and σ do not hold; check the bead's size and index and the optics"
        ));
    }
    let mut out = fit_map(&f);
    super::analysis_values::with_warnings(c, "fit_beam", &mut out, warnings);
    Ok(out)
}

/// Half the field the beam fit needs around the bead, µm (`analysis::beam_fit`: ≥ 1.2 µm).
const BEAD_FIELD_HALF_UM: f64 = 0.6;

fn fit_map(f: &BeamFit) -> Map {
    let mut out = Map::new();
    for (k, v) in [
        ("pupil_filling", f.pupil_filling),
        ("inv_f0_sq", f.inv_f0_sq),
        ("polarization_deg", f.polarization_deg),
        ("qpd_rotation_deg", f.qpd_rotation_deg),
        ("offset_x", f.offset_x),
        ("offset_y", f.offset_y),
        ("offset_x_sq", f.offset_x_sq),
        ("offset_y_sq", f.offset_y_sq),
        ("defocus_sq_um2", f.defocus_sq),
        ("gain_x", f.gain_x),
        ("gain_y", f.gain_y),
        ("gain_ratio", f.gain_ratio),
        ("x0", f.x0),
        ("y0", f.y0),
    ] {
        out.insert(k.into(), v.value.into());
        out.insert(format!("{k}_sd").into(), v.sigma.into());
    }
    // the Sz gain: () when the scan does not determine it (a bead at the focus), with the reason
    match f.gain_z {
        Some(v) => {
            out.insert("gain_z".into(), v.value.into());
            out.insert("gain_z_sd".into(), v.sigma.into());
        }
        None => {
            out.insert("gain_z".into(), Dynamic::UNIT);
            out.insert("gain_z_sd".into(), Dynamic::UNIT);
            out.insert(
                "gain_z_note".into(),
                f.gain_z_note.clone().unwrap_or_default().into(),
            );
        }
    }
    let arr = |a: [f64; 3]| -> Array { a.iter().map(|&v| Dynamic::from(v)).collect() };
    out.insert("background".into(), arr(f.background).into());
    out.insert("residual_rms".into(), arr(f.residual_rms).into());
    out.insert("noise".into(), arr(f.noise).into());
    out.insert("chi2_red".into(), f.chi2_red.into());
    out.insert(
        "corr_polarization_rotation".into(),
        f.corr_polarization_rotation.into(),
    );
    out.insert("builds".into(), (f.builds as INT).into());
    out.insert("seconds".into(), f.seconds.into());
    let mut om = Map::new();
    om.insert("beam".into(), f.optics.beam.name().into());
    let f0 = f.optics.pupil_filling;
    om.insert(
        "pupil_filling".into(),
        (if f0.is_finite() {
            f0.min(UNIFORM_F0)
        } else {
            UNIFORM_F0
        })
        .into(),
    );
    out.insert("optics".into(), om.into());
    let mut mm = Map::new();
    mm.insert("offset_x".into(), f.misalignment.offset_x.into());
    mm.insert("offset_y".into(), f.misalignment.offset_y.into());
    mm.insert("rotation_deg".into(), f.misalignment.rotation_deg.into());
    mm.insert("gain_y".into(), f.misalignment.gain_y.into());
    out.insert("misalignment".into(), mm.into());
    out
}

/// `optics()`: the session's optical parameters (nm, mW).
fn optics(ctx: &Ctx) -> Map {
    optics_map(&ctx.optics())
}

/// `set_optics(changes)`: validates the changed optics, re-renders the simulator's scene with
/// them when a simulator is connected, then stores them in the session.
fn set_optics(c: &Ctx, spec: &Spec, m: &Map) -> RResult<Map> {
    let o = Opts::new(spec, m)?;
    let mut new = c.optics().into_optics();
    for (k, f) in [
        (WAVELENGTH_NM, &mut new.wavelength_nm as &mut f64),
        (N_MEDIUM, &mut new.n_medium),
        (W0_NM, &mut new.w0_nm),
        (NA, &mut new.na),
        (QPD_NA, &mut new.qpd_na),
        (POWER_MW, &mut new.power_mw),
        (PUPIL_FILLING, &mut new.pupil_filling),
    ] {
        if let Some(v) = o.f64(k)? {
            *f = v;
        }
    }
    if let Some(v) = o.int(N_THETA)? {
        new.n_theta = v.clamp(0, 100_000) as usize;
    }
    if let Some(v) = o.int(N_PHI)? {
        new.n_phi = v.clamp(0, 100_000) as usize;
    }
    if let Some(b) = o.string(BEAM)? {
        new.beam = Beam::parse(&b).map_err(|e| err("set_optics", e))?;
    }
    let new = ValidOptics::new(new).map_err(|e| err("set_optics", e))?;
    c.set_optics(new.clone())
        .map_err(|e| err("set_optics", e))?;
    Ok(optics_map(&new))
}

/// `response(#{x, y, z, d_nm, n, polarization})`: Rayleigh-dipole QPD signals (Sx, Sy, Sz,
/// normalised to the beam power) of a sphere displaced (x, y, z) µm from the focus (suppl. S2).
fn response_of(c: &Ctx, spec: &Spec, m: &Map) -> RResult<Map> {
    let o = Opts::new(spec, m)?;
    let model = DetectorModel {
        polarization: o.bool_or(POLARIZATION, false)?,
        misalignment: None,
    };
    let s = dipole_response_in_beam(
        &c.optics(),
        &model,
        [o.f64_or(X, 0.0)?, o.f64_or(Y, 0.0)?, o.f64_or(Z, 0.0)?],
        o.f64_or(D_NM, BEAD_D_NM)?,
        o.f64_or(N, BEAD_N)?,
    )
    .map_err(|e| err("response", e))?;
    let mut out = Map::new();
    out.insert("sx".into(), s.sx.into());
    out.insert("sy".into(), s.sy.into());
    out.insert("sz".into(), s.sz.into());
    Ok(out)
}

/// `p_scat_ratio(d_nm, n)`: P_scat/P_beam of a Rayleigh sphere at the focus, w0 read as the
/// 1/e² intensity radius (suppl. S1, docs/physics.md §6).
fn p_scat(c: &Ctx, d: &Dynamic, n: &Dynamic) -> RResult<f64> {
    p_scat_ratio(
        &c.optics(),
        num("p_scat_ratio", "d_nm", d)?,
        num("p_scat_ratio", "n", n)?,
    )
    .map_err(|e| err("p_scat_ratio", e))
}

/// `trap_depth_kt(#{shape, d_nm, n, temperature_k})`: depth of the gradient-force potential of
/// a sphere or a cylinder in kT at the laser power of the session's optics (suppl. S3).
fn trap_depth(c: &Ctx, spec: &Spec, m: &Map) -> RResult<f64> {
    let o = Opts::new(spec, m)?;
    let shape = match o.string(SHAPE)?.as_deref() {
        Some("sphere") => TrapShape::Sphere,
        Some("cylinder") => TrapShape::Cylinder,
        other => {
            return fail(format!(
                "trap_depth_kt: shape = {:?} is not one of \"sphere\", \"cylinder\"",
                other.unwrap_or("")
            ))
        }
    };
    trap_depth_kt(
        &c.optics(),
        shape,
        o.req_f64(D_NM)?,
        o.req_f64(N)?,
        o.f64_or(TEMPERATURE_K, ROOM_T_K)?,
    )
    .map_err(|e| err("trap_depth_kt", e))
}

/// `n_corr(n_obj, n_ref)`: sensitivity ratio of two objects of equal volume and indices n_obj,
/// n_ref in the medium of the session's optics (eq. nCor).
fn index_correction(c: &Ctx, a: &Dynamic, b: &Dynamic) -> RResult<f64> {
    n_corr(
        num("n_corr", "n_obj", a)?,
        num("n_corr", "n_ref", b)?,
        c.optics().n_medium,
    )
    .map_err(|e| err("n_corr", e))
}

/// `sphere_mass_kda(d_nm, density_g_cm3)`: mass (kDa) of a sphere of diameter d_nm (nm).
fn sphere_mass(d: &Dynamic, rho: &Dynamic) -> RResult<f64> {
    sphere_mass_kda(
        num("sphere_mass_kda", "d_nm", d)?,
        num("sphere_mass_kda", "density_g_cm3", rho)?,
    )
    .map_err(|e| err("sphere_mass_kda", e))
}

/// `max_sensitivity_model(#{d_nm, n, model})`: model maximum ∂Sx/∂x (1/µm) of a sphere at its
/// best focus z (µm) — point dipole, finite size (suppl. S6, Fig. 3c) or Lorenz–Mie — in the
/// session's beam (`set_optics(#{beam})`).
fn max_sensitivity_model(c: &Ctx, spec: &Spec, m: &Map) -> RResult<Map> {
    use crate::optics::mie_beam::{max_sensitivity_in_beam, SphereModel};
    let o = Opts::new(spec, m)?;
    let (dn, n) = (o.req_f64(D_NM)?, o.f64_or(N, BEAD_N)?);
    let model = match o.string(MODEL)?.as_deref() {
        None | Some("rayleigh") => SphereModel::Dipole,
        Some("finite_size") => SphereModel::FiniteSize { n_r: DEFAULT_N_R },
        Some("mie") => SphereModel::Mie,
        Some(other) => {
            return fail(format!(
                "max_sensitivity_model: model = {other:?} is not one of \"rayleigh\", \"finite_size\", \"mie\""
            ))
        }
    };
    let optics = c.optics();
    let (s, z) = max_sensitivity_in_beam(&optics, dn, n, model)
        .map_err(|e| err("max_sensitivity_model", e))?;
    let mut out = Map::new();
    out.insert("sens".into(), s.into());
    out.insert("z".into(), z.into());
    Ok(out)
}
