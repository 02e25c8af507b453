//! Binding family `scene`: scenes for the simulated instrument (`scene()`, beads, filaments,
//! aggregates, effects), `simulate` and the render `pipeline`.

use super::ctx::Ctx;
use super::keys::{D_NM, N, POINTS, SPACING_NM, X, Y, Z};
use super::registry::{
    err, fail, non_negative, num, number_pair, points, Doc, Opt, Opts, RResult, Registrar, Spec,
};
use super::types::{json_to_dynamic, ScanRef};
use crate::instrument::sim::render_xy;
use crate::instrument::sim::scene::{
    Aggregates, Bead, DiameterProfile, Filament, Scene, EFFECT_NAMES,
};
use rhai::{Array, Dynamic, Map, INT};

/// The options of this family's bindings, each key written once (`Opt`).
const COUNT: Opt = Opt::new("count", "int", "");
const N_SAMPLES: Opt = Opt::new("n_samples", "int", "");
const SEED: Opt = Opt::new("seed", "int", "");
const TAPER: Opt = Opt::new("taper", "array", "nm");
const ALPHA_TIP: Opt = Opt::new("alpha_tip", "map", "nm, µm");

/// A scene in scripts (cloned by value like every Rhai value; small).
#[derive(Debug, Clone, Default)]
pub struct SceneRef(pub Scene);

/// `[lo, hi]` of the key `key`.
fn pair(who: &str, key: &str, v: &Dynamic) -> RResult<[f64; 2]> {
    number_pair(who, key, v, "[lo, hi]", "must be [lo, hi] (2 numbers)")
}

const SCENE_EX: &str = "let s = scene(); s.add_bead(#{x: 0.0, y: 0.0, d_nm: 110.0, n: 1.572});";

/// Default bead of `add_bead`, `response` and `max_sensitivity_model`: the paper's reference
/// bead, 110 nm polystyrene (Sec. 3.1). Diameter nm, refractive index.
pub(crate) const BEAD_D_NM: f64 = 110.0;
pub(crate) const BEAD_N: f64 = 1.572;
/// Default filament of `add_filament`: a hydrated collagen fibril, diameter nm and index (its
/// bead-model spacing is the simulator's [`FILAMENT_SPACING_NM`]).
pub(crate) const FILAMENT_D_NM: f64 = 60.0;
pub(crate) const FILAMENT_N: f64 = 1.414;
pub(crate) use crate::instrument::sim::scene::FILAMENT_SPACING_NM;
/// Defaults of an `add_filament` α-tip's keys: full diameter, nm, and tip length, µm.
const ALPHA_TIP_D_NM: f64 = 100.0;
const ALPHA_TIP_UM: f64 = 3.0;
/// Defaults of `add_aggregates` (Sec. 6 background): diameter range nm, refractive index,
/// region [lo, hi] µm on x and y, random seed; and the most aggregates one call adds.
const AGGREGATE_D_NM: [f64; 2] = [40.0, 90.0];
const AGGREGATE_N: f64 = 1.45;
const AGGREGATE_REGION_UM: [f64; 2] = [-3.0, 3.0];
const AGGREGATE_SEED: i64 = 1;
const AGGREGATES_MAX: i64 = 100_000;
/// Samples averaged per pixel by `simulate(scene, grid)` unless `n_samples` says otherwise.
const SIMULATE_N_SAMPLES: i64 = crate::instrument::sim::scene::PAPER_SAMPLES_PER_PIXEL as i64;

pub fn register(r: &mut Registrar) {
    r.engine()
        .register_type_with_name::<SceneRef>("Scene")
        .register_fn("to_string", |s: &mut SceneRef| scene_summary(&s.0))
        .register_fn("to_debug", |s: &mut SceneRef| scene_summary(&s.0));

    bind_scene(r);
    bind_scene_objects(r);
    bind_scene_effects(r);
    bind_simulate(r);
}

/// `scene()` and what a Scene shows of itself.
fn bind_scene(r: &mut Registrar) {
    let d = Doc::func("scene")
        .returns("Scene", "an empty scene")
        .summary("start a scene for the simulated instrument")
        .help("Add objects with s.add_bead / s.add_filament / s.add_aggregates, choose effects with s.effects([...]), then simulate(s). Positions are stage coordinates (µm): an object at p is in the focus when the stage reads p.")
        .example("let s = scene(); s.add_bead(#{x: 1.0}); s.n_objects", "1");
    r.bind(d, SceneRef::default);
    r.engine()
        .register_get("n_objects", |s: &mut SceneRef| n_objects(s));
    r.getter(
        Doc::property("Scene", "seed")
            .returns("int", "")
            .summary("the seed of the scene's noise effects (settable: s.seed = k, k ≥ 0)")
            .help("simulate draws every noise effect from this seed, so the same scene and seed give the same noise; set another seed for another draw (e.g. repeated scans of one scene).")
            .example("let s = scene(); s.seed = 7; s.seed", "7")
            .example("let s = scene(); s.seed = -1", "error: seed = -1"),
        |s: &mut SceneRef| s.0.seed as INT,
    );
    r.engine()
        .register_set("seed", |s: &mut SceneRef, v: INT| -> RResult<()> {
            s.0.seed = non_negative("Scene.seed", "seed", v)?;
            Ok(())
        });
    r.engine()
        .register_get("effect_names", |s: &mut SceneRef| effect_names(s));
}

/// The objects a Scene holds: `add_bead`, `add_filament`, `add_aggregates`.
fn bind_scene_objects(r: &mut Registrar) {
    let d = Doc::method("Scene", "add_bead")
        .map(
            "bead",
            "a sphere",
            &[
                X.doc("optional: position (default 0)"),
                Y.doc("optional: position (default 0)"),
                Z.doc("optional: height (default 0)"),
                D_NM.doc(format!("optional: diameter (default {BEAD_D_NM})").as_str()),
                N.doc(
                    format!("optional: refractive index (default {BEAD_N}, polystyrene)").as_str(),
                ),
            ],
        )
        .summary("add a bead")
        .example(&format!("{SCENE_EX} s.n_objects"), "1")
        .example(
            "let s = scene(); s.add_bead(#{d_nm: -1.0})",
            "error: d_nm = -1",
        );
    let spec = d.spec();
    r.bind(d, move |s: &mut SceneRef, m: Map| add_bead(&spec, s, &m));

    let d = Doc::method("Scene", "add_filament")
        .map(
            "filament",
            "a polyline filament (bead model, Sec. 4.2)",
            &[
                POINTS.doc("vertices [[x, y], ...]"),
                Z.doc("optional: height (default 0)"),
                D_NM.doc(format!("optional: constant diameter (default {FILAMENT_D_NM})").as_str()),
                TAPER.doc("optional: [d_start, d_end] linear taper instead of d_nm"),
                ALPHA_TIP.doc(format!("optional: #{{d_nm, tip_um}}: parabola-of-revolution α-tip from the first point (Sec. 5; default d_nm {ALPHA_TIP_D_NM}, tip_um {ALPHA_TIP_UM})").as_str()),
                N.doc(format!("optional: refractive index (default {FILAMENT_N}, hydrated collagen)").as_str()),
                SPACING_NM.doc(format!("optional: bead-model spacing (default {FILAMENT_SPACING_NM})").as_str()),
            ],
        )
        .summary("add a filament (bead model: spheres every spacing_nm, volume factor 3h/4r)")
        .example("let s = scene(); s.add_filament(#{points: [[0.0, -5.0], [0.0, 5.0]], d_nm: 25.0, n: 1.587}); s.n_objects", "1")
        .example("let s = scene(); s.add_filament(#{points: []})", "error: points is empty");
    let spec = d.spec();
    r.bind(d, move |s: &mut SceneRef, m: Map| {
        add_filament(&spec, s, &m)
    });

    let [d_lo, d_hi] = AGGREGATE_D_NM;
    let [r_lo, r_hi] = AGGREGATE_REGION_UM;
    let d = Doc::method("Scene", "add_aggregates")
        .map(
            "aggregates",
            "point-like aggregates at random positions (Sec. 6 background)",
            &[
                COUNT.doc("how many"),
                D_NM.typed("array", "nm").doc(&format!(
                    "optional: [lo, hi] diameter range (default [{d_lo}, {d_hi}])"
                )),
                N.doc(&format!(
                    "optional: refractive index (default {AGGREGATE_N})"
                )),
                X.typed("array", "µm").doc(&format!(
                    "optional: [x0, x1] region (default [{r_lo}, {r_hi}])"
                )),
                Y.typed("array", "µm").doc(&format!(
                    "optional: [y0, y1] region (default [{r_lo}, {r_hi}])"
                )),
                Z.doc("optional: height (default 0)"),
                SEED.doc(&format!("optional: random seed (default {AGGREGATE_SEED})")),
            ],
        )
        .summary("add point-like aggregates (random sizes and positions from a seed)")
        .example(
            "let s = scene(); s.add_aggregates(#{count: 12, seed: 3}); s.n_objects",
            "12",
        )
        .example(
            "let s = scene(); s.add_aggregates(#{count: 2, seed: -3})",
            "error: add_aggregates: seed = -3",
        );
    let spec = d.spec();
    r.bind(d, move |s: &mut SceneRef, m: Map| {
        add_aggregates(&spec, s, &m)
    });
}

/// What a Scene renders with: `effects`, `effect`, `rotate`.
fn bind_scene_effects(r: &mut Registrar) {
    let d = Doc::method("Scene", "effects")
        .arg("names", "array", "", &format!("effect names: {}", EFFECT_NAMES.join(", ")))
        .summary("choose the effects to simulate (each adds exactly one pipeline stage; none = ideal superposition)")
        .help("Parameters take their documented defaults (docs/physics.md §7); change one with s.effect(name, #{...}).")
        .example("let s = scene(); s.effects([\"detector_noise\", \"drift\"]); s.effect_names", "[\"drift\", \"detector_noise\"]")
        .example("let s = scene(); s.effects([\"fog\"])", "error: unknown effect \"fog\"");
    r.bind(d, |s: &mut SceneRef, names: Array| effects(s, names));

    let d = Doc::method("Scene", "effect")
        .arg("name", "string", "", "effect name")
        .arg("params", "map", "", "parameters, e.g. #{sigma_sample: 1e-3} for detector_noise (see help)")
        .summary("enable one effect with parameters")
        .help("detector_noise #{sigma_sample}; laser_power_noise #{sigma_rel_sample}; pointing_noise #{sigma_nm_sample}; drift #{velocity_nm_s: [vx, vy, vz], random_walk_nm_sqrt_s}; misalignment #{offset_x, offset_y, rotation_deg, gain_y}; finite_size #{n_r, min_d_nm}; thermal_motion #{sigma_nm, samples}; mie #{min_d_nm, scattered_intensity} (beads as Lorenz–Mie spheres, docs/physics.md §9); stage_bandwidth #{hz} (the stage lags its target under the wave generator of raster scans, τ = 1/(2π hz)); detector_range #{range, sum_scale, sum_floor, power} (inputs ±range in signal units, clipped beyond; the sum input is sum_scale·power·(1 + Sz); a pixel whose sum is below sum_floor is dark; power 0–1 of the beam reaching the detector; defaults 1, 0.5, 0.01, 1: scans count clipped and dark pixels, docs/hardware.md); polarization and cross_terms take #{}.")
        .example("let s = scene(); s.effect(\"detector_noise\", #{sigma_sample: 1e-3}); s.effect_names", "[\"detector_noise\"]")
        .example("let s = scene(); s.effect(\"drift\", #{speed: 1.0})", "error: drift")
        .example("let s = scene(); s.effect(\"detector_range\", #{range: 0.0})", "error: effect: detector_range: range = 0: must be finite and > 0");
    r.bind(d, |s: &mut SceneRef, name: &str, params: Map| {
        effect(s, name, params)
    });

    let d = Doc::method("Scene", "rotate")
        .arg(
            "angle_deg",
            "float",
            "°",
            "counter-clockwise rotation of the sample",
        )
        .summary("rotate every object about the origin (the 19-angle rotation series)")
        .example(
            "let s = scene(); s.add_bead(#{x: 1.0}); s.rotate(90.0); s.n_objects",
            "1",
        );
    r.bind(d, |s: &mut SceneRef, a: Dynamic| rotate(s, &a));

    // ---------------- simulate ----------------
}

/// `simulate` and `pipeline`: the simulator imaging a Scene.
fn bind_simulate(r: &mut Registrar) {
    let ctx = r.ctx();
    let n_samples_doc = format!(
        "optional: samples averaged per pixel (noise effects; default {SIMULATE_N_SAMPLES})"
    );
    let grid_keys: &[(&str, &str, &str, &str)] = &[
        X.typed("array", "µm").doc("[from, to]"),
        Y.typed("array", "µm").doc("[from, to]"),
        ("nx", "int", "", "pixels along x"),
        ("ny", "int", "", "pixels along y"),
        Z.doc("optional: stage height (default 0)"),
        N_SAMPLES.doc(&n_samples_doc),
    ];
    let d = Doc::func("simulate")
        .arg("scene", "Scene", "", "what the simulated instrument sees")
        .map("grid", "optional second argument: render an XY image directly, without stage or clock", grid_keys)
        .form("simulate(scene) -> map")
        .form("simulate(scene, grid) -> Scan")
        .returns("map | Scan", "simulate(scene): #{stages, scatterers, notes} of the pipeline built (notes: beads the point dipole renders > 1 % off Mie); simulate(scene, grid): the rendered scan (not autosaved)")
        .summary("put a scene under the simulated instrument, or render it straight to an XY scan")
        .help("simulate(scene) connects the simulated instrument (the stage position and virtual clock are kept when one is already connected); scans then image the scene. The pipeline contains only the stages the scene's effects name. simulate(scene, grid) renders an image without moving anything (figures, tests). Noise effects draw from the scene's seed (s.seed): the same scene and seed give the same noise, another seed another draw.")
        .example(&format!("{SCENE_EX} simulate(s).stages"), "[\"superposition\", \"vector_beam\"]")
        .example("let s = scene(); s.add_bead(#{x: 0.0, y: 0.0, d_nm: 500.0}); simulate(s).notes.len()", "1")
        .example(&format!("{SCENE_EX} let sc = simulate(s, #{{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 21, ny: 21}}); sc.sx.cols"), "21")
        .example(&format!("{SCENE_EX} simulate(s, #{{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 0, ny: 21}})"), "error: nx = 0");
    r.bind_ctx(d, |c| move |s: SceneRef| install(&c, &s.0));
    let spec = Doc::func("simulate").map("grid", "", grid_keys).spec();
    let c = ctx.clone();
    r.overload("simulate", move |s: SceneRef, m: Map| {
        simulate_grid(&c, &spec, &s, &m)
    });

    let d = Doc::func("pipeline")
        .returns(
            "array",
            "[#{name, seconds, detail}] of the simulated instrument's render pipeline",
        )
        .summary("the stages the simulator built and the wall time spent in each so far")
        .example(
            &format!("{SCENE_EX} simulate(s); pipeline()[0].name"),
            "\"superposition\"",
        );
    r.bind_ctx(d, |c| move || pipeline(&c));
}

/// `scene.n_objects`: beads + filaments + aggregates (each aggregate counted).
fn n_objects(s: &SceneRef) -> INT {
    (s.0.beads.len() + s.0.filaments.len() + s.0.aggregates.iter().map(|a| a.count).sum::<usize>())
        as INT
}

/// `scene.effect_names`: the effects enabled, in pipeline order.
fn effect_names(s: &SceneRef) -> Array {
    s.0.effects
        .names()
        .into_iter()
        .map(|n| Dynamic::from(n.to_string()))
        .collect()
}

/// `scene.add_bead(#{x, y, z, d_nm, n})`: a sphere at (x, y, z) µm, diameter d_nm (nm).
fn add_bead(spec: &Spec, s: &mut SceneRef, m: &Map) -> RResult<()> {
    let o = Opts::new(spec, m)?;
    s.0.add_bead(Bead {
        pos: [o.f64_or(X, 0.0)?, o.f64_or(Y, 0.0)?, o.f64_or(Z, 0.0)?],
        d_nm: o.f64_or(D_NM, BEAD_D_NM)?,
        n: o.f64_or(N, BEAD_N)?,
    })
    .map_err(|e| err("add_bead", e))
}

/// `scene.add_filament(#{points, z, d_nm | taper | alpha_tip, n, spacing_nm})`: a polyline
/// filament with a constant, linear or α-tip diameter profile (bead model, Sec. 4.2).
fn add_filament(spec: &Spec, s: &mut SceneRef, m: &Map) -> RResult<()> {
    let o = Opts::new(spec, m)?;
    let pts = match m.get(POINTS.name) {
        Some(v) => points("add_filament", v)?,
        None => return fail("add_filament: missing key `points` ([[x, y], ...] µm)"),
    };
    // at the prompt a one-point "filament" is a mistake (the simulator's own tests use one)
    if pts.len() == 1 {
        return fail(
            "add_filament: points has 1 vertex; a filament needs at least two [x, y] vertices (a point object is add_bead)",
        );
    }
    let profile = if let Some(t) = m.get(TAPER.name) {
        let [a, b] = pair("add_filament", TAPER.name, t)?;
        DiameterProfile::Linear { d0_nm: a, d1_nm: b }
    } else if let Some(t) = m.get(ALPHA_TIP.name) {
        let Some(tm) = t.read_lock::<Map>() else {
            return fail(format!(
                "add_filament: alpha_tip must be #{{d_nm, tip_um}}, got {t}"
            ));
        };
        let g = |k: &str| {
            tm.get(k)
                .map(|v| num("add_filament", &format!("alpha_tip.{k}"), v))
                .transpose()
        };
        DiameterProfile::AlphaTip {
            d_nm: g("d_nm")?.unwrap_or(ALPHA_TIP_D_NM),
            tip_um: g("tip_um")?.unwrap_or(ALPHA_TIP_UM),
        }
    } else {
        DiameterProfile::Constant {
            d_nm: o.f64_or(D_NM, FILAMENT_D_NM)?,
        }
    };
    s.0.add_filament(Filament {
        points: pts,
        z: o.f64_or(Z, 0.0)?,
        profile,
        n: o.f64_or(N, FILAMENT_N)?,
        spacing_nm: o.f64_or(SPACING_NM, FILAMENT_SPACING_NM)?,
    })
    .map_err(|e| err("add_filament", e))
}

/// `scene.add_aggregates(#{count, d_nm, n, x, y, z, seed})`: `count` point-like aggregates with
/// diameters uniform in d_nm and positions uniform in the x × y region (µm), from `seed`.
fn add_aggregates(spec: &Spec, s: &mut SceneRef, m: &Map) -> RResult<()> {
    let o = Opts::new(spec, m)?;
    let count = o.req_int(COUNT)?;
    if !(0..=AGGREGATES_MAX).contains(&count) {
        return fail(format!(
            "add_aggregates: count = {count} is out of range: 0 ≤ count ≤ {AGGREGATES_MAX}"
        ));
    }
    let get_pair = |k: &str, dflt: [f64; 2]| -> RResult<[f64; 2]> {
        m.get(k)
            .map(|v| pair("add_aggregates", k, v))
            .transpose()
            .map(|p| p.unwrap_or(dflt))
    };
    s.0.add_aggregates(Aggregates {
        count: count as usize,
        d_nm: get_pair("d_nm", AGGREGATE_D_NM)?,
        n: o.f64_or(N, AGGREGATE_N)?,
        region: [
            get_pair("x", AGGREGATE_REGION_UM)?,
            get_pair("y", AGGREGATE_REGION_UM)?,
        ],
        z: o.f64_or(Z, 0.0)?,
        seed: non_negative(
            "add_aggregates",
            "seed",
            o.int(SEED)?.unwrap_or(AGGREGATE_SEED),
        )?,
    })
    .map_err(|e| err("add_aggregates", e))
}

/// `scene.effects([names])`: enable exactly these effects, each with its default parameters.
fn effects(s: &mut SceneRef, names: Array) -> RResult<()> {
    let mut fx = crate::instrument::sim::scene::Effects::default();
    for n in names {
        let name = n
            .into_string()
            .map_err(|t| err("effects", format!("effect names must be strings, got {t}")))?;
        fx.enable(&name).map_err(|e| err("effects", e))?;
    }
    s.0.effects = fx;
    Ok(())
}

/// `scene.effect(name, #{params})`: enable one effect, its parameters overlaid on the defaults
/// (unknown parameters refused).
fn effect(s: &mut SceneRef, name: &str, params: Map) -> RResult<()> {
    let mut fx = s.0.effects.clone();
    fx.enable(name).map_err(|e| err("effect", e))?;
    // overlay the parameters on the defaults through serde (unknown keys refused)
    let mut full = serde_json::to_value(&fx).map_err(|e| err("effect", e))?;
    let slot = &mut full[name];
    if let (Some(obj), false) = (slot.as_object_mut(), params.is_empty()) {
        for (k, v) in params {
            if !obj.contains_key(k.as_str()) {
                let allowed: Vec<&String> = obj.keys().collect();
                return fail(format!(
                    "effect: {name} has no parameter `{k}`; allowed: {allowed:?}"
                ));
            }
            obj.insert(k.to_string(), super::types::dynamic_to_json(&v));
        }
    }
    let fx2: crate::instrument::sim::scene::Effects =
        serde_json::from_value(full).map_err(|e| err("effect", format!("{name}: {e}")))?;
    fx2.check().map_err(|e| err("effect", e))?;
    s.0.effects = fx2;
    Ok(())
}

/// `scene.rotate(angle_deg)`: rotate every object counter-clockwise about the origin.
fn rotate(s: &mut SceneRef, a: &Dynamic) -> RResult<()> {
    s.0.rotate(num("rotate", "angle_deg", a)?, [0.0, 0.0]);
    Ok(())
}

/// `simulate(scene, grid)`: render the scene straight to an XY scan on the grid (no stage, no
/// clock; not autosaved), `n_samples` samples per pixel.
fn simulate_grid(ctx: &Ctx, spec: &Spec, s: &SceneRef, m: &Map) -> RResult<ScanRef> {
    let o = Opts::new(spec, m)?;
    let (xs, ys) = super::registry::grid_axes("simulate", &o)?;
    let ns = o.int(N_SAMPLES)?.unwrap_or(SIMULATE_N_SAMPLES);
    if !(1..=100_000_000).contains(&ns) {
        return fail(format!(
            "simulate: n_samples = {ns} is out of range: 1 ≤ n_samples ≤ 100000000"
        ));
    }
    let r = crate::instrument::sim::Renderer::checked(&ctx.optics(), &s.0, Default::default())
        .map_err(|e| err("simulate", e))?;
    for n in &r.notes {
        ctx.log(&format!("simulate: note: {n}"));
    }
    let scan = render_xy(&r, &xs, &ys, o.f64_or(Z, 0.0)?, ns as usize);
    Ok(ScanRef::new(scan, None))
}

/// `pipeline()`: the simulated instrument's render stages with their wall time so far.
fn pipeline(ctx: &Ctx) -> RResult<Array> {
    let Some(core) = ctx.sim_core() else {
        return fail("pipeline: no simulated instrument; call simulate(scene) first");
    };
    Ok(core
        .renderer()
        .stages()
        .iter()
        .map(|s| json_to_dynamic(&serde_json::to_value(s).unwrap_or_default()))
        .collect())
}

/// Connect (or re-scene) the simulated instrument: when the simulator is what is connected,
/// its scene is replaced (position and clock kept); otherwise (nothing, the mock, hardware) a
/// new simulated instrument replaces the connected one.
fn install(ctx: &Ctx, scene: &Scene) -> RResult<Map> {
    let core = ctx.simulate_scene(scene).map_err(|e| err("simulate", e))?;
    let r = core.renderer();
    let mut m = Map::new();
    m.insert(
        "stages".into(),
        Dynamic::from_array(r.stage_names().into_iter().map(Dynamic::from).collect()),
    );
    m.insert("scatterers".into(), (r.scatterers.len() as INT).into());
    for n in &r.notes {
        ctx.log(&format!("simulate: note: {n}"));
    }
    m.insert(
        "notes".into(),
        Dynamic::from_array(r.notes.iter().cloned().map(Dynamic::from).collect()),
    );
    Ok(m)
}

fn scene_summary(s: &Scene) -> String {
    format!(
        "Scene: {} beads, {} filaments, {} aggregates; effects: [{}]; seed {}",
        s.beads.len(),
        s.filaments.len(),
        s.aggregates.iter().map(|a| a.count).sum::<usize>(),
        s.effects.names().join(", "),
        s.seed
    )
}
