//! The prompt as an instrument console, driven through a pseudo-terminal as a person types:
//! Ctrl-C during a scan pauses it and asks; the answer resumes or aborts.

#[path = "support/pty.rs"]
mod pty;

use pty::Prompt;
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

fn dir(tag: &str) -> std::path::PathBuf {
    std::env::temp_dir().join(format!("bfpscope-console-{}-{tag}", std::process::id()))
}

/// A paced simulator (real-instrument speed) and a relative 10 × 10 scan at 10 ms dwell that
/// takes about 1.7 s; Ctrl-C once it runs.
fn start_and_interrupt(tag: &str) -> Prompt {
    let mut p = Prompt::start(&dir(tag), &[]);
    p.enter(
        "connect(#{backend: \"sim\", pace: 1.0}); mv(#{x: 1.0, y: 2.0})",
        T,
    );
    let from = p.out.len();
    p.type_line(
        "let s = scan_xy(#{x: [-0.5, 0.5], y: [-0.5, 0.5], nx: 10, ny: 10, dwell: 0.01, rel: true})",
    );
    p.wait_for_from(from, "ETA", T);
    std::thread::sleep(Duration::from_millis(500));
    p.send(b"\x03");
    p.wait_for_from(from, "paused> ", T);
    p
}

#[test]
fn ctrl_c_pauses_a_scan_and_enter_resumes_it() {
    let mut p = start_and_interrupt("resume");
    let from = p.out.len();
    p.wait_for_from(0, "scan_xy paused after ", T);
    assert!(
        p.out.contains("the stage waits at x = ") && p.out.contains("Enter or r: resume"),
        "{}",
        p.out
    );
    p.type_line("");
    p.wait_for_from(from, "bfp> ", T);
    let said = p.out[from..].to_string();
    assert!(said.contains("scan_xy: resumed at point "), "{said}");
    assert!(said.contains("scan_xy: complete in"), "{said}");
    let o = p.enter("[s.status, s.meta.pauses.len(), s.meta.points_measured]", T);
    assert!(o.contains("[\"complete\", 1, 100]"), "{o}");
    // paused after k points: k measured before, 100 − k after, each pixel once
    let o = p.enter(
        "let k = s.meta.pauses[0].after_points; [k > 0, k < 100, s.sx.min() == s.sx.min()]",
        T,
    );
    assert!(o.contains("[true, true, true]"), "{o}");
    let o = p.enter("wm()", T);
    assert!(o.contains("x = 1") && o.contains("y = 2"), "{o}");
    let out = p.quit();
    if std::env::var_os("BFPSCOPE_SHOW").is_some() {
        eprintln!("{out}");
    }
}

#[test]
fn ctrl_c_then_a_aborts_keeps_the_partial_scan_and_returns() {
    let mut p = start_and_interrupt("abort");
    let from = p.out.len();
    p.type_line("a");
    p.wait_for_from(from, "bfp> ", T);
    let said = p.out[from..].to_string();
    assert!(said.contains("aborted (Ctrl-C) after "), "{said}");
    assert!(said.contains("returned to start"), "{said}");
    // the partial scan is bound to the variable being assigned
    let o = p.enter("[s.status, s.meta.pauses[0].resumed]", T);
    assert!(o.contains("[\"aborted\", false]"), "{o}");
    let o = p.enter(
        "let k = s.meta.points_measured; [k == s.meta.pauses[0].after_points, k > 0, k < 100]",
        T,
    );
    assert!(o.contains("[true, true, true]"), "{o}");
    let o = p.enter("wm()", T);
    assert!(o.contains("x = 1") && o.contains("y = 2"), "{o}");
    let out = p.quit();
    if std::env::var_os("BFPSCOPE_SHOW").is_some() {
        eprintln!("{out}");
    }
}

#[test]
fn help_is_paged_at_the_terminal() {
    let mut p = Prompt::start(&dir("help"), &[]);
    let from = p.out.len();
    p.type_line("help()");
    p.wait_for_from(from, "-- more: ", T);
    let first = p.out[from..].to_string();
    // a screen's worth (the terminal's rows but one), starting with the first family
    let shown = first.lines().count();
    assert!((10..=60).contains(&shown), "{shown} lines:\n{first}");
    assert!(
        first.contains("core") && !first.contains("protocols (stdlib"),
        "{first}"
    );
    let from2 = p.out.len();
    p.type_line("");
    p.wait_for_from(from2, "-- more: ", T);
    let from3 = p.out.len();
    p.type_line("q");
    p.wait_for_from(from3, "bfp> ", T);
    assert!(
        p.out[from3..].contains("lines not shown"),
        "{}",
        &p.out[from3..]
    );
    // a short page is printed whole, without stopping
    let o = p.enter("help(\"mv\")", T);
    assert!(o.contains("mv(") && !o.contains("-- more"), "{o}");
    p.quit();
}
