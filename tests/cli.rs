//! The `bfpscope` binary: commands, exit codes, the scripted tests, the REPL through a pipe.

use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_bfpscope"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

fn tmp(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("bfpscope-cli-{}-{tag}", std::process::id()));
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
}
