//! Golden traces of protocol runs on the simulator: every stage move, QPD read (4 significant
//! digits) and protocol decision, stamped with the virtual clock. A change in a protocol's
//! behaviour shows up as a readable diff against the committed file in `tests/golden/`.
//! Refresh deliberately with `BFPSCOPE_BLESS="<one line saying why>" cargo test --test program golden::`
//! and review the diff: the reason is added to the file's `# ` header (kept, not compared).

use crate::support::cleanup;

use bfpscope::instrument::trace::check_golden;
use bfpscope::script::{Settings, Workbench};
use std::path::Path;

fn run(tag: &str, script: &str) -> String {
    let dir = std::env::temp_dir().join(format!("bfpscope-golden-{}-{tag}", std::process::id()));
    cleanup::at_exit(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    let (s, _buf) = Settings::captured(dir);
    let mut wb = Workbench::new(s);
    let v = wb
        .eval_source(tag, script)
        .unwrap_or_else(|e| panic!("{tag}: {e}"));
    v.into_string().expect("the script returns the trace text")
}

fn golden(name: &str, script: &str) {
    let text = run(name, script);
    let bless = std::env::var("BFPSCOPE_BLESS").ok();
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(format!("{name}.trace"));
    if let Err(e) = check_golden(&text, &path, bless.as_deref()) {
        panic!("{e}");
    }
}

#[test]
fn focus_protocol_trace() {
    golden(
        "focus",
        r#"
        import "focus" as focus;
        let s = scene();
        s.add_bead(#{x: 0.0, y: 0.0, d_nm: 110.0, n: 1.572});
        simulate(s);
        mv(#{z: 0.3});
        trace_start();
        focus::search(#{half_um: 0.6, n: 9, z_half_um: 0.6, nz: 9});
        trace_text()
        "#,
    );
}

#[test]
fn rotation_protocol_trace() {
    golden(
        "rotation",
        r#"
        import "rotation" as rotation;
        let s = scene();
        s.add_bead(#{x: -2.0, y: 1.5, d_nm: 110.0, n: 1.572});
        s.add_filament(#{points: [[0.5, -5.0], [0.5, 5.0]], d_nm: 80.0, n: 1.41});
        simulate(s);
        trace_start();
        rotation::series(#{scene: s, fiducial: [-2.0, 1.5], filament: [0.5, 0.0], n_angles: 3, n: 7, box_um: 1.2, fid_n: 9, focus: false});
        trace_text()
        "#,
    );
}
