//! CI runs the quick accuracy report: every knob sweep, the instrument-time trade-off
//! and the plots, in-process into a temporary folder. Asserts that the files are written, that
//! each default meets its knee's error criterion (errors are deterministic; times are reported,
//! not asserted: a test is no benchmark), and the trade-off's physics (the 1/√t law and its
//! closed-form prediction, the microtubule's linear density).

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
        verbose: false,
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
    let _ = std::fs::remove_dir_all(&dir);
}
