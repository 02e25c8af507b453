//! Core bindings: `help`, the test assertions (`assert`, `assert_close`, `assert_err`),
//! `linspace`, `version`.

use super::ctx::Ctx;
use super::registry::{binding_list, fail, find, help_index, int, num, Doc, RResult, Registrar};
use rhai::{Array, Dynamic, FnPtr, Map, NativeCallContext};

/// `assert_close`'s check, shared with the Rust tests: |a − b| ≤ rel·max(|a|, |b|).
pub fn close(a: f64, b: f64, rel: f64) -> bool {
    a == b || (a - b).abs() <= rel * a.abs().max(b.abs())
}

binding_list! {
    pub fn register {
        bind_help_and_asserts, bind_numbers, bind_protocol, bind_trace
    }
}

/// `help` and the assertions of scripted tests.
fn bind_help_and_asserts(r: &mut Registrar) {
    let d = Doc::func("help")
        .opt(
            "name",
            "string",
            "",
            "a binding (`mv`, `img.max`, `scan.sx`) or a family (`scans`)",
        )
        .form("help(name)")
        .summary(
            "list every binding by family, or show one binding's arguments, units and examples",
        )
        .example(
            "help(\"scan_lne\")",
            "error: help: no binding called \"scan_lne\"; did you mean `scan_line`?",
        );
    r.bind_ctx(d, |c| move || help_all(&c));
    let c = r.ctx();
    r.overload("help", move |name: &str| help_one(&c, name));

    let d = Doc::func("assert")
        .arg("cond", "bool", "", "must be true")
        .opt("message", "string", "", "what was expected")
        .form("assert(cond, message)")
        .summary("fail the script (test) with `message` unless `cond` is true")
        .example("assert(1 + 1 == 2, \"arithmetic\")", "()")
        .example(
            "assert(false, \"the bead is gone\")",
            "error: assertion failed: the bead is gone",
        );
    r.bind(d, |cond: Dynamic, msg: &str| check(cond, msg));
    r.overload("assert", |cond: Dynamic| check(cond, ""));

    let d = Doc::func("assert_close")
        .arg("a", "float", "", "value obtained")
        .arg("b", "float", "", "value expected")
        .arg("rel", "float", "", "relative tolerance, 0 ≤ rel")
        .summary("fail unless |a − b| ≤ rel·max(|a|, |b|); the message shows both values and the relative difference")
        .example("assert_close(1.0, 1.0005, 1e-3)", "()")
        .example("assert_close(1.0, 1.1, 1e-3)", "error: assert_close: a = 1 and b = 1.1 differ by 9.091e-2 (relative) > rel = 1e-3");
    r.bind(d, |a: Dynamic, b: Dynamic, rel: Dynamic| {
        assert_close(&a, &b, &rel)
    });

    let d = Doc::func("assert_err")
        .arg("f", "fn", "", "a closure `|| …` that must throw")
        .opt("contains", "string", "", "text the error message must contain")
        .form("assert_err(f, contains)")
        .returns("string", "the error message")
        .summary("pass if calling `f` throws (optionally with a message containing `contains`); returns the message")
        .example("assert_err(|| mv(#{x: 1000.0}))", "\"mv refused, nothing was moved: x = 1000 µm is above the soft limit x ≤ 50 µm\"")
        .example("assert_err(|| 1 + 1)", "error: assert_err: expected an error, but the closure returned 2")
        .example("assert_err(|| qpd(0), \"out of range\").len() > 0", "true");
    r.bind_ctx(d, |c| {
        move |ctx: NativeCallContext, f: FnPtr| expect_err(&ctx, &f, None, &c.docs())
    });
    let c = r.ctx();
    r.overload(
        "assert_err",
        move |ctx: NativeCallContext, f: FnPtr, contains: &str| {
            expect_err(&ctx, &f, Some(contains), &c.docs())
        },
    );
}

/// `linspace` and `fmt`.
fn bind_numbers(r: &mut Registrar) {
    let d = Doc::func("linspace")
        .arg("from", "float", "", "first value")
        .arg("to", "float", "", "last value")
        .arg(
            "n",
            "int",
            "",
            &format!("number of values, 1 ≤ n ≤ {LINSPACE_MAX}"),
        )
        .returns("array", "n floats")
        .summary("evenly spaced values from `from` to `to` inclusive")
        .example("linspace(0, 1, 5)", "[0.0, 0.25, 0.5, 0.75, 1.0]");
    r.bind(d, |a: Dynamic, b: Dynamic, n: Dynamic| linspace(&a, &b, &n));

    let d = Doc::func("fmt")
        .arg("x", "number", "", "a value")
        .arg("digits", "int", "", "significant digits, 1–17")
        .returns(
            "string",
            "x with that many significant digits (scientific notation outside 1e-3…1e6)",
        )
        .summary("format a number for printing")
        .example("fmt(3.14159265, 3)", "\"3.14\"")
        .example("fmt(0.000012345, 2)", "\"1.2e-5\"")
        .example("fmt(1.0, 0)", "error: digits = 0");
    r.bind(d, |x: Dynamic, digits: Dynamic| fmt(&x, &digits));
}

/// A protocol's dialogue and record: `ask`, `answer`, `protocol_begin`, `protocol_end`, `provenance`.
fn bind_protocol(r: &mut Registrar) {
    let d = Doc::func("ask")
        .arg("question", "string", "", "what the operator must do or answer")
        .returns("string", "the answer line (without the newline)")
        .summary("ask the operator and wait for the answer (hardware protocols: \"rotate the sample, then press Enter\")")
        .help("Prints the question and reads one line from the terminal. Answers queued with answer([...]) are used first, so scripted tests can answer prompts. End of input (no terminal, no queued answer) is an error, so an unattended script never waits forever.")
        .example("answer([\"yes\"]); ask(\"rotated?\")", "\"yes\"");
    r.bind_ctx(d, |c| move |q: &str| ask(&c, q));

    let d = Doc::func("answer")
        .arg(
            "answers",
            "array",
            "",
            "strings, used in order by the next calls of ask()",
        )
        .returns("int", "answers now queued")
        .summary("queue answers for ask() (scripted tests and unattended runs)")
        .example("answer([\"y\", \"y\"])", "2");
    r.bind_ctx(d, |c| move |a: Array| answer(&c, &a));

    let d = Doc::func("protocol_begin")
        .arg("name", "string", "", "the protocol (stdlib module and function)")
        .arg("args", "map", "", "its arguments")
        .returns("()", "")
        .summary("mark the start of a protocol: every scan, template, figure and CSV written until protocol_end() records it with its arguments")
        .example("protocol_begin(\"focus::search\", #{axis: \"x\"}); provenance().protocol.name", "\"focus::search\"");
    r.bind_ctx(d, |c| {
        move |name: &str, args: Map| protocol_begin(&c, name, args)
    });

    let d = Doc::func("protocol_end")
        .returns("()", "")
        .summary("mark the end of the innermost protocol")
        .example(
            "protocol_begin(\"x\", #{}); protocol_end(); provenance().protocol",
            "()",
        );
    r.bind_ctx(d, |c| move || protocol_end(&c));

    let d = Doc::func("provenance")
        .returns("map", "#{program, script: #{path, sha256, repl_line}, git_revision, protocol: #{name, args} or (), written}")
        .summary("what every file written from a script carries (scan metadata, template JSON, PNG text chunk, CSV trailer)")
        .example("provenance().program.starts_with(\"bfpscope\")", "true");
    r.bind_ctx(d, |c| move || provenance(&c));
}

/// The command trace and the version: `trace_*`, `version`.
fn bind_trace(r: &mut Registrar) {
    let d = Doc::func("trace_start")
        .returns("()", "")
        .summary("record every move, read and protocol decision of the connected instrument, with its clock's time (golden traces)")
        .help("Protocols call trace_note at their decisions. tests/golden.rs compares traces of protocol runs on the simulator with the committed files in tests/golden/; BFPSCOPE_BLESS=\"<one line saying why>\" cargo test --test program golden:: rewrites them deliberately, adding the reason to the file's # header.")
        .example("trace_start(); mv(#{x: 0.5}); trace_text().contains(\"move\")", "true");
    r.bind_ctx(d, |c| move || c.trace_start());

    let d = Doc::func("trace_note")
        .arg(
            "text",
            "string",
            "",
            "a decision, e.g. \"focus: best z = 0.012 µm\"",
        )
        .returns("()", "")
        .summary("record a protocol decision in the running trace (nothing when not tracing)")
        .example(
            "trace_start(); trace_note(\"chose z\"); trace_text().contains(\"chose z\")",
            "true",
        );
    r.bind_ctx(d, |c| move |t: &str| c.trace_note(t));

    let d = Doc::func("trace_text")
        .returns(
            "string",
            "one line per event: simulated time, then what happened",
        )
        .summary("the trace recorded since trace_start()")
        .example("trace_text()", "error: trace_text: not tracing");
    r.bind_ctx(d, |c| move || trace_text(&c));

    let d = Doc::func("version")
        .returns("string", "")
        .summary("program name and version")
        .example("version().starts_with(\"bfpscope \")", "true");
    r.bind(d, version);
}

/// The largest `n` that `linspace` accepts.
const LINSPACE_MAX: i64 = 10_000_000;

/// `help()`: every binding by family, then the protocols.
fn help_all(ctx: &Ctx) {
    ctx.page(&format!(
        "{}\n{}",
        help_index(&ctx.docs()),
        super::console::protocols_index()
    ));
}

/// `help(name)`: the long help of a binding, the one-line list of a family, or a protocol's page.
fn help_one(ctx: &Ctx, name: &str) -> RResult<()> {
    let docs = ctx.docs();
    let hits = find(&docs, name);
    if hits.is_empty() {
        if let Some(page) = super::console::protocol_help(name) {
            ctx.page(&page);
            return Ok(());
        }
        let names: Vec<&str> = docs.iter().map(|d| d.name.as_str()).collect();
        return fail(format!(
            "help: no binding called {name:?}{}; help() lists them all",
            super::console::suggestion(name, names)
        ));
    }
    let mut text: Vec<String> =
        if hits.iter().all(|d| d.family.eq_ignore_ascii_case(name)) && hits.len() > 1 {
            hits.iter().map(|d| format!("  {}", d.one_line())).collect()
        } else {
            hits.iter().map(|d| d.long_help()).collect()
        };
    // a name that is both a binding (`fitresult.beads`) and a stdlib protocol module
    // (`beads`): both pages, each introduced
    if let Some(page) = super::console::protocol_help(name) {
        text.insert(
            0,
            format!("`{name}` names a binding and a stdlib protocol module; the binding:"),
        );
        text.push(format!(
            "\nthe protocol module (import \"{name}\" as {name};):\n{page}"
        ));
    }
    ctx.page(&text.join("\n"));
    Ok(())
}

/// `assert_close(a, b, rel)`: fail unless [`close`]`(a, b, rel)`; NaN is never close.
fn assert_close(a: &Dynamic, b: &Dynamic, rel: &Dynamic) -> RResult<()> {
    let a = super::registry::to_f64(a).ok_or_else(|| {
        format!(
            "assert_close: a must be a number, got {} {a}",
            a.type_name()
        )
    })?;
    let b = super::registry::to_f64(b).ok_or_else(|| {
        format!(
            "assert_close: b must be a number, got {} {b}",
            b.type_name()
        )
    })?;
    let rel = num("assert_close", "rel", rel)?;
    if rel < 0.0 {
        return fail(format!(
            "assert_close: rel = {rel} is out of range: rel ≥ 0"
        ));
    }
    if a.is_nan() || b.is_nan() {
        return fail(format!(
            "assert_close: a = {a}, b = {b}: NaN is never close"
        ));
    }
    if close(a, b, rel) {
        Ok(())
    } else {
        let d = (a - b).abs() / a.abs().max(b.abs());
        fail(format!(
            "assert_close: a = {a} and b = {b} differ by {d:.3e} (relative) > rel = {rel:e}"
        ))
    }
}

/// `linspace(from, to, n)`: n evenly spaced values, both ends included.
fn linspace(a: &Dynamic, b: &Dynamic, n: &Dynamic) -> RResult<Array> {
    let (a, b) = (num("linspace", "from", a)?, num("linspace", "to", b)?);
    let n = int("linspace", "n", n)?;
    if !(1..=LINSPACE_MAX).contains(&n) {
        return fail(format!(
            "linspace: n = {n} is out of range: 1 ≤ n ≤ {LINSPACE_MAX}"
        ));
    }
    Ok(crate::acquire::plan::linspace(a, b, n as usize)
        .into_iter()
        .map(Dynamic::from)
        .collect())
}

/// `fmt(x, digits)`: [`fmt_sig`] with 1 ≤ digits ≤ 17 checked.
fn fmt(x: &Dynamic, d: &Dynamic) -> RResult<String> {
    let x = super::registry::to_f64(x)
        .ok_or_else(|| format!("fmt: x must be a number, got {} {x}", x.type_name()))?;
    let d = int("fmt", "digits", d)?;
    if !(1..=17).contains(&d) {
        return fail(format!(
            "fmt: digits = {d} is out of range: 1 ≤ digits ≤ 17"
        ));
    }
    Ok(fmt_sig(x, d as usize))
}

/// `ask(question)`: the next queued answer, else one line from the terminal; end of input is an
/// error so an unattended script never waits.
fn ask(ctx: &Ctx, q: &str) -> RResult<String> {
    if let Some(a) = ctx
        .answers
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .pop_front()
    {
        ctx.print(&format!("{q} {a}"));
        return Ok(a);
    }
    ctx.print(q);
    let mut line = String::new();
    match std::io::stdin().read_line(&mut line) {
        Ok(0) => fail(format!("ask: no answer to \"{q}\": end of input (queue answers with answer([...]) when running unattended)")),
        Ok(_) => Ok(line.trim_end_matches(['\n', '\r']).to_string()),
        Err(e) => fail(format!("ask: cannot read the answer to \"{q}\": {e}")),
    }
}

/// `answer([...])`: queue answers for `ask`; returns how many are queued.
fn answer(ctx: &Ctx, a: &Array) -> i64 {
    let mut q = ctx.answers.lock().unwrap_or_else(|e| e.into_inner());
    q.extend(a.iter().map(|v| v.to_string()));
    q.len() as i64
}

/// `protocol_begin(name, args)`: push a protocol onto the provenance stack.
fn protocol_begin(ctx: &Ctx, name: &str, args: Map) {
    let v = serde_json::json!({
        "name": name,
        "args": super::types::dynamic_to_json(&Dynamic::from_map(args)),
    });
    ctx.protocols
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .push(v);
}

/// `protocol_end()`: pop the innermost protocol.
fn protocol_end(ctx: &Ctx) {
    ctx.protocols
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .pop();
}

/// `provenance()`: the provenance record every written file carries, as a map.
fn provenance(ctx: &Ctx) -> Dynamic {
    super::types::json_to_dynamic(&ctx.provenance())
}

/// `trace_text()`: the trace since `trace_start()`; an error when not tracing.
fn trace_text(ctx: &Ctx) -> RResult<String> {
    ctx.trace_text().map_or_else(
        || fail("trace_text: not tracing; call trace_start() first"),
        Ok,
    )
}

/// `version()`: "bfpscope <version>".
fn version() -> String {
    format!("bfpscope {}", env!("CARGO_PKG_VERSION"))
}

/// `assert(cond[, message])`: fail with "assertion failed[: message]" unless `cond` is true.
fn check(cond: Dynamic, msg: &str) -> RResult<()> {
    match cond.as_bool() {
        Ok(true) => Ok(()),
        Ok(false) => fail(if msg.is_empty() {
            "assertion failed".to_string()
        } else {
            format!("assertion failed: {msg}")
        }),
        Err(t) => fail(format!(
            "assert: cond must be true or false, got {t} {cond}"
        )),
    }
}

/// `assert_err(f[, contains])`: call `f`; its error message (checked to contain `contains`), or an
/// error when it returns. Ctrl-C passes through.
fn expect_err(
    ctx: &NativeCallContext,
    f: &FnPtr,
    contains: Option<&str>,
    docs: &[super::Doc],
) -> RResult<String> {
    match f.call_within_context::<Dynamic>(ctx, ()) {
        Ok(v) => fail(format!(
            "assert_err: expected an error, but the closure returned {}",
            super::types::show(&v)
        )),
        Err(e) => {
            if matches!(*e, rhai::EvalAltResult::ErrorTerminated(..)) {
                return Err(e); // Ctrl-C is never swallowed
            }
            let msg = super::errors::error_message(&e, docs);
            match contains {
                Some(t) if !msg.contains(t) => fail(format!(
                    "assert_err: the error {msg:?} does not contain {t:?}"
                )),
                _ => Ok(msg),
            }
        }
    }
}

/// `x` with `d` significant digits: fixed notation for 1e-3 ≤ |x| < 1e6, otherwise scientific.
pub fn fmt_sig(x: f64, d: usize) -> String {
    if !x.is_finite() {
        return x.to_string();
    }
    if x == 0.0 {
        return "0".into();
    }
    let e = x.abs().log10().floor() as i32;
    if (-3..6).contains(&e) {
        let dec = (d as i32 - 1 - e).max(0) as usize;
        format!("{x:.dec$}")
    } else {
        let s = format!("{:.*e}", d - 1, x);
        s
    }
}
