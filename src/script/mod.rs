//! The Rhai engine and the binding registry. One file per binding family; each family is
//! declared once in [`FAMILIES`]. `Workbench` is one scripting session: engine, variables and
//! functions that persist across REPL lines, and the shared [`Ctx`].

/// The stop rule's words (the prompt prints them; `acquire` owns the rule).
pub use crate::acquire::stop_rule;
pub mod analysis_values;
pub mod console;
pub mod core;
pub mod crlb;
pub mod ctx;
pub mod doc;
pub mod errors;
pub mod filament_fit;
pub mod filaments;
pub mod files;
pub mod focus_crlb;
pub mod hardware;
pub mod keys;
pub mod mie;
pub mod motion;
pub mod optics;
pub mod protocols;
pub mod registry;
pub mod scans;
pub mod scene;
pub mod sensitivity;
pub mod stats;
pub mod targeted;
pub mod templates;
pub mod testing;
pub mod types;
pub mod units;
pub mod values;
pub mod view;
pub mod words;

pub use ctx::{Ctx, Sandbox, ScriptInfo, Settings};
pub use errors::{error_message, ScriptError};
pub use registry::{Doc, Registrar};
pub use types::{show, ImageRef, ProfileRef, ScanRef};

use rhai::{Dynamic, Engine, Position, Scope, AST};
use std::path::Path;
use std::sync::atomic::Ordering;
use std::sync::Arc;

/// Every binding family, in the order `help()` lists them. Add a family here once.
/// A family's registration function.
pub type RegisterFn = fn(&mut Registrar);

pub const FAMILIES: &[(&str, RegisterFn)] = &[
    ("core", core::register),
    ("motion", motion::register),
    ("hardware", hardware::register),
    ("scans", scans::register),
    ("types", types::register),
    ("optics", optics::register),
    ("scene", scene::register),
    ("mie", mie::register),
    ("sensitivity", sensitivity::register),
    ("templates", templates::register),
    ("filaments", filaments::register),
    ("crlb", crlb::register),
    ("filament_fit", filament_fit::register),
    ("focus_crlb", focus_crlb::register),
    ("targeted", targeted::register),
    ("stats", stats::register),
    ("files", files::register),
    ("console", console::register),
    ("view", view::register),
];

/// Each variable's type as scripts name it and, for a map, its keys (completion after `name.`).
pub type VarTypes = std::collections::HashMap<String, (String, Vec<String>)>;

/// Build an engine with the sandbox, the abort hook, print routing, module resolution and
/// every binding family; returns the declarations too.
pub fn build_engine(ctx: Arc<Ctx>) -> (Engine, Arc<Vec<Doc>>) {
    let mut engine = Engine::new();
    let sb = ctx.settings.sandbox;
    engine
        .set_max_operations(sb.max_operations)
        .set_max_call_levels(sb.max_call_levels)
        .set_max_expr_depths(sb.max_expr_depth, sb.max_expr_depth)
        .set_max_string_size(sb.max_string_size)
        .set_max_array_size(sb.max_array_size)
        .set_max_map_size(sb.max_map_size)
        // reading a key a map does not have is an error (`s.meta.dwell_s` returned () and the
        // script went on); writing a new key still adds it
        .set_fail_on_invalid_map_property(true);
    let abort = ctx.settings.abort.clone();
    engine.on_progress(move |_| {
        if abort.load(Ordering::Relaxed) {
            Some("interrupted (Ctrl-C)".into())
        } else {
            None
        }
    });
    let c = ctx.clone();
    engine.on_print(move |s| c.print(s));
    let c = ctx.clone();
    engine.on_debug(move |s, src, pos| {
        let at = match (src, pos.line()) {
            (Some(src), Some(l)) => format!("{src}:{l}: "),
            (None, Some(l)) => format!("line {l}: "),
            _ => String::new(),
        };
        c.print(&format!("{at}{s}"))
    });
    // stdlib modules: `import "focus" as focus;` from ./stdlib or the source tree's stdlib/;
    // no caching, so edited modules are picked up at once.
    let mut resolvers = rhai::module_resolvers::ModuleResolversCollection::new();
    for dir in [
        std::path::PathBuf::from("stdlib"),
        Path::new(env!("CARGO_MANIFEST_DIR")).join("stdlib"),
    ] {
        let mut r = rhai::module_resolvers::FileModuleResolver::new_with_path(dir);
        r.enable_cache(false);
        resolvers.push(r);
    }
    engine.set_module_resolver(resolvers);

    let mut docs = vec![];
    {
        let mut reg = Registrar::new(&mut engine, &mut docs, ctx.clone());
        for (family, f) in FAMILIES {
            reg.begin_family(family);
            f(&mut reg);
        }
    }
    let docs = Arc::new(docs);
    let _ = ctx.docs.set(docs.clone());
    (engine, docs)
}

/// Every declaration (builds a throw-away engine).
pub fn all_docs() -> Arc<Vec<Doc>> {
    let (s, _) = Settings::captured(std::env::temp_dir().join("bfpscope-docs"));
    build_engine(Arc::new(Ctx::new(s))).1
}

/// One scripting session.
pub struct Workbench {
    pub engine: Engine,
    pub scope: Scope<'static>,
    /// Functions defined so far (REPL lines are merged in).
    lib: AST,
    pub ctx: Arc<Ctx>,
    pub docs: Arc<Vec<Doc>>,
    /// The text last compiled and its source name (for the "did you mean" of a map key).
    text: (String, String),
}

impl Workbench {
    pub fn new(settings: Settings) -> Workbench {
        let ctx = Arc::new(Ctx::new(settings));
        let (engine, docs) = build_engine(ctx.clone());
        Workbench {
            engine,
            scope: Scope::new(),
            lib: AST::empty(),
            ctx,
            docs,
            text: Default::default(),
        }
    }

    /// A key read from a map that does not have it (`s.meta.dwel`): when the map is a chain of
    /// names in the script's scope (`s.meta`), the keys it has, with the closest; otherwise the
    /// message as it was.
    fn map_key_hint(&mut self, e: &mut ScriptError) {
        let Some(key) = e.message.strip_prefix(errors::NO_KEY).map(|r| {
            r.split(|c: char| !(c.is_alphanumeric() || c == '_'))
                .find(|w| !w.is_empty())
                .unwrap_or_default()
                .to_string()
        }) else {
            return;
        };
        let (Some(line), Some(col), true) = (e.line, e.column, e.source == self.text.0) else {
            return;
        };
        let Some(l) = self.text.1.lines().nth(line.saturating_sub(1)) else {
            return;
        };
        let chars: Vec<char> = l.chars().collect();
        // the property's name starts at `col` (1-based), after a `.`
        let dot = col.saturating_sub(2);
        if chars.get(dot) != Some(&'.') {
            return;
        }
        let start = (0..dot)
            .rev()
            .take_while(|&i| chars[i].is_alphanumeric() || chars[i] == '_' || chars[i] == '.')
            .last()
            .unwrap_or(dot);
        let chain: String = chars[start..dot].iter().collect();
        let first = chain.chars().next();
        if chain.is_empty() || first.is_some_and(|c| c.is_ascii_digit() || c == '.') {
            return;
        }
        let Ok(v) = self
            .engine
            .eval_expression_with_scope::<Dynamic>(&mut self.scope, &chain)
        else {
            return;
        };
        let Some(m) = v.read_lock::<rhai::Map>() else {
            return;
        };
        let keys: Vec<&str> = m.keys().map(|k| k.as_str()).collect();
        let hint = words::suggestion(&key, keys.iter().copied());
        let stop = if hint.is_empty() { "." } else { "" };
        e.message = format!(
            "`{chain}` has no key `{key}`{hint}{stop} Its keys: {}",
            keys.join(", ")
        );
    }

    /// Set a script variable (`run --set key=value`).
    pub fn set_var(&mut self, name: &str, value: Dynamic) {
        self.scope.set_or_push(name.to_string(), value);
    }

    /// Names of the variables and script functions defined so far (for completion).
    pub fn user_names(&self) -> Vec<String> {
        let mut v: Vec<String> = self
            .scope
            .iter_raw()
            .map(|(n, _, _)| n.to_string())
            .collect();
        v.extend(self.lib.iter_functions().map(|f| f.name.to_string()));
        v.sort();
        v.dedup();
        v
    }

    /// Each variable's type as scripts name it (`Scan`, `Image`, `map`, `array`, …) and, for a
    /// map, its keys (for completion after `name.`).
    pub fn user_types(&self) -> VarTypes {
        self.scope
            .iter_raw()
            .map(|(n, _, v)| {
                let ty = self.engine.map_type_name(v.type_name()).to_string();
                let keys = v
                    .read_lock::<rhai::Map>()
                    .map(|m| m.keys().map(|k| k.to_string()).collect())
                    .unwrap_or_default();
                (n.to_string(), (ty, keys))
            })
            .collect()
    }

    fn compile(&mut self, source: &str, text: &str) -> Result<AST, ScriptError> {
        let mut ast = self
            .engine
            .compile_with_scope(&self.scope, text)
            .map_err(|e| ScriptError::from_parse(&e, source))?;
        ast.set_source(source);
        self.text = (source.to_string(), text.to_string());
        Ok(ast)
    }

    fn run_ast(&mut self, ast: &AST, source: &str) -> Result<Dynamic, ScriptError> {
        self.ctx.settings.abort.store(false, Ordering::SeqCst);
        self.ctx.set_partial(None);
        // a protocol that failed earlier never reached protocol_end(): a new entry starts clean
        self.ctx
            .protocols
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clear();
        let r = self
            .engine
            .eval_ast_with_scope::<Dynamic>(&mut self.scope, ast);
        let mut r = r.map_err(|e| ScriptError::from_eval(&e, source, &self.docs));
        if let Err(e) = &mut r {
            self.map_key_hint(e);
        }
        if let Err(e) = &r {
            self.ctx.view_error(&e.to_string());
        }
        if r.as_ref().is_err_and(|e| e.interrupted) {
            self.ctx.settings.abort.store(false, Ordering::SeqCst);
        }
        r
    }

    /// Evaluate one REPL entry: variables and functions persist across entries.
    pub fn eval_line(&mut self, text: &str) -> Result<Dynamic, ScriptError> {
        self.ctx.set_script(ScriptInfo {
            path: None,
            sha256: None,
            line: Some(text.to_string()),
        });
        let ast = self.compile("repl", text)?;
        let merged = self.lib.merge(&ast);
        let r = self.run_ast(&merged, "repl");
        let mut lib = merged;
        lib.clear_statements();
        self.lib = lib;
        if r.is_ok() {
            // `import "focus" as focus;` lasts for the session, as variables do: the module is
            // resolved once more and registered under its alias for the following entries.
            for (path, alias) in import_statements(text) {
                let m = self.engine.module_resolver().resolve(
                    &self.engine,
                    None,
                    &path,
                    Position::NONE,
                );
                if let Ok(m) = m {
                    self.engine.register_static_module(alias.as_str(), m);
                }
            }
        }
        r
    }

    /// Evaluate source text named `source` (`eval`, tests) with the session's functions.
    pub fn eval_source(&mut self, source: &str, text: &str) -> Result<Dynamic, ScriptError> {
        let ast = self.compile(source, text)?;
        let merged = self.lib.merge(&ast);
        self.run_ast(&merged, source)
    }

    /// Compile a script file and record its path and hash for the scans' metadata.
    pub fn load_file(&mut self, path: &Path) -> Result<AST, ScriptError> {
        let name = path.display().to_string();
        let text = std::fs::read(path)
            .map_err(|e| ScriptError::plain(format!("cannot read script: {e}"), &name))?;
        let src = String::from_utf8(text)
            .map_err(|_| ScriptError::plain("script is not UTF-8 text", &name))?;
        self.ctx.set_script(ScriptInfo {
            path: Some(std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf())),
            sha256: Some(ctx::sha256_hex(src.as_bytes())),
            line: None,
        });
        self.compile(&name, &src)
    }

    /// Run a script file.
    pub fn run_file(&mut self, path: &Path) -> Result<Dynamic, ScriptError> {
        let ast = self.load_file(path)?;
        let merged = self.lib.merge(&ast);
        self.run_ast(&merged, &path.display().to_string())
    }

    /// Run an already compiled AST (its top-level statements).
    pub fn run_compiled(&mut self, ast: &AST, source: &str) -> Result<Dynamic, ScriptError> {
        self.run_ast(ast, source)
    }

    /// Call a script function of `ast` without re-running its top-level statements.
    /// Evaluate the script's top level, then call its function `name` (no arguments).
    pub fn call_fn(&mut self, ast: &AST, name: &str, source: &str) -> Result<Dynamic, ScriptError> {
        self.ctx.settings.abort.store(false, Ordering::SeqCst);
        self.ctx
            .protocols
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clear();
        let opts = rhai::CallFnOptions::new().eval_ast(true).rewind_scope(true);
        self.engine
            .call_fn_with_options::<Dynamic>(opts, &mut self.scope, ast, name, ())
            .map_err(|e| ScriptError::from_eval(&e, source, &self.docs))
    }
}

/// The seed study of the targeted protocols, `scripts/targeted_study.rhai` (embedded), run as
/// `bfpscope run` would (the default instrument connected first) in a throw-away session on the
/// simulator whose scans are autosaved to a temporary folder (removed afterwards): the numbers `bfpscope accuracy` reports (`accuracy::report::ReportOptions::targeted`).
/// `quick` (CI): targeted::bead over 2 seeds and targeted::filament over 1 seed of a 1 µm
/// stretch; else 20 seeds of each, 3 µm. Returns the script's map as JSON
/// (`{bead: {...}, filament: {...}}`).
pub fn targeted_study(quick: bool) -> Result<serde_json::Value, String> {
    let dir = std::env::temp_dir().join(format!("bfpscope-targeted-study-{}", std::process::id()));
    let (settings, _printed) = Settings::captured(&dir);
    let mut wb = Workbench::new(settings);
    // the default instrument first, as `bfpscope run` and `bfpscope test` connect it: the study's
    // simulate(scene) then keeps its settle time (a sim attached by simulate() alone settles
    // 10 ms per move)
    motion::connect_config(&wb.ctx, &crate::config::Config::default())
        .map_err(|e| format!("scripts/targeted_study.rhai: {e}"))?;
    let (n, nf, len) = if quick { (2, 1, 1.0) } else { (20, 20, 3.0) };
    wb.set_var("n_seeds", Dynamic::from(n as i64));
    wb.set_var("fil_seeds", Dynamic::from(nf as i64));
    wb.set_var("fil_len_um", Dynamic::from(len));
    let r = wb.eval_source(
        "scripts/targeted_study.rhai",
        include_str!("../../scripts/targeted_study.rhai"),
    );
    let _ = std::fs::remove_dir_all(&dir);
    let v = r.map_err(|e| format!("scripts/targeted_study.rhai: {e}"))?;
    Ok(types::dynamic_to_json(&v))
}

/// `(path, alias)` of every `import "path" as alias` statement in a REPL entry (a plain scan:
/// string literals and comments elsewhere on the line are not imports Rhai would accept either,
/// and a failed resolve is ignored).
fn import_statements(text: &str) -> Vec<(String, String)> {
    let mut out = vec![];
    let mut rest = text;
    while let Some(i) = rest.find("import") {
        let before_ok = rest[..i]
            .chars()
            .last()
            .is_none_or(|c| !(c.is_alphanumeric() || c == '_'));
        rest = &rest[i + 6..];
        if !before_ok {
            continue;
        }
        let t = rest.trim_start();
        let Some(t) = t.strip_prefix('"') else {
            continue;
        };
        let Some(end) = t.find('"') else { continue };
        let path = t[..end].to_string();
        let t = t[end + 1..].trim_start();
        let Some(t) = t.strip_prefix("as") else {
            continue;
        };
        if !t.starts_with(char::is_whitespace) {
            continue;
        }
        let alias: String = t
            .trim_start()
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect();
        if !alias.is_empty() {
            out.push((path, alias));
        }
    }
    out
}

#[cfg(test)]
mod import_tests {
    use super::import_statements;

    #[test]
    fn finds_import_statements() {
        assert_eq!(
            import_statements(r#"import "focus" as focus; let x = 1; import "tips" as t;"#),
            vec![
                ("focus".into(), "focus".into()),
                ("tips".into(), "t".into())
            ]
        );
        assert!(import_statements(r#"let reimport = "x" ; important()"#).is_empty());
    }
}
