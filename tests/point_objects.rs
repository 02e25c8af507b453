//! A lone point object is never measured as a filament, in noise or not, at
//! any scan size, position or pixel size; a filament of the same contrast still is.
//!
//! The scans come from the simulator (instrument::sim: the vector beam, the bead rendered by
//! the point-dipole response, the filament as a chain of dipoles, detector noise per sample);
//! the measurement uses the model template's angle curve — two independent paths. The bead is
//! the paper's 110 nm polystyrene reference bead; the filament has its index and the diameter
//! whose per-line maximum of ∂Sx/∂x equals the bead's peak ∂Sx/∂x ("the same contrast",
//! checked in `the_filament_has_the_beads_contrast`).

use crate::analysis_support;

use analysis_support::model_template;
use bfpscope::analysis::orientation::{
    measure_filament, AngleCurve, AngleCurveOptions, MeasureOptions,
};
use bfpscope::analysis::sensitivity::{sensitivity, Axis, Stencil};
use bfpscope::analysis::template::Template;
use bfpscope::data::Scan;
use bfpscope::instrument::sim::scene::{
    Bead, DetectorNoise, DiameterProfile, Filament, Scene, FILAMENT_SPACING_NM,
    PAPER_DETECTOR_SIGMA_SAMPLE,
};
use bfpscope::instrument::sim::{render_xy, Renderer};
use bfpscope::optics::rayleigh::DetectorModel;
use bfpscope::optics::template::TemplateSpec;
use bfpscope::optics::Optics;
use proptest::prelude::*;
use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

/// Pixel sizes swept, µm.
const PIXELS: [f64; 4] = [0.025, 0.04, 0.05, 0.1];
/// Samples per pixel swept (at 100 kHz: 0.3 ms, 1 ms, 10 ms dwell); 0: no detector noise.
const SAMPLES: [usize; 4] = [0, 30, 100, 1000];
/// The filament's diameter (nm) of the bead's contrast (see the module docs).
const FIL_D_NM: f64 = 45.0;

fn template() -> &'static Template {
    static T: OnceLock<Template> = OnceLock::new();
    T.get_or_init(|| model_template(&Optics::default(), &DetectorModel::default()))
}

fn curve(px: f64) -> Arc<AngleCurve> {
    static C: OnceLock<Mutex<HashMap<u64, Arc<AngleCurve>>>> = OnceLock::new();
    let m = C.get_or_init(|| Mutex::new(HashMap::new()));
    if let Some(c) = m.lock().unwrap().get(&px.to_bits()) {
        return c.clone();
    }
    let c = Arc::new(
        AngleCurve::compute(
            template(),
            &AngleCurveOptions {
                pixel_um: px,
                ..Default::default()
            },
        )
        .unwrap(),
    );
    m.lock().unwrap().insert(px.to_bits(), c.clone());
    c
}

fn bead(x: f64, y: f64) -> Bead {
    Bead {
        pos: [x, y, 0.0],
        d_nm: 110.0,
        n: 1.572,
    }
}

/// A straight filament through `p` at `angle_deg` from the y-axis, 20 µm long.
fn filament(p: (f64, f64), angle_deg: f64, d_nm: f64) -> Filament {
    let t = angle_deg.to_radians();
    let (dx, dy) = (10.0 * t.sin(), 10.0 * t.cos());
    Filament {
        points: vec![[p.0 - dx, p.1 - dy], [p.0 + dx, p.1 + dy]],
        z: 0.0,
        profile: DiameterProfile::Constant { d_nm },
        n: 1.572,
        spacing_nm: FILAMENT_SPACING_NM,
    }
}

/// An XY scan of ±half µm around the origin at pixel px, focus at z = 0, `samples` per pixel
/// (0: noise-free).
fn scan(mut scene: Scene, half: f64, px: f64, samples: usize, seed: u64) -> Scan {
    if samples > 0 {
        scene.effects.detector_noise = Some(DetectorNoise {
            sigma_sample: PAPER_DETECTOR_SIGMA_SAMPLE,
        });
    }
    scene.seed = seed;
    let r = Renderer::checked(&Optics::default(), &scene, TemplateSpec::default()).unwrap();
    let n = (2.0 * half / px).round() as usize + 1;
    let ax: Vec<f64> = (0..n).map(|i| -half + i as f64 * px).collect();
    render_xy(&r, &ax, &ax, 0.0, samples.max(1))
}

fn measure(
    s: &Scan,
    px: f64,
) -> Result<bfpscope::analysis::orientation::FilamentMeasurement, String> {
    measure_filament(&s.sx, &s.sy, &curve(px), &MeasureOptions::default())
        .map_err(|e| e.to_string())
}

/// The refusals that say "this is not a filament" (no line of maxima; maxima too short for a
/// filament; point objects in a row; too few maxima on the line; an object too short to measure
/// once its ends are left out) — not a bad input, a template or a calibration failure. A point
/// object must be refused with one of these.
const NOT_A_FILAMENT: [&str; 5] = [
    "no filament found",
    "do not form a filament",
    "do not form one filament",
    "maxima lie on the filament line",
    "the filament is too short to measure",
];

/// `r` is a refusal saying the scan holds no filament (see [`NOT_A_FILAMENT`]).
fn refused_as_no_filament<T>(r: &Result<T, String>) -> bool {
    matches!(r, Err(e) if NOT_A_FILAMENT.iter().any(|k| e.contains(k)))
}

fn max_sens_x(s: &Scan) -> f64 {
    let d = sensitivity(&s.sx, Axis::X, Stencil::Central2).unwrap();
    d.data.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
}

/// "The same contrast": the filament's maximum ∂Sx/∂x (filament along y: every row's maximum)
/// is the bead's peak ∂Sx/∂x within 10 %, noise-free, at 25 nm pixels.
#[test]
fn the_filament_has_the_beads_contrast() {
    let mut b = Scene::default();
    b.add_bead(bead(0.0, 0.0)).unwrap();
    let mut f = Scene::default();
    f.add_filament(filament((0.0, 0.0), 0.0, FIL_D_NM)).unwrap();
    let (sb, sf) = (
        max_sens_x(&scan(b, 1.0, 0.025, 0, 0)),
        max_sens_x(&scan(f, 1.0, 0.025, 0, 0)),
    );
    println!(
        "peak ∂Sx/∂x: bead {sb:.4e}, {FIL_D_NM} nm filament {sf:.4e}, ratio {:.3}",
        sf / sb
    );
    assert!((sf / sb - 1.0).abs() < 0.1, "bead {sb}, filament {sf}");
}

/// The case a newcomer met: a 110 nm bead in the middle of a ±1 µm scan, 41 × 41, 1 ms, with
/// detector noise, once measured as a fibril at −89.94° from 28 maxima. Refused at every seed,
/// and the message says why.
#[test]
fn a_lone_noisy_bead_in_the_middle_of_the_scan_is_refused() {
    for seed in 0..6 {
        let mut sc = Scene::default();
        sc.add_bead(bead(0.0, 0.0)).unwrap();
        let s = scan(sc, 1.0, 0.05, 100, seed);
        let e = measure(&s, 0.05).expect_err("a lone bead measured as a filament");
        assert!(e.contains("do not form a filament"), "seed {seed}: {e}");
    }
}

/// Counterexamples the property test drew before the refusal held at coarse pixels, kept as
/// fixed cases (position as fractions of the scan's half-width):
/// - a CI run (2026-11-27): a lone bead in a ±2.75 µm scan of 0.1 µm pixels, 100 samples,
///   measured as a filament at −33.0° from 15 maxima — a five-line median cut short at the
///   scan's edge let two noisy maxima of the last three lines count as strong;
/// - a sweep: the same at ±2.49 µm, 30 samples, at 7.3° from 23 maxima — the parabolas' own
///   1σ (2 degrees of freedom at 5 points) was 2–3× low, so noisy tails counted as 4σ;
/// - a sweep, noise-free: a bead at the corner of a ±1.19 µm scan of 0.05 µm pixels, at 40.2°
///   from 20 maxima — its side lobe's maxima, 1.7 % of its peak, away from the bead.
#[test]
fn counterexamples_of_the_sweep_are_refused() {
    for (half, fx, fy, px, samples, seed) in [
        (
            2.747677108017579,
            0.608361039527651,
            0.3013890490791673,
            0.1,
            100,
            33,
        ),
        (2.4930549410214726, 0.0, 0.35880278040249597, 0.1, 30, 478),
        (
            1.1887526734358576,
            -0.9822536242865398,
            0.9662487295110058,
            0.05,
            0,
            350,
        ),
    ] {
        let mut sc = Scene::default();
        sc.add_bead(bead(fx * half, fy * half)).unwrap();
        let s = scan(sc, half, px, samples, seed);
        let r = measure(&s, px);
        assert!(
            refused_as_no_filament(&r),
            "bead at ({:.2}, {:.2}) in ±{half:.2} µm, {px} µm pixels, {samples} samples: not refused as no filament: {:?}",
            fx * half,
            fy * half,
            r.map(|m| (m.angle_deg, m.points.len()))
        );
    }
}

/// A counterexample on the other side: a 45 nm filament at −20.8° in a ±2.79 µm scan of 0.1 µm
/// pixels, 30 samples, refused as "point objects in a row": runs of 4–5 lines where no maximum
/// was read (a parabola over the flat top of the ridge came out convex in noise) counted as no
/// signal, and the five-line median widened them past 0.6 µm.
#[test]
fn a_filament_with_lines_not_read_at_coarse_pixels_is_measured() {
    let half = 2.78875444554446;
    let mut sc = Scene::default();
    sc.add_filament(filament(
        (-0.07888029825674375 * half, -0.1480358531739604 * half),
        -20.782916362315248,
        FIL_D_NM,
    ))
    .unwrap();
    let s = scan(sc, half, 0.1, 30, 431);
    let m = measure(&s, 0.1).expect("the filament is measured");
    let truth = -20.782916362315248;
    assert!(
        (m.angle_deg - truth).abs() < 3.0 * m.angle_err_deg,
        "{} ± {} (truth {truth})",
        m.angle_deg,
        m.angle_err_deg
    );
}

proptest! {
    // A fixed seed: CI draws the same cases every run. To explore, draw fresh ones:
    // `PO_RANDOM=1 PO_CASES=2000 cargo test --test physics point_objects::` (3,500 random cases of both
    // properties after the coarse-pixel fixes, 2026-11-27: no counterexample).
    #![proptest_config(ProptestConfig {
        cases: std::env::var("PO_CASES").ok().and_then(|c| c.parse().ok()).unwrap_or(24),
        failure_persistence: None,
        rng_seed: if std::env::var("PO_RANDOM").is_ok() { proptest::test_runner::RngSeed::Random } else { proptest::test_runner::RngSeed::Fixed(0x5eed_0033) },
        ..ProptestConfig::default()
    })]

    /// No single point object is accepted: any scan size (±0.5 … ±3 µm), any bead position in
    /// the scan (edges included), any pixel size and noise level.
    #[test]
    fn a_lone_bead_is_never_a_filament(
        half in 0.5f64..3.0,
        fx in -1.0f64..1.0,
        fy in -1.0f64..1.0,
        ipx in 0usize..PIXELS.len(),
        ins in 0usize..SAMPLES.len(),
        seed in 0u64..1000,
    ) {
        let px = PIXELS[ipx];
        let mut sc = Scene::default();
        sc.add_bead(bead(fx * half, fy * half)).unwrap();
        let s = scan(sc, half, px, SAMPLES[ins], seed);
        let r = measure(&s, px);
        prop_assert!(refused_as_no_filament(&r), "bead at ({:.2}, {:.2}) in ±{half:.2} µm, {px} µm pixels, {} samples: not refused as no filament: {:?}",
            fx * half, fy * half, SAMPLES[ins], r.as_ref().map(|m| (m.angle_deg, m.points.len())));
    }

    /// A filament of the same contrast through the middle third of a scan of ±1.5 … ±3 µm, at
    /// any angle, pixel size and noise level, is still measured, along its own direction.
    #[test]
    fn a_filament_of_the_same_contrast_is_measured(
        half in 1.5f64..3.0,
        fx in -0.33f64..0.33,
        fy in -0.33f64..0.33,
        angle in -90.0f64..90.0,
        ipx in 0usize..PIXELS.len(),
        ins in 0usize..SAMPLES.len(),
        seed in 0u64..1000,
    ) {
        let px = PIXELS[ipx];
        let mut sc = Scene::default();
        sc.add_filament(filament((fx * half, fy * half), angle, FIL_D_NM)).unwrap();
        let s = scan(sc, half, px, SAMPLES[ins], seed);
        let m = measure(&s, px);
        prop_assert!(m.is_ok(), "{FIL_D_NM} nm filament at {angle:.1}° through ({:.2}, {:.2}) in ±{half:.2} µm, {px} µm pixels, {} samples: refused: {:?}",
            fx * half, fy * half, SAMPLES[ins], m.as_ref().err());
        let m = m.unwrap();
        // angles are measured from the y-axis towards x, modulo 180°
        let d = ((m.angle_deg - angle) + 90.0).rem_euclid(180.0) - 90.0;
        // within the fit's own 4σ (and 1° for the pixel grid)
        prop_assert!(d.abs() < 1.0 + 4.0 * m.angle_err_deg, "measured at {:.2}° ± {:.2}°, true {angle:.2}°", m.angle_deg, m.angle_err_deg);
    }
}
