//! CI runs the quick accuracy report: every knob sweep, the instrument-time trade-off
//! and the plots, in-process into a temporary folder. Asserts that the files are written, that
//! each default meets its knee's error criterion (errors are deterministic; times are reported,
//! not asserted: a test is no benchmark), and the trade-off's physics (the 1/√t law and its
//! closed-form prediction, the microtubule's linear density), the Cramér–Rao bound beside every
//! row (against the scaling law's closed form), the whole-image filament fit beside the per-row
//! maxima, the targeted protocols' seed study (2 bead seeds, 1 filament seed over 1 µm: the full
//! study is `bfpscope accuracy` or `bfpscope run scripts/targeted_study.rhai`), and both Pareto
//! figures.

use crate::support::cleanup;

use bfpscope::accuracy::report::{run, KneeVerdict, ReportOptions};

#[test]
fn quick_report_writes_files_and_defaults_meet_the_knee_criterion() {
    let dir = std::env::temp_dir().join(format!("bfpscope-accuracy-{}", std::process::id()));
    cleanup::at_exit(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    let r = run(&ReportOptions {
        quick: true,
        out: dir.clone(),
        criterion: None,
        sweep: None,
        verbose: false,
        targeted: Some(bfpscope::script::targeted_study),
    })
    .unwrap();

    // files: the report and one PNG per knob plus the trade-off figure
    let md = std::fs::read_to_string(dir.join("accuracy.md")).unwrap();
    assert!(md.contains("## Defaults") && md.contains("Machine:") && md.contains("cores"));
    assert!(md.contains("Time to reach the paper's resolution"));
    let ids: Vec<&str> = r.knobs.iter().map(|k| k.knob.id.as_str()).collect();
    for id in [
        "quadrature",
        "quadrature_misaligned",
        "quadrature_paraxial",
        "quadrature_misaligned_paraxial",
        "template",
        "template_paraxial",
        "bead_spacing",
        "finite_size",
        "finite_size_paraxial",
        "mie_grid",
        "mie_terms",
        "model_170",
        "model_500",
        "fit_tolerance",
        "fit_patience",
        "stencil",
        "dwell",
    ] {
        assert!(ids.contains(&id), "knob {id} missing from {ids:?}");
    }
    for k in &r.knobs {
        let bytes = std::fs::read(&k.png).unwrap();
        assert!(
            bytes.starts_with(b"\x89PNG") && bytes.len() > 10_000,
            "{}",
            k.png.display()
        );
        assert!(md.contains(&format!("accuracy/{}.png", k.knob.id)));
        assert!(
            k.knob.default_point().is_some(),
            "{} has no default",
            k.knob.id
        );
        assert!(
            k.knob
                .points
                .iter()
                .all(|p| p.error > 0.0 && p.seconds > 0.0),
            "{}: {:?}",
            k.knob.id,
            k.knob.points
        );
    }
    assert!(dir.join("accuracy/tradeoff.png").is_file());
    assert!(dir.join("accuracy/tradeoff_filament.png").is_file());

    // defaults at the knee; the two documented exceptions must stay what the report says
    for k in &r.knobs {
        match (k.knob.id.as_str(), &k.verdict) {
            // the point dipole is not meant for 500 nm beads (docs/accuracy.md#model_500)
            ("model_500", v) => {
                assert!(
                    matches!(v, KneeVerdict::Below { .. }),
                    "{}: {v:?}",
                    k.knob.id
                )
            }
            // the vector beam's detection grid (16, 8) reaches ρ ≤ 1.51 µm, the knob's points 2.24 µm
            // (docs/accuracy.md#quadrature; measured 3.6e-4 and 5.1e-4 of the peak); inside its
            // reach it meets the criterion (unit test in accuracy::tests)
            ("quadrature" | "quadrature_misaligned", v) => {
                let e = k.knob.default_point().unwrap().error;
                assert!(
                    matches!(v, KneeVerdict::Below { .. }) && (1e-4..1e-3).contains(&e),
                    "{}: {v:?} {e}",
                    k.knob.id
                )
            }
            (_, KneeVerdict::AtKnee) => {}
            // The default must meet the knee's error criterion (deterministic). Whether it is
            // also the cheapest such setting is a timing question: on a loaded 2-core machine
            // in the dev profile the measured ratio reached 1.8× (fit_patience, CI clone while
            // other builds ran), so it is reported, not asserted; docs/accuracy.md measures it
            // in release with repeats (once reported as "up to 4× slower").
            (_, KneeVerdict::Above { time_ratio }) => {
                eprintln!("{}: default above the knee by {time_ratio:.2}×", k.knob.id)
            }
            (id, v) => panic!("{id}: default does not meet the knee's error criterion: {v:?}"),
        }
    }

    // what the paper's approximation costs: the paraxial beam is percents off the default vector
    // beam (measured 5.1 % RMS of the peak on a 64×64 image), far beyond the 3e-5 criterion, and
    // cheaper (templates from scratch: 2.1 ms against 17.4 ms in release)
    let beam = r
        .knobs
        .iter()
        .find(|k| k.knob.id == "beam")
        .expect("beam knob");
    let p = &beam.knob.points;
    assert_eq!(
        (p[0].setting.as_str(), p[1].setting.as_str()),
        ("paraxial", "vector")
    );
    assert!(p[1].is_default && p[1].error < 1e-15, "{p:?}");
    assert!(p[0].error > 0.02 && p[0].error < 0.1, "{p:?}");
    // the point dipole's domain for polystyrene: within 1 % of Mie at 170 nm (the paper's largest
    // bead), beyond it at 350 nm. The full report (eight diameters) finds point_dipole_error
    // crossing 1 % between 190 and 200 nm (195 nm). This quick run interpolates linearly between
    // 170 and 250 nm. The error grows like d² (the first finite-size term, (k d)²), a convex
    // function: its chord lies above it, so the chord's crossing is at or below the true one
    // (≤ 200 nm); and for e = c·d² with the true crossing d* ≥ 190 nm the chord crosses at
    // 170 + 80·(d*² − 170²)/(250² − 170²) ≥ 187.1 nm.
    let ps = &r.validity[0];
    assert_eq!(ps.n, 1.572);
    assert!(ps.points[0].1.abs() < 0.01, "{:?}", ps.points);
    assert!(ps.points.last().unwrap().1.abs() > 0.03, "{:?}", ps.points);
    let d1 = ps.d_1pct.unwrap();
    assert!((187.0..=200.0).contains(&d1), "{d1}");
    assert!(md.contains("Where the point dipole holds"));

    // trade-off: σ ∝ 1/√t between decades of dwell, and the closed-form law at 0.1 s
    let t = &r.tradeoff;
    for w in t.bead.windows(2) {
        let ratio = w[0].sigma_fit / w[1].sigma_fit;
        let expect = (w[1].dwell_s / w[0].dwell_s).sqrt();
        assert!((ratio / expect - 1.0).abs() < 0.15, "{ratio} vs {expect}");
    }
    let at = t
        .bead
        .iter()
        .find(|r| (r.dwell_s - 0.1).abs() < 1e-12)
        .unwrap();
    let pred = t.predicted_sigma_kda(0.1, 0.05);
    assert!(
        (at.sigma_fit / pred - 1.0).abs() < 0.1,
        "{} vs {pred}",
        at.sigma_fit
    );
    assert!((at.mean / t.ref_mass_kda - 1.0).abs() < 0.01);
    // the simulator at its "paper noise" beats the paper's 950 kDa by the factor the scaling law
    // gives for the documented per-sample noise (950 kDa / σ_pred; the fit's scatter about σ_pred
    // is the 10 % above, so the factor is within 1/0.9 − 1 = 11 % of it), and the report prints
    // that factor
    let f = 950.0 / at.sigma_fit;
    let f_pred = 950.0 / pred;
    assert!((f / f_pred - 1.0).abs() < 0.112, "{f} vs {f_pred}");
    assert!(
        md.contains(&format!("{f:.1}× better than the paper's 950 kDa")),
        "the report's factor: {f:.1}"
    );
    let mt = t
        .microtubule
        .iter()
        .find(|r| (r.dwell_s - 0.1).abs() < 1e-12)
        .unwrap();
    assert_eq!(mt.found, t.seeds);
    assert!((mt.mean / t.mt_true_mu - 1.0).abs() < 0.05, "{}", mt.mean);

    // the information limit beside every row: the bead's bound (the Fisher information of the
    // 64×64 pixels, analysis::crlb) against the closed form σ_s·h·m/√(f·t·I) of the scaling law
    // (the template's integral on a 20 nm grid: an independent path), and the fit at it
    for r in &t.bead {
        let pred = t.predicted_sigma_kda(r.dwell_s, 0.05);
        assert!(
            (r.crlb / pred - 1.0).abs() < 0.02,
            "CRLB {} vs closed form {pred}",
            r.crlb
        );
        let mass = r
            .estimators
            .iter()
            .find(|e| e.estimator == "bead mass (weight)")
            .unwrap();
        assert!((mass.fit_sigma / mass.crlb - 1.0).abs() < 0.1, "{mass:?}");
        let ex = &r.estimators[0];
        assert_eq!(ex.estimator, "bead x");
        assert!((ex.fit_sigma / ex.crlb - 1.0).abs() < 0.1, "{ex:?}");
        assert!(r.efficiency().is_finite() && r.efficiency() > 0.0);
    }
    // the bound scales as 1/√t exactly (integer samples per pixel)
    let (a, b) = (&t.bead[0], &t.bead[t.bead.len() - 1]);
    assert!(((a.crlb / b.crlb) / (b.dwell_s / a.dwell_s).sqrt() - 1.0).abs() < 1e-9);
    // the microtubule: the whole-image fit's own 1σ sits at the bound, the per-row maxima's above
    // it; at 1 ms the whole-image fit finds the filament where the per-row maxima do not
    let fit = t
        .microtubule_fit
        .iter()
        .find(|r| (r.dwell_s - 0.1).abs() < 1e-12)
        .unwrap();
    assert_eq!(fit.found, t.seeds);
    assert!((fit.mean / t.mt_true_mu - 1.0).abs() < 0.05, "{}", fit.mean);
    assert!(
        (fit.sigma_fit / fit.crlb - 1.0).abs() < 0.1,
        "{} vs {}",
        fit.sigma_fit,
        fit.crlb
    );
    assert!(
        mt.sigma_fit > 1.5 * mt.crlb,
        "per-row {} vs bound {}",
        mt.sigma_fit,
        mt.crlb
    );
    let at_1ms = |rows: &[bfpscope::accuracy::instrument::TradeRow]| {
        rows.iter()
            .find(|r| (r.dwell_s - 1e-3).abs() < 1e-12)
            .unwrap()
            .found
    };
    assert_eq!(at_1ms(&t.microtubule_fit), t.seeds);
    assert_eq!(at_1ms(&t.microtubule), 0);
    assert!(md.contains("| CRLB | efficiency |"));
    assert!(md.contains("whole-image bead-model fit"));
    assert!(md.contains("### Efficiency of every estimator"));

    // the targeted protocols (one quick seed study): the bead at 950 kDa within a tenth of the
    // raster's 26.9 s, its σ at its bound; the filament over 1 µm
    let tb = r
        .targeted
        .iter()
        .find(|x| x.protocol == "targeted::bead")
        .unwrap();
    assert_eq!(tb.seeds, 2);
    assert!(tb.time_max_s <= 2.7, "{tb:?}");
    assert!(
        tb.sigma_mean <= 950.0 && (tb.sigma_mean / tb.crlb_mean - 1.0).abs() < 0.3,
        "{tb:?}"
    );
    assert!((tb.mean - tb.truth).abs() < 4.0 * tb.sigma_mean, "{tb:?}");
    let tf = r
        .targeted
        .iter()
        .find(|x| x.protocol == "targeted::filament")
        .unwrap();
    assert_eq!((tf.seeds, tf.length_um), (1, 1.0));
    assert!((tf.mean - tf.truth).abs() < 4.0 * tf.sigma_mean, "{tf:?}");
    assert!(
        tf.crlb_mean > 0.0 && tf.crlb_mean <= tf.sigma_mean * 1.1,
        "{tf:?}"
    );
    assert!(
        md.contains("### Targeted protocols")
            && md.contains("`targeted::bead` (110 nm PS bead, mass) | 2 |")
    );
    // the Pareto figures: both written and shown
    for p in &r.pareto {
        let bytes = std::fs::read(p).unwrap();
        assert!(
            bytes.starts_with(b"\x89PNG") && bytes.len() > 10_000,
            "{}",
            p.display()
        );
    }
    assert!(
        md.contains("(accuracy/tradeoff.png)") && md.contains("(accuracy/tradeoff_filament.png)")
    );
    let _ = std::fs::remove_dir_all(&dir);
}
