//! The sweep's scenes on an XY field: the paper's detector noise × a factor, a digitiser of
//! finite range for one scene in four, the square field rendered by the simulator. Shared by the
//! families of the sweep (beads, fibrils, microtubules, max_sens).

use super::focus::Outcome;
use crate::instrument::sim::scene::{
    Bead, DetectorNoise, DetectorRange, Scene, PAPER_DETECTOR_SIGMA_SAMPLE, PAPER_SAMPLES_PER_PIXEL,
};
use crate::instrument::sim::{render_xy, Renderer};
use crate::optics::params::Optics;
use crate::optics::params::REF_BEAD_N;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Samples per simulated pixel read: the paper's (and `simulate`'s default), so that noise × 1
/// is the paper's per-pixel noise.
pub(super) const N_SAMPLES: usize = PAPER_SAMPLES_PER_PIXEL;

/// One scene in four goes through a digitiser of finite range: ±r signal units, r log-uniform
/// over 3·10⁻⁴–0.3 (a 110 nm bead's Sx peaks near 2·10⁻³, a 500 nm bead's near 0.2), so that
/// some scenes clip and some do not.
pub(super) fn draw_clip(rng: &mut ChaCha8Rng) -> Option<f64> {
    let r = (3e-4f64.ln() + rng.random::<f64>() * 1000f64.ln()).exp();
    (rng.random_range(0..4) == 0).then_some(r)
}

/// The scene with the paper's detector noise × `noise` drawn from `seed`, rendered on a square
/// field of ±`half` µm in pixels of `pixel` µm (None when the renderer refuses the scene).
pub(super) fn render_field(
    optics: &Optics,
    mut sc: Scene,
    half: f64,
    pixel: f64,
    (noise, clip): (f64, Option<f64>),
    seed: u64,
) -> Option<crate::data::Scan> {
    sc.effects.detector_noise = Some(DetectorNoise {
        sigma_sample: noise * PAPER_DETECTOR_SIGMA_SAMPLE,
    });
    // the sum input at half the range with the full beam, its floor at 1 % of it
    sc.effects.detector_range = clip.map(|r| DetectorRange {
        range: r,
        sum_scale: 0.5 * r,
        sum_floor: 0.01 * r,
        power: 1.0,
    });
    sc.seed = seed;
    let n = (2.0 * half / pixel).round() as usize + 1;
    let axis: Vec<f64> = (0..n)
        .map(|i| -half + 2.0 * half * i as f64 / (n - 1) as f64)
        .collect();
    let r = Renderer::checked(optics, &sc, Default::default()).ok()?;
    Some(render_xy(&r, &axis, &axis, 0.0, N_SAMPLES))
}

/// ", input range ±r" of a scene with a finite digitiser range, "" without.
pub(super) fn clip_words(clip: Option<f64>) -> String {
    clip.map(|r| format!(", input range ±{r:.2e}"))
        .unwrap_or_default()
}

/// A scene holding one polystyrene bead `[x µm, y µm, z µm, d nm]` (z: its height above the
/// focal plane), or nothing (an empty field).
pub(super) fn one_bead_scene(bead: Option<[f64; 4]>) -> Scene {
    let mut sc = Scene::default();
    if let Some([x, y, z, d]) = bead {
        let _ = sc.add_bead(Bead {
            pos: [x, y, z],
            d_nm: d,
            n: REF_BEAD_N,
        });
    }
    sc
}

/// The bead `[x, y, z, d]` in words, or "empty field".
pub(super) fn bead_words(bead: Option<[f64; 4]>) -> String {
    match bead {
        Some([x, y, z, d]) => {
            format!("bead d {d:.1} nm at ({x:.3}, {y:.3}) µm, {z:.3} µm from the focus")
        }
        None => "empty field".into(),
    }
}

/// An empty field's outcome: an answer without a warning is an object found where there is
/// none (an outlier by any measure), else the flags or the refusal `why`.
pub(super) fn empty_field_outcome(
    found: Option<(f64, f64)>,
    why: Vec<String>,
    what: &str,
) -> Outcome {
    match found {
        Some((x, y)) if why.is_empty() => Outcome::Answer {
            value: 1.0,
            truth: 0.0,
            sigma: None,
            rel_limit: Some(0.05),
            what: format!("an object found at ({x:.3}, {y:.3}) µm in an empty field: {what}"),
        },
        _ => Outcome::Flagged(why),
    }
}
