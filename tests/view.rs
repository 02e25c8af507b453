//! The live view in a real browser: Debian's headless Chromium, driven through
//! chromedriver (W3C WebDriver), against a workbench running in this process on the simulator.
//! The browser is required: without it these tests fail with the command that installs it.
//!
//! Screenshots go to `$CARGO_TARGET_TMPDIR/view-screenshots/` (the guide's are copied from
//! there: docs/figures/view_*.png).

use crate::support::cleanup;

use crate::support;

use bfpscope::script::view::start_view;
use bfpscope::script::{Settings, Workbench};
use serde_json::json;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::Duration;
use support::webdriver::{http, Browser};

const BEAD: &str = "let s = scene(); s.add_bead(#{x: 0.0, y: 0.0, d_nm: 110.0, n: 1.572});";

fn bench(tag: &str) -> (Workbench, String, PathBuf) {
    let dir = std::env::temp_dir().join(format!("bfpscope-view-{}-{tag}", std::process::id()));
    cleanup::at_exit(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    let (s, _out) = Settings::captured(&dir);
    let wb = Workbench::new(s);
    let url = start_view(&wb.ctx, "127.0.0.1", 0).expect("view starts");
    (wb, url, dir)
}

fn shots() -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("view-screenshots")
}

fn open(url: &str) -> Browser {
    let b = Browser::start();
    b.goto(url);
    b.wait_for(
        "return document.getElementById('conn').textContent === 'live'",
        Duration::from_secs(20),
        "the page's event stream",
    );
    b
}

/// Painted pixels per displayed row of the heat map, top row first, sampled at the centre of
/// each of the `n × n` image pixels from the canvas itself (unmeasured pixels are #e8e8e8).
const ROWS: &str = r#"
const cv = document.getElementById('map'), d = cv.dataset, n = arguments[0];
const L = +d.plotLeft, T = +d.plotTop, W = +d.plotWidth, H = +d.plotHeight;
const img = cv.getContext('2d').getImageData(L, T, W, H).data;
const rows = [];
for (let r = 0; r < n; r++) {
  const py = Math.floor((r + 0.5) * H / n);
  let painted = 0;
  for (let c = 0; c < n; c++) {
    const px = Math.floor((c + 0.5) * W / n), k = 4 * (py * W + px);
    if (!(img[k] === 232 && img[k + 1] === 232 && img[k + 2] === 232)) painted++;
  }
  rows.push(painted);
}
return rows;
"#;

fn rows_painted(b: &Browser, n: usize) -> Vec<usize> {
    let v = b.js(ROWS, json!([n]));
    v.as_array()
        .expect("row counts")
        .iter()
        .map(|x| x.as_u64().unwrap() as usize)
        .collect()
}

/// (full rows, they are the bottom ones in a block, at most one partial row just above them)
fn fill_pattern(rows: &[usize], n: usize) -> (usize, bool) {
    let full = rows.iter().filter(|&&p| p == n).count();
    let bottom_block = rows[rows.len() - full..].iter().all(|&p| p == n);
    let partial: Vec<usize> = (0..rows.len())
        .filter(|&i| rows[i] > 0 && rows[i] < n)
        .collect();
    let partial_ok =
        partial.is_empty() || (partial.len() == 1 && partial[0] + full + 1 == rows.len());
    let empty_above = rows[..rows.len() - full - partial.len()]
        .iter()
        .all(|&p| p == 0);
    (full, bottom_block && partial_ok && empty_above)
}

#[test]
fn a_64_by_64_scan_fills_in_row_by_row_and_the_pointer_reads_stage_coordinates() {
    let (mut wb, url, dir) = bench("live");
    let _ = wb
        .eval_source(
            "t",
            &format!("{BEAD} connect(#{{backend: \"sim\", scene: s, pace: 0.5, settle: 0.001}});"),
        )
        .unwrap();
    let b = open(&url);
    let scan = std::thread::spawn(move || {
        let r = wb.eval_source(
            "t",
            "scan_xy(#{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 64, ny: 64, dwell: 0.001})",
        );
        // the workbench (and its view) must outlive the scan: hand it back
        (wb, r.map(|_| ()).map_err(|e| e.to_string()))
    });
    b.wait_for(
        "return document.getElementById('progress').value > 0.15",
        Duration::from_secs(60),
        "15 % of the scan on the page",
    );
    let a = rows_painted(&b, 64);
    b.screenshot(&shots().join("view_scan.png"));
    std::thread::sleep(Duration::from_millis(1500));
    let c = rows_painted(&b, 64);
    let (full_a, ok_a) = fill_pattern(&a, 64);
    let (full_c, ok_c) = fill_pattern(&c, 64);
    assert!(
        ok_a && ok_c,
        "rows fill from the bottom (y = -1 µm) up:\n{a:?}\n{c:?}"
    );
    assert!(full_a >= 9, "{full_a} rows at 15 %: {a:?}");
    assert!(
        full_c > full_a && full_c < 64,
        "rows {full_a} then {full_c}: the canvas must grow row by row while the scan runs"
    );
    // a reload in the middle of the scan draws what is already measured, then follows
    b.goto(&url);
    b.wait_for(
        "return document.getElementById('conn').textContent === 'live'",
        Duration::from_secs(20),
        "the reloaded page's event stream",
    );
    b.wait_for(
        &format!(
            "return document.getElementById('progress').value * 4096 >= {}",
            64 * full_c
        ),
        Duration::from_secs(20),
        "the reloaded page to catch up",
    );
    let (full_r, ok_r) = fill_pattern(&rows_painted(&b, 64), 64);
    assert!(
        ok_r && full_r >= full_c,
        "after the reload: {full_r} rows (before it: {full_c})"
    );
    let (_wb, r) = scan.join().unwrap();
    r.expect("the scan completes");
    b.wait_for(
        "return document.getElementById('progress-text').textContent.includes('complete')",
        Duration::from_secs(20),
        "the scan's end on the page",
    );
    assert_eq!(
        fill_pattern(&rows_painted(&b, 64), 64),
        (64, true),
        "all 64 rows"
    );

    // the pointer over pixel (row 36, column 28), near the bead: the plan's grid, x = -1 + 28·2/63 µm,
    // y = -1 + 36·2/63 µm, and the saved scan's value there
    let g = b.js(
        "const cv = document.getElementById('map'), r = cv.getBoundingClientRect(), d = cv.dataset; \
         return [r.left, r.top, +d.plotLeft, +d.plotTop, +d.plotWidth, +d.plotHeight];",
        json!([]),
    );
    let g: Vec<f64> = g
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let (col, row) = (28.0, 36.0);
    let px = g[0] + g[2] + (col + 0.5) * g[4] / 64.0;
    let py = g[1] + g[3] + (63.0 - row + 0.5) * g[5] / 64.0; // y grows upwards
    b.pointer_to(px.round() as i64, py.round() as i64);
    let text = b
        .js(
            "return document.getElementById('readout').textContent",
            json!([]),
        )
        .as_str()
        .unwrap()
        .to_string();
    let (x, y) = (-1.0 + col * 2.0 / 63.0, -1.0 + row * 2.0 / 63.0);
    let want = format!("x = {x:.3} µm, y = {y:.3} µm");
    assert!(text.contains(&want), "readout {text:?}, expected {want:?}");
    assert!(text.contains("pixel (row 36, column 28)"), "{text}");
    let saved = bfpscope::data::npz::load_scan(dir.join("scan_0001.npz")).unwrap();
    let sx = saved.sx.data[[36, 28]];
    let peak = saved.sx.data.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let shown: f64 = text
        .split("Sx = ")
        .nth(1)
        .and_then(|t| t.split(' ').next())
        .and_then(|t| t.parse().ok())
        .unwrap_or_else(|| panic!("no Sx value in {text:?}"));
    assert!(
        sx.abs() > 0.2 * peak,
        "pixel (36, 28) is on the bead's signal: {sx} (peak {peak})"
    );
    assert!(
        ((shown - sx) / sx).abs() < 1e-3,
        "readout Sx {shown}, saved {sx}"
    );

    // Sx and Sy are signed: a symmetric colour scale; Sz is not
    for (ch, symmetric) in [("sy", true), ("sz", false), ("sx", true)] {
        b.js(
            &format!("document.querySelector('#channels button[data-ch={ch}]').click()"),
            json!([]),
        );
        assert_eq!(
            b.js(
                "return document.getElementById('symmetric').checked",
                json!([])
            ),
            json!(symmetric),
            "{ch}"
        );
    }
}

#[test]
fn a_figure_appears_and_an_aborted_scan_is_listed_with_its_status() {
    let (mut wb, url, _dir) = bench("figs");
    let b = open(&url);
    let _ = wb
        .eval_source(
            "t",
            &format!(
            "{BEAD} let sc = simulate(s, #{{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 41, ny: 41}}); \
             plot(sc, \"bead_fig.png\", #{{title: \"110 nm bead\"}});"
        ),
        )
        .unwrap();
    b.wait_for(
        "return [...document.querySelectorAll('#figures figure')].some(f => f.dataset.name === 'bead_fig.png' \
         && f.querySelector('img').complete && f.querySelector('img').naturalWidth > 0)",
        Duration::from_secs(20),
        "the figure on the page",
    );
    b.screenshot(&shots().join("view_figure.png"));

    // a line scan draws as a line plot; clicking a saved scan in the list shows it with its
    // metadata
    let _ = wb.eval_source("t", &format!("{BEAD} connect(#{{backend: \"sim\", scene: s}}); scan_line(#{{axis: \"x\", from: -1.0, to: 1.0, n: 41, dwell: 0.001}});"));
    b.wait_for(
        "return document.getElementById('map').dataset.kind === 'line' && \
         document.getElementById('progress-text').textContent.startsWith('41 / 41 points · complete')",
        Duration::from_secs(20),
        "the line scan as a line plot",
    );
    b.js(
        "document.querySelector('#scans tbody tr[data-number=\"1\"]').click()",
        json!([]),
    );
    b.wait_for(
        "return !document.getElementById('meta').hidden && \
         document.getElementById('meta-text').textContent.includes('\"kind\": \"scan_line\"')",
        Duration::from_secs(20),
        "scan 1 and its metadata",
    );
    b.js("document.getElementById('live-button').click()", json!([]));

    // a scan interrupted as Ctrl-C does (the shared abort flag)
    let _ = wb
        .eval_source(
            "t",
            &format!("{BEAD} connect(#{{backend: \"sim\", scene: s, pace: 1.0, settle: 0.001}});"),
        )
        .unwrap();
    let abort = wb.ctx.settings.abort.clone();
    let scan = std::thread::spawn(move || {
        let r = wb.eval_source(
            "t",
            "scan_xy(#{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 32, ny: 32, dwell: 0.001})",
        );
        (wb, r.map(|_| ()).map_err(|e| e.to_string()))
    });
    b.wait_for(
        "return document.getElementById('progress').value > 0.1",
        Duration::from_secs(60),
        "the scan under way",
    );
    abort.store(true, Ordering::SeqCst);
    let (_wb, r) = scan.join().unwrap();
    let err = r.expect_err("an aborted scan is an error");
    assert!(err.contains("aborted"), "{err}");
    b.wait_for(
        "return [...document.querySelectorAll('#scans tbody tr')].some(r => r.dataset.status === 'aborted' \
         && r.textContent.includes('aborted') && r.dataset.number === '2')",
        Duration::from_secs(20),
        "scan 2 listed as aborted",
    );
    // the scans table and the progress line come from separate events: under load the table
    // may say "aborted" a moment before the line does (CI on a loaded machine, 2026-12-07)
    b.wait_for(
        "return document.getElementById('progress-text').textContent.includes('aborted')",
        Duration::from_secs(20),
        "the progress line to say the scan was aborted",
    );
}

#[test]
fn a_request_without_the_token_is_refused() {
    let (_wb, url, _dir) = bench("token");
    let addr: std::net::SocketAddr = url
        .trim_start_matches("http://")
        .split('/')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let token = url.split("token=").nth(1).unwrap();
    // the same length, one character different
    let wrong = format!(
        "{}{}",
        if token.starts_with('0') { '1' } else { '0' },
        &token[1..]
    );
    assert_ne!(wrong, token);
    for path in ["/", "/events", "/api/state", "/figure/1", "/api/scan/1"] {
        assert_eq!(http(addr, "GET", path, None).0, 403, "{path}");
        assert_eq!(
            http(addr, "GET", &format!("{path}?token={wrong}"), None).0,
            403,
            "{path} with a wrong token"
        );
    }
    assert_eq!(
        http(addr, "GET", &format!("/api/state?token={token}"), None).0,
        200
    );
    // and in the browser
    let b = Browser::start();
    b.goto(&format!("http://{addr}/"));
    let body = b.js("return document.body.innerText", json!([]));
    assert!(body.as_str().unwrap().contains("403 Forbidden"), "{body}");
}

#[test]
fn after_a_rotation_series_the_page_lists_every_scan() {
    let (mut wb, url, dir) = bench("rotation");
    let b = open(&url);
    let _ = wb.eval_source(
        "t",
        r#"
        import "rotation" as rotation;
        let s = scene();
        s.add_bead(#{x: -2.0, y: 1.5, d_nm: 110.0, n: 1.572});
        s.add_filament(#{points: [[0.5, -5.0], [0.5, 5.0]], d_nm: 110.0, n: 1.572});
        simulate(s);
        let r = rotation::series(#{scene: s, fiducial: [-2.0, 1.5], filament: [0.5, 0.0], n_angles: 5, n: 31, box_um: 2.0, fid_n: 21, focus: false});
        plot_xy([#{x: r.angles_deg, y: r.sx, label: "Sx (data)", style: "points"},
                 #{x: r.angles_deg, y: r.model_sx, label: "Sx (bead model)"},
                 #{x: r.angles_deg, y: r.sy, label: "Sy (data)", style: "points"},
                 #{x: r.angles_deg, y: r.model_sy, label: "Sy (bead model)"}],
                "rotation_curve.png", #{xlabel: "angle (°)", ylabel: "max. sensitivity (norm.)", title: "rotation series"});
        "#,
    )
    .unwrap();
    let files = std::fs::read_dir(&dir)
        .unwrap()
        .filter(|e| {
            let n = e.as_ref().unwrap().file_name();
            let n = n.to_string_lossy();
            n.starts_with("scan_") && n.ends_with(".npz")
        })
        .count();
    assert!(files >= 10, "{files} scans for 5 angles");
    b.wait_for(
        &format!(
            "return document.querySelectorAll('#scans tbody tr').length === {files} && \
             [...document.querySelectorAll('#scans tbody tr')].every(r => r.dataset.status === 'complete') && \
             [...document.querySelectorAll('#figures figure')].some(f => f.dataset.name === 'rotation_curve.png')"
        ),
        Duration::from_secs(20),
        "every scan of the series and its figure",
    );
    b.screenshot(&shots().join("view_rotation.png"));
}

/// The line of text under the progress bar.
fn progress_text(b: &Browser) -> String {
    b.js(
        "return document.getElementById('progress-text').textContent",
        json!([]),
    )
    .as_str()
    .unwrap()
    .to_string()
}

/// The seconds of "… · 2.3 s elapsed …" (or "1 min 4 s elapsed").
fn elapsed_shown(text: &str) -> f64 {
    let head = text
        .split(" elapsed")
        .next()
        .and_then(|t| t.rsplit(" · ").next())
        .unwrap_or_else(|| panic!("no elapsed time in {text:?}"));
    let w: Vec<&str> = head.split(' ').collect();
    match w.as_slice() {
        [s, "s"] => s.parse().unwrap(),
        [m, "min", s, "s"] => 60.0 * m.parse::<f64>().unwrap() + s.parse::<f64>().unwrap(),
        _ => panic!("elapsed time {head:?} in {text:?}"),
    }
}

#[test]
fn a_paused_scan_shows_paused_with_its_eta_standing_still_then_running_again() {
    let (mut wb, url, _dir) = bench("pause");
    let _ = wb
        .eval_source(
            "t",
            &format!("{BEAD} connect(#{{backend: \"sim\", scene: s, pace: 1.0, settle: 0.001}});"),
        )
        .unwrap();
    // the prompt's question, answered by this test: "paused" goes out, "resume" comes in
    let (to_test, paused) = std::sync::mpsc::channel::<()>();
    let (resume, from_test) = std::sync::mpsc::channel::<()>();
    let (to_test, from_test) = (
        std::sync::Mutex::new(to_test),
        std::sync::Mutex::new(from_test),
    );
    wb.ctx.set_pause_question(Some(std::sync::Arc::new(
        move |_p: &bfpscope::acquire::Paused| {
            let _ = to_test.lock().unwrap().send(());
            from_test
                .lock()
                .unwrap()
                .recv_timeout(Duration::from_secs(60))
                .is_ok()
        },
    )));
    let b = open(&url);
    let abort = wb.ctx.settings.abort.clone();
    let scan = std::thread::spawn(move || {
        let r = wb.eval_source(
            "t",
            "scan_xy(#{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 40, ny: 40, dwell: 0.001})",
        );
        (wb, r.map(|_| ()).map_err(|e| e.to_string()))
    });
    b.wait_for(
        "return document.getElementById('progress').value > 0.1 && \
         document.getElementById('progress-text').textContent.includes('ETA')",
        Duration::from_secs(60),
        "the scan under way with its ETA",
    );
    abort.store(true, Ordering::SeqCst);
    paused
        .recv_timeout(Duration::from_secs(20))
        .expect("the engine pauses");
    b.wait_for(
        "return document.getElementById('progress-text').textContent.includes(' · paused')",
        Duration::from_secs(10),
        "\"paused\" on the page",
    );
    let a = progress_text(&b);
    std::thread::sleep(Duration::from_millis(1600));
    let c = progress_text(&b);
    assert!(
        !a.contains("running") && !a.contains("ETA"),
        "while paused: {a:?}"
    );
    assert_eq!(a, c, "nothing ticks while the scan is paused");
    resume.send(()).unwrap();
    b.wait_for(
        "const t = document.getElementById('progress-text').textContent; \
         return t.includes(' · running') && t.includes('ETA') && t.includes('paused)')",
        Duration::from_secs(10),
        "\"running\" and an ETA again after the resume",
    );
    let r = progress_text(&b);
    // the pause (≥ 1.6 s) is shown and left out of the ETA's cost per point
    let shown_pause: f64 = r
        .split(" (")
        .nth(1)
        .and_then(|t| t.split(" s paused)").next())
        .and_then(|t| t.parse().ok())
        .unwrap_or_else(|| panic!("no pause time in {r:?}"));
    assert!(shown_pause >= 1.6, "{r}");
    let (_wb, res) = scan.join().unwrap();
    res.expect("the resumed scan completes");
    b.wait_for(
        "return document.getElementById('progress-text').textContent.includes('1600 / 1600 points · complete')",
        Duration::from_secs(30),
        "the scan's end",
    );
}

#[test]
fn a_tab_opened_after_a_scan_shows_the_scans_own_duration() {
    let (mut wb, url, dir) = bench("duration");
    let _ = wb
        .eval_source(
            "t",
            &format!(
                "{BEAD} connect(#{{backend: \"sim\", scene: s, pace: 1.0, settle: 0.001}}); \
                 scan_xy(#{{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 24, ny: 24, dwell: 0.001}});"
            ),
        )
        .unwrap();
    let saved = bfpscope::data::npz::load_scan(dir.join("scan_0001.npz")).unwrap();
    let wall = saved.meta["time"]["wall_s"].as_f64().unwrap();
    assert!(wall > 0.5, "a scan of {wall} s");
    // the tab opens well after the scan ended
    std::thread::sleep(Duration::from_secs(4));
    let b = open(&url);
    b.wait_for(
        "return document.getElementById('progress-text').textContent.includes('576 / 576 points · complete')",
        Duration::from_secs(20),
        "the ended scan on the page",
    );
    let t = progress_text(&b);
    let shown = elapsed_shown(&t);
    // the page rounds to 0.1 s; the view's start and end bracket the engine's clock by the
    // saving of the file (milliseconds)
    assert!(
        (shown - wall).abs() <= 0.15,
        "{t:?}: the scan took {wall:.2} s (its metadata)"
    );
    assert!(!t.contains("ETA"), "{t}");
    std::thread::sleep(Duration::from_millis(1100));
    assert_eq!(progress_text(&b), t, "an ended scan's time stands still");
}

#[test]
fn the_page_never_scrolls_sideways_from_360_px_up() {
    let (mut wb, url, _dir) = bench("width");
    let _ = wb
        .eval_source(
            "t",
            &format!(
                "{BEAD} note(\"a long note without spaces: bead_110nm_polystyrene_in_water_reference_for_the_calibration_of_today\"); \
                 let sc = simulate(s, #{{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 21, ny: 21}}); \
                 plot(sc, \"bead_fig.png\", #{{title: \"110 nm bead\"}}); \
                 connect(#{{backend: \"sim\", scene: s}}); \
                 scan_xy(#{{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 21, ny: 21, dwell: 0.001}});"
            ),
        )
        .unwrap();
    let b = open(&url);
    b.wait_for(
        "return document.getElementById('progress-text').textContent.includes('complete') && \
         document.querySelectorAll('#figures figure').length === 1 && \
         document.querySelectorAll('#scans tbody tr').length === 1",
        Duration::from_secs(20),
        "the scan, its row and the figure",
    );
    for width in [1280u32, 1024, 1012, 1000, 800, 360] {
        let inner = b.set_window(width, 900);
        assert_eq!(inner, width as i64, "the window is {width} px wide");
        // let the layout settle
        std::thread::sleep(Duration::from_millis(200));
        let w = b.js(
            "const e = document.documentElement; \
             const wide = [...document.querySelectorAll('body *')].filter(x => x.getBoundingClientRect().right > e.clientWidth + 0.5).map(x => x.tagName + '#' + x.id + '.' + x.className); \
             return [e.scrollWidth, e.clientWidth, wide.slice(0, 6)]",
            json!([]),
        );
        assert!(
            w[0].as_i64() <= w[1].as_i64(),
            "at {width} px the page is {} px wide (viewport {}): {}",
            w[0],
            w[1],
            w[2]
        );
        // the map is drawn whole, scaled to the column when the window is narrow
        let cw = b
            .js(
                "return document.getElementById('map').getBoundingClientRect().width",
                json!([]),
            )
            .as_f64()
            .unwrap();
        assert!(cw > 0.5 * (width.min(636) as f64), "map {cw} px at {width}");
        if width == 1012 {
            b.screenshot(&shots().join("view_1012.png"));
        }
        if width == 360 {
            b.screenshot(&shots().join("view_360.png"));
        }
    }
}

/// A scan whose Sx clipped at the detector's range (the simulator's `detector_range` effect)
/// says so on the page when it ends: `WARNING:` with the number of clipped Sx pixels the scan
/// recorded, and the range.
#[test]
fn a_clipped_scan_shows_its_warning_on_the_page() {
    let (mut wb, url, _dir) = bench("clipped");
    let v = wb
        .eval_source(
            "t",
            &format!(
                "{BEAD} s.effect(\"detector_range\", #{{range: 1e-3, sum_scale: 5e-4}}); \
                 connect(#{{backend: \"sim\", scene: s, settle: 0.001}}); \
                 let sc = scan_xy(#{{x: [-0.6, 0.6], y: [-0.6, 0.6], nx: 13, ny: 13, dwell: 0.001}}); \
                 sc.meta.clipped.sx.pixels"
            ),
        )
        .unwrap();
    let px = v.as_int().expect("clipped Sx pixels");
    assert!(px > 0, "the scene clips Sx");
    let b = open(&url);
    let want = format!("{px} pixels of Sx");
    b.wait_for(
        &format!(
            "return document.getElementById('progress-text').textContent.includes('WARNING:') && \
             document.getElementById('progress-text').textContent.includes({want:?})"
        ),
        Duration::from_secs(20),
        "the clip warning on the page",
    );
    let t = progress_text(&b);
    assert!(
        t.contains("clipped") && t.contains("±0.001 input range"),
        "{t}"
    );
    b.screenshot(&shots().join("view_clipped.png"));
}
