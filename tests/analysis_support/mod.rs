//! Helpers shared by tests/analysis.rs and tests/analysis_hard.rs: synthetic scenes rendered from
//! a template by superposition, with seeded Gaussian pixel noise.
#![allow(dead_code)]

use bfpscope::analysis::bead_model::{render_scene, BeadModelOptions, Filament};
use bfpscope::analysis::template::Template;
use bfpscope::data::{Image, Scan};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

/// Analytic stand-in template: Sx = u·exp(−r²/w²), Sy = v·exp(−r²/w²), w = 0.4 µm (so the
/// reference bead's max ∂Sx/∂x is 1 at the origin), grid 20 nm over ±1.6 µm.
pub fn standin() -> Template {
    Template::analytic_standin(0.4, 0.02, 1.6).unwrap()
}

/// Regular axis of n pixels of size h starting at x0 (µm).
pub fn axis(n: usize, h: f64, x0: f64) -> Vec<f64> {
    (0..n).map(|i| x0 + i as f64 * h).collect()
}

/// Add white Gaussian noise of standard deviation sigma to every channel (seeded).
pub fn add_noise(scan: &mut Scan, sigma: f64, seed: u64) {
    if sigma <= 0.0 {
        return;
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let nd = Normal::new(0.0, sigma).unwrap();
    for img in [&mut scan.sx, &mut scan.sy, &mut scan.sz] {
        img.data.mapv_inplace(|v| v + nd.sample(&mut rng));
    }
}

/// Render beads (x, y, weight) and filaments on an n×n grid of pixel h from origin (0, 0), add
/// noise.
pub fn scene(
    tpl: &Template,
    beads: &[(f64, f64, f64)],
    fils: &[Filament],
    n: usize,
    h: f64,
    sigma: f64,
    seed: u64,
) -> Scan {
    let x = axis(n, h, 0.0);
    let mut s = render_scene(tpl, beads, fils, &BeadModelOptions::default(), &x, &x).unwrap();
    add_noise(&mut s, sigma, seed);
    s
}

/// Weight of a polystyrene bead of diameter d relative to the 110 nm reference: (d/110)³.
pub fn ps_weight(d_nm: f64) -> f64 {
    (d_nm / 110.0).powi(3)
}

/// Peak |Sx| of the template (signal units) — noise levels are stated relative to it.
pub fn sx_peak(tpl: &Template) -> f64 {
    tpl.grid.data.iter().map(|n| n[0].abs()).fold(0.0, f64::max)
}

pub fn img_max(img: &Image) -> f64 {
    img.data
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(f64::NEG_INFINITY, f64::max)
}

/// The paper's noise level, derived from its mass resolution: a single reference-bead fit has a
/// weight uncertainty of 950 kDa / m(110 nm PS) = 950/440 600 ≈ 0.0022 (Sec. 3.2). For white
/// pixel noise σ on Sx and Sy, σ_C = σ/√Σ(Tx² + Ty²) over the pixels, so
/// σ = 0.0022·√Σ(Tx² + Ty²) for pixels of `h` µm.
pub fn paper_noise(tpl: &Template, h: f64) -> f64 {
    let rb = tpl.reference;
    let sigma_c = 950.0 / rb.mass_kda();
    let ((u0, u1), (v0, v1)) = tpl.extent();
    let mut s = 0.0;
    let nu = ((u1 - u0) / h) as i64;
    let nv = ((v1 - v0) / h) as i64;
    for j in 0..=nv {
        for i in 0..=nu {
            let t = tpl.eval(u0 + i as f64 * h, v0 + j as f64 * h);
            s += t[0] * t[0] + t[1] * t[1];
        }
    }
    sigma_c * s.sqrt()
}

// ---- Physics model and simulator (optics::template, instrument::sim) ----

use bfpscope::analysis::template::RefBead;
use bfpscope::instrument::sim::render_xy;
use bfpscope::instrument::sim::scene::{
    Bead as SimBead, DetectorNoise, DiameterProfile, Filament as SimFilament, Scene,
    PAPER_DETECTOR_SIGMA_SAMPLE,
};
use bfpscope::instrument::sim::Renderer;
use bfpscope::optics::rayleigh::DetectorModel;
use bfpscope::optics::template::TemplateSpec;
use bfpscope::optics::Optics;

/// The paper's optics in the paper's beam: the paraxial scalar Gaussian of suppl. S3 (a named
/// approximation since the one-beam work; the default beam is the aplanatic vector focus). The tests
/// that reproduce the paper's numbers use it.
pub fn paper_optics() -> Optics {
    Optics {
        beam: bfpscope::optics::Beam::Paraxial,
        ..Optics::default()
    }
}

/// Samples per pixel of the paper's 0.1 s dwell at 100 kHz.
pub const PAPER_SAMPLES: usize = 10_000;

/// The project's "paper noise" per pixel (docs/physics.md §7): 2e-3 per sample over 10⁴ samples
/// = 2e-5 of the beam power (0.84 % of the 110 nm bead's peak Sx).
pub fn paper_sigma_pixel() -> f64 {
    PAPER_DETECTOR_SIGMA_SAMPLE / (PAPER_SAMPLES as f64).sqrt()
}

/// Model template of the 110 nm polystyrene reference bead for `optics` (ideal QPD unless
/// `detector` says otherwise), 20 nm grid, in focus.
pub fn model_template(optics: &Optics, detector: &DetectorModel) -> Template {
    let rb = RefBead {
        n_medium: optics.n_medium,
        ..RefBead::default()
    };
    Template::from_optics(optics, detector, rb, 0.02, 0.0).unwrap()
}

/// Simulate an XY scan of `scene` on an n×n grid of pixel h from (0, 0) at z = 0, with
/// `n_samples` per pixel (the scene's effects decide the noise).
pub fn simulate(optics: &Optics, scene: &Scene, n: usize, h: f64, n_samples: usize) -> Scan {
    let r = Renderer::checked(optics, scene, TemplateSpec::default()).unwrap();
    let ax = axis(n, h, 0.0);
    render_xy(&r, &ax, &ax, 0.0, n_samples)
}

pub fn sim_bead(x: f64, y: f64, d_nm: f64, n: f64) -> SimBead {
    SimBead {
        pos: [x, y, 0.0],
        d_nm,
        n,
    }
}

pub fn sim_filament(points: Vec<[f64; 2]>, profile: DiameterProfile, n: f64) -> SimFilament {
    SimFilament {
        points,
        z: 0.0,
        profile,
        n,
        spacing_nm: 50.0,
    }
}

/// Straight simulated filament through `centre` at `angle_deg` from the y-axis.
pub fn sim_straight(
    centre: [f64; 2],
    angle_deg: f64,
    length: f64,
    d_nm: f64,
    n: f64,
) -> SimFilament {
    let t = angle_deg.to_radians();
    let (dx, dy) = (0.5 * length * t.sin(), 0.5 * length * t.cos());
    sim_filament(
        vec![
            [centre[0] - dx, centre[1] - dy],
            [centre[0] + dx, centre[1] + dy],
        ],
        DiameterProfile::Constant { d_nm },
        n,
    )
}

/// A scene with the paper's detector noise (seeded).
pub fn noisy(mut scene: Scene, sigma_sample: f64, seed: u64) -> Scene {
    scene.effects.detector_noise = Some(DetectorNoise { sigma_sample });
    scene.seed = seed;
    scene
}
