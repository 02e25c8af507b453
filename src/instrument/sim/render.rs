//! The render pipeline: built from the scene's effects and nothing else (DESIGN: "simulate only
//! what the scene calls for"). An ideal scene is one stage, `superposition`: Σ αᵢ·T(s − pᵢ)
//! over precomputed single-scatterer templates (Sec. 4.1).

use super::domain::DomainCheck;
use super::scene::{MieEffect, Scatterer, Scene};
use crate::optics::beam::{DipoleTier, OpticsArg, ValidOptics, DIPOLE_D_NM, DIPOLE_N};
use crate::optics::finite_size::sphere_points;
use crate::optics::grid::Grid2;
use crate::optics::mie_template::{MieTemplate, MieTemplateSpec};
use crate::optics::params::OpticsError;
use crate::optics::rayleigh::{Detection, DetectorModel};
use crate::optics::template::{ModelTemplate, TemplateSpec};
use rand::Rng;
use rand_distr::StandardNormal;
use serde::Serialize;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// One pipeline stage with the wall time spent in it so far.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct StageInfo {
    pub name: String,
    pub seconds: f64,
    pub detail: String,
}

/// Template planes (and z weights) per scatterer, for one stage height.
type ScattererPlanes = Arc<Vec<Vec<(Arc<Grid2>, f64)>>>;

pub struct Renderer {
    pub optics: ValidOptics,
    pub scene: Scene,
    pub det: Arc<Detection>,
    pub template: Arc<ModelTemplate>,
    pub scatterers: Vec<Scatterer>,
    /// Mie templates (one per distinct bead (d, n), then the dipole limit for every other
    /// scatterer when the scene has the `mie` effect) and, per scatterer, which one renders it
    /// (`None`: the paraxial Rayleigh template; only without `mie`).
    pub mie: Vec<Arc<MieTemplate>>,
    pub mie_of: Vec<Option<usize>>,
    n_objects: usize,
    /// Name of the stage that renders through the angular-spectrum templates: "mie" when the
    /// scene names the effect (or in the paraxial beam), "vector_beam" when the vector beam
    /// alone sends the scatterers there.
    mie_stage: &'static str,
    stages: Mutex<Vec<StageInfo>>,
    /// Beads outside the point dipole's domain in a scene without `mie` or `finite_size`: what
    /// the simulator noticed about its own model (recorded in scan metadata, printed by
    /// `simulate`).
    pub notes: Vec<String>,
    /// (stage z bits, per-scatterer planes and weights) for the last z rendered
    plane_cache: Mutex<Option<(u64, ScattererPlanes)>>,
}

const SUPERPOSITION: &str = "superposition";
/// The stage that renders a scene without the `mie` effect in the vector beam.
pub const VECTOR_BEAM: &str = "vector_beam";

/// The point dipole's relative error `e` in words: "+16.6 % off", or "76.898× the value of" when
/// |e| ≥ 1 (a huge percentage reads badly).
fn how_far_off(e: f64) -> String {
    if e.abs() < 1.0 {
        format!("{:+.1} % off", 100.0 * e)
    } else {
        format!("{:.3}× the value of", 1.0 + e)
    }
}

/// Notes on beads the point dipole renders more than 1 % off the Mie tier (normalised to the
/// 110 nm polystyrene reference), from the domain check.
fn model_notes(domain: &DomainCheck) -> Vec<String> {
    let mut notes = vec![];
    for d in &domain.entries {
        if let Some(e) = domain.outside(d.d_nm, d.n) {
            let off = how_far_off(e);
            notes.push(format!(
                "bead d = {} nm, n = {}: the point dipole's sensitivity is {off} the Mie tier \
                 (relative to a 110 nm polystyrene bead; docs/accuracy.md#model_500); add the `mie` effect if \
                 its amplitude matters",
                d.d_nm, d.n
            ));
        }
    }
    notes
}

/// The scene picks the tier (vector beam only): the beads (object indices) outside the
/// point dipole's measured domain (the domain check) with one note per species. They are
/// rendered as Lorenz–Mie spheres in the vector beam automatically unless the scene pins a tier
/// by naming `mie` or `finite_size`.
fn auto_mie_beads(scene: &Scene, domain: &DomainCheck) -> (Vec<usize>, Vec<String>) {
    let mut out = vec![];
    for (i, b) in scene.beads.iter().enumerate() {
        if domain.outside(b.d_nm, b.n).is_some() {
            out.push(i);
        }
    }
    let notes = domain
        .entries
        .iter()
        .filter_map(|d| {
            domain.outside(d.d_nm, d.n).map(|e| {
                format!(
                    "bead d = {} nm, n = {}: outside the point dipole's domain (its sensitivity would be {} the Mie tier, docs/accuracy.md#model_500): rendered by the Lorenz–Mie tier in the vector beam (name the `mie` or `finite_size` effect to pin a tier)",
                    d.d_nm, d.n, how_far_off(e)
                )
            })
        })
        .collect();
    (out, notes)
}

/// The scatterers with every bead of at least `min_d_nm` (not rendered as a Mie sphere)
/// replaced by the dipoles of a sphere rule of order `n_r` (the `finite_size` effect, S6).
fn sphere_dipoles(
    scatterers: &[Scatterer],
    min_d_nm: f64,
    n_r: usize,
    is_mie: &dyn Fn(&Scatterer) -> bool,
) -> Vec<Scatterer> {
    let mut out = Vec::with_capacity(scatterers.len());
    for s in scatterers {
        match s.d_nm {
            // Mie beads are whole spheres already
            Some(d) if d >= min_d_nm && d > 0.0 && !is_mie(s) => {
                for (o, w) in sphere_points(d * 1e-3, n_r) {
                    out.push(Scatterer {
                        pos: [s.pos[0] + o[0], s.pos[1] + o[1], s.pos[2] + o[2]],
                        alpha: s.alpha * w,
                        ..*s
                    });
                }
            }
            _ => out.push(*s),
        }
    }
    out
}

/// The Mie tier's templates: one per bead species rendered as a Lorenz–Mie sphere, and one
/// point dipole in the same beam for every other scatterer; `mie_of[i]` is scatterer i's
/// template. Returns the species (d, n), the count of Mie beads and of point dipoles.
#[allow(clippy::type_complexity)]
fn mie_templates(
    optics: &ValidOptics,
    scene: &Scene,
    scatterers: &[Scatterer],
    spec: MieTemplateSpec,
    is_mie: &dyn Fn(&Scatterer) -> bool,
    mie: &mut Vec<Arc<MieTemplate>>,
    mie_of: &mut [Option<usize>],
) -> Result<(Vec<(f64, f64)>, usize, usize), OpticsError> {
    let mut keys: Vec<(f64, f64)> = Vec::new();
    let mut n_mie = 0;
    for (i, s) in scatterers.iter().enumerate() {
        if !is_mie(s) {
            continue;
        }
        let (d, n) = (s.d_nm.unwrap_or(0.0), scene.beads[s.object].n);
        let idx = match keys.iter().position(|&(a, b)| a == d && b == n) {
            Some(i) => i,
            None => {
                mie.push(MieTemplate::shared(optics, d, n, spec, false)?);
                keys.push((d, n));
                keys.len() - 1
            }
        };
        mie_of[i] = Some(idx);
        n_mie += 1;
    }
    // Every other scatterer (filament beads, aggregates, beads below min_d_nm, finite-size
    // dipoles) renders as a point dipole in the same angular-spectrum beam: the Mie
    // tier's own small-sphere limit. The paraxial Rayleigh template would put them in a
    // different beam (at the paper's optics its focus is 1.34× narrower and its maximum
    // sensitivity 1.4–1.6× larger than the Mie tier's dipole limit, docs/physics.md §9),
    // so a scene would mix two instruments.
    let n_dip = scatterers.len() - n_mie;
    if n_dip > 0 {
        mie.push(MieTemplate::shared(
            optics,
            DIPOLE_D_NM,
            DIPOLE_N,
            spec,
            true,
        )?);
        let idx = mie.len() - 1;
        for m in mie_of.iter_mut().filter(|m| m.is_none()) {
            *m = Some(idx);
        }
    }
    Ok((keys, n_mie, n_dip))
}

/// The pipeline stages the scene's other effects add, applied per read (their cost is in the
/// read): name and what each does.
fn effect_stages(fx: &super::scene::Effects) -> Vec<(&'static str, String)> {
    let mut out = Vec::new();
    if let Some(t) = fx.thermal_motion {
        out.push((
            "thermal_motion",
            format!(
                "rigid jitter σ = {} nm per object, {} configurations per read",
                t.sigma_nm, t.samples
            ),
        ));
    }
    if let Some(d) = fx.drift {
        out.push((
            "drift",
            format!(
                "{:?} nm/s + random walk {} nm/√s",
                d.velocity_nm_s, d.random_walk_nm_sqrt_s
            ),
        ));
    }
    if let Some(b) = fx.stage_bandwidth {
        out.push((
            "stage_bandwidth",
            format!(
                "stage lag τ = {:.3} ms ({} Hz) under the wave generator (raster lines)",
                b.tau_s() * 1e3,
                b.hz
            ),
        ));
    }
    if let Some(p) = fx.pointing_noise {
        out.push((
            "pointing_noise",
            format!("beam jitter σ = {} nm per sample", p.sigma_nm_sample),
        ));
    }
    if fx.cross_terms == Some(true) {
        out.push((
            "cross_terms",
            "|Σ E_scat|² over the cone (all scatterers, per pixel)".into(),
        ));
    }
    if let Some(l) = fx.laser_power_noise {
        out.push((
            "laser_power_noise",
            format!("relative power noise σ = {} per sample", l.sigma_rel_sample),
        ));
    }
    if let Some(d) = fx.detector_noise {
        out.push((
            "detector_noise",
            format!("white noise σ = {:e} per sample", d.sigma_sample),
        ));
    }
    if let Some(d) = fx.detector_range {
        out.push(("detector_range", super::detector::describe(&d)));
    }
    out
}

/// What the Mie stage renders, for the pipeline's stage list: `[Mie beads, point dipoles,
/// beads the scene sent to the Mie tier, sphere templates]`.
fn mie_stage_detail(
    optics: &ValidOptics,
    vector: bool,
    mie_stage: &str,
    m: &MieEffect,
    [n_mie, n_dip, n_auto, n_keys]: [usize; 4],
) -> String {
    if mie_stage == VECTOR_BEAM {
        format!(
            "aplanatic vector beam, NA {}, pupil filling {}: {n_dip} scatterers as point dipoles; {n_mie} beads outside the point dipole's domain ({} picked by the scene) as Lorenz–Mie spheres ({} sphere templates)",
            optics.na,
            optics.pupil_filling,
            n_auto,
            n_keys
        )
    } else {
        format!(
            "{}{n_mie} beads ≥ {} nm{} as Lorenz–Mie spheres in the angular-spectrum beam ({} sphere templates{}); {n_dip} other scatterers (filaments, aggregates, smaller beads) as point dipoles in the same beam",
            if vector {
                format!("aplanatic vector beam, NA {}, pupil filling {}: ", optics.na, optics.pupil_filling)
            } else {
                String::new()
            },
            m.min_d_nm,
            if n_auto == 0 {
                String::new()
            } else {
                format!(" or outside the point dipole's domain ({} picked by the scene)", n_auto)
            },
            n_keys,
            if m.scattered_intensity { ", with |E_s|²" } else { "" }
        )
    }
}

/// The detector's stages: the vector dipole field (`polarization`) and the QPD's
/// misalignment, with the time since `t0` for the first.
fn detector_stages(
    model: &DetectorModel,
    vector: bool,
    t0: Instant,
) -> Vec<(&'static str, f64, String)> {
    let mut out = Vec::new();
    if model.polarization {
        out.push((
            "polarization",
            t0.elapsed().as_secs_f64(),
            if vector {
                "inherent in the vector beam (its dipole field is always vectorial): nothing added"
                    .into()
            } else {
                "vector dipole field, x-polarised beam: cone weights × (1 − cos²φ(1 − cosθ))".into()
            },
        ));
    }
    if let Some(m) = model.misalignment {
        out.push((
            "misalignment",
            0.0,
            format!(
                "QPD offset ({}, {}) of the cone radius, rotation {}°, Sy gain {}",
                m.offset_x, m.offset_y, m.rotation_deg, m.gain_y
            ),
        ));
    }
    out
}

impl Renderer {
    /// Build the pipeline for `scene`, first running the point dipole's domain check (a stage
    /// of its own, `domain check`) through the process-wide memo
    /// ([`DomainCheck::run_shared`]), so a scene built again costs no Mie response. The
    /// simulator runs the check through its session memo and calls [`Renderer::new`].
    pub fn checked(
        optics: &impl OpticsArg,
        scene: &Scene,
        spec: TemplateSpec,
    ) -> Result<Self, OpticsError> {
        let optics = optics.valid()?;
        let domain = DomainCheck::run_shared(&optics, scene);
        Self::new(&*optics, scene, spec, &domain)
    }

    /// Build the pipeline for `scene` with the result of its domain check.
    pub fn new(
        optics: &impl OpticsArg,
        scene: &Scene,
        spec: TemplateSpec,
        domain: &DomainCheck,
    ) -> Result<Self, OpticsError> {
        let optics = optics.valid()?;
        let optics: &ValidOptics = &optics;
        let t0 = Instant::now();
        let fx = &scene.effects;
        let model = DetectorModel {
            polarization: fx.polarization == Some(true),
            misalignment: fx.misalignment,
        };
        let det = Arc::new(Detection::new(optics, &model)?);
        let template = Arc::new(ModelTemplate::new(det.clone(), spec)?);
        let mut scatterers = scene.scatterers(optics.n_medium);
        // beads come first in `scatterers` (objects 0 … n_beads − 1)
        let n_beads = scene.beads.len();
        // With the vector beam every scatterer goes through the angular-spectrum
        // templates (dipole limit), and beads outside the dipole's domain through Mie, unless
        // the scene pins a tier (`mie` / `finite_size`).
        let vector = optics.beam().dipoles() == DipoleTier::AngularSpectrum;
        if vector && fx.cross_terms == Some(true) {
            return Err(OpticsError::Invalid(
                "effect cross_terms is modelled in the paraxial beam only (|Σ E_scat|² with the paper's Gaussian focus, docs/physics.md §8); the session's beam is \"vector\": set_optics(#{beam: \"paraxial\"}) to use it, or the mie effect's scattered_intensity for one sphere's |E_s|² in the vector beam".into(),
            ));
        }
        let pinned = fx.mie.is_some() || fx.finite_size.is_some();
        let (auto_mie, auto_notes) = if vector && !pinned {
            auto_mie_beads(scene, domain)
        } else {
            (vec![], vec![])
        };
        let mie_stage = if fx.mie.is_none() && vector {
            VECTOR_BEAM
        } else {
            "mie"
        };
        let mie_fx = fx.mie.or(vector.then_some(MieEffect {
            min_d_nm: f64::INFINITY,
            scattered_intensity: false,
        }));
        let is_mie = |s: &Scatterer| match (mie_fx, s.d_nm) {
            (Some(m), Some(d)) => {
                s.object < n_beads && (d >= m.min_d_nm || auto_mie.contains(&s.object)) && d > 0.0
            }
            _ => false,
        };
        let n_objects = scatterers.iter().map(|s| s.object + 1).max().unwrap_or(0);
        let mut stages = vec![StageInfo {
            name: SUPERPOSITION.into(),
            seconds: 0.0,
            detail: format!(
                "{} scatterers from {} objects; template h = {} µm, hz = {} µm, {:?}",
                scatterers.len(),
                n_objects,
                spec.h,
                spec.hz,
                spec.interp
            ),
        }];
        let mut push = |name: &str, secs: f64, detail: String| {
            stages.push(StageInfo {
                name: name.into(),
                seconds: secs,
                detail,
            })
        };
        if !domain.entries.is_empty() {
            push(
                "domain check",
                domain.seconds,
                format!(
                    "point dipole vs Mie tier for {} bead species (d ≥ 200 nm, or ≥ 60 nm off polystyrene's index)",
                    domain.entries.len()
                ),
            );
        }
        for (name, secs, detail) in detector_stages(&model, vector, t0) {
            push(name, secs, detail);
        }
        if let Some(fs) = fx.finite_size {
            let t = Instant::now();
            scatterers = sphere_dipoles(&scatterers, fs.min_d_nm, fs.n_r, &is_mie);
            let n = scatterers.len();
            push(
                "finite_size",
                t.elapsed().as_secs_f64(),
                format!(
                    "beads ≥ {} nm as sphere rules of order {} → {n} dipoles",
                    fs.min_d_nm, fs.n_r
                ),
            );
        }
        let mut mie: Vec<Arc<MieTemplate>> = Vec::new();
        let mut mie_of = vec![None; scatterers.len()];
        if let Some(m) = mie_fx {
            let t = Instant::now();
            let spec = MieTemplateSpec {
                grid: spec,
                detector: model,
                scattered_intensity: m.scattered_intensity,
            };
            let (keys, n_mie, n_dip) = mie_templates(
                optics,
                scene,
                &scatterers,
                spec,
                &is_mie,
                &mut mie,
                &mut mie_of,
            )?;
            let detail = mie_stage_detail(
                optics,
                vector,
                mie_stage,
                &m,
                [n_mie, n_dip, auto_mie.len(), keys.len()],
            );
            push(mie_stage, t.elapsed().as_secs_f64(), detail);
        }
        for (name, detail) in effect_stages(fx) {
            push(name, 0.0, detail);
        }
        let notes = if vector {
            auto_notes
        } else if fx.mie.is_none() && fx.finite_size.is_none() {
            model_notes(domain)
        } else {
            vec![]
        };
        Ok(Self {
            notes,
            optics: optics.clone(),
            scene: scene.clone(),
            det,
            template,
            scatterers,
            mie,
            mie_of,
            n_objects,
            mie_stage,
            stages: Mutex::new(stages),
            plane_cache: Mutex::new(None),
        })
    }

    /// The stages built, in order, with the time spent in each so far.
    pub fn stages(&self) -> Vec<StageInfo> {
        self.stages
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }

    pub fn stage_names(&self) -> Vec<String> {
        self.stages().into_iter().map(|s| s.name).collect()
    }

    /// The digitiser's view of a reading of `n` samples (the `detector_range` effect, when
    /// the scene has it): the means as read and the clipped samples per channel.
    pub fn detect(&self, v: [f64; 3], sd: [f64; 3], n: usize) -> ([f64; 3], [usize; 3]) {
        match &self.scene.effects.detector_range {
            Some(d) => {
                let t = Instant::now();
                let r = super::detector::apply(d, v, sd, n);
                self.add_time("detector_range", t.elapsed().as_secs_f64());
                r
            }
            None => (v, [0; 3]),
        }
    }

    fn add_time(&self, name: &str, secs: f64) {
        if let Some(s) = self
            .stages
            .lock()
            .unwrap()
            .iter_mut()
            .find(|s| s.name == name)
        {
            s.seconds += secs;
        }
    }

    /// Per-scatterer template planes for stage height z (cached for the last z).
    fn planes_at(&self, z: f64) -> ScattererPlanes {
        let key = z.to_bits();
        if let Some((k, p)) = self
            .plane_cache
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .as_ref()
        {
            if *k == key {
                return p.clone();
            }
        }
        let p: Arc<Vec<_>> = Arc::new(
            self.scatterers
                .iter()
                .zip(&self.mie_of)
                .map(|(s, m)| match m {
                    None => self.template.planes_for(z - s.pos[2]),
                    Some(i) => self.mie_planes(*i, z - s.pos[2]),
                })
                .collect(),
        );
        *self
            .plane_cache
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Some((key, p.clone()));
        p
    }

    /// Mie template planes for displacement z, timed into the `mie` stage. A plane that cannot
    /// be built (not expected for validated scenes) falls back to the Rayleigh template and says
    /// so in the stage detail, which scan metadata records.
    fn mie_planes(&self, i: usize, z: f64) -> Vec<(Arc<Grid2>, f64)> {
        let t = Instant::now();
        let r = self.mie[i].planes_for(z);
        self.add_time(self.mie_stage, t.elapsed().as_secs_f64());
        match r {
            Ok(p) => p,
            Err(e) => {
                if let Some(st) = self
                    .stages
                    .lock()
                    .unwrap()
                    .iter_mut()
                    .find(|s| s.name == self.mie_stage)
                {
                    let note = format!("; Rayleigh used at z = {z} µm: {e}");
                    if !st.detail.contains(&note) {
                        st.detail += &note;
                    }
                }
                self.template.planes_for(z)
            }
        }
    }

    /// Ideal superposition at stage position s with optional per-object lateral offsets (µm).
    fn superpose(
        &self,
        planes: &[Vec<(Arc<Grid2>, f64)>],
        s: [f64; 3],
        obj_offset: Option<&[[f64; 2]]>,
    ) -> [f64; 3] {
        let mut out = [0.0; 3];
        for (sc, pl) in self.scatterers.iter().zip(planes) {
            let (mut dx, mut dy) = (s[0] - sc.pos[0], s[1] - sc.pos[1]);
            if let Some(o) = obj_offset {
                dx -= o[sc.object][0];
                dy -= o[sc.object][1];
            }
            for (g, w) in pl {
                let v = g.eval(dx, dy);
                let f = w * sc.alpha;
                out[0] += f * v[0];
                out[1] += f * v[1];
                out[2] += f * v[2];
            }
        }
        out
    }

    /// The Escat·Escat* term over the cone (main text Sec. 4.1, suppl. S7): per cone node the
    /// coherent sum of all scattered fields, |Σ_p E_p|², normalised to the beam power.
    pub fn cross_term(&self, s: [f64; 3]) -> [f64; 3] {
        let det = &self.det;
        let k = det.k;
        let mut out = [0.0; 3];
        // per-scatterer amplitude and base phase
        let parts: Vec<(f64, f64, [f64; 3])> = self
            .scatterers
            .iter()
            .filter_map(|sc| {
                let d = [s[0] - sc.pos[0], s[1] - sc.pos[1], s[2] - sc.pos[2]];
                let (w, inv_r, gouy) = det.beam_at(d[2]);
                let rho2 = d[0] * d[0] + d[1] * d[1];
                let a = sc.alpha * (det.w0 / w) * (-rho2 / (w * w)).exp();
                (a != 0.0).then(|| (a, k * d[2] + 0.5 * k * rho2 * inv_r - gouy, d))
            })
            .collect();
        if parts.is_empty() {
            return out;
        }
        let pref = 2.0 * k.powi(4) / (std::f64::consts::PI * det.w0 * det.w0);
        for n in &det.nodes {
            let (mut re, mut im) = (0.0, 0.0);
            for (a, base, d) in &parts {
                let (sp, cp) = (base - k * (d[0] * n.u + d[1] * n.v + d[2] * n.c)).sin_cos();
                re += a * cp;
                im += a * sp;
            }
            let i = pref * n.wq * n.pol_ss * (re * re + im * im);
            for c in 0..3 {
                out[c] += n.s[c] * i;
            }
        }
        out
    }

    /// One QPD reading at actual stage position `s` (drift already applied by the caller),
    /// averaging `n_samples` samples: the pipeline, stage by stage.
    pub fn render_point<R: Rng>(
        &self,
        s: [f64; 3],
        n_samples: usize,
        rng: &mut R,
    ) -> ([f64; 3], [f64; 3]) {
        let fx = &self.scene.effects;
        let n = n_samples.max(1) as f64;
        let mut pos = s;
        if let Some(p) = fx.pointing_noise {
            let t = Instant::now();
            let sig = p.sigma_nm_sample * 1e-3 / n.sqrt();
            pos[0] += sig * rng.sample::<f64, _>(StandardNormal);
            pos[1] += sig * rng.sample::<f64, _>(StandardNormal);
            self.add_time("pointing_noise", t.elapsed().as_secs_f64());
        }
        let planes = self.planes_at(pos[2]);
        let mut v = [0.0; 3];
        if let Some(th) = fx.thermal_motion {
            let t = Instant::now();
            let m = th.samples.max(1);
            let sig = th.sigma_nm * 1e-3;
            let mut offs = vec![[0.0; 2]; self.n_objects];
            for _ in 0..m {
                for o in offs.iter_mut() {
                    *o = [
                        sig * rng.sample::<f64, _>(StandardNormal),
                        sig * rng.sample::<f64, _>(StandardNormal),
                    ];
                }
                let a = self.superpose(&planes, pos, Some(&offs));
                for c in 0..3 {
                    v[c] += a[c] / m as f64;
                }
            }
            self.add_time("thermal_motion", t.elapsed().as_secs_f64());
        } else {
            let t = Instant::now();
            v = self.superpose(&planes, pos, None);
            self.add_time(SUPERPOSITION, t.elapsed().as_secs_f64());
        }
        if fx.cross_terms == Some(true) {
            let t = Instant::now();
            let c = self.cross_term(pos);
            for k in 0..3 {
                v[k] += c[k];
            }
            self.add_time("cross_terms", t.elapsed().as_secs_f64());
        }
        let mut std = [0.0; 3];
        if let Some(l) = fx.laser_power_noise {
            let t = Instant::now();
            let sd = l.sigma_rel_sample;
            let eps = sd / n.sqrt() * rng.sample::<f64, _>(StandardNormal);
            // Sx, Sy are differences of intensities that all scale with the power; Sz is the
            // total (1 + δ) minus the calibrated baseline 1.
            v[0] *= 1.0 + eps;
            v[1] *= 1.0 + eps;
            v[2] = (1.0 + eps) * (1.0 + v[2]) - 1.0;
            std[0] += (sd * v[0]).powi(2);
            std[1] += (sd * v[1]).powi(2);
            std[2] += (sd * (1.0 + v[2])).powi(2);
            self.add_time("laser_power_noise", t.elapsed().as_secs_f64());
        }
        if let Some(d) = fx.detector_noise {
            let t = Instant::now();
            let sig = d.sigma_sample / n.sqrt();
            for c in 0..3 {
                v[c] += sig * rng.sample::<f64, _>(StandardNormal);
                std[c] += d.sigma_sample.powi(2);
            }
            self.add_time("detector_noise", t.elapsed().as_secs_f64());
        }
        (v, std.map(f64::sqrt))
    }

    /// Ideal superposition over a whole XY grid at stage height z: Σ αᵢ·T(s − pᵢ) (Sec. 4.1),
    /// dimensionless signals. Returns row-major (y, x) arrays of Sx, Sy, Sz. This is the
    /// benchmarked hot path (docs/performance.md, "Rendering").
    ///
    /// Rows are rendered in parallel (rayon); each pixel sums its scatterers in the scene's
    /// order, and each scatterer only touches the pixels inside its template's support. The
    /// cubic stencil along x (node index and Keys weights) is computed once per scatterer and
    /// pixel column, along y once per scatterer and row, with [`Grid2::eval`]'s own arithmetic,
    /// so the image is bit-identical to [`Renderer::render_grid_reference`].
    pub fn render_grid_ideal(&self, xs: &[f64], ys: &[f64], z: f64) -> [Vec<f64>; 3] {
        use rayon::prelude::*;
        let t = Instant::now();
        let (nx, ny) = (xs.len(), ys.len());
        let planes = self.planes_at(z);
        // each distinct plane once, its nodes padded to four lanes (Sx, Sy, Sz, 0) so that one
        // node is one 256-bit vector
        let mut distinct: Vec<(*const Grid2, Vec<[f64; 4]>)> = Vec::new();
        let mut terms = Vec::new();
        for (sc, pl) in self.scatterers.iter().zip(planes.iter()) {
            for (g, w) in pl {
                let ((u0, u1), (v0, v1)) = g.extent();
                let (ix0, ix1) = index_window(xs, sc.pos[0] + u0, sc.pos[0] + u1);
                let (iy0, iy1) = index_window(ys, sc.pos[1] + v0, sc.pos[1] + v1);
                if ix0 >= ix1 || iy0 >= iy1 {
                    continue;
                }
                let key = Arc::as_ptr(g);
                let plane = match distinct.iter().position(|(p, _)| *p == key) {
                    Some(k) => k,
                    None => {
                        let pad = g.data.iter().map(|v| [v[0], v[1], v[2], 0.0]).collect();
                        distinct.push((key, pad));
                        distinct.len() - 1
                    }
                };
                terms.push(Term {
                    g,
                    plane,
                    f: w * sc.alpha,
                    pos: [sc.pos[0], sc.pos[1]],
                    ix0,
                    iy: (iy0, iy1),
                    sx: xs[ix0..ix1]
                        .iter()
                        .map(|&x| g.stencil_u(x - sc.pos[0]))
                        .collect(),
                });
            }
        }
        let padded: Vec<&[[f64; 4]]> = distinct.iter().map(|(_, p)| p.as_slice()).collect();
        let rows = Rows {
            terms: &terms,
            padded: &padded,
            xs,
            ys,
        };
        let mut px = vec![[0.0f64; 4]; nx * ny];
        #[cfg(target_arch = "x86_64")]
        let avx = std::arch::is_x86_feature_detected!("avx");
        px.par_chunks_mut(nx.max(1))
            .enumerate()
            .for_each(|(iy, row)| {
                #[cfg(target_arch = "x86_64")]
                if avx {
                    // SAFETY: the CPU has AVX (checked above); the function only differs from
                    // `render_row` in the instructions the compiler may pick.
                    unsafe { render_row_avx(&rows, iy, row) };
                    return;
                }
                render_row(&rows, iy, row)
            });
        let out = [0, 1, 2].map(|c| px.iter().map(|p| p[c]).collect());
        self.add_time(SUPERPOSITION, t.elapsed().as_secs_f64());
        out
    }

    /// The reference implementation of [`Renderer::render_grid_ideal`] (before the speed work):
    /// serial, scatterer-major, [`Grid2::eval`] per scatterer and pixel. Kept for the test that
    /// holds the fast path to it (`tests/sim.rs`) and for the render bench's "before" numbers.
    pub fn render_grid_reference(&self, xs: &[f64], ys: &[f64], z: f64) -> [Vec<f64>; 3] {
        let (nx, ny) = (xs.len(), ys.len());
        let mut out = [vec![0.0; nx * ny], vec![0.0; nx * ny], vec![0.0; nx * ny]];
        let planes = self.planes_at(z);
        for (sc, pl) in self.scatterers.iter().zip(planes.iter()) {
            for (g, w) in pl {
                let ((u0, u1), (v0, v1)) = g.extent();
                let f = w * sc.alpha;
                let (ix0, ix1) = index_window(xs, sc.pos[0] + u0, sc.pos[0] + u1);
                let (iy0, iy1) = index_window(ys, sc.pos[1] + v0, sc.pos[1] + v1);
                for iy in iy0..iy1 {
                    let dy = ys[iy] - sc.pos[1];
                    let row = iy * nx;
                    for ix in ix0..ix1 {
                        let v = g.eval(xs[ix] - sc.pos[0], dy);
                        out[0][row + ix] += f * v[0];
                        out[1][row + ix] += f * v[1];
                        out[2][row + ix] += f * v[2];
                    }
                }
            }
        }
        out
    }
}

/// One (scatterer, template plane) term of [`Renderer::render_grid_ideal`]: its weight w·α,
/// pixel window and cubic stencils along x (one per pixel column of the window).
struct Term<'a> {
    g: &'a Grid2,
    /// index of the padded copy of `g`'s nodes
    plane: usize,
    f: f64,
    pos: [f64; 2],
    ix0: usize,
    iy: (usize, usize),
    sx: Vec<Option<(usize, [f64; 4])>>,
}

/// What every pixel row of [`Renderer::render_grid_ideal`] reads: the terms, the padded planes
/// they index, and the grid's axes.
struct Rows<'a> {
    terms: &'a [Term<'a>],
    padded: &'a [&'a [[f64; 4]]],
    xs: &'a [f64],
    ys: &'a [f64],
}

/// Add every term's contribution to pixel row `iy` (four lanes per pixel: Sx, Sy, Sz, 0).
/// Per lane the arithmetic is [`Grid2::eval`]'s fast path, in its order, without fused
/// multiply-adds, so the sums are bit-identical to the reference path.
#[inline(always)]
fn render_row(rows: &Rows, iy: usize, row: &mut [[f64; 4]]) {
    let Rows {
        terms,
        padded,
        xs,
        ys,
    } = *rows;
    for tm in terms.iter().filter(|tm| tm.iy.0 <= iy && iy < tm.iy.1) {
        let (g, f) = (tm.g, tm.f);
        let dy = ys[iy] - tm.pos[1];
        let out = &mut row[tm.ix0..tm.ix0 + tm.sx.len()];
        let sv = g.stencil_v(dy);
        let data = padded[tm.plane];
        for ((o, st), &x) in out.iter_mut().zip(&tm.sx).zip(&xs[tm.ix0..]) {
            let v = match (st, &sv) {
                (Some((iu, wu)), Some((iv, wv))) => {
                    let mut v = [0.0; 4];
                    for (b, &wvb) in wv.iter().enumerate() {
                        let base = (iv + b) * g.nu + iu;
                        let nodes = &data[base..base + 4];
                        let mut acc = [0.0; 4];
                        for (n, &wua) in nodes.iter().zip(wu) {
                            for c in 0..4 {
                                acc[c] += wua * n[c];
                            }
                        }
                        for c in 0..4 {
                            v[c] += wvb * acc[c];
                        }
                    }
                    v
                }
                _ => {
                    let e = g.eval(x - tm.pos[0], dy);
                    [e[0], e[1], e[2], 0.0]
                }
            };
            for c in 0..4 {
                o[c] += f * v[c];
            }
        }
    }
}

/// [`render_row`] compiled for AVX (four f64 lanes: one template node per vector).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn render_row_avx(rows: &Rows, iy: usize, row: &mut [[f64; 4]]) {
    render_row(rows, iy, row)
}

/// Indices [i0, i1) of a monotonic axis whose values fall inside [lo, hi].
fn index_window(a: &[f64], lo: f64, hi: f64) -> (usize, usize) {
    if a.is_empty() {
        return (0, 0);
    }
    let asc = a.len() < 2 || a[1] >= a[0];
    if asc {
        (
            a.partition_point(|&v| v < lo),
            a.partition_point(|&v| v <= hi),
        )
    } else {
        // descending axis: the window is where lo ≤ v ≤ hi
        (
            a.partition_point(|&v| v > hi),
            a.partition_point(|&v| v >= lo),
        )
    }
}
