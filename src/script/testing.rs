//! `bfpscope test DIR`: the scripted test runner.
//!
//! Every `*.rhai` file in DIR (sorted, not recursive) is a test file. A file that defines
//! functions named `test_*` contributes one test per function: for each, a fresh workbench
//! runs the file's top-level statements (setup) and then calls the function. A file without
//! `test_*` functions is one test: the whole file runs. A test passes when it runs without an
//! error (`assert`, `assert_close`, `assert_err` throw on failure). Each test gets its own
//! fresh session folder in the system temp dir. Output: one line per test, then exactly
//! `N passed, N failed`.

use super::{Settings, Workbench};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// One test's result.
#[derive(Debug, Clone)]
pub struct TestResult {
    pub name: String,
    pub passed: bool,
    pub message: String,
    pub seconds: f64,
}

/// The `*.rhai` files of a folder, sorted.
pub fn test_files(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "rhai") && p.is_file())
        .collect();
    v.sort();
    Ok(v)
}

fn fresh_dir(tag: &str) -> PathBuf {
    use std::sync::atomic::{AtomicU64, Ordering};
    static N: AtomicU64 = AtomicU64::new(0);
    std::env::temp_dir().join(format!(
        "bfpscope-test-{}-{}-{tag}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    ))
}

/// Run every test in `dir`; `base` provides the sandbox, limits and abort flag; printing goes
/// to a per-test buffer shown only when the test fails. Writes the report to `out`.
pub fn run_dir(
    dir: &Path,
    base: &Settings,
    out: &mut dyn Write,
) -> std::io::Result<Vec<TestResult>> {
    let files = test_files(dir)?;
    let mut results = vec![];
    for file in &files {
        let fname = file
            .file_name()
            .map(|f| f.to_string_lossy().to_string())
            .unwrap_or_default();
        // Compile once to find the test functions.
        let probe = Workbench::new(settings_for(base, "probe").0);
        let fns: Vec<String> =
            match std::fs::read_to_string(file).map(|src| probe.engine.compile(&src)) {
                Ok(Ok(ast)) => {
                    let mut v: Vec<String> = ast
                        .iter_functions()
                        .filter(|f| f.name.starts_with("test_") && f.params.is_empty())
                        .map(|f| f.name.to_string())
                        .collect();
                    v.sort();
                    v.dedup();
                    v
                }
                _ => vec![], // reported by the run below
            };
        let tests: Vec<Option<String>> = if fns.is_empty() {
            vec![None]
        } else {
            fns.into_iter().map(Some).collect()
        };
        for t in tests {
            let name = match &t {
                Some(f) => format!("{fname}::{f}"),
                None => fname.clone(),
            };
            let (settings, buf, dir) = settings_for(base, &fname);
            let t0 = Instant::now();
            let mut wb = Workbench::new(settings);
            // A test function runs after the file's top level (which `call_fn` evaluates first,
            // so its `const`s are visible as `global::NAME`); a file without test functions is
            // its top level.
            let r = match wb.load_file(file) {
                Err(e) => Err(e),
                Ok(ast) => match &t {
                    Some(f) => wb.call_fn(&ast, f, &file.display().to_string()).map(|_| ()),
                    None => wb
                        .run_compiled(&ast, &file.display().to_string())
                        .map(|_| ()),
                },
            };
            let secs = t0.elapsed().as_secs_f64();
            let res = match r {
                Ok(()) => {
                    writeln!(out, "ok    {name} ({secs:.2} s)")?;
                    let _ = std::fs::remove_dir_all(&dir);
                    TestResult {
                        name,
                        passed: true,
                        message: String::new(),
                        seconds: secs,
                    }
                }
                Err(e) => {
                    writeln!(out, "FAIL  {name}: {e}")?;
                    let printed = buf.lock().map(|b| b.clone()).unwrap_or_default();
                    for l in printed.lines().take(40) {
                        writeln!(out, "      | {l}")?;
                    }
                    TestResult {
                        name,
                        passed: false,
                        message: e.to_string(),
                        seconds: secs,
                    }
                }
            };
            results.push(res);
        }
    }
    let passed = results.iter().filter(|r| r.passed).count();
    writeln!(out, "{} passed, {} failed", passed, results.len() - passed)?;
    Ok(results)
}

type Captured = std::sync::Arc<std::sync::Mutex<String>>;

fn settings_for(base: &Settings, tag: &str) -> (Settings, Captured, PathBuf) {
    let dir = fresh_dir(&tag.replace(['/', '.'], "_"));
    let (mut s, buf) = Settings::captured(&dir);
    s.limits = base.limits;
    s.sandbox = base.sandbox;
    s.abort = base.abort.clone();
    s.config = base.config.clone();
    s.config_path = base.config_path.clone();
    (s, buf, dir)
}

/// Compare two script values: numbers (int or float) to a relative 1e-9 (absolute 1e-12 near
/// zero), arrays and maps element by element, everything else by its printed form.
pub fn values_match(a: &rhai::Dynamic, b: &rhai::Dynamic) -> bool {
    use super::registry::to_f64;
    if let (Some(x), Some(y)) = (to_f64(a), to_f64(b)) {
        return x == y || (x - y).abs() <= 1e-9 * x.abs().max(y.abs()) || (x - y).abs() <= 1e-12;
    }
    if let (Some(x), Some(y)) = (a.read_lock::<rhai::Array>(), b.read_lock::<rhai::Array>()) {
        return x.len() == y.len() && x.iter().zip(y.iter()).all(|(p, q)| values_match(p, q));
    }
    if let (Some(x), Some(y)) = (a.read_lock::<rhai::Map>(), b.read_lock::<rhai::Map>()) {
        return x.len() == y.len()
            && x.iter()
                .all(|(k, v)| y.get(k).is_some_and(|w| values_match(v, w)));
    }
    if a.is_unit() || b.is_unit() {
        return a.is_unit() && b.is_unit();
    }
    a.type_name() == b.type_name() && super::show(a) == super::show(b)
}

/// The keys of every number in a result (maps inside maps and arrays too), for the check that
/// every result value has its unit (`script::units`).
pub fn numeric_keys(v: &rhai::Dynamic, out: &mut std::collections::BTreeSet<String>) {
    if let Some(a) = v.read_lock::<rhai::Array>() {
        a.iter().for_each(|x| numeric_keys(x, out));
    } else if let Some(m) = v.read_lock::<rhai::Map>() {
        for (k, x) in m.iter() {
            if super::registry::to_f64(x).is_some() {
                out.insert(k.to_string());
            } else if let Some(a) = x.read_lock::<rhai::Array>() {
                if a.iter().any(|e| super::registry::to_f64(e).is_some()) {
                    out.insert(k.to_string());
                }
            }
            numeric_keys(x, out);
        }
    }
}

/// Run every example of every declaration in a fresh workbench connected to the mock
/// instrument; returns the number run and one message per mismatch.
pub fn check_examples(docs: &[super::Doc]) -> (usize, Vec<String>) {
    let (n, failures, _) = run_examples(docs);
    (n, failures)
}

/// As [`check_examples`], also returning the keys of the numbers in the examples' results.
pub fn run_examples(
    docs: &[super::Doc],
) -> (usize, Vec<String>, std::collections::BTreeSet<String>) {
    let mut n = 0;
    let mut failures = vec![];
    let mut keys = std::collections::BTreeSet::new();
    for d in docs {
        for ex in &d.examples {
            n += 1;
            let (settings, _buf, dir) = settings_for(&Settings::default(), "example");
            let mut wb = Workbench::new(settings);
            if let Err(e) = wb.eval_source("setup", "connect(#{backend: \"mock\"})") {
                failures.push(format!("{}: setup failed: {e}", d.name));
                continue;
            }
            let got = wb.eval_source("example", &ex.code);
            let what = format!("{} example `{}`", d.signature(), ex.code);
            match (ex.expect.strip_prefix("error:"), got) {
                (Some(text), Err(e)) => {
                    if !e.message.contains(text.trim()) {
                        failures.push(format!(
                            "{what}: error {:?} does not contain {:?}",
                            e.message,
                            text.trim()
                        ));
                    }
                }
                (Some(_), Ok(v)) => failures.push(format!(
                    "{what}: expected an error, got {}",
                    super::show(&v)
                )),
                (None, Err(e)) => failures.push(format!("{what}: failed: {e}")),
                (None, Ok(v)) => {
                    numeric_keys(&v, &mut keys);
                    match Workbench::new(settings_for(&Settings::default(), "expect").0)
                        .eval_source("expected", &ex.expect)
                    {
                        Err(e) => failures.push(format!(
                            "{what}: expected value `{}` does not evaluate: {e}",
                            ex.expect
                        )),
                        Ok(want) => {
                            if !values_match(&v, &want) {
                                failures.push(format!(
                                    "{what}: got {} (debug {v:?}), expected {}",
                                    super::show(&v),
                                    ex.expect
                                ));
                            }
                        }
                    }
                }
            }
            let _ = std::fs::remove_dir_all(&dir);
        }
    }
    (n, failures, keys)
}
