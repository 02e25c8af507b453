//! The scripting workbench in-process: every binding example, the generated API reference,
//! help, REPL semantics, error positions, the sandbox and Ctrl-C.

use crate::support::cleanup;

use bfpscope::script::registry::{api_markdown, help_index, Kind};
use bfpscope::script::{all_docs, Settings, Workbench};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

fn wb(tag: &str) -> (Workbench, std::sync::Arc<std::sync::Mutex<String>>) {
    let dir = std::env::temp_dir().join(format!("bfpscope-wb-{}-{tag}", std::process::id()));
    cleanup::at_exit(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    let (s, buf) = Settings::captured(dir);
    (Workbench::new(s), buf)
}

#[test]
fn every_binding_example_runs_and_gives_its_expected_result() {
    let docs = all_docs();
    let (n, failures, keys) = bfpscope::script::testing::run_examples(&docs);
    assert!(n >= 60, "only {n} examples");
    assert!(
        failures.is_empty(),
        "{} of {n} examples failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
    // every number in a result has its unit: in its key (`w0_nm`), printed after it (`x`), or
    // it is one of the dimensionless quantities listed here
    let unknown = without_unit(&keys);
    assert!(
        unknown.is_empty(),
        "result keys without a unit (name it in the key, add a bare key to script::units::BARE, or list it as dimensionless): {unknown:?}"
    );
}

/// The keys with neither a unit (`script::units`) nor a place in [`DIMENSIONLESS`].
fn without_unit(keys: &std::collections::BTreeSet<String>) -> Vec<&String> {
    keys.iter()
        .filter(|k| bfpscope::script::units::unit_of_key(k).is_none())
        .filter(|k| {
            let base = k
                .strip_suffix("_sd")
                .or_else(|| k.strip_suffix("_err"))
                .unwrap_or(k);
            !DIMENSIONLESS.contains(&k.as_str()) && !DIMENSIONLESS.contains(&base)
        })
        .collect()
}

/// Result keys whose numbers carry no unit: signals normalised to the beam power, counts,
/// indices, ratios, fit statistics, refractive indices.
const DIMENSIONLESS: &[&str] = &[
    // the fitted beam (fit_beam; a key's `_sd` has the key's unit): QPD gains and their ratio,
    // BFP offsets in cone radii, 1/f0², the fit's χ²/dof, residual and noise (signals
    // normalised to the beam power), a correlation, a count of plane builds
    "gain_x",
    "gain_y",
    "gain_z",
    "gain_ratio",
    "offset_x",
    "offset_y",
    // their squares (cone radii²: at the focus an offset's sign is not measured)
    "offset_x_sq",
    "offset_y_sq",
    "inv_f0_sq",
    "chi2_red",
    "corr_polarization_rotation",
    "residual_rms",
    "noise",
    "background",
    "builds",
    // ratios of signals or sensitivities
    "asymmetry",
    "model_asymmetry",
    "implied_gain_y",
    "bead_fraction",
    "improvement",
    "undetected_rel",
    // weights in reference beads
    "detection_limit",
    "mean_corr",
    "mean_corr_after",
    "sbr",
    "sbr_before",
    "sbr_after",
    "uniformity",
    "uniformity_before",
    "uniformity_after",
    "pupil_filling",
    // counts and indices
    "last_scan",
    "n_beads",
    "n_objects",
    "n_points",
    "n_excluded",
    "n_theta",
    "n_phi",
    "protofilaments",
    "protofilaments_exact",
    // refractive index, numerical apertures
    "n_medium",
    "na",
    "qpd_na",
];

#[test]
fn every_number_in_a_protocol_result_has_its_unit() {
    let (mut w, _) = wb("units");
    let v = w
        .eval_source(
            "units",
            r#"
            import "calibrate" as calibrate; import "focus" as focus;
            import "aggregates" as aggregates; import "microtubule" as microtubule;
            let s = scene();
            s.add_bead(#{x: -3.0, y: 3.0, d_nm: 110.0, n: 1.572});
            s.add_filament(#{points: [[0.0, -3.0], [0.0, 3.0]], d_nm: 17.0, n: 1.587});
            s.add_aggregates(#{count: 6, x: [-1.0, 1.0], y: [-1.5, 1.5], seed: 2});
            s.effects(["detector_noise"]);
            simulate(s);
            let c = calibrate::reference_beads(#{beads: [[-3.0, 3.0]], n: 33, dwell: 0.001});
            mv(#{x: -3.0, y: 3.0, z: 0.2});
            let f = focus::search(#{n: 21, nz: 17});
            let m = simulate(s, #{x: [-1.5, 1.5], y: [-2.0, 2.0], nx: 61, ny: 81, n_samples: 1000});
            let t = template_model(#{h_um: 0.02});
            let a = aggregates::remove(m, t);
            let d = microtubule::density(a.scan, t, #{skip_um: 0.2});
            c.remove("template"); a.remove("scan");
            [c, f, a, d, status(), optics(), pos()]
            "#,
        )
        .unwrap();
    let mut keys = std::collections::BTreeSet::new();
    bfpscope::script::testing::numeric_keys(&v, &mut keys);
    assert!(keys.len() > 20, "{keys:?}");
    let unknown = without_unit(&keys);
    assert!(
        unknown.is_empty(),
        "result keys without a unit: {unknown:?}"
    );
}

#[test]
fn every_binding_has_a_summary_and_an_example() {
    for d in all_docs().iter() {
        assert!(!d.summary.is_empty(), "{} has no summary", d.name);
        assert!(
            !d.examples.is_empty(),
            "{} ({}) has no example",
            d.name,
            d.family
        );
    }
}

#[test]
fn api_reference_is_up_to_date() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/api.md");
    let want = api_markdown(&all_docs());
    let have = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        have == want,
        "docs/api.md is stale: run `cargo run -- docs` and commit it"
    );
}

/// The stop rule's prose has one source (`acquire::stop_rule`): every copy in the README, the
/// guide and the hardware notes is generated from it (`bfpscope docs`), and none is missing.
#[test]
fn stop_rule_copies_in_the_docs_are_up_to_date() {
    use bfpscope::acquire::stop_rule::{with_stop_rule, STOP_RULE_DOCS};
    for (path, want) in STOP_RULE_DOCS {
        let full = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(path);
        let have = std::fs::read_to_string(&full).unwrap();
        let (new, n) = with_stop_rule(&have).unwrap();
        assert_eq!(n, want, "{path}: copies of the stop rule");
        assert!(
            new == have,
            "{path}: the stop rule is stale: run `cargo run -- docs` and commit it"
        );
    }
}

#[test]
fn help_lists_every_binding_by_family_with_units() {
    let docs = all_docs();
    let text = help_index(&docs);
    for d in docs.iter() {
        assert!(
            text.contains(&d.signature()),
            "help() misses {}",
            d.signature()
        );
    }
    let line = docs
        .iter()
        .find(|d| d.name == "scan_xy")
        .unwrap()
        .one_line();
    assert!(text.contains(&line), "{text}");
    assert!(
        line.contains("x, y, z: µm") && line.contains("dwell: s"),
        "{line}"
    );
    assert!(
        text.contains("\nmotion\n") && text.contains("\nscans\n"),
        "{text}"
    );

    let (mut w, buf) = wb("help");
    let _ = w.eval_line("help(\"mv\")").unwrap();
    let out = buf.lock().unwrap().clone();
    assert!(out.contains("mv(#{x, y, z})"), "{out}");
    assert!(out.contains("[µm]"), "{out}");
    assert!(out.contains("examples:"), "{out}");
    let _ = w.eval_line("help(\"img.max\")").unwrap();
    assert!(buf.lock().unwrap().contains("img.max()"));
    let e = w.eval_line("help(\"scan_xyz\")").unwrap_err();
    assert!(
        e.message
            .contains("did you mean `scan_xy` or `scan_xz` or `scan_yz`?"),
        "{e}"
    );
}

#[test]
fn methods_and_properties_are_declared_with_their_type() {
    let docs = all_docs();
    let has = |ty: &str, name: &str| {
        docs.iter().any(|d| {
            d.name == name
                && matches!(&d.kind, Kind::Method { ty: t } | Kind::Property { ty: t } if t == ty)
        })
    };
    for (ty, name) in [
        ("Scan", "sx"),
        ("Scan", "meta"),
        ("Scan", "status"),
        ("Image", "rows"),
        ("Image", "abs_max"),
        ("Image", "row"),
        ("Profile", "max"),
        ("Profile", "t"),
    ] {
        assert!(has(ty, name), "{ty}.{name} not declared");
    }
}

#[test]
fn repl_lines_keep_functions_and_variables() {
    let (mut w, _) = wb("repl");
    let _ = w.eval_line("fn sq(x) { x * x }").unwrap();
    assert_eq!(w.eval_line("sq(7)").unwrap().as_int().unwrap(), 49);
    let _ = w.eval_line("let a = 5;").unwrap();
    assert_eq!(w.eval_line("a + sq(2)").unwrap().as_int().unwrap(), 9);
    // an error does not lose earlier definitions
    let e = w.eval_line("sq(").unwrap_err().to_string();
    assert!(
        e.ends_with(
            "syntax error: Expecting ')' to close the arguments list of this function call 'sq'"
        ),
        "{e}"
    );
    let e = w.eval_line("nope()").unwrap_err().to_string();
    assert!(e.contains("function not found: nope ()"), "{e}");
    assert_eq!(w.eval_line("sq(a)").unwrap().as_int().unwrap(), 25);
    // redefinition wins
    let _ = w.eval_line("fn sq(x) { x * x * 2 }").unwrap();
    assert_eq!(w.eval_line("sq(3)").unwrap().as_int().unwrap(), 18);
    assert!(w.user_names().contains(&"a".to_string()));
    // a stdlib module imported on one line stays imported (protocols at the prompt)
    let _ = w.eval_line(r#"import "focus" as focus;"#).unwrap();
    let h = w.eval_line("focus::help()").unwrap().into_string().unwrap();
    assert!(h.starts_with("focus::search"), "{h}");
    let e = w
        .eval_line(r#"import "no_such_module" as nope;"#)
        .unwrap_err()
        .to_string();
    assert!(e.ends_with("Module not found: no_such_module"), "{e}");
}

#[test]
fn errors_are_one_line_with_position() {
    let (mut w, _) = wb("errors");
    let e = w
        .eval_source("t.rhai", "let a = 1;\nlet b = qpd(10);")
        .unwrap_err();
    assert_eq!(e.to_string().lines().count(), 1);
    assert_eq!(
        (e.source.as_str(), e.line, e.column),
        ("t.rhai", Some(2), Some(9)),
        "{e}"
    );
    assert!(e.message.contains("no instrument connected"), "{e}");
    let e = w
        .eval_source("t.rhai", "fn f(x) {\n  x + undefined_var\n}\nf(1)")
        .unwrap_err();
    assert_eq!(e.line, Some(2), "{e}");
    assert!(
        e.message.contains("undefined_var") && e.message.contains("(in f)"),
        "{e}"
    );
    let e = w.eval_source("t.rhai", "let x = ;").unwrap_err();
    assert!(e.message.starts_with("syntax error"), "{e}");
    let e = w.eval_line("scan_xy").unwrap_err();
    assert!(
        e.message.contains(
            "scan_xy is a function; usage: scan_xy(#{x, y, nx, ny, z, dwell, rel, snake, mode, samples_per_pixel})"
        ),
        "{e}"
    );
}

#[test]
fn runaway_loop_is_stopped_with_a_clear_message() {
    let dir = std::env::temp_dir().join(format!("bfpscope-wb-{}-runaway", std::process::id()));
    cleanup::at_exit(&dir);
    let (mut s, _) = Settings::captured(dir);
    s.sandbox.max_operations = 200_000;
    let mut w = Workbench::new(s);
    let t0 = Instant::now();
    let e = w.eval_line("let i = 0; loop { i += 1; }").unwrap_err();
    assert!(
        e.message.contains("too many operations (runaway loop?)"),
        "{e}"
    );
    assert!(t0.elapsed() < Duration::from_secs(5));
    let e = w.eval_line("fn r(n) { r(n + 1) } r(0)").unwrap_err();
    assert!(
        e.message.contains("nested too deeply") || e.message.contains("too many operations"),
        "{e}"
    );
    // the session survives
    assert_eq!(w.eval_line("1 + 1").unwrap().as_int().unwrap(), 2);
    let e = w.eval_line("let s = \"x\"; loop { s += s; }").unwrap_err();
    assert!(
        e.message.contains("too large") || e.message.contains("too many operations"),
        "{e}"
    );
}

#[test]
fn ctrl_c_interrupts_pure_computation_and_the_session_survives() {
    let (mut w, _) = wb("ctrlc");
    let flag = w.ctx.settings.abort.clone();
    let t = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(200));
        flag.store(true, Ordering::SeqCst);
    });
    let t0 = Instant::now();
    let e = w.eval_line("let i = 0; loop { i += 1; }").unwrap_err();
    t.join().unwrap();
    assert!(e.interrupted, "{e}");
    assert!(e.message.contains("interrupted (Ctrl-C)"), "{e}");
    assert!(t0.elapsed() < Duration::from_secs(5));
    assert!(
        !w.ctx.settings.abort.load(Ordering::SeqCst),
        "flag cleared after the interruption"
    );
    assert_eq!(w.eval_line("40 + 2").unwrap().as_int().unwrap(), 42);
}

#[test]
fn ctrl_c_is_not_swallowed_by_assert_err() {
    let (mut w, _) = wb("ctrlc-assert");
    let flag = w.ctx.settings.abort.clone();
    let t = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(150));
        flag.store(true, Ordering::SeqCst);
    });
    let e = w.eval_line("assert_err(|| { loop {} }); 1").unwrap_err();
    t.join().unwrap();
    assert!(e.interrupted, "{e}");
}

#[test]
fn values_print_readably() {
    let (mut w, buf) = wb("print");
    let _ = w.eval_line("connect(#{backend: \"mock\"})").unwrap();
    let _ = w.eval_line("let s = scan_xy(#{x: [-0.5, 0.5], y: [-0.2, 0.2], nx: 11, ny: 5}); print(s); print(s.sx); print(s.sx.row(2));").unwrap();
    let out = buf.lock().unwrap().clone();
    assert!(
        out.contains("Scan scan_xy 5×11 (y: -0.2 … 0.2 µm, x: -0.5 … 0.5 µm), status complete"),
        "{out}"
    );
    assert!(
        out.contains("Image 5×11 (rows × cols; y: -0.2 … 0.2 µm, x: -0.5 … 0.5 µm) min"),
        "{out}"
    );
    assert!(
        out.contains("Profile of 11 points (x: -0.5 … 0.5 µm)"),
        "{out}"
    );
    let v = w.eval_line("s.sx").unwrap();
    assert!(bfpscope::script::show(&v).starts_with("Image 5×11"));
    let v = w.eval_line("#{a: [1, 2.5], b: \"t\"}").unwrap();
    assert_eq!(bfpscope::script::show(&v), "#{a: [1, 2.5], b: \"t\"}");
    // a long result map (status()) on several lines, one key per line
    let v = w.eval_line("status()").unwrap();
    let st = bfpscope::script::show(&v);
    assert!(st.starts_with("#{\n  backend: \"mock\","), "{st}");
    assert!(st.lines().count() > 5, "{st}");
    // floats with sensible significant digits, integral floats keep their .0
    let v = w
        .eval_line("[0.1 + 0.2, 0.049999999999999996, 2.0, 1.0 / 3.0, 1e-9]")
        .unwrap();
    assert_eq!(
        bfpscope::script::show(&v),
        "[0.3, 0.05, 2.0, 0.333333, 1e-9]"
    );
}

#[test]
fn scans_record_the_script_path_and_hash() {
    let dir = std::env::temp_dir().join(format!("bfpscope-wb-{}-prov", std::process::id()));
    cleanup::at_exit(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let script = dir.join("prov.rhai");
    let text = "connect(#{backend: \"mock\"});\nlet s = scan_line(#{axis: \"x\", from: 0, to: 1, n: 4});\ns.meta\n";
    std::fs::write(&script, text).unwrap();
    let (s, _) = Settings::captured(dir.join("data"));
    let mut w = Workbench::new(s);
    let meta = w.run_file(&script).unwrap();
    let json = bfpscope::script::types::dynamic_to_json(&meta);
    assert_eq!(
        json["script"]["sha256"],
        bfpscope::script::ctx::sha256_hex(text.as_bytes())
    );
    assert!(json["script"]["path"]
        .as_str()
        .unwrap()
        .ends_with("prov.rhai"));
    assert_eq!(json["optics"]["wavelength_nm"], 1064.0);
    assert_eq!(json["plan"]["kind"], "scan_line");
    assert!(json["program"].as_str().unwrap().starts_with("bfpscope "));
    assert!(dir.join("data/scan_0001.npz").exists());
}

#[test]
fn scripted_test_runner_counts_passes_and_failures() {
    let dir = std::env::temp_dir().join(format!("bfpscope-wb-{}-runner", std::process::id()));
    cleanup::at_exit(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("a.rhai"), "fn test_ok() { assert(true, \"\") }\nfn test_bad() { assert_close(1.0, 1.5, 0.01) }\nfn helper() {}").unwrap();
    std::fs::write(
        dir.join("b.rhai"),
        "let x = 1;\nassert(x == 1, \"whole file\");",
    )
    .unwrap();
    std::fs::write(
        dir.join("c.rhai"),
        "print(\"shown on failure\");\nlet y = ;",
    )
    .unwrap();
    std::fs::write(dir.join("notes.txt"), "not a test").unwrap();
    let mut out = Vec::new();
    let r = bfpscope::script::testing::run_dir(&dir, &Settings::default(), &mut out).unwrap();
    let text = String::from_utf8(out).unwrap();
    assert_eq!(r.len(), 4, "{text}");
    assert_eq!(text.lines().last().unwrap(), "2 passed, 2 failed", "{text}");
    assert!(text.contains("ok    a.rhai::test_ok"), "{text}");
    assert!(text.contains("FAIL  a.rhai::test_bad: "), "{text}");
    assert!(
        text.contains("a.rhai:2:"),
        "position of the failure: {text}"
    );
    assert!(text.contains("differ by"), "{text}");
    assert!(text.contains("ok    b.rhai"), "{text}");
    assert!(text.contains("FAIL  c.rhai"), "{text}");
}

#[test]
fn variable_types_for_completion_use_the_script_names() {
    let (mut w, _) = wb("types");
    let _ = w
        .eval_line(
            "connect(#{backend: \"mock\"}); let sc = scan_line(#{axis: \"x\", from: -1.0, to: 1.0, n: 5, dwell: 0.001}); \
             let im = sc.sx; let r = #{angle_deg: 1.0, n: 3}; let a = [1, 2];",
        )
        .unwrap();
    let t = w.user_types();
    assert_eq!(t["sc"].0, "Scan");
    assert_eq!(t["im"].0, "Image");
    assert_eq!(t["r"].0, "map");
    let mut keys = t["r"].1.clone();
    keys.sort();
    assert_eq!(keys, ["angle_deg", "n"]);
    assert_eq!(t["a"].0, "array");
}

/// In a script, a complete scan whose autosave fails is an error (the run exits
/// non-zero), naming the failure and the session folder; it was a warning and `s.path` empty.
#[test]
fn a_failed_autosave_is_a_script_error() {
    let dir = std::env::temp_dir().join(format!("bfpscope-wb-{}-nosave", std::process::id()));
    cleanup::at_exit(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("a_file");
    std::fs::write(&file, "x").unwrap();
    let (s, _buf) = Settings::captured(&file);
    let mut w = Workbench::new(s);
    let _ = w
        .eval_source("setup", "connect(#{backend: \"mock\"})")
        .unwrap();
    let e = w
        .eval_source(
            "t",
            "let s = scan_line(#{axis: \"x\", from: 0.0, to: 1.0, n: 3, dwell: 0.001}); s.path",
        )
        .unwrap_err();
    assert!(
        e.message
            .contains("scan_line complete but NOT SAVED — AUTOSAVE FAILED"),
        "{e}"
    );
    assert!(
        e.message
            .contains(&format!("(session folder {})", file.display())),
        "{e}"
    );
}

/// `help("beads")` showed only the `FitResult.beads` property; a name that is both a
/// binding and a protocol module shows both.
#[test]
fn help_of_a_name_that_is_both_shows_both() {
    let (mut w, buf) = wb("help-both");
    let _ = w.eval_source("t", "help(\"beads\")").unwrap();
    let text = buf.lock().unwrap().clone();
    assert!(
        text.contains("names a binding and a stdlib protocol module"),
        "{text}"
    );
    assert!(text.contains("fitresult.beads"), "the property: {text}");
    assert!(
        text.contains("beads::multi") && text.contains("beads::sizes"),
        "the protocols: {text}"
    );
}
