//! The `bfpscope` binary: commands, exit codes, the scripted tests, the REPL through a pipe.

use crate::support::cleanup;
use crate::support::emulate::Emulator;

use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::support::fakebench;

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_bfpscope"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

fn tmp(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("bfpscope-cli-{}-{tag}", std::process::id()));
    cleanup::at_exit(&d);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn run(args: &[&str]) -> (i32, String, String) {
    let o = bin().args(args).stdin(Stdio::null()).output().unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into(),
        String::from_utf8_lossy(&o.stderr).into(),
    )
}

#[test]
fn scripted_tests_pass() {
    let data = tmp("scripted");
    let (code, out, err) = run(&["--data", data.to_str().unwrap(), "test", "tests/scripts"]);
    let last = out.lines().last().unwrap_or("");
    assert_eq!(code, 0, "stdout:\n{out}\nstderr:\n{err}");
    assert!(last.ends_with(" passed, 0 failed"), "{out}");
    let n: usize = last.split(' ').next().unwrap().parse().unwrap();
    assert!(n >= 17, "only {n} scripted tests ran:\n{out}");
}

#[test]
fn eval_prints_the_value() {
    let (code, out, _) = run(&["eval", "[1 + 2, 2.5 * 2.0, \"µm\"]"]);
    assert_eq!((code, out.trim()), (0, "[3, 5.0, \"µm\"]"));
    let (code, out, _) = run(&["eval", "()"]);
    assert_eq!((code, out.as_str()), (0, ""));
}

#[test]
fn script_error_exits_1_with_file_line_column() {
    let d = tmp("err");
    let f = d.join("bad.rhai");
    std::fs::write(&f, "let a = 1;\nlet b = linspace(0, 1, 0);\n").unwrap();
    let (code, _, err) = run(&["run", f.to_str().unwrap()]);
    assert_eq!(code, 1);
    assert!(
        err.contains("bad.rhai:2:9: linspace: n = 0 is out of range: 1 ≤ n ≤ 10000000"),
        "{err}"
    );
    assert_eq!(
        err.trim().lines().count(),
        1,
        "one line, no backtrace: {err}"
    );
    let (code, _, err) = run(&["eval", "1 +"]);
    assert_eq!(code, 1);
    assert!(err.contains("eval:1:"), "{err}");
}

#[test]
fn run_passes_set_values_as_variables() {
    let d = tmp("set");
    let f = d.join("vars.rhai");
    std::fs::write(&f, "print(`${n * 2} ${label} ${dwell + 0.5} ${flag}`);").unwrap();
    let (code, out, err) = run(&[
        "run",
        f.to_str().unwrap(),
        "--set",
        "n=21",
        "--set",
        "label=bead1",
        "--set",
        "dwell=0.25",
        "--set",
        "flag=true",
    ]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(out.trim(), "42 bead1 0.75 true");
}

#[test]
fn usage_errors_exit_2() {
    assert_eq!(run(&["frobnicate"]).0, 2);
    assert_eq!(run(&["run"]).0, 2);
    assert_eq!(run(&["run", "/no/such/file.rhai"]).0, 2);
    let d = tmp("usage");
    let f = d.join("ok.rhai");
    std::fs::write(&f, "1").unwrap();
    assert_eq!(run(&["run", f.to_str().unwrap(), "--set", "9x=1"]).0, 2);
    assert_eq!(run(&["--config", "/no/such/config.toml", "eval", "1"]).0, 2);
    let cfg = d.join("bad.toml");
    std::fs::write(&cfg, "[safety]\nsoft_limits = { x = [1, -1] }\n").unwrap();
    let (code, _, err) = run(&["--config", cfg.to_str().unwrap(), "eval", "1"]);
    assert_eq!(code, 2);
    assert!(err.contains("soft_limits"), "{err}");
    assert_eq!(run(&["--version"]).0, 0);
}

#[test]
fn config_limits_apply_to_scripts() {
    let d = tmp("config");
    let cfg = d.join("bfpscope.toml");
    std::fs::write(
        &cfg,
        "[safety]\nsoft_limits = { x = [-2.0, 2.0] }\n\n[sandbox]\nmax_operations = 100000\n",
    )
    .unwrap();
    let (code, _, err) = run(&[
        "--config",
        cfg.to_str().unwrap(),
        "--data",
        d.join("data").to_str().unwrap(),
        "eval",
        "connect(#{backend: \"mock\"}); mv(#{x: 3.0})",
    ]);
    assert_eq!(code, 1);
    assert!(
        err.contains("x = 3 µm is above the soft limit x ≤ 2 µm"),
        "{err}"
    );
    let (code, _, err) = run(&["--config", cfg.to_str().unwrap(), "eval", "loop {}"]);
    assert_eq!(code, 1);
    assert!(err.contains("too many operations"), "{err}");
}

#[test]
fn a_misspelled_table_is_refused_never_ignored() {
    // a typo in [safety] would drop the soft limits; a [stagee] or [Stage] naming a PI
    // controller would start the simulator in its place: both stop the start (exit 2), naming
    // the file, the table, its line and the nearest known name
    let d = tmp("config_typos");
    for (text, word, nearest, line) in [
        (
            "[saftey]\nsoft_limits = { x = [-2.0, 2.0] }\n",
            "saftey",
            "safety",
            1,
        ),
        (
            "# stage\n[stagee]\nbackend = \"gcs\"\nport = \"/dev/ttyUSB0\"\n",
            "stagee",
            "stage",
            2,
        ),
        (
            "[Stage]\nbackend = \"gcs\"\nport = \"/dev/ttyUSB0\"\n",
            "Stage",
            "stage",
            1,
        ),
        (
            "[optics]\nwavelenght_nm = 800\n",
            "optics.wavelenght_nm",
            "wavelength_nm",
            2,
        ),
    ] {
        let cfg = d.join("bfpscope.toml");
        std::fs::write(&cfg, text).unwrap();
        let (code, out, err) = run(&[
            "--config",
            cfg.to_str().unwrap(),
            "eval",
            "status().backend",
        ]);
        assert_eq!(code, 2, "{text}: {out}{err}");
        assert!(out.is_empty(), "nothing ran: {out}");
        let unknown = word.rsplit('.').next().unwrap();
        assert!(
            err.contains(&format!(
                "{}: {word}: unknown field `{unknown}`; did you mean `{nearest}`?",
                cfg.display()
            )) && err.contains(&format!("(line {line})")),
            "{text}: {err}"
        );
    }
}

#[test]
fn the_optics_table_sets_the_session_optics() {
    let d = tmp("config_optics");
    let cfg = d.join("bfpscope.toml");
    std::fs::write(&cfg, "[optics]\nwavelength_nm = 800\nbeam = \"paraxial\"\n").unwrap();
    let (code, out, err) = run(&[
        "--config",
        cfg.to_str().unwrap(),
        "eval",
        "let o = optics(); `${o.wavelength_nm} ${o.beam} ${o.na}`",
    ]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(out.trim(), "800.0 paraxial 1.2");
    // out of set_optics' range: refused at start-up with the key, the value and the range
    std::fs::write(&cfg, "[optics]\nwavelength_nm = 50\n").unwrap();
    let (code, _, err) = run(&["--config", cfg.to_str().unwrap(), "eval", "1"]);
    assert_eq!(code, 2);
    assert!(
        err.contains("optics.wavelength_nm: wavelength_nm = 50 is out of range: 100 ≤ wavelength_nm ≤ 20000 (line 2)"),
        "{err}"
    );
}

#[test]
fn docs_check_passes() {
    let (code, out, err) = run(&["docs", "--check"]);
    assert_eq!(code, 0, "{out}{err}");
}

#[test]
fn repl_through_a_pipe_survives_errors_and_keeps_definitions() {
    let data = tmp("repl");
    let mut child = bin()
        .args(["--data", data.to_str().unwrap(), "repl"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let session = "fn sq(x) {\n  x * x\n}\nqpd(0)\nprint(`sq = ${sq(7)}`);\nlet a = [1,\n 2];\na.len\nconnect(#{backend: \"mock\"});\nmv(#{x: 99.0})\npos().x\n";
    child
        .stdin
        .take()
        .unwrap()
        .write_all(session.as_bytes())
        .unwrap();
    let o = child.wait_with_output().unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{out}\n{err}");
    assert!(out.contains("sq = 49"), "{out}\n{err}");
    assert!(
        out.contains("\n2\n") || out.contains(" 2\n"),
        "multi-line array: {out}"
    );
    assert!(
        err.contains("error: repl:1:1: qpd: n = 0 is out of range"),
        "{err}"
    );
    assert!(err.contains("x = 99 µm is above the soft limit"), "{err}");
    assert!(out.contains("0.0"), "{out}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn repl_survives_ctrl_c_during_a_running_script() {
    let data = tmp("repl-ctrlc");
    let mut child = bin()
        .args(["--data", data.to_str().unwrap()])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdin = child.stdin.take().unwrap();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel::<String>();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            if tx.send(line.unwrap_or_default()).is_err() {
                break;
            }
        }
    });
    let wait_for = |what: &str| -> bool {
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(20) {
            if let Ok(l) = rx.recv_timeout(Duration::from_millis(100)) {
                if l.contains(what) {
                    return true;
                }
            }
        }
        false
    };
    writeln!(stdin, "print(\"ready\");").unwrap();
    stdin.flush().unwrap();
    assert!(wait_for("ready"), "the REPL did not start");
    writeln!(stdin, "let i = 0; loop {{ i += 1; }}").unwrap();
    stdin.flush().unwrap();
    std::thread::sleep(Duration::from_millis(400));
    let pid = child.id().to_string();
    let k = Command::new("kill").args(["-INT", &pid]).status().unwrap();
    assert!(k.success());
    writeln!(stdin, "print(`alive ${{40 + 2}}`);").unwrap();
    stdin.flush().unwrap();
    assert!(wait_for("alive 42"), "the REPL did not survive Ctrl-C");
    drop(stdin);
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{err}");
    assert!(err.contains("interrupted (Ctrl-C)"), "{err}");
}

#[test]
fn the_simulated_instrument_is_connected_by_default() {
    let data = tmp("default-sim");
    let (code, out, err) = run(&[
        "--data",
        data.to_str().unwrap(),
        "eval",
        "[status().instrument.backend, limits().x]",
    ]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(out.trim(), "[\"sim\", [-37.5, 37.5]]");
}

#[test]
fn demo_script_runs() {
    let data = tmp("demo");
    let (code, out, err) = run(&["--data", data.to_str().unwrap(), "run", "scripts/demo.rhai"]);
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(
        std::fs::read_dir(&data).unwrap().count() >= 1,
        "the demo saves a scan"
    );
    // The README's demo output was stale (A = 71.14 nm there, 79.64 printed). Every
    // line of the README's block after "It prints" is printed by the demo, as shown (the demo's
    // scene is seeded, so its numbers are the same on every run).
    let readme =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md")).unwrap();
    let at = readme
        .find("It prints")
        .expect("the README shows the demo's output");
    let block = readme[at..]
        .split("```text\n")
        .nth(1)
        .and_then(|b| b.split("```").next())
        .expect("a text block after \"It prints\"");
    let lines: Vec<&str> = block.lines().filter(|l| !l.trim().is_empty()).collect();
    assert!(lines.len() >= 3, "{block}");
    for l in &lines {
        assert!(
            out.lines().any(|o| o.trim_end() == l.trim_end()),
            "README demo line not printed by the demo: {l:?}\n--- demo output:\n{out}"
        );
    }
    // and every number in them agrees with the demo's scene (scripts/demo.rhai): the bead at
    // (−2.0, 0.5) µm, a 110 nm polystyrene bead (one reference bead), the fibril at 20°, 60 nm,
    // each within 3σ of its own stated uncertainty
    let nums = |l: &str| -> Vec<f64> {
        l.split(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-'))
            .filter_map(|w| w.trim_end_matches('.').parse::<f64>().ok())
            .collect()
    };
    let line = |prefix: &str| {
        lines
            .iter()
            .find(|l| l.starts_with(prefix))
            .unwrap_or_else(|| panic!("no README demo line starts with {prefix:?}"))
    };
    let within = |what: &str, v: f64, truth: f64, sigma: f64| {
        assert!(
            sigma > 0.0 && (v - truth).abs() < 3.0 * sigma,
            "README demo: {what} = {v} ± {sigma}, the scene's truth {truth}"
        );
    };
    // "bead: at (x, y) µm ± e nm; weight w ± we reference beads; …"
    let b = nums(line("bead: at"));
    within("bead x (µm)", b[0], -2.0, b[2] / 1000.0);
    within("bead y (µm)", b[1], 0.5, b[2] / 1000.0);
    within("bead weight", b[3], 1.0, b[4]);
    // "fibril: angle a° ± e° (truth 20°), n maxima (…)"
    let f = nums(line("fibril: angle"));
    within("fibril angle (°)", f[0], 20.0, f[1]);
    // "fibril: corrected sensitivity s ± e; A = a nm → d = d ± e nm (truth 60 nm); status"
    let d = nums(line("fibril: corrected"));
    within("fibril diameter (nm)", d[3], 60.0, d[4]);
}

/// Lines of a child's stdout, read on a thread (so waiting for one can time out).
fn line_reader(out: std::process::ChildStdout) -> std::sync::mpsc::Receiver<String> {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines() {
            let Ok(l) = line else { break };
            if tx.send(l).is_err() {
                break;
            }
        }
    });
    rx
}

#[test]
fn emulate_pair_serves_a_simulated_bead_through_the_drivers_until_ctrl_c() {
    use bfpscope::instrument::gcs::{GcsOptions, GcsStage};
    use bfpscope::instrument::scpi::{ScpiOptions, ScpiQpd};
    use bfpscope::instrument::sim::Renderer;
    use bfpscope::instrument::{Qpd, Stage};

    let emulator = Emulator::start(&["pair"]);
    let text = emulator.text.clone();
    assert!(
        text.starts_with("scene: 1 bead(s), 0 filament(s)"),
        "{text}"
    );
    let (sp, qp) = (emulator.path_of("stage:"), emulator.path_of("qpd:"));
    assert!(
        sp.starts_with("/dev/") && qp.starts_with("/dev/") && sp != qp,
        "{text}"
    );
    assert!(
        text.contains("travel -37.5–37.5 × -37.5–37.5 × -25–25 µm"),
        "{text}"
    );
    // the printed bfpscope.toml snippet points at the emulators
    let snippet = emulator.toml();
    let cfg = bfpscope::config::Config::from_toml_str(snippet, "snippet").unwrap();
    assert_eq!(cfg.qpd.port.as_deref(), Some(qp.as_str()));

    // the real drivers talk to them; the QPD images the reference bead at the stage position
    let mut stage = GcsStage::open(&sp, 115_200, GcsOptions::default()).unwrap();
    let mut qpd = ScpiQpd::open(&qp, 115_200, ScpiOptions::default()).unwrap();
    let renderer = Renderer::checked(
        &bfpscope::optics::Optics::default(),
        &bfpscope::script::motion::reference_bead_scene(),
        bfpscope::optics::template::TemplateSpec::default(),
    )
    .unwrap();
    let n = 1000;
    let sigma = 1e-4 / (n as f64).sqrt(); // emulator noise 1e-4 V per sample, 1 V per unit
    let mut seen = vec![];
    for x in [-0.2, 0.2] {
        stage.move_to([x, 0.0, 0.0]).unwrap();
        assert_eq!(stage.position().unwrap(), [x, 0.0, 0.0]);
        let r = qpd.read(n).unwrap();
        let want = renderer.render_grid_ideal(&[x], &[0.0], 0.0);
        for (got, want) in [(r.sx, want[0][0]), (r.sy, want[1][0]), (r.sz, want[2][0])] {
            assert!(
                (got - want).abs() < 5.0 * sigma,
                "at x = {x}: {got} vs the simulator's {want} (σ {sigma})"
            );
        }
        assert!(
            want[0][0].abs() > 50.0 * sigma,
            "bead signal {}",
            want[0][0]
        );
        seen.push(r.sx);
    }
    assert!(seen[0] * seen[1] < 0.0, "Sx is odd in x: {seen:?}");
    drop((stage, qpd));

    // Ctrl-C (SIGINT) stops it cleanly
    assert_eq!(emulator.interrupt(), Some(0));
}

#[test]
fn emulate_gcs_over_tcp_prints_its_address_and_serves_the_driver_until_ctrl_c() {
    // PI controllers speak GCS on TCP port 50000; the emulator serves the
    // same on a loopback port and prints where.
    use bfpscope::instrument::gcs::{GcsOptions, GcsStage};
    use bfpscope::instrument::{DeviceError, Stage};

    let emulator = Emulator::start(&["gcs", "--tcp", "127.0.0.1:0", "--one-axis-per-query"]);
    let text = emulator.text.clone();
    let line = emulator.line("stage:");
    assert!(
        line.starts_with("stage: PI GCS 2.0 stage (axes 1 2 3, travel -37.5–37.5 × -37.5–37.5 × -25–25 µm, servo off, one axis per query, no baud limit, 1 ms latency) on tcp://127.0.0.1:"),
        "{text}"
    );
    let url = line.rsplit(" on ").next().unwrap().to_string();
    // the printed snippet names the TCP port
    let snippet = emulator.toml();
    assert!(
        snippet.contains(&format!(
            "[stage]\nbackend = \"gcs\"\nport = \"{url}\"\naxes = {{ x = \"1\", y = \"2\", z = \"3\" }}\n"
        )),
        "{snippet}"
    );

    // connect (one axis per query detected), move, fault, stop
    let mut s = GcsStage::open(&url, 115_200, GcsOptions::default()).unwrap();
    assert_eq!(s.name(), format!("PI E-727 on {url}"));
    assert!(s.one_axis_per_query());
    s.move_to([1.5, -2.0, 0.5]).unwrap();
    assert_eq!(s.position().unwrap(), [1.5, -2.0, 0.5]);
    match s.move_to([100.0, -2.0, 0.5]) {
        Err(DeviceError::Controller {
            command, code: 7, ..
        }) => assert_eq!(command, "MOV 1 100.000000"),
        other => panic!("{other:?}"),
    }
    s.stop().unwrap();
    assert_eq!(s.position().unwrap(), [1.5, -2.0, 0.5]);
    drop(s);

    assert_eq!(emulator.interrupt(), Some(0));
    // the port is closed
    let e = GcsStage::open(&url, 115_200, GcsOptions::default())
        .err()
        .expect("closed");
    assert!(e.to_string().contains("cannot connect to"), "{e}");
}

#[test]
fn emulate_redpitaya_serves_the_board_on_a_loopback_port_until_ctrl_c() {
    // `bfpscope emulate redpitaya --inputs 4` serves a GCS stage and a Red Pitaya
    // SCPI server sharing the stage position, and prints a config for both.
    use bfpscope::instrument::redpitaya::{ChannelMap, RedPitaya, RedPitayaOptions};
    use bfpscope::instrument::Qpd;

    let emulator = Emulator::start(&["redpitaya", "--inputs", "4"]);
    let text = emulator.text.clone();
    let line = emulator.line("redpitaya:");
    assert!(line.contains("STEMlab 125-14 4-input"), "{text}");
    // the stage's OUT1 drives the board's external trigger, and the config says so
    assert!(line.contains("DIO0_P wired to the stage's OUT1"), "{text}");
    assert!(text.contains("}\ntrigger_line = 1\n"), "{text}");
    let url = line.rsplit(" on ").next().unwrap();
    let (host, port) = url.trim_start_matches("tcp://").rsplit_once(':').unwrap();
    assert_eq!(host, "127.0.0.1");
    assert!(
        text.contains(&format!(
            "[qpd]\nbackend = \"redpitaya\"\nhost = \"127.0.0.1\"\nport = {port}\nchannels = {{ sx = 1, sy = 2, sz = 3 }}\n"
        )),
        "{text}"
    );
    let opts = RedPitayaOptions {
        channels: ChannelMap {
            sx: 1,
            sy: 2,
            sz: Some(3),
        },
        ..RedPitayaOptions::default()
    };
    let mut rp = RedPitaya::open(host, port.parse().unwrap(), opts).unwrap();
    assert!(rp.idn().starts_with("REDPITAYA,"));
    // the stage is parked away from the bead: Sz of the scene is finite, the read succeeds
    let r = rp.read(100).unwrap();
    assert_eq!(r.n, 15625);
    assert!(r.sz.is_finite() && r.sx_std > 0.0, "{r}");
    drop(rp);
    assert_eq!(emulator.interrupt(), Some(0));
}

#[test]
fn emulate_rejects_an_unknown_device_and_a_bad_scene_file() {
    let (code, _, err) = run(&["emulate", "laser"]);
    assert_eq!(code, 2);
    assert!(
        err.contains(
            "emulate: unknown device `laser` (expected `stage` (alias `gcs`), `qpd`, `pair`, `kpa101`, \
             `kpz101`, `thorlabs`, `redpitaya` or `nidaq`)"
        ),
        "{err}"
    );
    let d = tmp("emulate-scene");
    let f = d.join("scene.json");
    std::fs::write(&f, "{\"beads\": 3}").unwrap();
    let (code, _, err) = run(&["emulate", "pair", "--scene", f.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(
        err.contains("emulate: --scene") && err.contains("scene.json"),
        "{err}"
    );
}

#[test]
fn config_speed_limit_and_legacy_limits_table() {
    let d = tmp("speed");
    let cfg = d.join("bfpscope.toml");
    std::fs::write(&cfg, "[safety]\nmax_speed_um_s = 10.0\n").unwrap();
    // mock: settle 1 ms, dwell 1 ms (explicit: the default is 10 ms); 0.1 µm steps → 50 µm/s
    let (code, _, err) = run(&[
        "--config",
        cfg.to_str().unwrap(),
        "--data",
        d.join("data").to_str().unwrap(),
        "eval",
        "connect(#{backend: \"mock\"}); [limits().max_speed_um_s, scan_line(#{axis: \"x\", from: 0.0, to: 1.0, n: 11, dwell: 0.001})]",
    ]);
    assert_eq!(code, 1);
    assert!(
        err.contains("50 µm/s exceeds max_speed_um_s = 10 µm/s"),
        "{err}"
    );
    let (code, out, err) = run(&["--config", cfg.to_str().unwrap(), "eval", "status().limits"]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("max speed 10 µm/s"), "{out}");
    // the old [limits] table: a usage error that gives the [safety] equivalent
    std::fs::write(&cfg, "[limits]\nx = [-5.0, 5.0]\n").unwrap();
    let (code, _, err) = run(&["--config", cfg.to_str().unwrap(), "eval", "1"]);
    assert_eq!(code, 2);
    assert!(
        err.contains("limits: the [limits] table is now [safety]")
            && err.contains("write [safety] soft_limits = { x = [-5.0, 5.0] }")
            && err.contains("(line 1)"),
        "{err}"
    );
}

#[test]
fn repl_console_words_last_result_notes_session_log_and_quit() {
    let data = tmp("console");
    let mut child = bin()
        .args(["--data", data.to_str().unwrap(), "repl"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let session = "6 * 7\n_ + 1\nconnect(#{backend: \"mock\"});\nnote(\"sample 3\");\nlet s = lup(\"x\", -0.5, 0.5, 10, 0.001);\nscans(#{note: \"sample\"}).len()\nscans()[0].kind\numvr(#{x: 0.25})\nscna_xy(#{})\ns.sxx\nquit\nprint(\"after quit\");\n";
    child
        .stdin
        .take()
        .unwrap()
        .write_all(session.as_bytes())
        .unwrap();
    let o = child.wait_with_output().unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{out}\n{err}");
    assert!(out.contains("42\n43\n"), "{out}");
    assert!(
        out.contains("\n1\n\"line\"\n") || out.contains("\n1\nline\n"),
        "{out}"
    );
    assert!(out.contains("x = 0.2500 µm"), "umvr shows where: {out}");
    assert!(err.contains("did you mean `scan_xy`?"), "{err}");
    assert!(!err.contains("bfpscope::"), "Rust type path in {err}");
    assert!(
        err.contains("Scan has no property `sxx`; did you mean `sx`?"),
        "{err}"
    );
    assert!(!out.contains("after quit"), "{out}");
    // the session log holds the entries and what they gave
    let log = std::fs::read_to_string(data.join("session.log")).unwrap();
    assert!(log.contains("bfp> 6 * 7\n42\n"), "{log}");
    assert!(log.contains("did you mean `scan_xy`?"), "{log}");
    // the note is in the scan's metadata
    let sc = bfpscope::data::npz::load_scan(data.join("scan_0001.npz")).unwrap();
    assert_eq!(sc.meta["notes"], serde_json::json!(["sample 3"]));
    // where docs/files.md says the metadata sits in the file: under user_meta
    let stored = bfpscope::data::npz::file_meta(&sc);
    assert_eq!(
        stored["user_meta"]["notes"],
        serde_json::json!(["sample 3"])
    );
    assert!(stored["user_meta"]["plan"].is_object(), "{stored}");
}

#[test]
fn bfpscope_config_variable_is_honoured_with_its_safety_table() {
    // bfpscope.example.toml says "point $BFPSCOPE_CONFIG at it"; a config loaded that
    // way must bring its [safety] table, and a bad one must stop the start, not be dropped.
    let dir = tmp("envcfg");
    // `limits().x` with $BFPSCOPE_CONFIG naming a file holding `safety`
    let limits_x_with = |name: &str, safety: &str| {
        let file = dir.join(name);
        std::fs::write(&file, format!("[safety]\n{safety}\n")).unwrap();
        bin()
            .env("BFPSCOPE_CONFIG", &file)
            .args([
                "--data",
                dir.join("d").to_str().unwrap(),
                "eval",
                "limits().x",
            ])
            .output()
            .unwrap()
    };
    let out = limits_x_with("lab.toml", "soft_limits = { x = [-3.0, 4.0] }");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout} {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(stdout.trim(), "[-3.0, 4.0]");
    let out = limits_x_with("bad.toml", "soft_limits = { x = [4.0, -3.0] }");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(stderr.contains("safety.soft_limits.x"), "{stderr}");
}

#[test]
fn repl_binds_a_partial_scan_to_the_variable_being_assigned() {
    let data = tmp("partial");
    let mut child = bin()
        .args(["--data", data.to_str().unwrap(), "repl"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // the mock raises the Ctrl-C flag after 7 reads, as the key would
    let session = "connect(#{backend: \"mock\", abort_after_reads: 7});\n\
                   let s = scan_line(#{axis: \"x\", from: -1.0, to: 1.0, n: 21, dwell: 0.001});\n\
                   print(`${s.status} ${s.meta.points_measured} ${s.cols}`);\n\
                   _.status\n";
    child
        .stdin
        .take()
        .unwrap()
        .write_all(session.as_bytes())
        .unwrap();
    let o = child.wait_with_output().unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("the partial scan (aborted, 7 of 21 points) is in `s` and _"),
        "{err}"
    );
    assert!(out.contains("aborted 7 21\naborted\n"), "{out}\n{err}");
}

/// A session folder scans cannot be saved in is refused at start-up, before any
/// motion; a scan whose autosave fails in a script makes the run fail (non-zero exit).
#[test]
fn a_session_folder_that_cannot_hold_scans_is_refused_at_start_up() {
    let d = tmp("nodata");
    let file = d.join("not_a_folder");
    std::fs::write(&file, "x").unwrap();
    let script = d.join("scan.rhai");
    std::fs::write(
        &script,
        "let s = scan_line(#{axis: \"x\", from: 0.0, to: 1.0, n: 3, dwell: 0.001}); print(`path ${s.path}`);",
    )
    .unwrap();
    let (code, out, err) = run(&[
        "--data",
        file.to_str().unwrap(),
        "run",
        script.to_str().unwrap(),
    ]);
    assert_eq!(code, 2, "{out}\n{err}");
    assert!(
        err.contains(&format!(
            "the session folder {} exists and is not a folder: scans could not be saved (give another with --data DIR)",
            file.display()
        )),
        "{err}"
    );
    assert!(!out.contains("path"), "the script ran: {out}");
    // a folder below a regular file cannot be created
    let below = file.join("sub");
    let (code, _, err) = run(&["--data", below.to_str().unwrap(), "repl"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains(&format!(
            "cannot be created: {} is not a folder",
            file.display()
        )),
        "{err}"
    );
}

/// At the prompt, a scan whose autosave fails (the session folder replaced by a file
/// after start-up) is an error that keeps the scan in memory, in the entry's variable, with a
/// one-line way to save it elsewhere; saving it there works.
#[test]
fn a_scan_that_cannot_be_saved_at_the_prompt_stays_in_memory_with_a_way_out() {
    let d = tmp("unsaved");
    let sess = d.join("session");
    let mut child = bin()
        .args(["--data", sess.to_str().unwrap(), "repl"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdin = child.stdin.take().unwrap();
    let rx = line_reader(child.stdout.take().unwrap());
    stdin.write_all(b"print(\"ready\");\n").unwrap();
    let t0 = Instant::now();
    loop {
        let l = rx
            .recv_timeout(Duration::from_secs(60))
            .expect("the prompt answers");
        if l.contains("ready") {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(60));
    }
    // the folder becomes a regular file: the autosave must fail. The session log of the entry
    // just answered may (re)create the folder between our remove and write: retry until the
    // file stands (after that the log cannot create it again).
    let mut tries = 0;
    loop {
        if sess.is_dir() {
            let _ = std::fs::remove_dir_all(&sess);
        }
        match std::fs::write(&sess, "x") {
            Ok(()) => break,
            Err(e) => {
                tries += 1;
                assert!(
                    tries < 200,
                    "cannot replace the session folder by a file: {e}"
                );
                std::thread::sleep(Duration::from_millis(10));
            }
        }
    }
    let elsewhere = d.join("rescued.npz");
    let session = format!(
        "connect(#{{backend: \"mock\"}});\n\
         let s = scan_line(#{{axis: \"x\", from: 0.0, to: 1.0, n: 5, dwell: 0.001}});\n\
         print(`kept ${{s.status}} ${{s.cols}}`);\n\
         s.save(\"{}\");\n\
         print(`reloaded ${{load_scan(\"{}\").cols}}`);\n",
        elsewhere.display(),
        elsewhere.display()
    );
    stdin.write_all(session.as_bytes()).unwrap();
    drop(stdin);
    let mut out = String::new();
    while let Ok(l) = rx.recv_timeout(Duration::from_secs(60)) {
        out.push_str(&l);
        out.push('\n');
    }
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("scan_line complete but NOT SAVED — AUTOSAVE FAILED"),
        "{err}"
    );
    assert!(
        err.contains("the scan is in `s` and _, NOT on disk; save it elsewhere: s.save(\"/a/writable/folder/scan.npz\")"),
        "{err}"
    );
    assert!(out.contains("kept complete 5\n"), "{out}\n{err}");
    assert!(out.contains("reloaded 5\n"), "{out}\n{err}");
}

/// `bfpscope test` on a folder without any test printed "0 passed, 0 failed" and
/// exited 0; it is an error, as a missing folder is.
#[test]
fn test_on_a_folder_without_tests_is_an_error() {
    let d = tmp("notests");
    std::fs::write(d.join("readme.txt"), "no tests here").unwrap();
    let (code, out, err) = run(&["test", d.to_str().unwrap()]);
    assert_eq!(code, 2, "{out}\n{err}");
    assert!(
        err.contains(&format!(
            "test: {}: no test in the folder (no *.rhai file)",
            d.display()
        )),
        "{err}"
    );
    assert!(!out.contains("0 passed"), "{out}");
}

/// session.log lacked the "saved to …npz" lines, the positions `wa()`/`umv()` print and
/// the "saved" lines of figures: everything printed is logged with its entry.
#[test]
fn the_session_log_holds_everything_printed() {
    let data = tmp("sessionlog");
    let mut child = bin()
        .args(["--data", data.to_str().unwrap(), "repl"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let session = "connect(#{backend: \"mock\"});\n\
                   let s = scan_xy(#{x: [0.0, 0.2], y: [0.0, 0.2], nx: 3, ny: 3, dwell: 0.001});\n\
                   umv(#{x: 0.25})\n\
                   wa()\n\
                   plot(s, \"fig.png\");\n\
                   print(\"hello log\");\n";
    child
        .stdin
        .take()
        .unwrap()
        .write_all(session.as_bytes())
        .unwrap();
    let o = child.wait_with_output().unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{out}\n{err}");
    let log = std::fs::read_to_string(data.join("session.log")).unwrap();
    let scan = data.join("scan_0001.npz");
    // the autosave line follows the entry that made the scan
    let i = log.find("bfp> let s = scan_xy").expect("the scan entry");
    let j = log[i..]
        .find(&format!("saved to {}", scan.display()))
        .map(|j| i + j)
        .unwrap_or_else(|| panic!("no saved-to line after the scan entry:\n{log}"));
    assert!(
        !log[i..j].contains("bfp> umv"),
        "the saved line belongs to the scan:\n{log}"
    );
    assert!(log.contains("x = 0.2500 µm"), "umv's position:\n{log}");
    let wa = log.find("bfp> wa()").expect("the wa entry");
    assert!(log[wa..].contains("µm"), "wa's positions:\n{log}");
    assert!(
        log.contains(&format!("saved {}", data.join("fig.png").display())),
        "the figure's saved line:\n{log}"
    );
    assert!(
        log.contains("bfp> print(\"hello log\");\nhello log\n"),
        "{log}"
    );
}

/// At the prompt, `connect(#{backend: "madlib"})` takes the paper's bench (a Nano-Drive through
/// Madlib, an NI board through NI-DAQmx) with the rest of its settings from the config, also
/// after another backend; a library that is not where the config says is named with the places
/// searched; without a config naming the board, the missing key is named.
#[test]
fn connect_madlib_at_the_prompt_takes_the_bench_or_says_what_is_missing() {
    let lib = fakebench::library();
    let d = tmp("madlib");
    let cfg = d.join("bench.toml");
    std::fs::write(&cfg, bfpscope::config::bench::fake_bench_config(&lib)).unwrap();
    let eval = |config: Option<&std::path::Path>, script: &str| {
        let mut c = bin();
        if let Some(p) = config {
            c.args(["--config", p.to_str().unwrap()]);
        }
        let o = c
            .args(["--data", d.to_str().unwrap(), "eval", script])
            .env_remove("BFPSCOPE_CONFIG")
            .env_remove("BFPSCOPE_MADLIB")
            .env_remove("BFPSCOPE_NIDAQMX")
            .current_dir(&d)
            .stdin(Stdio::null())
            .output()
            .unwrap();
        (
            o.status.code(),
            String::from_utf8_lossy(&o.stdout).to_string(),
            String::from_utf8_lossy(&o.stderr).to_string(),
        )
    };
    let (code, out, err) = eval(
        Some(&cfg),
        r#"connect(#{backend: "sim"}); print(status().instrument.stage); connect(#{backend: "madlib"}); let s = status().instrument; print(`stage ${s.stage.name}`); print(`qpd ${s.qpd.name} ${s.qpd.product_type}`)"#,
    );
    assert_eq!(code, Some(0), "{out}\n{err}");
    assert!(
        out.contains("stage Mad City Labs Nano-Drive #2847"),
        "{out}\n{err}"
    );
    assert!(
        out.contains("qpd NI PCI-6120 Dev1 PCI-6120"),
        "{out}\n{err}"
    );
    // the library is not where the config says: which, where, how
    let moved = d.join("moved.toml");
    let text = bfpscope::config::bench::fake_bench_config(&lib);
    let nowhere = d.join("nowhere/libmadlib.so");
    let text = text.replacen(
        &format!("library = \"{}\"", lib.display()),
        &format!("library = \"{}\"", nowhere.display()),
        1,
    );
    std::fs::write(&moved, text).unwrap();
    let (code, out, err) = eval(Some(&moved), r#"connect(#{backend: "madlib"})"#);
    assert_ne!(code, Some(0), "{out}");
    assert!(
        err.contains("Madlib library not loaded") && err.contains("nowhere/libmadlib.so"),
        "{err}"
    );
    assert!(err.contains("stage.library"), "{err}");
    // no config: the board's name is the first thing missing
    let (code, _, err) = eval(None, r#"connect(#{backend: "madlib"})"#);
    assert_ne!(code, Some(0));
    assert!(
        err.contains("qpd.device: required when backend = \"nidaqmx\""),
        "{err}"
    );
}

/// From the prompt, the paper's bench as `bfpscope emulate nidaq` configures it: a raster of the
/// fake's 110 nm bead streamed on the NI board's clock, and the bead fitted where the fake puts
/// it (the stage at the middle of its range, 37.5 µm).
#[test]
fn a_raster_on_the_emulated_nidaq_bench_from_the_prompt_finds_the_bead() {
    let lib = fakebench::library();
    let d = tmp("nidaqraster");
    let cfg = d.join("bench.toml");
    std::fs::write(&cfg, bfpscope::config::bench::fake_bench_config(&lib)).unwrap();
    let script = r#"umv(#{x: 37.5, y: 37.5, z: 25.0});
let s = scan_xy(#{x: [37.0, 38.0], y: [37.0, 38.0], nx: 21, ny: 21, dwell: 0.0001, mode: "raster"});
let f = fit_beads(s, template_model(#{h_um: 0.02}), #{n_beads: 1});
let b = f.beads[0];
print(`raster ${s.meta.status} ${s.meta.raster.path} ${s.meta.instrument.stage.backend}`);
print(`bead ${(b.x - 37.5) * 1000.0} ${(b.y - 37.5) * 1000.0} ${b.weight}`);"#;
    let o = bin()
        .args([
            "--config",
            cfg.to_str().unwrap(),
            "--data",
            d.to_str().unwrap(),
            "eval",
            script,
        ])
        .env_remove("BFPSCOPE_CONFIG")
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let (out, err) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert_eq!(o.status.code(), Some(0), "{out}\n{err}");
    assert!(
        out.contains("raster complete frame stream madlib"),
        "{out}\n{err}"
    );
    let l = out
        .lines()
        .find(|l| l.starts_with("bead "))
        .expect("bead line");
    let v: Vec<f64> = l[5..].split(' ').map(|x| x.parse().unwrap()).collect();
    // the fake's bead at the stage's 37.5 µm; the template from the same optics: within 5 nm,
    // weight 1 within 3 %
    assert!(v[0].abs() < 5.0 && v[1].abs() < 5.0, "{l}");
    assert!((v[2] - 1.0).abs() < 0.03, "{l}");
}

/// A KPZ101 whose strain gauge is not zeroed: the connect at the start of `eval` and of `run`
/// says so on stderr (the cube and the remedy) and writes it to the session log; the value
/// or the script's output is unchanged on stdout.
#[test]
fn a_kpz101_gauge_not_zeroed_is_said_by_eval_and_run() {
    use bfpscope::instrument::emulator::{
        shared_position, standin_bead, start_kpa101_emulator, start_kpz101_emulator,
        KpaEmulatorConfig, KpzEmulatorConfig,
    };
    for (k, cmd) in ["eval", "run"].iter().enumerate() {
        // a fresh set of cubes per process (a pseudo-terminal serves one connection)
        let pos = shared_position([10.0, 10.0, 10.0]);
        let cubes: Vec<_> = (0..3)
            .map(|axis| {
                start_kpz101_emulator(
                    KpzEmulatorConfig {
                        serial: 29_000_001 + axis as u32,
                        axis,
                        travel_um: 20.0,
                        gauge_offset_um: 0.5,
                        ..KpzEmulatorConfig::default()
                    },
                    pos.clone(),
                )
                .unwrap()
            })
            .collect();
        let kpa =
            start_kpa101_emulator(KpaEmulatorConfig::default(), pos.clone(), |p: [f64; 3]| {
                standin_bead([p[0] - 10.0, p[1] - 10.0, p[2] - 10.0])
            })
            .unwrap();
        let d = tmp(&format!("kpz-gauge-{k}"));
        let cfg = d.join("bfpscope.toml");
        std::fs::write(
            &cfg,
            format!(
                "[stage]\nbackend = \"kpz101\"\nports = {{ x = \"{}\", y = \"{}\", z = \"{}\" }}\ntimeout_ms = 300\n\
                 settle_s = 0.0\n\n[qpd]\nbackend = \"kpa101\"\nport = \"{}\"\ntimeout_ms = 300\n\n[safety]\nmax_step_um = 2.0\n",
                cubes[0].path(),
                cubes[1].path(),
                cubes[2].path(),
                kpa.path()
            ),
        )
        .unwrap();
        let data = d.join("data");
        let script = d.join("where.rhai");
        std::fs::write(&script, "print(`x = ${pos().x}`);\n").unwrap();
        let (cfg_s, data_s) = (cfg.to_str().unwrap(), data.to_str().unwrap());
        let (code, out, err) = if *cmd == "eval" {
            run(&["--config", cfg_s, "--data", data_s, "eval", "pos().x"])
        } else {
            run(&[
                "--config",
                cfg_s,
                "--data",
                data_s,
                "run",
                script.to_str().unwrap(),
            ])
        };
        assert_eq!(code, 0, "{cmd}: {out}\n{err}");
        let warning = err
            .lines()
            .find(|l| l.starts_with("WARNING: connect: "))
            .unwrap_or_else(|| panic!("{cmd}: no connect warning on stderr: {err}"));
        assert!(
            warning.contains("Thorlabs KPZ101")
                && warning.contains("the strain gauge of x, y, z is not zeroed")
                && warning.contains("zero_gauge()"),
            "{cmd}: {warning}"
        );
        assert!(!out.contains("WARNING"), "{cmd}: stdout {out}");
        // the session log keeps it
        let logs: Vec<String> = walk_files(&data)
            .into_iter()
            .filter(|p| p.file_name().is_some_and(|n| n == "session.log"))
            .map(|p| std::fs::read_to_string(p).unwrap())
            .collect();
        assert!(
            logs.iter().any(|l| l.contains(warning)),
            "{cmd}: session logs {logs:?}"
        );
    }
}

/// Every file under `dir`.
fn walk_files(dir: &std::path::Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                out.extend(walk_files(&p));
            } else {
                out.push(p);
            }
        }
    }
    out
}

/// The answers of a sweep dump: (value, σ, scene) per line.
fn dump_lines(path: &std::path::Path) -> Vec<(f64, Option<f64>, serde_json::Value)> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            (
                v["value"].as_f64().unwrap(),
                v["sigma"].as_f64(),
                v["scene"].clone(),
            )
        })
        .collect()
}

#[test]
fn a_sweep_prints_its_tallies_as_json_and_replays_a_dumped_scene_to_the_same_answer() {
    let d = tmp("sweep");
    let dump = d.join("dump.jsonl");
    let o = bin()
        // the microtubule family's scenes take minutes in a debug build: `--family` leaves it out
        .args([
            "sweep",
            "--n",
            "3",
            "--seed",
            "7",
            "--json",
            "--family",
            "beads,fibril,focus",
        ])
        .env("BFPSCOPE_SWEEP_DUMP", &dump)
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    let j: serde_json::Value = serde_json::from_str(&out).expect("one JSON object");
    for k in ["fit_beads.x", "measure_filament.diameter"] {
        let t = &j[k];
        let cases = t["cases"].as_u64().unwrap_or_else(|| panic!("{k}: {t}"));
        let in_domain = t["in_domain"].as_u64().unwrap();
        let flagged = t["flagged"].as_f64().unwrap();
        // every case is either inside the domain or flagged/refused
        assert!(
            (in_domain as f64 + flagged * cases as f64 - cases as f64).abs() < 1e-9,
            "{k}: {t}"
        );
        assert!(t["unflagged_outliers"].is_u64(), "{k}: {t}");
    }
    // the first dumped answer, replayed from its scene alone, is the same answer
    let lines = dump_lines(&dump);
    let (value, sigma, scene) = lines
        .first()
        .expect("an in-domain answer in 3 + 3 scenes")
        .clone();
    let dump2 = d.join("replay.jsonl");
    let o = bin()
        .args(["sweep", "--replay", &scene.to_string()])
        .env("BFPSCOPE_SWEEP_DUMP", &dump2)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let again = dump_lines(&dump2);
    assert_eq!(again.first().map(|a| (a.0, a.1)), Some((value, sigma)));
    // without --json, redirected: progress as lines on stderr (the bar needs a terminal), and
    // the slowest scene with the command that replays it, whose JSON is a bead scene
    let (code, out, err) = run(&["sweep", "--n", "2", "--seed", "7", "--family", "beads"]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("sweep: 2 of 2 scenes"), "{err}");
    let replay = out
        .lines()
        .find_map(|l| l.trim().strip_prefix("(bfpscope sweep --replay '"))
        .and_then(|l| l.strip_suffix("')"))
        .unwrap_or_else(|| panic!("no replay command: {out}"));
    let scene: serde_json::Value = serde_json::from_str(replay).expect("the scene's JSON");
    assert_eq!(scene["family"], "beads", "{scene}");
    // a scene that is not one is refused in words
    let (code, _, err) = run(&["sweep", "--replay", "{\"family\": \"stars\"}"]);
    assert_eq!(code, 2);
    assert!(err.contains("not a sweep scene"), "{err}");
}

/// A disk that refuses the autosave's bytes (a file size limit, as a full disk does: the
/// writes fail with EFBIG where a full disk gives ENOSPC) ends the scan with the autosave's
/// failure in words, naming the file and the system's reason, and nothing else on stderr: the
/// zip writer's own "ZipWriter drop failed: Io(…)" (printed raw from its `Drop` when the archive
/// could not be finished) was printed before it.
#[test]
fn a_refused_autosave_is_said_in_words_and_nothing_raw() {
    let d = tmp("refused-autosave");
    let script =
        "let s = scene(); s.add_bead(#{x: 0.0, y: 0.0, d_nm: 110.0, n: 1.572}); simulate(s); \
                  scan_xy(#{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 64, ny: 64, dwell: 0.001}).status";
    let o = Command::new("sh")
        .arg("-c")
        // the signal a write beyond the limit raises is ignored (across exec), so the write fails
        .arg("trap '' XFSZ; ulimit -f 16; exec \"$0\" eval \"$1\"")
        .arg(env!("CARGO_BIN_EXE_bfpscope"))
        .arg(script)
        .current_dir(&d)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("AUTOSAVE FAILED"), "{err}");
    assert!(err.contains("File too large (os error 27)"), "{err}");
    assert!(!err.contains("ZipWriter"), "{err}");
    assert!(!err.contains("Io("), "{err}");
}

/// A key read from a map that does not have it is an error naming the map, the key, the
/// closest key and all its keys (it returned () and the script went on with nothing).
#[test]
fn a_misspelt_map_key_says_which_keys_the_map_has() {
    let (code, _, err) = run(&[
        "eval",
        "let m = #{a: 1, dwell: 2}; let s = #{meta: m}; s.meta.dwel",
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains(
            "eval:1:55: `s.meta` has no key `dwel`; did you mean `dwell`? Its keys: a, dwell"
        ),
        "{err}"
    );
}
