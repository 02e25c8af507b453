//! The console family: protocol option declarations (`protocol_options`, `protocol_page`),
//! the help pages of the stdlib protocols, and "did you mean" for misspelled names.
//!
//! A stdlib protocol declares its options once, as a map returned by a function of its module
//! (`fn reference_beads_decl() { #{name, summary, usage, args: [...], returns, saves, example} }`)
//! and lists its declarations in `fn protocols() { [reference_beads_decl()] }`. The protocol
//! checks its options with `let o = protocol_options(reference_beads_decl(), opts);` (unknown
//! keys, wrong types and out-of-range values are refused with the bindings' wording; defaults
//! are filled in), `help("calibrate")` and `calibrate::help()` print the page made from the same
//! declaration.
//!
//! An argument declaration: `#{key, ty, unit, default, min, max, one_of, required, doc}`; `ty`
//! is `float` (int accepted), `int`, `bool`, `string`, `array`, `map`, `[from, to]`, or any
//! other type name (`Template`, `AngleCurve`: checked by Rhai's type name).

use super::ctx::Ctx;
use super::registry::{fail, to_f64, Doc, RResult, Registrar};
use super::types::ScanRef;
pub use super::words::{
    did_you_mean, edit_distance, fmt_num, suggestion, user_type, user_type_name, user_words,
};
use rhai::{Array, Dynamic, Engine, Map, NativeCallContext};
use std::path::{Path, PathBuf};

fn get_str(m: &Map, k: &str) -> String {
    m.get(k).map(|v| v.to_string()).unwrap_or_default()
}

/// "Unknown property 'sxx' - a getter is not registered for type 'Scan'" → "Scan has no
/// property `sxx`; did you mean `sx`?" (properties and methods of that type from the
/// declarations); other messages unchanged.
pub fn property_hint(msg: &str, docs: &[Doc]) -> String {
    let Some(rest) = msg.strip_prefix("Unknown property '") else {
        return msg.to_string();
    };
    let Some((name, rest)) = rest.split_once('\'') else {
        return msg.to_string();
    };
    let ty = rest
        .rsplit_once("for type '")
        .map(|(_, t)| user_type(t.trim_end_matches('\'')))
        .unwrap_or_default();
    use super::registry::Kind;
    let members: Vec<&str> = docs
        .iter()
        .filter(|d| match &d.kind {
            Kind::Property { ty: t } | Kind::Method { ty: t } => *t == ty,
            _ => false,
        })
        .map(|d| d.name.as_str())
        .collect();
    format!(
        "{ty} has no property `{name}`{}; its properties and methods: {}",
        suggestion(name, members.iter().copied()),
        members.join(", ")
    )
}

fn show_value(v: &Dynamic) -> String {
    match to_f64(v) {
        Some(x) if !v.is_string() => fmt_num(x),
        _ => super::show(v),
    }
}

fn show_default(v: &Dynamic) -> String {
    if v.is_string() {
        format!("{:?}", v.to_string())
    } else {
        show_value(v)
    }
}

fn with_unit(x: &str, unit: &str) -> String {
    if unit.is_empty() {
        x.to_string()
    } else {
        format!("{x} {unit}")
    }
}

/// The argument declarations of a protocol declaration.
fn decl_args(decl: &Map) -> RResult<Vec<Map>> {
    let name = get_str(decl, "name");
    let Some(args) = decl.get("args") else {
        return Ok(vec![]);
    };
    let Some(a) = args.read_lock::<Array>() else {
        return fail(format!(
            "protocol_options: {name}: args must be an array of maps"
        ));
    };
    a.iter()
        .map(|x| {
            x.read_lock::<Map>().map(|m| m.clone()).ok_or_else(|| {
                format!("protocol_options: {name}: every entry of args must be a map, got {x}")
                    .into()
            })
        })
        .collect()
}

/// Check a value against one argument declaration; `who` and `key` name it in messages.
fn check_value(who: &str, a: &Map, v: &Dynamic) -> RResult<Dynamic> {
    let key = get_str(a, "key");
    let ty = get_str(a, "ty");
    let unit = get_str(a, "unit");
    let help = format!("help(\"{who}\")");
    let wrong = |what: &str| -> RResult<Dynamic> {
        fail(format!(
            "{who}: {key} must be {what}, got {} {}; see {help}",
            user_type_name(v),
            show_default(v)
        ))
    };
    let out = match ty.as_str() {
        "float" | "number" => match to_f64(v) {
            Some(x) if x.is_finite() => Dynamic::from_float(x),
            Some(x) => return fail(format!("{who}: {key} = {x} is not a finite number")),
            None => return wrong("a number"),
        },
        "int" => match (v.as_int(), v.as_float()) {
            (Ok(i), _) => Dynamic::from_int(i),
            (_, Ok(f)) if f.fract() == 0.0 && f.abs() < 9e15 => Dynamic::from_int(f as i64),
            _ => return wrong("an integer"),
        },
        "bool" => match v.as_bool() {
            Ok(b) => Dynamic::from_bool(b),
            Err(_) => return wrong("true or false"),
        },
        "string" => {
            if !v.is_string() {
                return wrong("a string");
            }
            v.clone()
        }
        "array" | "[from, to]" | "[x, y]" => {
            let Some(arr) = v.read_lock::<Array>() else {
                return wrong(if ty == "array" {
                    "an array"
                } else {
                    "[from, to] (two numbers)"
                });
            };
            if ty != "array" && (arr.len() != 2 || arr.iter().any(|x| to_f64(x).is_none())) {
                drop(arr);
                return wrong(&format!("{ty} (two numbers)"));
            }
            drop(arr);
            v.clone()
        }
        "map" => {
            if !v.is_map() {
                return wrong("a map #{…}");
            }
            v.clone()
        }
        "" | "any" => v.clone(),
        other => {
            let got = user_type_name(v);
            if !other.split('|').any(|t| t.trim() == got) {
                return wrong(&format!("a {other}"));
            }
            v.clone()
        }
    };
    if let Some(x) = to_f64(&out).filter(|_| !out.is_string()) {
        let min = a.get("min").and_then(to_f64);
        let max = a.get("max").and_then(to_f64);
        if min.is_some_and(|m| x < m) || max.is_some_and(|m| x > m) {
            let range = match (min, max) {
                (Some(lo), Some(hi)) => format!("[{}, {}]", fmt_num(lo), fmt_num(hi)),
                (Some(lo), None) => format!("≥ {}", fmt_num(lo)),
                (None, Some(hi)) => format!("≤ {}", fmt_num(hi)),
                _ => unreachable!(),
            };
            return fail(format!(
                "{who}: {key} = {} is out of range; allowed: {}; see {help}",
                with_unit(&fmt_num(x), &unit),
                with_unit(&range, &unit)
            ));
        }
    }
    if let Some(choices) = a
        .get("one_of")
        .and_then(|c| c.read_lock::<Array>().map(|c| c.clone()))
    {
        if !choices.iter().any(|c| c.to_string() == out.to_string()) {
            let list: Vec<String> = choices.iter().map(show_default).collect();
            return fail(format!(
                "{who}: {key} = {} is not one of {}{}",
                show_default(&out),
                list.join(", "),
                suggestion(
                    &out.to_string(),
                    choices
                        .iter()
                        .map(|c| c.clone().into_string().unwrap_or_default())
                        .collect::<Vec<_>>()
                        .iter()
                        .map(|s| s.as_str())
                )
            ));
        }
    }
    Ok(out)
}

/// `protocol_options(decl, opts)`: the checked options with defaults filled in.
pub fn protocol_options(decl: &Map, opts: &Dynamic) -> RResult<Map> {
    let who = get_str(decl, "name");
    let Some(opts) = opts.read_lock::<Map>().map(|m| m.clone()) else {
        return fail(format!(
            "{who}: the options must be a map #{{…}}, got {} {}; see help(\"{who}\")",
            user_type_name(opts),
            show_value(opts)
        ));
    };
    let args = decl_args(decl)?;
    let keys: Vec<String> = args.iter().map(|a| get_str(a, "key")).collect();
    for k in opts.keys() {
        if !keys.iter().any(|d| d == k.as_str()) {
            return fail(format!(
                "{who}: unknown option `{k}`{}; options: {}; see help(\"{who}\")",
                suggestion(k, keys.iter().map(|s| s.as_str())),
                keys.join(", ")
            ));
        }
    }
    let mut out = Map::new();
    for a in &args {
        let key = get_str(a, "key");
        match opts.get(key.as_str()) {
            Some(v) if !v.is_unit() => {
                out.insert(key.as_str().into(), check_value(&who, a, v)?);
            }
            _ => {
                if a.get("required").and_then(|r| r.as_bool().ok()) == Some(true) {
                    return fail(format!(
                        "{who}: option `{key}` is required ({}); see help(\"{who}\")",
                        get_str(a, "doc")
                    ));
                }
                if let Some(d) = a.get("default") {
                    out.insert(key.as_str().into(), d.clone());
                }
            }
        }
    }
    Ok(out)
}

/// The one-line summary of a protocol for `help()`.
pub fn protocol_line(decl: &Map) -> String {
    format!(
        "  {:<34} {}",
        get_str(decl, "name"),
        get_str(decl, "summary")
    )
}

/// The full help page of a protocol, from its declaration.
pub fn protocol_page(decl: &Map) -> RResult<String> {
    let name = get_str(decl, "name");
    let call = match get_str(decl, "usage") {
        c if c.is_empty() => format!("{name}(#{{…}})"),
        c => c,
    };
    let mut s = format!("{call}  —  {}\n", get_str(decl, "summary"));
    if let Some(p) = decl
        .get("params")
        .and_then(|p| p.read_lock::<Array>().map(|a| a.clone()))
    {
        if !p.is_empty() {
            s.push_str("arguments:\n");
            for x in p {
                if let Some(m) = x.read_lock::<Map>() {
                    s.push_str(&format!(
                        "  {:<12} {:<10} {}\n",
                        get_str(&m, "key"),
                        get_str(&m, "ty"),
                        get_str(&m, "doc")
                    ));
                }
            }
        }
    }
    let args = decl_args(decl)?;
    if !args.is_empty() {
        s.push_str("options (map keys):\n");
        for a in &args {
            let unit = get_str(a, "unit");
            let unit_s = if unit.is_empty() {
                String::new()
            } else {
                format!(" [{unit}]")
            };
            let mut extra = vec![];
            if a.get("required").and_then(|r| r.as_bool().ok()) == Some(true) {
                extra.push("required".to_string());
            } else if let Some(d) = a.get("default") {
                extra.push(format!("default {}", with_unit(&show_default(d), &unit)));
            } else {
                extra.push("optional".to_string());
            }
            let (lo, hi) = (a.get("min").and_then(to_f64), a.get("max").and_then(to_f64));
            match (lo, hi) {
                (Some(l), Some(h)) => extra.push(format!("{}…{}", fmt_num(l), fmt_num(h))),
                (Some(l), None) => extra.push(format!("≥ {}", fmt_num(l))),
                (None, Some(h)) => extra.push(format!("≤ {}", fmt_num(h))),
                _ => {}
            }
            if let Some(c) = a
                .get("one_of")
                .and_then(|c| c.read_lock::<Array>().map(|c| c.clone()))
            {
                extra.push(format!(
                    "one of {}",
                    c.iter().map(show_default).collect::<Vec<_>>().join(", ")
                ));
            }
            s.push_str(&format!(
                "  {:<12} {}{unit_s}  {} ({})\n",
                get_str(a, "key"),
                get_str(a, "ty"),
                get_str(a, "doc"),
                extra.join("; ")
            ));
        }
    }
    for (k, title) in [
        ("returns", "returns"),
        ("saves", "saves"),
        ("stage", "stage"),
    ] {
        let v = get_str(decl, k);
        if !v.is_empty() {
            s.push_str(&format!("{title}: {v}\n"));
        }
    }
    let h = get_str(decl, "help");
    if !h.is_empty() {
        s.push('\n');
        s.push_str(h.trim());
        s.push('\n');
    }
    let ex = get_str(decl, "example");
    if !ex.is_empty() {
        s.push_str(&format!("\nexample:\n  {ex}\n"));
    }
    Ok(s)
}

/// Folders holding the stdlib modules (as the module resolver searches them).
pub fn stdlib_dirs() -> Vec<PathBuf> {
    vec![
        PathBuf::from("stdlib"),
        Path::new(env!("CARGO_MANIFEST_DIR")).join("stdlib"),
    ]
}

/// The protocol declarations of the stdlib module `module` (its `protocols()` function, run on
/// a bare engine: declarations are literal maps).
pub fn module_protocols(module: &str) -> Option<Vec<Map>> {
    if module.is_empty() || !module.chars().all(|c| c.is_alphanumeric() || c == '_') {
        return None;
    }
    let path = stdlib_dirs()
        .into_iter()
        .map(|d| d.join(format!("{module}.rhai")))
        .find(|p| p.is_file())?;
    let mut engine = Engine::new();
    engine.set_max_expr_depths(0, 0);
    let ast = match engine.compile_file(path.clone()) {
        Ok(a) => a,
        Err(e) => {
            eprintln!("{}: {e}", path.display());
            return None;
        }
    };
    let opts = rhai::CallFnOptions::new().eval_ast(false);
    let v: Dynamic =
        match engine.call_fn_with_options(opts, &mut rhai::Scope::new(), &ast, "protocols", ()) {
            Ok(v) => v,
            Err(e) => {
                eprintln!("{}: {e}", path.display());
                return None;
            }
        };
    let a = v.read_lock::<Array>()?.clone();
    Some(
        a.iter()
            .filter_map(|x| x.read_lock::<Map>().map(|m| m.clone()))
            .collect(),
    )
}

/// Names of the stdlib modules (sorted).
pub fn stdlib_modules() -> Vec<String> {
    let mut v = vec![];
    for d in stdlib_dirs() {
        if let Ok(rd) = std::fs::read_dir(d) {
            for e in rd.flatten() {
                let p = e.path();
                if p.extension().is_some_and(|x| x == "rhai") {
                    if let Some(s) = p.file_stem().and_then(|s| s.to_str()) {
                        v.push(s.to_string());
                    }
                }
            }
        }
        if !v.is_empty() {
            break;
        }
    }
    v.sort();
    v.dedup();
    v
}

/// `help()`'s protocol section: one line per protocol of every stdlib module.
pub fn protocols_index() -> String {
    let mut s = String::from(
        "protocols (stdlib: import \"focus\" as focus; help(\"focus\") for the page)\n",
    );
    for m in stdlib_modules() {
        for d in module_protocols(&m).unwrap_or_default() {
            s.push_str(&protocol_line(&d));
            s.push('\n');
        }
    }
    s
}

/// The help page for `name` when it is a stdlib module (`calibrate`) or one of its protocols
/// (`calibrate::reference_beads`); None otherwise.
pub fn protocol_help(name: &str) -> Option<String> {
    let name = name.trim().trim_end_matches("()");
    let (module, func) = match name.split_once("::") {
        Some((m, f)) => (m, Some(f)),
        None => (name, None),
    };
    let decls = module_protocols(module)?;
    let pages: Vec<String> = decls
        .iter()
        .filter(|d| func.is_none_or(|f| get_str(d, "name") == format!("{module}::{f}")))
        .filter_map(|d| protocol_page(d).ok())
        .collect();
    if pages.is_empty() {
        None
    } else {
        Some(pages.join("\n"))
    }
}

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

pub fn register(r: &mut Registrar) {
    let d = Doc::func("pwd")
        .returns("string", "the session folder")
        .summary("the session folder: where scans, figures, templates and the session log go")
        .example("pwd() == status().data_dir", "true");
    let c = r.ctx();
    r.bind(d, move || pwd(&c));

    let d = Doc::func("ls")
        .returns("array", "file names in the session folder, sorted")
        .summary("list the session folder")
        .example("ls().len() >= 0", "true");
    let c = r.ctx();
    r.bind(d, move || ls(&c));

    let d = Doc::func("note")
        .arg("text", "string", "", "a note (sample, condition, what you are doing)")
        .returns("array", "all notes so far")
        .summary("add a note to the metadata of every later scan (meta.notes); note() with \"\" clears them")
        .example("note(\"sample 3, 110 nm PS\"); note(\"after refocus\").len()", "2")
        .example("note(\"a\"); note(\"\").len()", "0");
    let c = r.ctx();
    r.bind(d, move |text: &str| note(&c, text));

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
    let c = r.ctx();
    r.bind(d, move |filter: Map| scans(&c, &filter));
    let c = r.ctx();
    r.overload("scans", move || scans_all(&c));

    // SPEC words
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

#[cfg(test)]
mod protocol_tests {
    use super::*;

    #[test]
    fn every_stdlib_module_declares_its_protocols() {
        for m in [
            "focus",
            "calibrate",
            "rotation",
            "aggregates",
            "tips",
            "microtubule",
            "beads",
        ] {
            let d = module_protocols(m).unwrap_or_else(|| panic!("{m}: no protocols()"));
            assert!(!d.is_empty(), "{m}");
            let page = protocol_help(m).unwrap();
            assert!(page.contains(&format!("{m}::")), "{page}");
            assert!(
                page.contains("example:") && page.contains("returns:"),
                "{page}"
            );
        }
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
