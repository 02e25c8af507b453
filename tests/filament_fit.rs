//! The information limit of filament measurements: the Cramér–Rao bounds attached to the
//! per-row method's measurement (Sec. 4.2 steps 4–5) and the whole-image bead-model fit, on
//! scenes made by the simulator (an independent path: its own renderer of the scene's
//! filament, its own noise).

use crate::analysis_support::*;
use bfpscope::analysis::orientation::{
    measure_filament, AngleCurve, AngleCurveOptions, MeasureOptions,
};
use bfpscope::analysis::quantities;
use bfpscope::instrument::sim::scene::{Scene, PAPER_DETECTOR_SIGMA_SAMPLE};
use bfpscope::optics::rayleigh::DetectorModel;
use bfpscope::optics::Optics;

const H: f64 = 0.05;

/// A 13-protofilament microtubule (protein cylinder, n = 1.587, in n_s = 1.335) along y with a
/// 2° tilt through (1.6, 1.6), detector noise at `samples` per pixel.
fn microtubule_scan(o: &Optics, samples: usize, seed: u64) -> bfpscope::data::Scan {
    let mut sc = Scene::default();
    sc.add_filament(sim_straight(
        [1.6, 1.6],
        2.0,
        8.0,
        mt_d_nm(),
        quantities::PROTEIN_N,
    ))
    .unwrap();
    simulate(
        o,
        &noisy(sc, PAPER_DETECTOR_SIGMA_SAMPLE, seed),
        64,
        H,
        samples,
    )
}

fn mt_d_nm() -> f64 {
    let mu = 13.0 * quantities::PROTOFILAMENT_MDA_PER_UM;
    let da_per_nm3 = quantities::PROTEIN_DENSITY_G_CM3 * 1e-21 * quantities::DA_PER_G;
    (4.0 * mu * 1e3 / da_per_nm3 / std::f64::consts::PI).sqrt()
}

fn mt_optics() -> Optics {
    Optics {
        n_medium: 1.335,
        ..Optics::default()
    }
}

/// The per-row measurement carries the bound of the data it read: the pixel noise it states is
/// the simulator's (σ_s/√n), and the method's own 1σ of the angle and of the mean corrected
/// sensitivity sit above their bounds (the parabola maxima use a 0.4 µm window of each row).
#[test]
fn per_row_measurement_states_its_cramer_rao_bounds() {
    let o = mt_optics();
    let tpl = model_template(&o, &DetectorModel::default());
    let curve = AngleCurve::compute(&tpl, &AngleCurveOptions::default()).unwrap();
    let samples = 1000; // 10 ms per pixel
    let s = microtubule_scan(&o, samples, 5);
    let m = measure_filament(&s.sx, &s.sy, &curve, &MeasureOptions::default()).unwrap();
    let c = m
        .crlb
        .expect("a noisy scan measured with a computed curve has a bound");
    let sig = PAPER_DETECTOR_SIGMA_SAMPLE / (samples as f64).sqrt();
    for k in 0..2 {
        assert!(
            (c.sigma[k] / sig - 1.0).abs() < 0.1,
            "σ {:?} vs {sig}",
            c.sigma
        );
    }
    println!(
        "per-row: angle {:.3} ± {:.3}° (CRLB {:.3}°), mean_corr {:.4} ± {:.4} (CRLB {:.4}; {:.2} %)",
        m.angle_deg,
        m.angle_err_deg,
        c.angle_deg,
        m.mean_corr,
        m.sem_corr,
        c.mean_corr,
        100.0 * c.lin_dens_rel
    );
    assert!(c.angle_deg > 0.0 && c.angle_deg < m.angle_err_deg);
    assert!(c.mean_corr > 0.0 && c.mean_corr < m.sem_corr);
    assert!((c.diameter_rel - 0.5 * c.lin_dens_rel).abs() < 1e-15);
    // a curve loaded from a file carries no template: no bound, and the measurement is the same
    let loaded: AngleCurve = serde_json::from_str(&serde_json::to_string(&curve).unwrap()).unwrap();
    assert!(loaded.template.is_none());
    let m2 = measure_filament(&s.sx, &s.sy, &loaded, &MeasureOptions::default()).unwrap();
    assert!(m2.crlb.is_none());
    assert_eq!(m2.mean_corr, m.mean_corr);
}
