//! One owner for the session's optics and scene: after `set_optics` or a
//! new scene, the connected simulator images exactly what the session says, and the scan's
//! metadata records it.

use crate::support::cleanup;

use bfpscope::script::{Settings, Workbench};

fn wb(tag: &str) -> Workbench {
    let dir = std::env::temp_dir().join(format!("bfpscope-so-{}-{tag}", std::process::id()));
    cleanup::at_exit(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    let (s, _buf) = Settings::captured(dir);
    Workbench::new(s)
}

/// Run `code` for its effect; panics with the script's error.
fn run(wb: &mut Workbench, code: &str) {
    if let Err(e) = wb.eval_line(code) {
        panic!("{code}: {e}");
    }
}

fn f(wb: &mut Workbench, expr: &str) -> f64 {
    let v = wb.eval_line(expr).unwrap_or_else(|e| panic!("{expr}: {e}"));
    v.as_float()
        .unwrap_or_else(|_| panic!("{expr}: not a number: {v}"))
}

/// Largest |difference| of two scans' Sx over the grid, relative to the first's peak.
const DIFF: &str = "fn diff(a, b) { (a.sx - b.sx).abs_max() / a.sx.abs_max() }";

const GRID: &str = "#{x: [-0.6, 0.6], y: [-0.3, 0.3], nx: 13, ny: 3}";

#[test]
fn set_optics_and_a_new_scene_reach_the_connected_simulator() {
    let mut w = wb("owner");
    run(&mut w, DIFF);
    run(
        &mut w,
        "let s = scene(); s.add_bead(#{x: 0.0, y: 0.0, d_nm: 110.0, n: 1.572}); simulate(s);",
    );
    let scan = "scan_xy(#{x: [-0.6, 0.6], y: [-0.3, 0.3], nx: 13, ny: 3, dwell: 0.001})";
    run(&mut w, &format!("let a = {scan};"));
    // the scan is what a renderer built afresh from the session's optics and scene gives
    let fresh = f(&mut w, &format!("diff(simulate(s, {GRID}), a)"));
    assert!(fresh < 1e-9, "before set_optics: {fresh:e}");

    run(&mut w, "set_optics(#{wavelength_nm: 800.0});");
    run(&mut w, &format!("let b = {scan};"));
    assert_eq!(f(&mut w, "b.meta.optics.wavelength_nm"), 800.0);
    // the new wavelength changed the image (by far more than the agreement checked next) …
    let moved = f(&mut w, "diff(a, b)");
    assert!(
        moved > 0.05,
        "the 800 nm scan differs from the 1064 nm one by only {moved:e}"
    );
    // … and the connected simulator renders in it: the scan equals a fresh 800 nm render
    let after = f(&mut w, &format!("diff(simulate(s, {GRID}), b)"));
    eprintln!("1064 → 800 nm: the scan moved by {moved:.3} of its peak; the fresh render differs by {fresh:e} before, {after:e} after");
    assert!(after < 1e-9, "after set_optics: {after:e}");

    // a new scene under the same simulator: imaged, and recorded in the scan's metadata
    run(
        &mut w,
        "let s2 = scene(); s2.add_bead(#{x: 0.25, y: 0.0, d_nm: 110.0, n: 1.572}); simulate(s2);",
    );
    run(&mut w, &format!("let c = {scan};"));
    assert_eq!(f(&mut w, "c.meta.scene.beads[0].pos[0]"), 0.25);
    assert_eq!(f(&mut w, "c.meta.optics.wavelength_nm"), 800.0);
    let scene_moved = f(&mut w, "diff(b, c)");
    assert!(scene_moved > 0.05, "{scene_moved:e}");
    let again = f(&mut w, &format!("diff(simulate(s2, {GRID}), c)"));
    assert!(again < 1e-9, "after the new scene: {again:e}");

    // a refused set_optics changes nothing: the session and the simulator keep 800 nm
    let e = w
        .eval_line("set_optics(#{na: 2.0})")
        .unwrap_err()
        .to_string();
    assert!(e.contains("na = 2") && e.contains("0.01 ≤ na ≤ 1.7"), "{e}");
    run(&mut w, &format!("let d = {scan};"));
    assert_eq!(f(&mut w, "d.meta.optics.wavelength_nm"), 800.0);
    assert_eq!(f(&mut w, "optics().wavelength_nm"), 800.0);
    let same = f(&mut w, "diff(c, d)");
    assert!(same < 1e-9, "{same:e}");
}

/// The mock images no scene: its scans record none (the scene of an earlier simulator is not
/// carried over), and the emulated instrument, whose emulators render the optics it was
/// connected with, refuses new optics rather than record ones it does not image.
#[test]
fn the_scene_is_the_connected_instruments() {
    let mut w = wb("mock");
    run(
        &mut w,
        "let s = scene(); s.add_bead(#{x: 0.0, y: 0.0}); simulate(s);",
    );
    let sim_meta = w
        .eval_line("scan_line(#{axis: \"x\", from: -0.2, to: 0.2, n: 3, dwell: 0.001}).meta.scene.beads.len()")
        .unwrap();
    assert_eq!(sim_meta.as_int().unwrap(), 1);
    run(&mut w, "connect(#{backend: \"mock\"});");
    let mock_meta = w
        .eval_line("scan_line(#{axis: \"x\", from: -0.2, to: 0.2, n: 3, dwell: 0.001}).meta.scene")
        .unwrap();
    assert!(
        mock_meta.is_unit(),
        "the mock's scan records a scene: {mock_meta}"
    );
    run(&mut w, "connect(#{backend: \"emulated\"});");
    let e = w
        .eval_line("set_optics(#{wavelength_nm: 800.0})")
        .unwrap_err()
        .to_string();
    assert!(e.contains("set_optics") && e.contains("emulated"), "{e}");
    assert_eq!(f(&mut w, "optics().wavelength_nm"), 1064.0);
}
