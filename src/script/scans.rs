//! Scan bindings: `scan_line`, `scan_xy`, `scan_xz`, `scan_yz`, SPEC's `ascan`, `dscan`,
//! `mesh`, `dmesh`, and scan files (`scan.save`, `load_scan`). Bindings only build a
//! [`Plan`]; the one scan engine (`acquire::run`) executes it natively with every safety rule,
//! with the acquisition strategy of its mode (point by point, hardware-timed lines).

use super::ctx::Ctx;
use super::keys::{AXIS, DWELL};
use super::registry::{binding_list, fail, int, num, Doc, Opt, Opts, RResult, Registrar, Spec};
use super::types::ScanRef;
use crate::acquire::plan::{Axis, Plan, Sweep, DEFAULT_DWELL_S, MAX_POINTS_PER_AXIS};
use crate::acquire::raster::{RasterOptions, DEFAULT_SAMPLES_PER_PIXEL};
use crate::acquire::strategy::{PointStrategy, Strategy};
use crate::acquire::{run, ScanEnv};
use crate::data::Scan;
use rhai::{Dynamic, Map};
use std::path::PathBuf;

/// The stop rule of every scan, every mode, for the help (one source: `acquire::stop_rule`).
use crate::acquire::stop_rule::STOP_RULE;

/// The options of this family's bindings, each key written once (`Opt`).
const FROM: Opt = Opt::new("from", "float", "µm");
const N: Opt = Opt::new("n", "int", "");
const REL: Opt = Opt::new("rel", "bool", "");
const SNAKE: Opt = Opt::new("snake", "bool", "");
const MODE: Opt = Opt::new("mode", "string", "");
const TO: Opt = Opt::new("to", "float", "µm");
const SAMPLES_PER_PIXEL: Opt = Opt::new("samples_per_pixel", "int", "");

/// Where the stage is after a SPEC scan (help text): back at the start for a relative scan
/// (`rel`), at the last point for an absolute one; then [`STOP_RULE`].
fn where_the_stage_ends(rel: bool) -> String {
    if rel {
        format!("Positions are relative to where the stage is, and the stage returns there at the end. {STOP_RULE}")
    } else {
        format!("The stage stays at the last point. {STOP_RULE}")
    }
}

/// The help text of the `dwell` option, naming the default.
fn dwell_help() -> String {
    format!(
        "dwell per point, default {DEFAULT_DWELL_S} (the accuracy report's knee for the paper's mass resolution)"
    )
}

/// Execute a plan on the connected instrument; complete → the scan, otherwise a script error
/// that tells what happened and where the partial scan was saved.
pub fn execute(c: &Ctx, plan: Plan) -> RResult<ScanRef> {
    execute_mode(c, plan, None)
}

/// As [`execute`]; `raster`: a hardware-timed raster (the engine with the line strategy) with
/// these options instead of point by point.
pub fn execute_mode(c: &Ctx, plan: Plan, raster: Option<RasterOptions>) -> RResult<ScanRef> {
    let meta = c.scan_meta();
    let store = c.store.clone();
    let save = move |s: &Scan| store.autosave(s).map_err(|e| e.to_string());
    let log = |s: &str| c.log(s);
    let kind = plan.kind.clone();
    let hub = c.view_hub();
    let question = c.pause_question();
    c.with_instrument(&kind, |inst| {
        let env = ScanEnv {
            limits: &c.settings.limits,
            abort: &c.settings.abort,
            progress: c.settings.progress,
            log: &log,
            meta,
            save: &save,
            observer: hub
                .as_deref()
                .map(|h| h as &dyn crate::acquire::ScanObserver),
            pause: question
                .as_deref()
                .map(|q| q as &dyn Fn(&crate::acquire::Paused) -> bool),
        };
        let mut strategy: Box<dyn Strategy> = match raster {
            Some(o) => crate::acquire::strategy::for_raster(inst, o),
            None => Box::new(PointStrategy::new()),
        };
        let run = run(inst, &plan, strategy.as_mut(), &env).map_err(|e| e.to_string())?;
        match run.summary() {
            // A complete scan that could not be saved is not a success: a script stops here
            // (non-zero exit); at the prompt the scan is kept in memory (bound to the entry's
            // variable and `_`, see repl) with the way to save it elsewhere.
            Ok(msg) if run.saved.is_err() => {
                c.set_partial(Some(ScanRef::new(run.scan, None)));
                fail(format!(
                    "{kind} complete but NOT SAVED — {msg} (session folder {}); the scan is only in memory",
                    c.store.dir().display()
                ))
            }
            Ok(msg) => {
                let t = run.scan.meta["time"]["instrument_s"]
                    .as_f64()
                    .unwrap_or(0.0);
                c.log(&format!(
                    "{kind}: complete in {} instrument time, {msg}",
                    crate::acquire::plan::fmt_seconds(t)
                ));
                let path = run.saved.ok().map(|p| p.display().to_string());
                Ok(ScanRef::new(run.scan, path))
            }
            Err(msg) => {
                let path = run.saved.as_ref().ok().map(|p| p.display().to_string());
                c.set_partial(Some(ScanRef::new(run.scan, path)));
                fail(msg)
            }
        }
    })
}

fn axis_arg(who: &str, v: &Dynamic, usage: &str) -> RResult<Axis> {
    let s = if v.is_string() {
        v.to_string()
    } else {
        String::new()
    };
    Axis::parse(&s).map_or_else(
        || {
            fail(format!(
                "{who}: axis = {v} is not one of \"x\", \"y\", \"z\"; usage: {usage}"
            ))
        },
        Ok,
    )
}

/// Number of SPEC intervals → points (intervals + 1), checked.
fn intervals(who: &str, name: &str, v: &Dynamic) -> RResult<i64> {
    let k = int(who, name, v)?;
    if k < 1 || k as usize > MAX_POINTS_PER_AXIS - 1 {
        return fail(format!("{who}: {name} = {k} is out of range: 1 ≤ {name} ≤ {} (SPEC counts intervals: {name} + 1 points)", MAX_POINTS_PER_AXIS - 1));
    }
    Ok(k + 1)
}

fn grid_doc(name: &str, fast: Axis, slow: Axis, fixed: Axis) -> Doc {
    let (f, s, x) = (fast.name(), slow.name(), fixed.name());
    let nf = format!("n{f}");
    let ns = format!("n{s}");
    let keys: Vec<(String, &str, &str, String)> = vec![
        (f.into(), "[from, to]", "µm", format!("{f} range (columns)")),
        (s.into(), "[from, to]", "µm", format!("{s} range (rows)")),
        (nf.clone(), "int", "", format!("points along {f}, 1 ≤ {nf} ≤ {MAX_POINTS_PER_AXIS}")),
        (ns.clone(), "int", "", format!("points along {s}, 1 ≤ {ns} ≤ {MAX_POINTS_PER_AXIS}")),
        (x.into(), "float", "µm", format!("optional: {x} held during the scan (default: where it is)")),
        (DWELL.name.into(), "float", "s", dwell_help()),
        (REL.name.into(), "bool", "", "positions relative to the start, return to start at the end; default false".into()),
        (SNAKE.name.into(), "bool", "", "alternate the direction of every other row (pixels stored in image order); default false".into()),
        (MODE.name.into(), "string", "", format!("\"points\" (default: move, settle, read at every pixel) or \"raster\": hardware-timed lines, the {f} axis sweeping each row at pitch/dwell under the controller's clock, the digitiser's samples binned by the stage's measured position (needs a wave generator and a triggered digitiser: the simulator, PI GCS + Red Pitaya)")),
        (SAMPLES_PER_PIXEL.name.into(), "int", "", format!("raster: digitiser samples asked per pixel, ≥ 1; default {DEFAULT_SAMPLES_PER_PIXEL}")),
    ];
    let keys_ref: Vec<(&str, &str, &str, &str)> = keys
        .iter()
        .map(|(a, b, c, d)| (a.as_str(), *b, *c, d.as_str()))
        .collect();
    Doc::func(name)
        .map("plan", &format!("the {f}{s} raster"), &keys_ref)
        .returns("Scan", "sx, sy, sz images (columns along x-axis name, rows along the other), metadata; autosaved")
        .summary(&format!("2-D scan over {f} (columns) and {s} (rows), {x} fixed"))
        .help(&format!(
            "The whole plan is checked against the soft limits and the step-size rule before the first \
             move (a raster: also every line's waveform, ramps included, and the line speed), and the ETA is \
             printed. A progress bar shows when stderr is a terminal. {STOP_RULE} Every scan is autosaved in \
             the session folder (`scan.path`)."
        ))
        .example(
            &format!("let s = scan_{f}{s}(#{{{f}: [-1.0, 1.0], {s}: [-0.5, 0.5], {nf}: 21, {ns}: 11, dwell: 0.001}}); [s.cols, s.rows, s.status]"),
            "[21, 11, \"complete\"]",
        )
        .example(
            &format!("scan_{f}{s}(#{{{f}: [-1.0, 1.0], {s}: [0, 1], {nf}: 0, {ns}: 3}})"),
            &format!("error: scan_{f}{s}: {nf} = 0 is out of range: 1 ≤ {nf} ≤ 4096"),
        )
}

fn register_grid(r: &mut Registrar, fast: Axis, slow: Axis, fixed: Axis) {
    let name = format!("scan_{}{}", fast.name(), slow.name());
    let mut d = grid_doc(&name, fast, slow, fixed);
    if fast == Axis::X && slow == Axis::Y {
        d = d
            .example(
                "let s = scan_xy(#{x: [-0.5, 0.5], y: [-0.5, 0.5], nx: 5, ny: 4, snake: true}); s.sx.at(1, 0) == scan_xy(#{x: [-0.5, 0.5], y: [-0.5, 0.5], nx: 5, ny: 4}).sx.at(1, 0)",
                "true",
            )
            .example("mv(#{x: 1.0}); scan_xy(#{x: [-0.5, 0.5], y: [-0.5, 0.5], nx: 5, ny: 5, rel: true}); pos().x", "1.0")
            .example("scan_xy(#{x: [45.0, 55.0], y: [0, 1], nx: 11, ny: 2})", "error: point 7 of 22: x = 51 µm is above the soft limit x ≤ 50 µm")
            .example("scan_xy(#{x: [0, 1], y: [0, 1], nx: 2, ny: 2, speed: 3})", "error: unknown key `speed`");
    }
    let spec = d.spec();
    r.bind_ctx(d, |c| {
        move |m: Map| scan_grid(&c, &spec, [fast, slow, fixed], &m)
    });
}

binding_list! { pub fn register { bind_scan_planes, bind_spec_scans, bind_mesh, bind_scan_files } }

/// `scan_line` and the plane scans `scan_xy`, `scan_xz`, `scan_yz`.
fn bind_scan_planes(r: &mut Registrar) {
    let d = Doc::func("scan_line")
        .map(
            "plan",
            "the line",
            &[
                AXIS.doc("\"x\", \"y\" or \"z\""),
                FROM.doc("first position"),
                TO.doc("last position"),
                N.doc(&format!("number of points, 1 ≤ n ≤ {MAX_POINTS_PER_AXIS}")),
                DWELL.doc(&dwell_help()),
                REL.doc("from/to relative to the start, return to start at the end; default false"),
            ],
        )
        .returns("Scan", "one row (the line) of sx, sy, sz; autosaved")
        .summary("line scan along one axis")
        .help(&format!("Same safety rules as scan_xy (pre-flight, ETA, autosave). Take the profile with `scan.sx.row(0)`. {STOP_RULE}"))
        .example("let s = scan_line(#{axis: \"x\", from: -1.0, to: 1.0, n: 41}); [s.rows, s.cols, s.x[20]]", "[1, 41, 0.0]")
        .example("scan_line(#{axis: \"q\", from: 0, to: 1, n: 3})", "error: axis = q is not one of")
        .example("scan_line(#{axis: \"z\", from: 0, to: 1, n: 3, dwell: -1})", "error: scan_line: dwell = -1 is out of range: 0 ≤ dwell ≤ 60 s");
    r.bind_map(d, scan_line);

    register_grid(r, Axis::X, Axis::Y, Axis::Z);
    register_grid(r, Axis::X, Axis::Z, Axis::Y);
    register_grid(r, Axis::Y, Axis::Z, Axis::X);

    // SPEC vocabulary
}

/// SPEC's line scans: `ascan`, `dscan`, `a2scan`, `d2scan`.
fn bind_spec_scans(r: &mut Registrar) {
    // each form with its example: (name, relative, (code, expected))
    for (name, rel, (code, expect)) in [
        ("ascan", false, ("let s = ascan(\"y\", -1, 1, 20, 0.001); [s.cols, s.x[20], pos().y]", "[21, 1.0, 1.0]")),
        ("dscan", true, ("mv(#{x: 2.0}); let s = dscan(\"x\", -0.5, 0.5, 10, 0.001); [s.cols, s.x[0], pos().x]", "[11, 1.5, 2.0]")),
    ] {
        let what = if rel { "relative" } else { "absolute" };
        let d = Doc::func(name)
            .arg("axis", "string", "", "\"x\", \"y\" or \"z\"")
            .arg("from", "float", "µm", if rel { "start, relative to the current position" } else { "start position" })
            .arg("to", "float", "µm", if rel { "end, relative to the current position" } else { "end position" })
            .arg("intervals", "int", "", "number of intervals (SPEC): intervals + 1 points")
            .arg("dwell", "float", "s", "count time per point")
            .returns("Scan", "a line scan (one row); autosaved")
            .summary(&format!("SPEC {what} line scan: intervals + 1 points from `from` to `to`"))
            .help(&format!(
                "As in SPEC, the fourth argument counts intervals, so `{name}(\"x\", -1, 1, 20, 0.01)` measures 21 points. {}",
                where_the_stage_ends(rel)
            ))
            .example(code, expect)
            .example(
                &format!("{name}(\"x\", 0, 1)"),
                &format!("error: usage: {name}(axis, from, to, intervals, dwell)"),
            );
        let spec = d.spec();
        r.bind_ctx(d, |c| {
            move |axis: Dynamic, from: Dynamic, to: Dynamic, n: Dynamic, dwell: Dynamic| {
                spec_line(&c, &spec, rel, [&axis, &from, &to], &n, &dwell)
            }
        });
    }
    for (name, rel, (code, expect)) in [
        ("a2scan", false, ("let s = a2scan(\"x\", 0, 1, \"y\", 0, -2, 4, 0.001); [s.cols, s.x[2], pos().x, pos().y]", "[5, 0.5, 1.0, -2.0]")),
        ("d2scan", true, ("mv(#{x: 2.0, y: 1.0}); let s = d2scan(\"x\", -0.5, 0.5, \"y\", 0.0, 1.0, 4, 0.001); [s.cols, s.x[4], pos().y]", "[5, 2.5, 1.0]")),
    ] {
        let what = if rel { "relative" } else { "absolute" };
        let d = Doc::func(name)
            .arg("axis1", "string", "", "first motor: \"x\", \"y\" or \"z\" (the image's columns follow it)")
            .arg("from1", "float", "µm", "")
            .arg("to1", "float", "µm", "")
            .arg("axis2", "string", "", "second motor, moved together with the first")
            .arg("from2", "float", "µm", "")
            .arg("to2", "float", "µm", "")
            .arg("intervals", "int", "", "number of intervals (SPEC): intervals + 1 points")
            .arg("dwell", "float", "s", "count time per point")
            .returns("Scan", "a line scan (one row) along both axes; autosaved (meta.plan.with is the second motor)")
            .summary(&format!("SPEC {what} two-motor line scan: both axes step together, intervals + 1 points"))
            .help(&format!(
                "Point i is at from1 + i·(to1 − from1)/intervals on axis1 and from2 + i·(to2 − from2)/intervals on \
                 axis2: a line across the sample at any angle. {} Every point is checked against the soft \
                 limits before the first move, like every scan.",
                where_the_stage_ends(rel)
            ))
            .example(code, expect)
            .example(
                &format!("{name}(\"x\", 0, 1, \"x\", 0, 1, 4, 0.001)"),
                &format!("error: {name}: both motors are x"),
            )
            .example(
                &format!("{name}(\"x\", 0, 1)"),
                &format!(
                    "error: usage: {name}(axis1, from1, to1, axis2, from2, to2, intervals, dwell)"
                ),
            );
        let spec = d.spec();
        r.bind_ctx(d, |c| {
            move |a1: Dynamic,
                  f1: Dynamic,
                  t1: Dynamic,
                  a2: Dynamic,
                  f2: Dynamic,
                  t2: Dynamic,
                  n: Dynamic,
                  dwell: Dynamic| {
                spec_line2(&c, &spec, rel, [&a1, &f1, &t1], [&a2, &f2, &t2], &n, &dwell)
            }
        });
    }
}

/// SPEC's `mesh` and `dmesh`.
fn bind_mesh(r: &mut Registrar) {
    for (name, rel) in [("mesh", false), ("dmesh", true)] {
        let what = if rel { "relative" } else { "absolute" };
        let mut d = Doc::func(name)
            .arg("axis1", "string", "", "fast axis (columns)")
            .arg("from1", "float", "µm", "")
            .arg("to1", "float", "µm", "")
            .arg(
                "intervals1",
                "int",
                "",
                "intervals along axis1 (intervals1 + 1 points)",
            )
            .arg("axis2", "string", "", "slow axis (rows)")
            .arg("from2", "float", "µm", "")
            .arg("to2", "float", "µm", "")
            .arg("intervals2", "int", "", "intervals along axis2")
            .arg("dwell", "float", "s", "count time per point")
            .returns("Scan", "2-D scan; autosaved")
            .summary(&format!("SPEC {what} 2-D mesh scan (raster, axis1 fast)"));
        d = if rel {
            d.help(&format!("Positions relative to the start; returns to the start at the end. {STOP_RULE}"))
                .example("let s = dmesh(\"x\", -0.5, 0.5, 4, \"z\", -0.2, 0.2, 2, 0.001); [s.cols, s.rows, s.axes, pos().z]", "[5, 3, [\"x\", \"z\"], 0.0]")
        } else {
            d.help(&where_the_stage_ends(false)).example(
                "let s = mesh(\"x\", -1, 1, 10, \"y\", -1, 1, 5, 0.001); [s.cols, s.rows]",
                "[11, 6]",
            )
        };
        d = d.example(
            &format!("{name}(\"x\", 0, 1, 4, \"x\", 0, 1, 4, 0.001)"),
            "error: both scan axes are x",
        );
        let spec = d.spec();
        r.bind_ctx(d, |c| {
            move |a1: Dynamic,
                  f1: Dynamic,
                  t1: Dynamic,
                  n1: Dynamic,
                  a2: Dynamic,
                  f2: Dynamic,
                  t2: Dynamic,
                  n2: Dynamic,
                  dwell: Dynamic| {
                spec_mesh(
                    &c,
                    &spec,
                    rel,
                    [&a1, &f1, &t1, &n1],
                    [&a2, &f2, &t2, &n2],
                    &dwell,
                )
            }
        });
    }

    // files (.npz through data::npz)
}

/// A scan on disk: `Scan.save` and `load_scan`.
fn bind_scan_files(r: &mut Registrar) {
    r.bind_ctx(
        Doc::method("Scan", "save")
            .arg("path", "string", "", "file to write (never overwritten); relative: in the session folder, as every save")
            .returns("string", "the path written")
            .summary("save the scan to a file (temporary name + rename; refuses to overwrite)")
            .example("let s = scan_line(#{axis: \"x\", from: 0, to: 1, n: 3}); let p = s.path + \".copy.npz\"; s.save(p); load_scan(p).cols", "3")
            .example("let s = scan_line(#{axis: \"x\", from: 0, to: 1, n: 3}); s.save(s.path)", "error: exists; scans are never overwritten"),
        |c| move |s: &mut ScanRef, path: &str| save_scan(&c, s, path),
    );
    r.bind_ctx(
        Doc::func("load_scan")
            .arg(
                "path",
                "string",
                "",
                "a scan file written by autosave or scan.save",
            )
            .returns("Scan", "")
            .summary("load a saved scan (unmeasured pixels come back as NaN)")
            .example(
                "let s = scan_line(#{axis: \"x\", from: 0, to: 1, n: 3}); load_scan(s.path).x",
                "[0.0, 0.5, 1.0]",
            )
            .example(
                "load_scan(\"no/such/file.npz\")",
                "error: load_scan: no/such/file.npz",
            ),
        |c| move |path: &str| load_scan(&c, path),
    );
}

/// Paths are used as given (relative to the working directory).
/// A file to read: a relative path is looked up in the session folder first (where every
/// save puts it), then as given (the working directory).
fn resolve(c: &Ctx, path: &str) -> PathBuf {
    let p = PathBuf::from(path);
    if p.is_relative() && !p.starts_with(c.store.dir()) {
        let q = c.store.dir().join(&p);
        if q.exists() {
            return q;
        }
    }
    p
}

/// `scan_xy` / `scan_xz` / `scan_yz(plan)`: a 2-D grid, `axes` = [fast (columns), slow
/// (rows), fixed]; point by point (mode "points") or as a hardware-timed raster (mode
/// "raster", `samples_per_pixel` digitiser samples per pixel).
fn scan_grid(c: &Ctx, spec: &Spec, axes: [Axis; 3], m: &Map) -> RResult<ScanRef> {
    let [fast, slow, fixed] = axes;
    let (fk, sk, xk) = (fast.name(), slow.name(), fixed.name());
    let (nfk, nsk) = (format!("n{fk}"), format!("n{sk}"));
    let o = Opts::new(spec, m)?;
    let who = spec.name.as_str();
    let (f0, f1) = o.req_range(fk)?;
    let (s0, s1) = o.req_range(sk)?;
    let fsw = Sweep::new(who, fast, f0, f1, o.req_int(&nfk)?, &nfk).map_err(|e| e.0)?;
    let ssw = Sweep::new(who, slow, s0, s1, o.req_int(&nsk)?, &nsk).map_err(|e| e.0)?;
    let fixed_v = o.f64(xk)?.map(|v| vec![(fixed, v)]).unwrap_or_default();
    let raster = match o.string(MODE)?.as_deref() {
        None | Some("points") => {
            if o.has(SAMPLES_PER_PIXEL) {
                return fail(format!("{who}: samples_per_pixel is for mode \"raster\""));
            }
            None
        }
        Some("raster") => {
            let spp = o
                .int(SAMPLES_PER_PIXEL)?
                .unwrap_or(DEFAULT_SAMPLES_PER_PIXEL as i64);
            if !(1..=1_000_000).contains(&spp) {
                return fail(format!(
                    "{who}: samples_per_pixel = {spp} is out of range: 1 ≤ samples_per_pixel ≤ 1000000"
                ));
            }
            Some(RasterOptions {
                samples_per_pixel: spp as usize,
            })
        }
        Some(other) => {
            return fail(format!(
                "{who}: mode = {other:?} is not one of \"points\", \"raster\""
            ))
        }
    };
    let plan = Plan::grid(
        who,
        fsw,
        ssw,
        fixed_v,
        o.f64_or(DWELL, DEFAULT_DWELL_S)?,
        o.bool_or(REL, false)?,
        o.bool_or(SNAKE, false)?,
    )
    .map_err(|e| e.0)?;
    execute_mode(c, plan, raster)
}

/// `scan_line(plan)`: a line of n points from `from` to `to` (µm) along one axis.
fn scan_line(c: &Ctx, spec: &Spec, m: &Map) -> RResult<ScanRef> {
    let o = Opts::new(spec, m)?;
    let axis = match m.get(AXIS.name) {
        Some(a) => axis_arg("scan_line", a, &spec.usage)?,
        None => {
            return fail(format!(
                "scan_line: missing key `axis`; usage: {}",
                spec.usage
            ))
        }
    };
    let sw = Sweep::new(
        "scan_line",
        axis,
        o.req_f64(FROM)?,
        o.req_f64(TO)?,
        o.req_int(N)?,
        "n",
    )
    .map_err(|e| e.0)?;
    let plan = Plan::line(
        "scan_line",
        sw,
        o.f64_or(DWELL, DEFAULT_DWELL_S)?,
        o.bool_or(REL, false)?,
    )
    .map_err(|e| e.0)?;
    execute(c, plan)
}

/// SPEC's `ascan(axis, from, to, intervals, dwell)` (`rel` false) and `dscan` (`rel` true,
/// positions relative to the start, returning there): intervals + 1 points.
fn spec_line(
    c: &Ctx,
    spec: &Spec,
    rel: bool,
    [axis, from, to]: [&Dynamic; 3],
    n: &Dynamic,
    dwell: &Dynamic,
) -> RResult<ScanRef> {
    let who = spec.name.as_str();
    let axis = axis_arg(who, axis, &spec.usage)?;
    let n = intervals(who, "intervals", n)?;
    let sw = Sweep::new(
        who,
        axis,
        num(who, "from", from)?,
        num(who, "to", to)?,
        n,
        "points",
    )
    .map_err(|e| e.0)?;
    let plan = Plan::line(who, sw, num(who, "dwell", dwell)?, rel).map_err(|e| e.0)?;
    execute(c, plan)
}

/// SPEC's `a2scan(axis1, from1, to1, axis2, from2, to2, intervals, dwell)` (`rel` false) and
/// `d2scan` (`rel` true): two motors stepping together, intervals + 1 points.
fn spec_line2(
    c: &Ctx,
    spec: &Spec,
    rel: bool,
    [a1, f1, t1]: [&Dynamic; 3],
    [a2, f2, t2]: [&Dynamic; 3],
    n: &Dynamic,
    dwell: &Dynamic,
) -> RResult<ScanRef> {
    let who = spec.name.as_str();
    let n = intervals(who, "intervals", n)?;
    let sweep = |a: &Dynamic, f: &Dynamic, t: &Dynamic, k: &str| -> RResult<Sweep> {
        let axis = axis_arg(who, a, &spec.usage)?;
        Sweep::new(
            who,
            axis,
            num(who, &format!("from{k}"), f)?,
            num(who, &format!("to{k}"), t)?,
            n,
            "points",
        )
        .map_err(|e| e.0.into())
    };
    let first = sweep(a1, f1, t1, "1")?;
    let second = sweep(a2, f2, t2, "2")?;
    let plan = Plan::line2(who, first, second, num(who, "dwell", dwell)?, rel).map_err(|e| e.0)?;
    execute(c, plan)
}

/// SPEC's `mesh(axis1, from1, to1, intervals1, axis2, from2, to2, intervals2, dwell)` (`rel`
/// false) and `dmesh` (`rel` true): a 2-D raster, axis1 fast.
fn spec_mesh(
    c: &Ctx,
    spec: &Spec,
    rel: bool,
    [a1, f1, t1, n1]: [&Dynamic; 4],
    [a2, f2, t2, n2]: [&Dynamic; 4],
    dwell: &Dynamic,
) -> RResult<ScanRef> {
    let who = spec.name.as_str();
    let a1 = axis_arg(who, a1, &spec.usage)?;
    let a2 = axis_arg(who, a2, &spec.usage)?;
    // sweep k (1 fast, 2 slow): its arguments are named from{k}, to{k}, intervals{k}, points{k}
    let sweep = |axis, [f, t, n]: [&Dynamic; 3], k: &str| -> RResult<Sweep> {
        Sweep::new(
            who,
            axis,
            num(who, &format!("from{k}"), f)?,
            num(who, &format!("to{k}"), t)?,
            intervals(who, &format!("intervals{k}"), n)?,
            &format!("points{k}"),
        )
        .map_err(|e| e.0.into())
    };
    let s1 = sweep(a1, [f1, t1, n1], "1")?;
    let s2 = sweep(a2, [f2, t2, n2], "2")?;
    let plan =
        Plan::grid(who, s1, s2, vec![], num(who, "dwell", dwell)?, rel, false).map_err(|e| e.0)?;
    execute(c, plan)
}

/// `Scan.save(path)`: write the scan to a new file (temporary name + rename, never
/// overwriting); returns the path.
fn save_scan(c: &Ctx, s: &ScanRef, path: &str) -> RResult<String> {
    // the one rule of every save: relative paths in the session folder (docs/files.md)
    let p = super::console::output_location(c.store.dir(), "scan.save", path)?;
    crate::acquire::store::save_scan(&p, &s.scan)
        .map_err(|e| format!("scan.save: {}: {e}", p.display()))?;
    Ok(p.display().to_string())
}

/// `load_scan(path)`: a scan file written by autosave or `Scan.save` (unmeasured pixels NaN).
fn load_scan(c: &Ctx, path: &str) -> RResult<ScanRef> {
    let p = resolve(c, path);
    let s = crate::acquire::store::load_scan(&p).map_err(|e| {
        // the library's message names the file already: say it once
        let e = e.to_string();
        let shown = p.display().to_string();
        if e.contains(&shown) {
            format!("load_scan: {e}")
        } else {
            format!("load_scan: {shown}: {e}")
        }
    })?;
    Ok(ScanRef::new(s, Some(p.display().to_string())))
}
