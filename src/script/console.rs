//! The console family: the bindings of the session at the prompt (pwd, ls, notes, the scan
//! list, wm/lup, protocol_options and protocol_page: their machinery is in `protocols`), the
//! one rule for every saved output's path, and "did you mean" for misspelled names.

use super::ctx::Ctx;
pub use super::protocols::{
    module_protocols, property_hint, protocol_help, protocol_line, protocol_options, protocol_page,
    protocols_index, stdlib_dirs, stdlib_modules,
};
use super::registry::{binding_list, fail, Doc, RResult, Registrar};
use super::types::ScanRef;
pub use super::words::{
    did_you_mean, edit_distance, fmt_num, suggestion, user_type, user_type_name, user_words,
};
use rhai::{Array, Dynamic, Map, NativeCallContext};
use std::path::{Path, PathBuf};

fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// `(number, path)` of the scan files in the session folder, by number.
fn scan_files(dir: &Path) -> Vec<(u64, PathBuf)> {
    let mut v: Vec<(u64, PathBuf)> = std::fs::read_dir(dir)
        .map(|rd| {
            rd.flatten()
                .filter_map(|e| {
                    crate::data::session::scan_number(&e.file_name().to_string_lossy())
                        .map(|n| (n, e.path()))
                })
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// One session scan as `scans()` lists it.
fn scan_entry(path: &Path, number: u64) -> Map {
    let mut m = Map::new();
    m.insert("number".into(), Dynamic::from_int(number as i64));
    m.insert("path".into(), path.display().to_string().into());
    match crate::data::npz::load_scan(path) {
        Ok(sc) => {
            let meta = &sc.meta;
            m.insert("kind".into(), crate::analysis::kind::plane(&sc.sx).into());
            m.insert("status".into(), sc.status.as_str().to_string().into());
            let s = |v: &serde_json::Value| -> Dynamic {
                v.as_str().map_or(Dynamic::UNIT, |x| x.to_string().into())
            };
            m.insert("time".into(), s(&meta["time"]["wall_start"]));
            m.insert("protocol".into(), s(&meta["protocol"]["name"]));
            let notes: Array = meta["notes"]
                .as_array()
                .map(|a| {
                    a.iter()
                        .filter_map(|n| n.as_str())
                        .map(|n| n.to_string().into())
                        .collect()
                })
                .unwrap_or_default();
            m.insert("notes".into(), notes.into());
            m.insert(
                "shape".into(),
                format!("{}×{}", sc.sx.cols(), sc.sx.rows()).into(),
            );
        }
        Err(e) => {
            m.insert("error".into(), e.to_string().into());
        }
    }
    m
}

/// The chosen channel of a line scan, as (t, v).
fn line_channel(
    who: &str,
    sc: &super::types::ScanRef,
    channel: &str,
) -> RResult<(Vec<f64>, Vec<f64>)> {
    let img = match channel {
        "sx" => &sc.scan.sx,
        "sy" => &sc.scan.sy,
        "sz" => &sc.scan.sz,
        other => {
            return fail(format!(
                "{who}: channel = {other:?} is not one of \"sx\", \"sy\", \"sz\"{}",
                suggestion(other, ["sx", "sy", "sz"])
            ))
        }
    };
    if img.rows() == 1 {
        Ok((img.x.clone(), img.data.row(0).to_vec()))
    } else if img.cols() == 1 {
        Ok((img.y.clone(), img.data.column(0).to_vec()))
    } else {
        fail(format!(
            "{who}: this is an {} scan; {who} needs a line scan (scan_line, ascan, dscan, lup)",
            crate::analysis::kind::plane(img)
        ))
    }
}

binding_list! {
    pub fn register {
        bind_session_files, bind_spec_moves, bind_lup, bind_line_statistics, bind_scan_kind, bind_protocol_pages
    }
}

/// `pwd`, `ls`, `note`, `scans`: the session folder and what is in it.
fn bind_session_files(r: &mut Registrar) {
    let d = Doc::func("pwd")
        .returns("string", "the session folder")
        .summary("the session folder: where scans, figures, templates and the session log go")
        .example("pwd() == status().data_dir", "true");
    r.bind_ctx(d, |c| move || pwd(&c));

    let d = Doc::func("ls")
        .returns("array", "file names in the session folder, sorted")
        .summary("list the session folder")
        .example("scan_line(#{axis: \"x\", from: -0.5, to: 0.5, n: 3, dwell: 0.0001}); ls().filter(|f| f.starts_with(\"scan_\"))", "[\"scan_0001.npz\"]");
    r.bind_ctx(d, |c| move || ls(&c));

    let d = Doc::func("note")
        .arg("text", "string", "", "a note (sample, condition, what you are doing)")
        .returns("array", "all notes so far")
        .summary("add a note to the metadata of every later scan (meta.notes); note() with \"\" clears them")
        .example("note(\"sample 3, 110 nm PS\"); note(\"after refocus\").len()", "2")
        .example("note(\"a\"); note(\"\").len()", "0");
    r.bind_ctx(d, |c| move |text: &str| note(&c, text));

    let d = Doc::func("scans")
        .map("filter", "optional", &[
            ("kind", "string", "", "optional: \"XY\", \"XZ\", \"YZ\" or \"line\""),
            ("protocol", "string", "", "optional: part of the protocol name (\"focus\")"),
            ("note", "string", "", "optional: part of a note"),
            ("since", "string", "", "optional: ISO time; scans started at or after it"),
        ])
        .returns("array", "#{number, path, kind, status, time, protocol, notes, shape} per scan, oldest first")
        .summary("list and search the session's scans by kind, time, protocol and notes")
        .example("connect(#{backend: \"mock\"}); note(\"test\"); scan_xz(#{x: [-0.5, 0.5], z: [-0.5, 0.5], nx: 5, nz: 5, dwell: 0.0001}); let l = scans(#{kind: \"XZ\"}); [l.len(), l[0].notes[0]]", "[1, \"test\"]")
        .example("scans(#{knd: \"XY\"})", "error: did you mean `kind`?");
    r.bind_ctx(d, |c| move |filter: Map| scans(&c, &filter));
    let c = r.ctx();
    r.overload("scans", move || scans_all(&c));

    // SPEC words
}

/// SPEC's `wm`, `umv`, `umvr`: where the motors are, moves that print as they go.
fn bind_spec_moves(r: &mut Registrar) {
    let d = Doc::func("wm")
        .summary("SPEC's `wm` (where motor): print the position of every axis (as wa)")
        .example("wm()", "()");
    r.bind(d, |ctx: NativeCallContext| wm(&ctx));
    for (name, base, what) in [("umv", "mv", "absolute"), ("umvr", "mvr", "relative")] {
        let d = Doc::func(name)
            .map(
                "target",
                &format!("{what} move, any subset of the axes"),
                &[
                    ("x", "float", "µm", "optional"),
                    ("y", "float", "µm", "optional"),
                    ("z", "float", "µm", "optional"),
                ],
            )
            .summary(&format!(
                "SPEC's `{name}`: {base} and then show where the stage is"
            ))
            .example(&format!("{name}(#{{x: 0.5}}); pos().x"), "0.5");
        r.bind(d, move |ctx: NativeCallContext, m: Map| {
            move_and_show(&ctx, base, m)
        });
    }
}

/// SPEC's `lup`: a relative line scan that returns to its start.
fn bind_lup(r: &mut Registrar) {
    let d = Doc::func("lup")
        .arg("axis", "string", "", "\"x\", \"y\" or \"z\"")
        .arg(
            "from",
            "float",
            "µm",
            "start, relative to the current position",
        )
        .arg("to", "float", "µm", "end, relative to the current position")
        .arg(
            "intervals",
            "int",
            "",
            "number of intervals: intervals + 1 points",
        )
        .arg("dwell", "float", "s", "count time per point")
        .returns(
            "Scan",
            "a line scan; autosaved; the stage returns to the start",
        )
        .summary("SPEC's `lup` (line-up scan) = dscan")
        .example(
            "mv(#{x: 2.0}); let s = lup(\"x\", -0.5, 0.5, 10, 0.001); [s.cols, pos().x]",
            "[11, 2.0]",
        );
    r.bind(
        d,
        |ctx: NativeCallContext, a: Dynamic, f: Dynamic, t: Dynamic, n: Dynamic, d: Dynamic| {
            lup(&ctx, a, f, t, n, d)
        },
    );
}

/// SPEC's `peak`, `cen`, `com`, `fwhm` of a line scan.
fn bind_line_statistics(r: &mut Registrar) {
    for (name, what) in [
        (
            "peak",
            "position of the largest deviation from the line's median",
        ),
        ("cen", "centre: the middle of the half-maximum crossings"),
        ("com", "centre of mass of |v − median|"),
        ("fwhm", "full width at half maximum of |v − median|"),
    ] {
        let d = Doc::func(name)
            .arg("scan", "Scan", "", "a line scan (scan_line, ascan, dscan, lup)")
            .opt("channel", "string", "", &format!("\"sx\", \"sy\" or \"sz\" (default {LINE_CHANNEL:?})"))
            .returns("float", "µm along the scanned axis")
            .summary(&format!("SPEC's `{name}` after a line scan: {what}"))
            .help("QPD signals are signed and sit on an offset: the statistics use w = |v − median(v)| of the chosen channel.")
            .example(&format!("mv(#{{x: 0.0}}); let s = dscan(\"x\", -1.0, 1.0, 40, 0.001); {name}(s, \"sx\") < 1.0"), "true")
            .example(&format!("{name}(scan_xy(#{{x: [-0.5, 0.5], y: [-0.5, 0.5], nx: 5, ny: 5}}))"), "error: this is an XY scan");
        r.bind(d, move |sc: ScanRef, channel: &str| {
            line_statistic(name, &sc, channel)
        });
        r.overload(name, move |sc: ScanRef| {
            line_statistic(name, &sc, LINE_CHANNEL)
        });
    }
}

/// `Scan.kind`: what kind of scan this is.
fn bind_scan_kind(r: &mut Registrar) {
    let d = Doc::property("Scan", "kind")
        .returns("string", "\"XY\", \"XZ\", \"YZ\" or \"line\"")
        .summary("what kind of scan this is (from its axes); analyses refuse the wrong kind, naming it")
        .example("connect(#{backend: \"mock\"}); scan_xz(#{x: [-0.5, 0.5], z: [-0.5, 0.5], nx: 5, nz: 5, dwell: 0.0001}).kind", "\"XZ\"")
        .example("connect(#{backend: \"mock\"}); scan_line(#{axis: \"x\", from: -0.5, to: 0.5, n: 5, dwell: 0.0001}).kind", "\"line\"");
    r.getter(d, |s: &mut ScanRef| scan_kind(s));
    let c = r.ctx();
    r.overload(
        "save",
        move |t: &mut super::types::TemplateRef, path: &str, m: Map| {
            save_template_with(&c, t, path, &m)
        },
    );
}

/// `protocol_options`, `protocol_page`: a protocol's declared options and its help page.
fn bind_protocol_pages(r: &mut Registrar) {
    let d = Doc::func("protocol_options")
        .arg("decl", "map", "", "the protocol's declaration #{name, summary, usage, args: [#{key, ty, unit, default, min, max, one_of, required, doc}], returns, saves, example}")
        .arg("opts", "map", "", "the options the user passed")
        .returns("map", "the options, checked, with the defaults filled in")
        .summary("check a protocol's options against its declaration (unknown keys, types, ranges) and fill in defaults")
        .help("Used by every stdlib protocol so that its options are checked as strictly as a binding's: an unknown key is refused with a \"did you mean\", a value outside [min, max] with the allowed range and unit. The same declaration makes the protocol's help page (help(\"calibrate\")).")
        .example("protocol_options(#{name: \"p\", args: [#{key: \"dwell\", ty: \"float\", unit: \"s\", \"default\": 0.01, min: 1e-5, max: 10.0}]}, #{}).dwell", "0.01")
        .example("protocol_options(#{name: \"p\", args: [#{key: \"dwell\", ty: \"float\", unit: \"s\", \"default\": 0.01}]}, #{dwel: 0.001})", "error: unknown option `dwel`; did you mean `dwell`?")
        .example("protocol_options(#{name: \"p\", args: [#{key: \"dwell\", ty: \"float\", unit: \"s\", min: 1e-5, max: 10.0}]}, #{dwell: 20})", "error: dwell = 20 s is out of range; allowed: [0.00001, 10] s");
    r.bind(d, |decl: Map, opts: Dynamic| protocol_options(&decl, &opts));

    let d = Doc::func("protocol_page")
        .arg("decls", "map | array", "", "one protocol declaration or an array of them")
        .returns("string", "the help page(s)")
        .summary("the help page of a protocol, made from its declaration (what `calibrate::help()` returns)")
        .example("protocol_page(#{name: \"p::run\", summary: \"does p\", args: [#{key: \"n\", ty: \"int\", \"default\": 3, doc: \"points\"}]}).contains(\"default 3\")", "true");
    r.bind(d, |decls: Dynamic| protocol_pages(&decls));
}

/// The channel the SPEC line statistics (`peak`, `cen`, `com`, `fwhm`) read when none is given.
const LINE_CHANNEL: &str = "sz";

/// `pwd()`: the session folder.
fn pwd(c: &Ctx) -> String {
    c.store.dir().display().to_string()
}

/// `ls()`: the file names in the session folder, sorted (empty if it cannot be read).
fn ls(c: &Ctx) -> Array {
    let mut v: Vec<String> = std::fs::read_dir(c.store.dir())
        .map(|rd| {
            rd.flatten()
                .map(|e| e.file_name().to_string_lossy().to_string())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v.into_iter().map(Dynamic::from).collect()
}

/// `note(text)`: add a note for the metadata of later scans (blank text clears them); returns
/// all notes.
fn note(c: &Ctx, text: &str) -> Array {
    let mut n = lock(&c.notes);
    if text.trim().is_empty() {
        n.clear();
    } else {
        n.push(text.to_string());
    }
    n.iter().map(|s| Dynamic::from(s.clone())).collect()
}

/// `scans(#{kind, protocol, note, since})`: the session's scans that match every given filter,
/// oldest first.
fn scans(c: &Ctx, filter: &Map) -> RResult<Array> {
    let keys = ["kind", "protocol", "note", "since"];
    for k in filter.keys() {
        if !keys.contains(&k.as_str()) {
            return fail(format!(
                "scans: unknown key `{k}`{}; allowed keys: {}",
                suggestion(k, keys),
                keys.join(", ")
            ));
        }
    }
    let get = |k: &str| filter.get(k).map(|v| v.to_string());
    let files = scan_files(c.store.dir());
    let mut out = Array::new();
    for (n, p) in files {
        let m = scan_entry(&p, n);
        let field = |k: &str| m.get(k).map(|v| v.to_string()).unwrap_or_default();
        if let Some(k) = get("kind") {
            if !field("kind").eq_ignore_ascii_case(&k) {
                continue;
            }
        }
        if let Some(pr) = get("protocol") {
            if !field("protocol").contains(&pr) {
                continue;
            }
        }
        if let Some(nt) = get("note") {
            let has = m
                .get("notes")
                .and_then(|a| {
                    a.read_lock::<Array>()
                        .map(|a| a.iter().any(|x| x.to_string().contains(&nt)))
                })
                .unwrap_or(false);
            if !has {
                continue;
            }
        }
        if let Some(since) = get("since") {
            if field("time") < since {
                continue;
            }
        }
        out.push(m.into());
    }
    Ok(out)
}

/// `scans()`: every scan of the session, oldest first.
fn scans_all(c: &Ctx) -> RResult<Array> {
    let files = scan_files(c.store.dir());
    Ok(files
        .into_iter()
        .map(|(n, p)| scan_entry(&p, n).into())
        .collect())
}

/// `wm()`: SPEC's where-motor, which is `wa()`.
fn wm(ctx: &NativeCallContext) -> RResult<()> {
    ctx.call_native_fn::<()>("wa", ())
}

/// `umv` / `umvr`: the move `base` (`mv` / `mvr`), then `wa()`.
fn move_and_show(ctx: &NativeCallContext, base: &str, m: Map) -> RResult<()> {
    let _ = ctx.call_native_fn::<Dynamic>(base, (m,))?;
    ctx.call_native_fn::<()>("wa", ())
}

/// `lup(axis, from, to, intervals, dwell)`: SPEC's line-up scan, which is `dscan`.
fn lup(
    ctx: &NativeCallContext,
    a: Dynamic,
    f: Dynamic,
    t: Dynamic,
    n: Dynamic,
    d: Dynamic,
) -> RResult<Dynamic> {
    ctx.call_native_fn::<Dynamic>("dscan", (a, f, t, n, d))
}

/// `peak` / `cen` / `com` / `fwhm` (`name`) of a line scan's `channel`, in µm along the scanned
/// axis (statistics of w = |v − median(v)|).
fn line_statistic(name: &str, sc: &ScanRef, channel: &str) -> RResult<f64> {
    let (t, v) = line_channel(name, sc, channel)?;
    let s = crate::analysis::spec::line_stats(&t, &v).map_err(|e| format!("{name}: {e}"))?;
    Ok(match name {
        "peak" => s.peak,
        "cen" => s.cen,
        "com" => s.com,
        _ => s.fwhm,
    })
}

/// `scan.kind`: "XY", "XZ", "YZ" or "line", from the scan's axes.
fn scan_kind(s: &ScanRef) -> String {
    crate::analysis::kind::plane(&s.scan.sx)
}

/// `template.save(path, #{overwrite})`: check the one option, then [`save_template`].
fn save_template_with(
    c: &Ctx,
    t: &super::types::TemplateRef,
    path: &str,
    m: &Map,
) -> RResult<String> {
    for k in m.keys() {
        if k.as_str() != "overwrite" {
            return fail(format!(
                "save: unknown key `{k}`{}; allowed keys: overwrite",
                suggestion(k, ["overwrite"])
            ));
        }
    }
    let ow = match m.get("overwrite") {
        None => false,
        Some(v) => v
            .as_bool()
            .map_err(|_| format!("save: overwrite must be true or false, got {v}"))?,
    };
    save_template(c, t, path, ow)
}

/// `protocol_page(decls)`: the help page of one declaration, or the pages of an array of them.
fn protocol_pages(decls: &Dynamic) -> RResult<String> {
    if let Some(m) = decls.read_lock::<Map>() {
        return protocol_page(&m);
    }
    let Some(a) = decls.read_lock::<Array>() else {
        return fail(format!(
            "protocol_page: decls must be a map or an array of maps, got {}",
            user_type_name(decls)
        ));
    };
    let mut pages = vec![];
    for d in a.iter() {
        let Some(m) = d.read_lock::<Map>() else {
            return fail("protocol_page: every declaration must be a map");
        };
        pages.push(protocol_page(&m)?);
    }
    Ok(pages.join("\n"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edit_distance_closed_cases() {
        assert_eq!(edit_distance("dwel", "dwell"), 1);
        assert_eq!(edit_distance("scna_xy", "scan_xy"), 2);
        assert_eq!(edit_distance("", "abc"), 3);
        assert_eq!(edit_distance("kitten", "sitting"), 3);
        assert_eq!(did_you_mean("pth", ["path", "beads", "n"]), vec!["path"]);
        assert_eq!(did_you_mean("axes", ["axis", "half_um"]), vec!["axis"]);
        assert!(did_you_mean("zzzzzz", ["path", "beads"]).is_empty());
        assert_eq!(did_you_mean("sxx", ["sx", "sy", "sz", "save"]), vec!["sx"]);
    }

    #[test]
    fn rust_paths_become_user_words() {
        assert_eq!(
            user_words("Function not found: measure_filament (bfpscope::script::types::ScanRef, &str | ImmutableString | String)"),
            "Function not found: measure_filament (Scan, string)"
        );
        assert_eq!(user_words("focus::search failed"), "focus::search failed");
        assert_eq!(user_type("bfpscope::script::types::CurveRef"), "AngleCurve");
    }

    #[test]
    fn numbers_for_people() {
        assert_eq!(fmt_num(0.049999999999999996), "0.05");
        assert_eq!(fmt_num(3.2), "3.2");
        assert_eq!(fmt_num(65.0), "65");
        assert_eq!(fmt_num(1e-5), "0.00001");
        assert_eq!(fmt_num(1234567.0), "1.23457e6");
        assert_eq!(fmt_num(-0.000123456789), "-0.000123457");
    }
}

/// The one place every saved output (figure, CSV, TIFF, template, protocol output) gets its
/// path: a relative path resolves inside the session folder (unless it already starts with
/// it); an existing file is never replaced unless `overwrite` — the next free numbered name
/// `stem_0002.ext`, `stem_0003.ext`, … is used instead (as scans are numbered); parent folders
/// are created. Returns the path to write.
pub fn output_path(session: &Path, who: &str, path: &str, overwrite: bool) -> RResult<PathBuf> {
    let p = output_location(session, who, path)?;
    if overwrite || !p.exists() {
        return Ok(p);
    }
    let stem = p
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("out")
        .to_string();
    let ext = p
        .extension()
        .and_then(|s| s.to_str())
        .map(|e| format!(".{e}"))
        .unwrap_or_default();
    for n in 2..100_000u32 {
        let q = p.with_file_name(format!("{stem}_{n:04}{ext}"));
        if !q.exists() {
            return Ok(q);
        }
    }
    fail(format!("{who}: no free numbered name for {}", p.display()))
}

/// Where a file a script writes goes — the one rule of every save (figures, CSV, TIFF,
/// templates, `scan.save`): a relative path resolves inside the session folder, whose missing
/// subfolders are created; a path outside the session folder must name an existing folder
/// (nothing is created outside the session folder). Numbering is the caller's
/// ([`output_path`]; `scan.save` refuses an existing file instead).
pub fn output_location(session: &Path, who: &str, path: &str) -> RResult<PathBuf> {
    if path.trim().is_empty() {
        return fail(format!("{who}: path is empty"));
    }
    let p = Path::new(path);
    let p = if p.is_absolute() || p.starts_with(session) {
        p.to_path_buf()
    } else {
        session.join(p)
    };
    if let Some(dir) = p.parent().filter(|d| !d.as_os_str().is_empty()) {
        if !dir.is_dir() {
            if dir.exists() {
                return fail(format!("{who}: {} is not a folder", dir.display()));
            }
            if !p.starts_with(session) {
                return fail(format!(
                    "{who}: folder {} does not exist; outside the session folder ({}) no folder is created: create it first, or give a path relative to the session folder",
                    dir.display(),
                    session.display()
                ));
            }
            std::fs::create_dir_all(dir)
                .map_err(|e| format!("{who}: cannot create folder {}: {e}", dir.display()))?;
        }
    }
    Ok(p)
}

#[cfg(test)]
mod output_tests {
    use super::output_path;

    #[test]
    fn outputs_are_numbered_not_overwritten_and_live_in_the_session() {
        let dir = std::env::temp_dir().join(format!("bfpscope-out-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let a = output_path(&dir, "t", "fig.png", false).unwrap();
        assert_eq!(a, dir.join("fig.png"));
        std::fs::write(&a, "1").unwrap();
        let b = output_path(&dir, "t", "fig.png", false).unwrap();
        assert_eq!(b, dir.join("fig_0002.png"));
        std::fs::write(&b, "2").unwrap();
        assert_eq!(
            output_path(&dir, "t", "fig.png", false).unwrap(),
            dir.join("fig_0003.png")
        );
        assert_eq!(
            output_path(&dir, "t", "fig.png", true).unwrap(),
            dir.join("fig.png")
        );
        // a path already inside the session folder is not nested again; subfolders are made
        let inside = dir.join("sub/x.csv");
        assert_eq!(
            output_path(&dir, "t", inside.to_str().unwrap(), false).unwrap(),
            inside
        );
        assert!(dir.join("sub").is_dir());
        assert!(output_path(&dir, "t", " ", false)
            .unwrap_err()
            .to_string()
            .contains("path is empty"));
        let _ = std::fs::remove_dir_all(&dir);
    }
}

/// `template.save(path[, #{overwrite}])`: JSON with the script's provenance, through
/// [`output_path`]; prints where it went.
pub fn save_template(
    c: &super::ctx::Ctx,
    t: &super::types::TemplateRef,
    path: &str,
    overwrite: bool,
) -> RResult<String> {
    let who = "save";
    let p = output_path(c.store.dir(), who, path, overwrite)?;
    let mut v = serde_json::to_value(&*t.0).map_err(|e| format!("{who}: {e}"))?;
    v["provenance"] = c.provenance();
    let text = serde_json::to_string_pretty(&v).map_err(|e| format!("{who}: {e}"))?;
    std::fs::write(&p, text).map_err(|e| format!("{who}: {}: {e}", p.display()))?;
    c.print(&format!("saved {}", p.display()));
    Ok(p.display().to_string())
}
