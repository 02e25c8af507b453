//! The truth sweep at a fixed seed, as CI runs it: random scenes of every family (beads,
//! fibrils, focus searches, and apart, fewer, microtubules among aggregates and beam fits; `bfpscope sweep`'s
//! scene space, src/accuracy/sweep.rs) rendered by
//! the simulator and measured by every estimator in the sweep. The error bars must cover the
//! truth as often as a Gaussian's do, within the binomial scatter of the in-domain count, and
//! no answer without a warning may be an outlier at this seed: at N = 2000 (docs/accuracy.md
//! "Truth sweep") the bead fit had none at seed 7, the filament diameter and the focus search
//! none at seeds 2026, 7 and 99 (seventh and eighth sessions, 2026-12-06), `max_sens` on XY
//! images none at seeds 2026, 7 and 99 (ninth session, 2026-12-07). The full sweep (2000
//! scenes a family) is the benchmark of docs/accuracy.md.
//!
//! Developers: `SWEEP_RANDOM=1` draws a fresh seed (printed), `SWEEP_N=500` more scenes:
//! `SWEEP_RANDOM=1 SWEEP_N=500 cargo test --release --test physics truth_sweep::`.

use bfpscope::accuracy::sweep::{run, SweepOptions, BEAM_DETECTION, BEAM_KEYS};

/// The 1σ and 2σ coverage of a Gaussian error bar.
const P1: f64 = 0.6827;
const P2: f64 = 0.9545;

/// The scenes a family runs (`SWEEP_N`, else `default`) and the seed (`SWEEP_RANDOM`: a fresh
/// one, else 2026).
fn n_and_seed(default: usize) -> (usize, u64) {
    let n = std::env::var("SWEEP_N")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default);
    let seed = if std::env::var_os("SWEEP_RANDOM").is_some() {
        rand::random::<u64>()
    } else {
        2026
    };
    (n, seed)
}

/// No unflagged outlier, and, from 20 answers in the domain, the 1σ and 2σ coverage within 3σ
/// of the binomial scatter about a Gaussian's.
fn assert_calibrated(k: &str, v: &bfpscope::accuracy::sweep::Tally) {
    assert_eq!(
        v.unflagged_outliers, 0,
        "{k}: answers without a warning beyond 4σ (or 5 %): {:#?}",
        v.examples
    );
    if v.coverage_1s.is_finite() && v.in_domain >= 20 {
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

#[test]
fn a_fixed_seed_sweep_gives_error_bars_that_cover_the_truth_and_answers_without_outliers() {
    let (n, seed) = n_and_seed(100);
    println!("truth sweep: {n} scenes a family, seed {seed}");
    let t = run(
        &SweepOptions {
            n,
            seed,
            // the microtubules run apart, fewer of them (below)
            families: ["beads", "fibril", "focus", "maxsens"]
                .map(String::from)
                .to_vec(),
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
        "max_sens.value",
        "max_sens.detection",
    ] {
        let v = t
            .get(k)
            .unwrap_or_else(|| panic!("{k} is not in the sweep"));
        assert!(v.cases > 0, "{k}: no case");
        assert_calibrated(k, v);
    }
}

/// Scenes that were unflagged outliers of the bead fit in the N = 2000, seed-2026 sweep at
/// e39f4ba (2026-12-06), as `BFPSCOPE_SWEEP_DUMP` wrote them: each bead is now found, or the
/// fit flagged. The grow step took its candidates from the derivative map's maxima, which at
/// high noise were noise; it now takes the matched filter's (the χ² gain of one added bead),
/// and a bead a candidate split into a pair merged back by less than ΔBIC 10 is flagged.
const BEAD_SCENES_ONCE_OUTLIERS: [&str; 8] = [
    // a 52 nm bead 0.36 µm from a 127 nm one, 7.5× noise: absorbed (one bead found, 2 % heavy, 14σ)
    r#"{"beads": [[-0.5858524485058054, -0.5913535670931972, 51.61207489569168], [-0.2252129765649611, -0.6122299525265018, 127.40658459453203]], "clip": null, "family": "beads", "noise": 7.502112016815414, "pixel_um": 0.051864253232648455, "seed": 5475287852335616866}"#,
    // a 44 nm bead 0.9 µm from a 131 nm one, 9.7× noise: missed
    r#"{"beads": [[0.002967093948622823, -0.25977653665506506, 131.39697143568202], [0.718099163679311, -0.9133621273493675, 43.57542580144105]], "clip": null, "family": "beads", "noise": 9.688624342406838, "pixel_um": 0.029954874142568942, "seed": 11731801155714187136}"#,
    // a 72 nm and a 53 nm bead 0.22 µm apart, 9.8× noise: read as one bead 17 % heavy, 0.05 µm off
    r#"{"beads": [[0.8572910173674901, -0.18806412984262777, 72.2417865437932], [-0.021559684829918657, 1.2957766159803716, 190.201517637235], [0.6854034823312953, -0.056676376372327475, 52.77590386063656], [-0.9794965987715064, -0.769775559214723, 206.1967649842356]], "clip": null, "family": "beads", "noise": 9.794126284230218, "pixel_um": 0.07520097421620693, "seed": 18278422024103164278}"#,
    // a lone 64 nm bead 0.19 µm beyond the edge, 3.2× noise: a noise bead at weight 0.02 found 0.9 µm inside
    r#"{"beads": [[-0.931408135342644, -1.390692306600516, 64.11089491456426]], "clip": null, "family": "beads", "noise": 3.2475507202178444, "pixel_um": 0.0714720693946384, "seed": 16803535266385002934}"#,
    // five beads, a 41 nm one 0.26 µm from an 85 nm one, 4.9× noise: y 4.6σ off
    r#"{"beads": [[1.1160654121337217, -1.036349585085522, 54.58268204373581], [-1.1912067446325534, 0.3684022182239006, 226.6450249892577], [-0.20978285975138933, 0.47655072980797897, 40.691623551832706], [0.49945736918993355, -0.5772240722279525, 47.855150029261495], [0.018755253341467215, 0.24217808123530382, 84.84011970660488]], "clip": null, "family": "beads", "noise": 4.8618313314373935, "pixel_um": 0.0681921436612823, "seed": 8266295830653027209}"#,
    // a 45 nm bead 0.27 µm from a 152 nm one, 6.1× noise: missed, the bright bead's y 17σ off
    r#"{"beads": [[1.2143283624660848, 1.2836487389547622, 77.31824799758503], [-1.3321755853874446, -1.332867060275753, 48.72188861980306], [0.04497504566757993, -0.13757917940638786, 152.060036906962], [-1.0045463423772563, -1.061146599758502, 56.06390146764759], [-0.020618844328359476, 0.11598424221597803, 44.52573661554492]], "clip": null, "family": "beads", "noise": 6.142794951941903, "pixel_um": 0.03608925454409382, "seed": 17860186347243166581}"#,
    // seed 7, N = 1000, after the matched filter (its positions as printed, to 0.1 nm): a 47 nm
    // bead 0.23 µm from a 67 nm one at 7.3× noise, fitted at 1.6σ and dropped although the BIC
    // preferred it; the 67 nm bead read 15 % heavy and 0.07 µm off
    r#"{"beads": [[0.1293, -0.0124, 47.0343], [0.352, -0.0789, 67.3691], [0.5412, 1.3719, 66.137], [0.7847, -0.1112, 42.6546]], "clip": null, "family": "beads", "noise": 7.2675, "pixel_um": 0.0261, "seed": 16670050618100560855}"#, // seed 7, N = 2000: a 47 nm bead 0.44 µm from a 189 nm one at the scan's edge went unfitted
    // (the large bead's misfit hid it, even noise-free) and moved a 131 nm bead 1.0 µm from it,
    // 1.3 µm from the large one, by 0.46 nm in y, 4.6σ
    r#"{"beads": [[-0.0016767537598409987, 1.0410502176958674, 191.59915685389356], [0.8832492688675568, 0.926499379381474, 46.55321362962245], [1.2336187140235726, 1.1888022451100193, 188.61309626780707], [0.9244285547456625, -0.07420838738293245, 130.6700170387284]], "clip": null, "family": "beads", "noise": 1.6191631594682976, "pixel_um": 0.0401359050315283, "seed": 102412135715211630}"#,
];

#[test]
fn bead_scenes_that_were_unflagged_outliers_are_now_found_or_flagged() {
    for scene in BEAD_SCENES_ONCE_OUTLIERS {
        let t = bfpscope::accuracy::sweep::replay_tallies(scene).expect("the scene replays");
        for (k, v) in &t {
            assert_eq!(v.unflagged_outliers, 0, "{k}: {:#?}", v.examples);
        }
        assert!(t.contains_key("fit_beads.count"), "{scene}: no bead fit");
    }
}

/// Focus scenes whose z_best was an unflagged outlier of `bfpscope sweep --n 2000` (seed 2026 at
/// the seventh session's code; seed 99 under a flag that was then taken out): a steepened top
/// of the focus curve narrowed the vertex's σ. Now it widens by the top's curvature over what
/// the curve's sides support (`focus::steep_top`).
const FOCUS_SCENES_ONCE_OUTLIERS: [&str; 2] = [
    // 121 nm bead at 6.5× the paper's noise, 100 nm rows: 82 nm off, σ 14.5 nm, 5.6σ
    r#"{"family":"focus","bead":[-0.308,1.27187,121.2],"noise":6.4590,"pixel_nm":50,"z_step_nm":100,"seed":9364780362231550516}"#,
    // 154 nm bead at 8× the paper's noise, 100 nm pixels and rows: 4.1σ
    r#"{"family":"focus","bead":[0.237,0.48433,153.8],"noise":8.0841,"pixel_nm":100,"z_step_nm":100,"seed":14604980884282667453}"#,
];

#[test]
fn focus_scenes_that_were_unflagged_outliers_are_now_within_their_sigma() {
    for scene in FOCUS_SCENES_ONCE_OUTLIERS {
        let t = bfpscope::accuracy::sweep::replay_tallies(scene).expect("the scene replays");
        let z = &t["focus_search.z_best"];
        assert_eq!((z.cases, z.in_domain), (1, 1), "{scene}");
        assert_eq!(z.unflagged_outliers, 0, "{scene}: {:#?}", z.examples);
    }
}

/// `max_sens` on an empty field: before the ninth session (2026-12-07) it read the largest
/// noise maximum of the sensitivity image as an object's, with status "ok" (8 of 9 empty
/// fields of the first 100 max_sens scenes at seed 2026, here one at 75 nm pixels). The best
/// row's maximum now stands against the image's own noise (`focus::ROW_PEAK_SNR`) and is
/// flagged.
#[test]
fn max_sens_on_an_empty_field_is_flagged() {
    let scene = r#"{"family":"maxsens","bead":null,"noise":3.2809,"pixel_nm":75,"seed":7322248145479594902,"clip":null}"#;
    let t = bfpscope::accuracy::sweep::replay_tallies(scene).expect("the scene replays");
    let d = &t["max_sens.detection"];
    assert_eq!(
        (d.cases, d.in_domain, d.unflagged_outliers),
        (1, 0, 0),
        "{d:#?}"
    );
    assert!(
        d.reasons.keys().any(|r| r.contains("own noise")),
        "{:?}",
        d.reasons
    );
}

/// `max_sens` on a bead far off the focus (sixteenth session, 2026-12-07): beyond ~0.8 µm the
/// bead's ∂Sx/∂x spreads into lobes across the rows (the noise-free second maximum is 0.03–0.17
/// of the first within 0.7 µm, 0.28–1 from 1 to 3 µm), and the 32 answers beyond 1 µm of the
/// three seeds' N = 2000 runs held only 55–58 % of their 1σ intervals. Here: a 110 nm bead at
/// the paper's noise is in the domain up to 0.6 µm from the focus and flagged from 1 µm on, and
/// the two 3σ answers of seed 7's run (3.3σ at −1.80 µm, 3.9σ at +1.90 µm) are flagged.
#[test]
fn max_sens_on_a_bead_far_off_the_focus_is_flagged() {
    let scene = |z: f64| {
        format!(
            r#"{{"family":"maxsens","bead":[0.1,0.05,{z},110.0],"noise":1.0,"pixel_nm":30,"seed":11,"clip":null}}"#
        )
    };
    let seed7 = [
        r#"{"bead": [-0.5184406423533505, 0.9428668423647437, -1.8035008695126078, 137.06283525725829], "clip": null, "family": "maxsens", "noise": 0.7146291650438319, "pixel_nm": 50, "seed": 13214839769579892414}"#.to_string(),
        r#"{"bead": [0.553967303488806, -0.8393456193549647, 1.9030589853270996, 194.09845260907002], "clip": null, "family": "maxsens", "noise": 2.5863451924448277, "pixel_nm": 20, "seed": 5372002028740144807}"#.to_string(),
    ];
    let near = [0.0, 0.3, -0.6].map(scene);
    let far = [1.0, -1.2, 1.5, -2.0, 2.6].map(scene);
    for (sc, in_domain) in near
        .iter()
        .map(|s| (s, true))
        .chain(far.iter().chain(&seed7).map(|s| (s, false)))
    {
        max_sens_scene_is(sc, in_domain, "second maximum");
    }
}

/// One max_sens scene replayed: one case, no unflagged outlier, in the domain or not, and (if
/// not) flagged with a reason holding `words`.
fn max_sens_scene_is(sc: &str, in_domain: bool, words: &str) {
    let t = bfpscope::accuracy::sweep::replay_tallies(sc).expect("the scene replays");
    let v = &t["max_sens.value"];
    assert_eq!((v.cases, v.unflagged_outliers), (1, 0), "{sc}: {v:#?}");
    assert_eq!(v.in_domain, usize::from(in_domain), "{sc}: {:?}", v.reasons);
    if !in_domain {
        assert!(
            v.reasons.keys().any(|r| r.contains(words)),
            "{sc}: {:?}",
            v.reasons
        );
    }
}

/// `max_sens` where the window about the maximum reaches the derivative image's empty outer
/// column (sixteenth session): the vertex 0.21 µm inside a scan of 50 nm pixels passed the
/// half-window margin, but the window about its nearest pixel lost a sample, and a 105 nm bead
/// read 1.5 % low noise-free. Once σ stopped counting the peak's shape as noise, the two such
/// answers of seeds 7 and 99 stood 4.2σ off. Flagged now; the same bead at the same sub-pixel
/// place 0.5 µm further in stays in the domain.
#[test]
fn max_sens_with_its_window_cut_by_the_edge_is_flagged() {
    let scene = |x: f64, noise: f64, seed: u64| {
        format!(
            r#"{{"family":"maxsens","bead":[{x},-0.5869499664321294,-0.399153308350805,104.80059814493595],"noise":{noise},"pixel_nm":50,"seed":{seed},"clip":null}}"#
        )
    };
    let seed99 = r#"{"bead": [-0.9886625119355834, 0.569736830517011, 0.0, 119.75953296919235], "clip": null, "family": "maxsens", "noise": 0.6667441069266333, "pixel_nm": 50, "seed": 7891929274627650539}"#;
    let cases = [
        (
            scene(0.982080467821981, 0.4913465588206867, 2272684425455734254),
            false,
        ),
        (scene(0.982080467821981, 0.0, 1), false),
        (seed99.to_string(), false),
        (
            scene(0.482080467821981, 0.4913465588206867, 2272684425455734254),
            true,
        ),
    ];
    for (sc, in_domain) in cases {
        max_sens_scene_is(&sc, in_domain, "of the scan's edge");
    }
}

/// Fibril scenes that were unflagged diameter outliers of `bfpscope sweep --n 2000 --seed 2026`
/// (and one of seed 99)
/// (the `scene` field of their `BFPSCOPE_SWEEP_DUMP` lines), each now within its σ or flagged.
const FIBRIL_SCENES_ONCE_OUTLIERS: [&str; 5] = [
    // (seed 2026, seventh session, once the correction's systematic fell from a flat 0.3 % to
    // its angle model) 2.33 µm at −58°, 75 nm pixels, its end 0.05 µm beyond the scan's edge:
    // the 4 edge lines stood 4.7 % low (below the 5 % test), the last 2 12 %; the end's maxima
    // bent the line 2° and the diameter read 3.4 % thin at 4.1σ (3.2 % noise-free)
    r#"{"angle_deg": -58.2, "centre": [-0.56, -0.54], "clip": 0.118, "d_nm": 77.0, "family": "fibril", "len_um": 2.33, "noise": 1.9454, "pixel_nm": 75, "seed": 3790540278916238608}"#,
    // 2.0 µm, both ends in the scan, low noise: the interior line's angle 0.6° off through the
    // ends (σ claimed 0.04°), the correction 1.5 % low, the diameter 0.8 % thin at 4.5σ
    r#"{"angle_deg": 55.535302957191846, "centre": [0.19272861564267485, -0.6387272181869652], "clip": null, "d_nm": 91.457708703603, "family": "fibril", "len_um": 2.0040182255458414, "noise": 0.23704919382736778, "pixel_nm": 30, "seed": 5426604955245316911}"#,
    // 2.8 µm near 45°, one end in the scan: 1.2 % thick at 4.2σ, the same end systematic
    r#"{"angle_deg": -47.07531276572976, "centre": [-0.7687732318970857, 0.013211888933907234], "clip": null, "d_nm": 125.11157397383934, "family": "fibril", "len_um": 2.7998111094156672, "noise": 5.590581734345806, "pixel_nm": 20, "seed": 14450850336560390790}"#,
    // 58 nm at 7.7× the paper's noise and 20 nm pixels, each maximum at 6σ: 3.4 % thin at 4.2σ
    r#"{"angle_deg": -5.423976368189088, "centre": [-0.2821646084493401, -0.28082579779505523], "clip": null, "d_nm": 57.6561642582714, "family": "fibril", "len_um": 3.587161142588356, "noise": 7.6823213854702015, "pixel_nm": 20, "seed": 10159378904788050856}"#,
    // (seed 99) 2.25 µm at 56°, its end 0.04 µm beyond the scan's edge, 5× the paper's noise:
    // the edge line's maximum did not clear 3σ of one maximum below a plateau read at its 90th
    // percentile, the end's maxima bent the interior line 2°, the diameter read 2.9 % thin at 5.5σ
    r#"{"angle_deg": 56.08173334421366, "centre": [0.602166986136508, 0.7879472368248326], "clip": 0.06559749931016226, "d_nm": 81.88033307202905, "family": "fibril", "len_um": 2.2536378386876548, "noise": 4.953794438773875, "pixel_nm": 20, "seed": 16770485003572424949}"#,
];

#[test]
fn fibril_scenes_that_were_unflagged_outliers_are_now_within_their_sigma_or_flagged() {
    for scene in FIBRIL_SCENES_ONCE_OUTLIERS {
        let t = bfpscope::accuracy::sweep::replay_tallies(scene).expect("the scene replays");
        let d = &t["measure_filament.diameter"];
        assert_eq!(d.cases, 1, "{scene}");
        assert_eq!(d.unflagged_outliers, 0, "{scene}: {:#?}", d.examples);
    }
}

/// The slowest microtubule scene of seed 2026 (N = 12): a 13.4 µm filament 16.4° from the QPD
/// x axis, noise × 6.7, 20 nm pixels, three aggregates. The filament shows in Sx, the channel
/// the objects are fitted in: CLEAN took it (and one-pixel noise spikes of the unsmoothed
/// detection map) for 60 objects, the fit took 335 s, and the removal erased the filament. Now
/// the removal refuses it, before any fit, and says why.
const MT_OFF_AXIS: &str = r#"{"family":"microtubule","len_um":13.38245159717844,"d_nm":23.513175998630235,"angle_deg":73.58895350760878,"centre":[5.482909196240237,1.2058440611093446],"aggregates":[[0.952999717499157,-0.4015237883708178,89.49139240591839],[0.8693105877454523,-0.21291062457828955,41.95124590256686],[-0.6831737167225068,-0.6102246867370652,51.79829887430727]],"noise":6.684018846032345,"pixel_nm":20,"seed":9143817694001983331,"clip":0.2018985446869819}"#;

#[test]
fn the_aggregate_removal_refuses_a_filament_that_shows_in_its_fitted_channel() {
    let said = bfpscope::accuracy::sweep::replay(MT_OFF_AXIS).expect("the scene replays");
    assert!(
        said.contains("refused: remove_background: the filament itself shows in Sx")
            && said.contains("° from the QPD x axis"),
        "{said}"
    );
    let t = bfpscope::accuracy::sweep::replay_tallies(MT_OFF_AXIS).expect("the scene replays");
    let v = &t["microtubule.mu"];
    assert_eq!((v.cases, v.in_domain), (1, 0), "{said}");
}

/// A microtubule along the y axis, no aggregate, the paper's noise, 30 nm pixels: nothing to
/// remove. The removal's CLEAN used to take the detection map's edge rows (one-sided
/// derivative, and fewer pixels in the smoothing there) for 8 objects and fitted 6. Its μ is in
/// the domain (the uniformity tests pass a uniform filament).
#[test]
fn the_aggregate_removal_finds_nothing_beside_a_clean_microtubule_at_the_papers_noise() {
    for (angle, seed) in [(0.0, 5), (2.0, 6), (-3.0, 7)] {
        let scene = format!(
            r#"{{"family":"microtubule","len_um":13.0,"d_nm":23.5,"angle_deg":{angle},"centre":[0.3,0.2],"aggregates":[],"noise":1.0,"pixel_nm":30,"seed":{seed},"clip":null}}"#
        );
        let said = bfpscope::accuracy::sweep::replay(&scene).expect("the scene replays");
        assert!(said.contains("  0 point objects removed ("), "{said}");
        // and its uniform region passes the uniformity tests: the answer is in the domain
        let t = bfpscope::accuracy::sweep::replay_tallies(&scene).expect("the scene replays");
        let v = &t["microtubule.mu"];
        assert_eq!(
            (v.cases, v.in_domain, v.unflagged_outliers),
            (1, 1, 0),
            "{said}"
        );
    }
}

/// An unflagged outlier of `bfpscope sweep --n 2000 --seed 2026 --family microtubule` (at
/// 648a212): a 6.3 µm microtubule 4.3° from the y axis, its end inside the field, noise × 0.14,
/// 40 nm pixels; the removal took the filament for 13 objects and μ read 86 % low, with no
/// warning. The removal moved the median maximum by −85 %: now it says so, and the answer is
/// out of the domain. (The class is open: a −19 % answer moved it by −5 %; docs/analysis.md.)
const MT_FILAMENT_TAKEN_FOR_OBJECTS: &str = r#"{"aggregates":[[0.24792688094230908,-3.419342304138612,92.06935823824696],[0.4225268980783561,-2.8401381731392594,91.98284163580986],[0.5732515826645153,2.5586481297569676,85.02593798411615],[0.5867251444519551,-2.985620988517058,84.85705599166444],[0.6291804603377337,1.4174326493014087,40.04220748676285]],"angle_deg":4.266041517122762,"centre":[0.3863187454023653,-1.8383322002339209],"clip":null,"d_nm":18.14333613007365,"family":"microtubule","len_um":6.269611755114823,"noise":0.1396972285223752,"pixel_nm":40,"seed":9346850379871553632}"#;

#[test]
fn a_removal_that_takes_the_filament_for_objects_is_flagged() {
    microtubule_scene_is_flagged(
        MT_FILAMENT_TAKEN_FOR_OBJECTS,
        &[
            "the removal moved the filament's median corrected maximum by -85 %",
            // since the footprints (sixth session): every maximum lies where the 13 objects'
            // subtraction can move it, and the density refuses before the warning is read
            "40 of the uniform region's 40 maxima lie where a removed point object's subtraction can move them",
        ],
    );
}

/// Replays a microtubule scene of the sweep and asserts that it says one of `why` and is out of
/// the domain (one case, no answer in the domain, no unflagged outlier); returns what it said.
fn microtubule_scene_is_flagged(scene: &str, why: &[&str]) -> String {
    let said = bfpscope::accuracy::sweep::replay(scene).expect("the scene replays");
    assert!(why.iter().any(|w| said.contains(w)), "{said}");
    let t = bfpscope::accuracy::sweep::replay_tallies(scene).expect("the scene replays");
    let v = &t["microtubule.mu"];
    assert_eq!(
        (v.cases, v.in_domain, v.unflagged_outliers),
        (1, 0, 0),
        "{said}"
    );
    said
}

/// The eight unflagged outliers of `bfpscope sweep --n 2000 --seed 2026 --family microtubule` (at
/// f07c752; the `scene` field of their `BFPSCOPE_SWEEP_DUMP` lines). Each had μ off by a bump,
/// a dip or a tilt of the maxima along the uniform region (an aggregate's residual, an
/// aggregate left undetected, a stretch of the filament removed as objects), which σ(μ) =
/// std/√n does not hold. `density` now tests the maxima's uniformity (a straight line's slope,
/// the von Neumann ratio) and flags each, or refuses where every maximum lies in a removed
/// object's footprint (the stretch of filament removed as 7 objects).
const MT_SCENES_ONCE_OUTLIERS: [&str; 8] = [
    // no aggregate: 2 objects removed at 4.3× the paper's noise, the maxima tilted; μ 5.4 % low at 3.4σ
    r#"{"aggregates": [], "angle_deg": 87.90721939432214, "centre": [3.4071331195005254, 0.350818430538824], "clip": null, "d_nm": 24.17758402957861, "family": "microtubule", "len_um": 9.170749505966809, "noise": 4.326201175593328, "pixel_nm": 40, "seed": 9258456673062039634}"#,
    // a 104 nm aggregate 0.25 µm from the line among seven, 4 objects removed; μ 5.7 % low at 3.2σ
    r#"{"aggregates": [[-2.767753500208864, 0.0051894982539041346, 31.600777619553533], [0.33550928642744926, -0.21824593473961346, 103.7502688058184], [1.9071753134351728, -0.3394198001532743, 54.15013268981501], [2.6282180756877627, -0.3795119728724972, 34.00523767831536], [3.2390994471930217, -0.6269751862568835, 58.54583577735895], [-1.4671272342466717, 0.5025212047964369, 72.35607781381499], [-3.9325789754457485, 0.6368606945734394, 33.36165474100557]], "angle_deg": -82.13302449546958, "centre": [-5.544999668901359, 0.7498144561354556], "clip": null, "d_nm": 20.762568720339836, "family": "microtubule", "len_um": 13.405823059975212, "noise": 4.18513682652055, "pixel_nm": 30, "seed": 18382160143699488781}"#,
    // 0.02° from the y axis at 0.67× the paper's noise, an end in the field: the removal took a
    // stretch of the filament for 7 objects; μ 19 % low at 9.7σ (the median moved −5 %)
    r#"{"aggregates": [[-0.5130385910894536, 0.042847906215122245, 52.82852721226508], [-0.2978310669816892, 0.5250773647672553, 41.825912182614466], [-0.22613213166858379, 3.4417804036388047, 36.45702678762596]], "angle_deg": 0.020221001051822896, "centre": [-0.29963520074666355, -4.586897351689713], "clip": null, "d_nm": 17.130293113000377, "family": "microtubule", "len_um": 12.231613701042605, "noise": 0.6735358792393931, "pixel_nm": 50, "seed": 10230839541867044478}"#,
    // a 69 nm aggregate beside the line, 3 objects removed, its residual tilted the maxima; μ 3.4 %
    // high at 4.5σ
    r#"{"aggregates": [[-1.2979011270356466, 0.17441300126199216, 68.77829900849663], [2.8761380037240105, 0.09311660483397634, 105.34475633157213], [-0.3862766655174913, -0.14888049840189704, 37.23732332485358], [3.760756213896509, 0.15873519291530663, 62.66694947369095]], "angle_deg": 85.7577232577606, "centre": [1.1464358384334101, -0.03518802713313715], "clip": null, "d_nm": 21.697290580009863, "family": "microtubule", "len_um": 10.09580918546359, "noise": 2.9069792948031825, "pixel_nm": 50, "seed": 18004672856005733838}"#,
    // a 46 nm aggregate on the line, 3 objects removed, its residual over half the uniform region;
    // μ 5.4 % high at 4.9σ
    r#"{"aggregates": [[-0.36016455726176927, 0.8048448327987103, 46.4197989210141], [-2.590925241253353, 0.7036897826982768, 116.38890554561506]], "angle_deg": 85.40374169955841, "centre": [2.9423080112164492, 1.0963167946936236], "clip": null, "d_nm": 19.18804975909675, "family": "microtubule", "len_um": 14.628058874838933, "noise": 2.420692964976432, "pixel_nm": 40, "seed": 10757395778282991970}"#,
    // seven aggregates, clipped inputs, 2 objects removed; μ 9.7 % high at 5.6σ
    r#"{"aggregates": [[2.5590999404363965, 0.718584065147301, 52.15837857505321], [2.092856154224685, 0.35803257098063773, 57.47666082949604], [0.34754712811317, 0.44031631425218404, 53.995998187940295], [0.3139307156105954, 0.5870795751265944, 38.20472769020495], [-1.5756667222989627, 0.4590991042474783, 74.9309072768388], [3.234069760542839, 0.4121255083207625, 41.547162370083214], [1.6055733721900856, 0.7277984920362546, 45.52899658346501]], "angle_deg": -89.44044684362503, "centre": [2.3880738669716304, 0.4203878048939825], "clip": 0.1782525660162712, "d_nm": 20.166878376589416, "family": "microtubule", "len_um": 12.638508010032153, "noise": 4.552891661725118, "pixel_nm": 30, "seed": 11462535432067470858}"#,
    // seven aggregates at 0.34× the paper's noise, 4 objects removed; μ 1.8 % low at 5.7σ
    r#"{"aggregates": [[-3.890954701633529, -0.27984120202832363, 92.34132038447207], [-0.6744729569590805, -0.5938711846905509, 54.81561864005338], [-3.7216665406176745, -0.27776446622683265, 33.68886293860353], [-0.7100610150206664, -0.20264071181894736, 37.40117204611997], [0.03722390537505672, 0.09066115770897973, 30.02318601787228], [-0.49582861219827207, 0.03705383841912696, 59.199198315009546], [0.6253245284080676, 0.1535482488527257, 77.69207849966521]], "angle_deg": 89.29716155254823, "centre": [-0.12114906373734186, -0.23359526087152696], "clip": null, "d_nm": 17.092782620346306, "family": "microtubule", "len_um": 9.627147355867274, "noise": 0.33998930535078964, "pixel_nm": 20, "seed": 14662383003986281754}"#,
    // aggregates on the line left undetected at 6× the paper's noise (0 objects removed); μ 12.3 %
    // high at 5.0σ
    r#"{"aggregates": [[-2.790436515874209, 0.8047992820383457, 114.47770494192424], [0.7520469273986458, 0.8208595317317794, 34.957246987615385], [-0.9226429440236934, 0.9790449745704624, 50.43250915790803], [-0.43856887101323394, 0.9333210032772883, 59.05651556382464], [2.736518711342807, 0.42568425577496205, 40.02993773429194], [3.626393516685535, 0.5968350119794864, 60.07167501315571], [-1.4027077274324196, 1.0243902421633626, 55.67785734675048], [2.9486034788405755, 0.6133803579818682, 115.34061414273896]], "angle_deg": -84.60404744973211, "centre": [0.7522056930002591, 0.8208445352793452], "clip": null, "d_nm": 20.544685712228386, "family": "microtubule", "len_um": 9.67750316338358, "noise": 6.034212811338118, "pixel_nm": 50, "seed": 1012579882022932395}"#,
];

#[test]
fn microtubule_scenes_that_were_unflagged_outliers_are_now_flagged_as_not_uniform() {
    for scene in MT_SCENES_ONCE_OUTLIERS {
        microtubule_scene_is_flagged(
            scene,
            &[
                "the maxima along the uniform region are not uniform",
                // the stretch taken for objects: every maximum in their footprints
                "maxima lie where a removed point object's subtraction can move them",
            ],
        );
    }
}

/// The three unflagged outliers of `bfpscope sweep --n 2000 --seed 99 --family microtubule` (at
/// 97dee43; unchanged at 944a427). At 5–7× the paper's noise the removal detects point objects
/// of 0.11–0.16 reference beads and up: one just below that on the filament would add 38–56
/// MDa/µm to μ (`Density::undetected_mda_um`), and each is now flagged for it.
const MT_SEED99_OUTLIERS: [&str; 3] = [
    // 6.1 µm near the x axis, 4.9× the paper's noise, 40 nm pixels, three aggregates of
    // 51–120 nm in the field and 4 objects removed: μ 5.8 % high at 3.5σ
    r#"{"aggregates":[[3.1146070002672137,0.0481410867008554,99.82839467514863],[1.987565372671184,-0.09178276414976623,119.80149742650593],[-3.9440810432579907,0.4299201592589492,41.77170193711286],[3.8694325943477406,-0.2504322837272222,40.24444645171464],[3.8127195406863996,-0.2503244000198711,72.85731745618428],[-0.365479122974397,0.23636644024544148,51.176450504425055],[1.4879226410221036,0.13612259858917541,97.2801626974798],[3.4519076117560155,0.029897708634927855,32.72423000432036]],"angle_deg":-86.90409367242188,"centre":[-1.3756411252193632,0.29100247317003963],"clip":null,"d_nm":20.485280696607944,"family":"microtubule","len_um":6.141489614401035,"noise":4.922752704582917,"pixel_nm":40,"seed":14971994818954117974}"#,
    // 11.1 µm near the x axis, 5.1× the paper's noise, clipped, 50 nm pixels, nothing in the
    // field to remove, 20 maxima: μ 5.2 % low at 2.5σ (beyond the 5 % test)
    r#"{"aggregates":[[2.9293181924570284,0.3272387830369297,51.59947289454194]],"angle_deg":84.4180523091012,"centre":[4.531342803131707,0.4838090790731815],"clip":0.07781295431169623,"d_nm":18.811797808361668,"family":"microtubule","len_um":11.102408248522087,"noise":5.137753439412283,"pixel_nm":50,"seed":14822276371796584352}"#,
    // 6.8 µm near the x axis, 7.3× the paper's noise, 50 nm pixels, 4 aggregates of 42–62 nm
    // within 0.3 µm of the line and none detected: μ 12.8 % high at 5.7σ
    r#"{"aggregates":[[0.6043513680603124,-0.14012645232740636,44.62640167390259],[3.695186311826401,-0.3639999612578879,70.79800629953682],[-1.6594740250059357,0.053293910116743615,41.70256047312453],[-0.0487256339425486,-0.1690045443175428,61.78134009868379],[-2.8782448910563145,-0.07952164947442972,54.64793804504046],[1.2860396043213458,-0.41006161902714855,56.01450754424592],[2.4066157612300927,0.20371600180369778,56.28107176110894]],"angle_deg":87.46811531536649,"centre":[1.381537025652618,-0.10576046050020227],"clip":null,"d_nm":21.270237399497688,"family":"microtubule","len_um":6.804025166155289,"noise":7.317857172100133,"pixel_nm":50,"seed":1230354839744607796}"#,
];

#[test]
fn microtubules_whose_aggregates_the_removal_cannot_see_are_flagged() {
    for scene in MT_SEED99_OUTLIERS {
        microtubule_scene_is_flagged(
            scene,
            &["one point object just below the removal's detection limit"],
        );
    }
}

/// The unflagged outliers of `bfpscope sweep --n 2000 --seed S --family microtubule` at the
/// thirteenth session's draw (seeds 2026 and 7; docs/accuracy.md; and seed 99's, found in the
/// fifteenth session's runs): aggregates of 34–35 nm on
/// the filament, below the removal's detection limit (0.028–0.035 reference beads at 2× the
/// paper's noise), each adding to every maximum within its reach. One object at that limit
/// would add 8.9–11.3 MDa/µm, less than a protofilament, so the undetected-object warning was
/// silent, while σ(μ) was 1.2–3.0 MDa/µm. A matched filter along the filament's line
/// (`analysis::faint`) finds them at 10–18σ, and the density now says what they add to μ.
const MT_FAINT_ON_THE_LINE: [&str; 3] = [
    // seed 2026: a 33.6 nm aggregate on the line, 20 nm pixels, 1.96× the paper's noise, 2
    // objects removed: μ 331.7 ± 1.23 against 325.7 MDa/µm (4.9σ)
    r#"{"family":"microtubule","aggregates":[[-1.1734470482809927,-0.6604692985093958,61.106990081297575],[-0.27302089329009127,-0.6792688418865356,33.61321706815117],[-2.9637368102852126,-0.6090900184596242,30.46751655006833]],"angle_deg":-88.5059593348372,"centre":[-1.9363142710925696,-0.6358870892716746],"clip":null,"d_nm":22.583647520359243,"len_um":13.795074603941078,"noise":1.9556233620883363,"pixel_nm":20,"seed":10455647693020138455}"#,
    // seed 7: two 35 nm aggregates on the line 0.58 µm apart, 40 nm pixels, 1.94× the paper's
    // noise, none removed: μ 366.8 ± 2.97 against 354.6 MDa/µm (4.1σ)
    r#"{"family":"microtubule","aggregates":[[0.03683357172666997,0.5781163342329363,34.747372345869664],[0.047150187195312596,0.0025450372189740385,34.82266078371034]],"angle_deg":0.07105302745882369,"centre":[0.045195936302004476,-1.5733240693080959],"clip":null,"d_nm":23.56656279538455,"len_um":13.700025746022886,"noise":1.943618396074318,"pixel_nm":40,"seed":10155100242929685835}"#,
    // seed 99 at this session's runs (fifteenth): three aggregates of 34–40 nm on the line, 20 nm
    // pixels, 1.15× the paper's noise: μ 297.1 ± 1.81 against 285.1 MDa/µm (6.6σ), its only
    // warning the matched filter's (one object, 0.0094 ± 0.0003 reference beads, 29σ)
    r#"{"family":"microtubule","aggregates":[[-0.5954818040448691,0.6518710413958273,33.930093503343265],[-0.5527257784706082,-0.34624887646760905,34.010453051696764],[-0.2562838976883383,0.5361994396043386,95.8702450500802],[-0.5927574530929571,0.5882723108816765,40.22472297341604],[-0.5786022799507743,0.25782624943756444,65.42638610172646],[-0.7179547632323349,3.5109464190257658,74.0885725232133],[-1.0125944845219887,3.5814196768149276,87.80566471088706],[-0.16187773850504306,-0.9477173946575055,32.829846837225524]],"angle_deg":-2.4528546293550946,"centre":[-0.6786506608042396,2.5934100727372313],"clip":null,"d_nm":21.13222197195485,"len_um":8.697493813892548,"noise":1.147045067639798,"pixel_nm":20,"seed":6036256137174848238}"#,
];

#[test]
fn aggregates_on_the_line_below_the_removals_limit_are_found_and_flagged() {
    for scene in MT_FAINT_ON_THE_LINE {
        let said = microtubule_scene_is_flagged(scene, &["below the removal's detection limit li"]);
        // by the matched filter (replayed: the 33.6 nm aggregate read 0.0135 ± 0.0008
        // reference beads for (33.6/110)³ × 0.50 = 0.0143, 0.03 µm from where it lies; the two
        // 35 nm ones 0.011 ± 0.001 for 0.016, each window taking in the other's negative lobe)
        assert!(
            said.contains("found by a matched filter along it"),
            "{said}"
        );
    }
}

/// Microtubule scenes in the CI run: 40 (15 s of release CPU at seed 2026; in the domain: 3).
/// At N = 2000 the family has no unflagged outlier at seeds 2026, 7, 99 and 1 (sixteenth
/// session: 146, 155, 176 and 167 answers in the domain, 1σ coverage 0.705–0.726;
/// docs/accuracy.md), so an outlier fails here;
/// the coverage is asserted once 20 answers are in the domain (`SWEEP_N`, `SWEEP_RANDOM` as
/// above; the benchmark, `bfpscope sweep --family microtubule`, runs 2000).
const MICROTUBULE_N: usize = 40;

#[test]
fn a_fixed_seed_microtubule_sweep_measures_the_linear_density_after_aggregate_removal() {
    let (n, seed) = n_and_seed(MICROTUBULE_N);
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
    assert_calibrated("microtubule.mu", v);
}

/// Scenes of the beam family CI runs: a profile over the pupil filling at seven planes per v
/// (the bead's height² and height × offset terms fitted since the fourteenth session), the
/// model relinearised about its answer, and the defocus test. 24 scenes took 577 s on the
/// shared 2-core machine (another sweep running), so CI ran 12, and a clean-clone `.ci/run`
/// then took 918 s, beyond CI's 15 minutes: CI runs 8 (the fifteenth session); the benchmark,
/// `bfpscope sweep --family beam`, runs 2000.
const BEAM_N: usize = 8;

/// The beam fit on random reference-bead scans (`bfpscope sweep --family beam`'s scenes:
/// random pupil filling, QPD misalignment, focus offsets to ±1 µm, noise, pixels, clipping,
/// empty fields): no answer without a warning is an outlier, and every scene is an answer, a
/// flag or a refusal. (The family's first run found a panic at the profile's bound, a bead
/// 0.34–0.5 µm off the focus read as a smaller pupil filling at 12–25σ, and offsets read as
/// o²/0.05 with either sign: `tests/beam_fit.rs` has each.)
#[test]
fn a_fixed_seed_beam_sweep_fits_the_beam_without_unflagged_outliers() {
    let (n, seed) = n_and_seed(BEAM_N);
    println!("truth sweep: {n} beam scenes, seed {seed}");
    let opts = SweepOptions {
        n,
        seed,
        families: vec!["beam".into()],
    };
    let t = run(&opts, &|_, _| {}).expect("the sweep runs");
    print!("{}", bfpscope::accuracy::sweep::table(&t));
    let scenes = t[BEAM_KEYS[0]].cases + t.get(BEAM_DETECTION).map_or(0, |d| d.cases);
    assert_eq!(scenes, n, "every scene is an answer, a flag or a refusal");
    for k in BEAM_KEYS.into_iter().chain([BEAM_DETECTION]) {
        if let Some(v) = t.get(k) {
            assert_calibrated(k, v);
        }
    }
    // the scenes reach the fit's domain and its flags
    assert!(t[BEAM_KEYS[0]].in_domain > 0, "no answer in the domain");
}
