//! Script errors as the user reads them: [`ScriptError`] (one line with the position) and
//! [`error_message`] (Rhai's error turned into the console's words: "did you mean", the
//! script names of types, the chain of functions the error passed through).

use super::console;
use super::doc::Doc;
use super::types::show;
use rhai::{EvalAltResult, ParseError, Position};

/// How the error of a key read from a map that does not have it begins (`Workbench` adds the
/// map's keys where it can).
pub const NO_KEY: &str = "the map has no key ";

/// A script error as the user sees it: one line, with the position.
#[derive(Debug, Clone, PartialEq)]
pub struct ScriptError {
    pub message: String,
    /// Script file (or `repl`, `eval`).
    pub source: String,
    pub line: Option<usize>,
    pub column: Option<usize>,
    /// Ctrl-C interrupted the script.
    pub interrupted: bool,
}

impl std::fmt::Display for ScriptError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match (self.line, self.column) {
            (Some(l), Some(c)) => write!(f, "{}:{l}:{c}: {}", self.source, self.message),
            (Some(l), None) => write!(f, "{}:{l}: {}", self.source, self.message),
            _ => write!(f, "{}: {}", self.source, self.message),
        }
    }
}

impl std::error::Error for ScriptError {}

fn pos_parts(p: Position) -> (Option<usize>, Option<usize>) {
    (p.line(), p.position())
}

/// The innermost error of a chain of function calls, its position and source.
fn innermost(e: &EvalAltResult) -> (&EvalAltResult, Position, Option<String>, Vec<String>) {
    let mut cur = e;
    let mut pos = e.position();
    let mut src = None;
    let mut chain = vec![];
    loop {
        match cur {
            EvalAltResult::ErrorInFunctionCall(name, s, inner, p) => {
                chain.push(name.clone());
                if !s.is_empty() {
                    src = Some(s.clone());
                }
                pos = if inner.position().is_none() {
                    *p
                } else {
                    inner.position()
                };
                cur = inner;
            }
            EvalAltResult::ErrorInModule(name, inner, p) => {
                chain.push(format!("module {name}"));
                src = Some(name.clone());
                pos = if inner.position().is_none() {
                    *p
                } else {
                    inner.position()
                };
                cur = inner;
            }
            _ => break,
        }
    }
    (cur, pos, src, chain)
}

/// The text of an error without its position (bindings' own messages come out verbatim);
/// `docs` turn "function not found" into the binding's usage.
pub fn error_message(e: &EvalAltResult, docs: &[Doc]) -> String {
    let (cur, _, _, _) = innermost(e);
    let msg = match cur {
        EvalAltResult::ErrorRuntime(d, _) => {
            if d.is_string() {
                d.to_string()
            } else {
                format!("thrown: {}", show(d))
            }
        }
        EvalAltResult::ErrorTerminated(..) => "interrupted (Ctrl-C)".to_string(),
        EvalAltResult::ErrorTooManyOperations(..) => {
            "script stopped: too many operations (runaway loop?); the limit is [sandbox] max_operations in bfpscope.toml".to_string()
        }
        EvalAltResult::ErrorStackOverflow(..) => {
            "script stopped: calls nested too deeply (runaway recursion?); the limit is [sandbox] max_call_levels".to_string()
        }
        EvalAltResult::ErrorDataTooLarge(what, _) => {
            format!("script stopped: {what} too large; the limits are [sandbox] max_string_size / max_array_size / max_map_size")
        }
        EvalAltResult::ErrorFunctionNotFound(sig, _) => {
            let name = sig.split(['(', ' ']).next().unwrap_or(sig).trim();
            let name = name.rsplit('.').next().unwrap_or(name);
            match docs.iter().find(|d| d.name == name) {
                Some(d) => format!("{name}: wrong arguments {}; usage: {}", sig.trim_start_matches(name).trim(), d.usage()),
                None => {
                    let names = docs.iter().map(|d| d.name.as_str());
                    format!("function not found: {}{}", console::user_words(sig), console::suggestion(name, names))
                }
            }
        }
        EvalAltResult::ErrorPropertyNotFound(name, _) => {
            format!("{NO_KEY}`{name}` (a map's keys: m.keys())")
        }
        EvalAltResult::ErrorVariableNotFound(name, _) => match docs.iter().find(|d| d.name == *name) {
            Some(d) => format!("{name} is a function; usage: {}", d.usage()),
            // only functions a user could have meant (properties like `x` are no variables), and
            // only for names long enough to be misspelt (`s` is not a misspelt `x`)
            None => format!(
                "variable not found: {name}{}",
                if name.chars().count() >= 3 {
                    console::suggestion(
                        name,
                        docs.iter()
                            .filter(|d| matches!(d.kind, super::doc::Kind::Function))
                            .map(|d| d.name.as_str()),
                    )
                } else {
                    String::new()
                }
            ),
        },
        other => {
            let text = other.to_string();
            let suffix = format!(" ({})", other.position());
            let t = match text.strip_suffix(&suffix) {
                Some(t) if !other.position().is_none() => t.to_string(),
                _ => text,
            };
            let t = if t.contains("Range<") || t.contains("RangeInclusive<") {
                // `a[0..4]`: Rhai indexes arrays by one int only
                format!("{t} — an array is indexed by one int (a[2]); a part of it is a.extract(0..4)")
            } else {
                t
            };
            console::property_hint(&t, docs)
        }
    };
    console::user_words(&msg)
}

/// Script functions (not bindings, not closures) the error passed through, innermost first.
fn fn_chain(e: &EvalAltResult, docs: &[Doc]) -> Vec<String> {
    let (_, _, _, chain) = innermost(e);
    let mut v: Vec<String> = chain
        .into_iter()
        .filter(|n| !n.starts_with("anon$") && !docs.iter().any(|d| &d.name == n))
        .collect();
    v.reverse();
    v
}

impl ScriptError {
    pub fn from_eval(e: &EvalAltResult, source: &str, docs: &[Doc]) -> ScriptError {
        let (cur, pos, src, _) = innermost(e);
        let (line, column) = pos_parts(pos);
        ScriptError {
            message: {
                let mut m = error_message(e, docs);
                let fns = fn_chain(e, docs);
                if !fns.is_empty() && !matches!(cur, EvalAltResult::ErrorTerminated(..)) {
                    m.push_str(&format!(" (in {})", fns.join(" ← ")));
                }
                m
            },
            source: src.unwrap_or_else(|| source.to_string()),
            line,
            column,
            interrupted: matches!(cur, EvalAltResult::ErrorTerminated(..)),
        }
    }
    pub fn from_parse(e: &ParseError, source: &str) -> ScriptError {
        let (line, column) = pos_parts(e.position());
        ScriptError {
            message: format!("syntax error: {}", e.err_type()),
            source: source.into(),
            line,
            column,
            interrupted: false,
        }
    }
    pub fn plain(message: impl Into<String>, source: &str) -> ScriptError {
        ScriptError {
            message: message.into(),
            source: source.into(),
            line: None,
            column: None,
            interrupted: false,
        }
    }
}
