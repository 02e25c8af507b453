//! Protocol option declarations (`protocol_options`, `protocol_page`) and the help pages of
//! the stdlib protocols (their modules found in `stdlib/`).
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

use super::registry::{fail, to_f64, Doc, RResult};
use super::words::{fmt_num, suggestion, user_type, user_type_name};
use rhai::{Array, Dynamic, Engine, Map};
use std::path::{Path, PathBuf};

/// The keys of a protocol option's declaration map (`#{min, max, default, required, one_of}`).
const DECL_MIN: &str = "min";
const DECL_MAX: &str = "max";
const DECL_DEFAULT: &str = "default";
const DECL_REQUIRED: &str = "required";
const DECL_ONE_OF: &str = "one_of";

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
        let min = a.get(DECL_MIN).and_then(to_f64);
        let max = a.get(DECL_MAX).and_then(to_f64);
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
        .get(DECL_ONE_OF)
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
                if a.get(DECL_REQUIRED).and_then(|r| r.as_bool().ok()) == Some(true) {
                    return fail(format!(
                        "{who}: option `{key}` is required ({}); see help(\"{who}\")",
                        get_str(a, "doc")
                    ));
                }
                if let Some(d) = a.get(DECL_DEFAULT) {
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
            if a.get(DECL_REQUIRED).and_then(|r| r.as_bool().ok()) == Some(true) {
                extra.push(DECL_REQUIRED.to_string());
            } else if let Some(d) = a.get(DECL_DEFAULT) {
                extra.push(format!("default {}", with_unit(&show_default(d), &unit)));
            } else {
                extra.push("optional".to_string());
            }
            let (lo, hi) = (
                a.get(DECL_MIN).and_then(to_f64),
                a.get(DECL_MAX).and_then(to_f64),
            );
            match (lo, hi) {
                (Some(l), Some(h)) => extra.push(format!("{}…{}", fmt_num(l), fmt_num(h))),
                (Some(l), None) => extra.push(format!("≥ {}", fmt_num(l))),
                (None, Some(h)) => extra.push(format!("≤ {}", fmt_num(h))),
                _ => {}
            }
            if let Some(c) = a
                .get(DECL_ONE_OF)
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
            "targeted",
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
