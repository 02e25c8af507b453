//! The interactive prompt (rustyline): history across sessions, completion of binding names,
//! methods and map keys, signature hints, multi-line input (an entry that Rhai's parser finds
//! unfinished continues on the next line), Ctrl-C cancels the line being typed or interrupts a
//! running script or scan, Ctrl-D exits. Works with piped stdin too (one entry per complete
//! statement), which is how the tests drive it.

use crate::script::ctx::{err_line, out_line};
use crate::script::registry::Kind;
use crate::script::{show, Doc, Workbench};
use rhai::{Engine, ParseErrorType};
use rustyline::completion::{Completer, Pair};
use rustyline::error::ReadlineError;
use rustyline::highlight::Highlighter;
use rustyline::hint::Hinter;
use rustyline::history::DefaultHistory;
use rustyline::validate::{ValidationContext, ValidationResult, Validator};
use rustyline::{Context, Editor, Helper};
use std::io::IsTerminal;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

/// True when `text` is an unfinished Rhai entry (an open block, bracket or call): the parser
/// ran into the end of the input.
pub fn is_incomplete(parser: &Engine, text: &str) -> bool {
    if text.trim().is_empty() {
        return false;
    }
    match parser.compile(text) {
        Ok(_) => false,
        Err(e) => match e.err_type() {
            ParseErrorType::UnexpectedEOF => true,
            ParseErrorType::MissingToken(..) => at_end(text, e.position()),
            _ => false,
        },
    }
}

fn at_end(text: &str, pos: rhai::Position) -> bool {
    let Some(line) = pos.line() else { return true };
    let lines: Vec<&str> = text.trim_end().lines().collect();
    let n = lines.len().max(1);
    if line > n {
        return true;
    }
    if line < n {
        return false;
    }
    let col = pos.position().unwrap_or(usize::MAX);
    col > lines.last().map_or(0, |l| l.chars().count())
}

/// The identifier (letters, digits, `_`) that `s` ends with; empty when none.
fn trailing_ident(s: &str) -> String {
    let start = s
        .char_indices()
        .rev()
        .take_while(|(_, c)| c.is_alphanumeric() || *c == '_')
        .last()
        .map_or(s.len(), |(i, _)| i);
    s[start..].to_string()
}

/// `head` ends inside an argument list: the call's name and which argument (0-based) comes
/// next, walking back over balanced brackets and counting the commas between.
fn call_and_argument(head: &str) -> Option<(String, usize)> {
    let (mut depth, mut arg) = (0i32, 0usize);
    for (j, ch) in head.char_indices().rev() {
        match ch {
            ')' | ']' | '}' => depth += 1,
            '(' | '[' | '{' if depth > 0 => depth -= 1,
            '(' => {
                let name = trailing_ident(head[..j].trim_end());
                return (!name.is_empty()).then_some((name, arg));
            }
            '[' | '{' => return None,
            ',' if depth == 0 => arg += 1,
            _ => {}
        }
    }
    None
}

/// Completion, hints and multi-line validation for the prompt.
pub struct ReplHelper {
    docs: Arc<Vec<Doc>>,
    /// Variables and script functions defined so far.
    pub user: Arc<Mutex<Vec<String>>>,
    /// The type of each variable (`Scan`, `Image`, `map`, …) and, for maps, their keys: after
    /// `name.` only what that type has is offered.
    pub types: Arc<Mutex<crate::script::VarTypes>>,
    parser: Engine,
}

impl ReplHelper {
    pub fn new(docs: Arc<Vec<Doc>>) -> Self {
        Self {
            docs,
            user: Arc::default(),
            types: Arc::default(),
            parser: Engine::new_raw(),
        }
    }

    /// Candidates for the word ending at `pos`: `(start, [(display, replacement)])`.
    pub fn candidates(&self, line: &str, pos: usize) -> (usize, Vec<(String, String)>) {
        let before = &line[..pos];
        let start = before
            .rfind(|c: char| !(c.is_alphanumeric() || c == '_'))
            .map_or(0, |i| {
                i + before[i..].chars().next().map_or(1, |c| c.len_utf8())
            });
        let word = &before[start..];
        let prev = before[..start].chars().last();
        let mut out: Vec<(String, String)> = vec![];
        if let Some(head) = before[..start].strip_suffix("::") {
            // `focus::<Tab>`: the module's protocols (from their declarations) and help
            let module = trailing_ident(head);
            let mut names = vec![("help".to_string(), "the module's help page".to_string())];
            for d in crate::script::console::module_protocols(&module).unwrap_or_default() {
                let full = d.get("name").map(|v| v.to_string()).unwrap_or_default();
                let summary = d.get("summary").map(|v| v.to_string()).unwrap_or_default();
                if let Some(f) = full.strip_prefix(&format!("{module}::")) {
                    names.push((f.to_string(), summary));
                }
            }
            for (n, summary) in names {
                if n.starts_with(word) {
                    out.push((format!("{n}  — {summary}"), format!("{n}(")));
                }
            }
            out.sort();
            return (start, out);
        }
        if prev == Some('.') {
            // the receiver: a variable whose type (or, for a map, whose keys) we know
            let recv = trailing_ident(&before[..start - 1]);
            let known = self.types.lock().ok().and_then(|t| t.get(&recv).cloned());
            if let Some((ty, keys)) = &known {
                if ty == "map" {
                    for k in keys.iter().filter(|k| k.starts_with(word)) {
                        out.push((format!("{k}  (key of {recv})"), k.clone()));
                    }
                    out.sort();
                    return (start, out);
                }
            }
            for d in self.docs.iter() {
                let ty = match &d.kind {
                    Kind::Method { ty } | Kind::Property { ty } => ty,
                    _ => continue,
                };
                if known.as_ref().is_some_and(|(t, _)| t != ty) {
                    continue;
                }
                let is_m = matches!(d.kind, Kind::Method { .. });
                if d.name.starts_with(word) {
                    let rep = if is_m {
                        format!("{}(", d.name)
                    } else {
                        d.name.clone()
                    };
                    out.push((format!("{}  ({})", d.signature(), d.family), rep));
                }
            }
        } else if let Some((b, arg)) = self.open_map_call(before) {
            if let Some(d) = self
                .docs
                .iter()
                .find(|d| d.name == b && matches!(d.kind, Kind::Function))
            {
                if let Some(p) = d.params.get(arg) {
                    for k in &p.keys {
                        if k.name.starts_with(word) {
                            let unit = if k.unit.is_empty() {
                                String::new()
                            } else {
                                format!(" [{}]", k.unit)
                            };
                            out.push((
                                format!("{}: {}{unit}", k.name, k.ty),
                                format!("{}: ", k.name),
                            ));
                        }
                    }
                }
            }
        } else {
            for d in self
                .docs
                .iter()
                .filter(|d| matches!(d.kind, Kind::Function))
            {
                if d.name.starts_with(word) {
                    out.push((d.name.clone(), format!("{}(", d.name)));
                }
            }
            if let Ok(u) = self.user.lock() {
                for n in u.iter().filter(|n| n.starts_with(word)) {
                    out.push((n.clone(), n.clone()));
                }
            }
        }
        out.sort();
        out.dedup_by(|a, b| a.1 == b.1);
        (start, out)
    }

    /// If the cursor is inside `name(a, b, #{ … ` (an unclosed map literal passed to a call, as
    /// any of its arguments), the name of the call and the argument's index.
    fn open_map_call(&self, before: &str) -> Option<(String, usize)> {
        let mut depth = 0i32;
        let bytes = before.as_bytes();
        let mut i = bytes.len();
        while i > 0 {
            i -= 1;
            match bytes[i] {
                b'}' => depth += 1,
                b'{' => {
                    if depth > 0 {
                        depth -= 1;
                    } else if i > 0 && bytes[i - 1] == b'#' {
                        return call_and_argument(&before[..i - 1]);
                    } else {
                        return None;
                    }
                }
                _ => {}
            }
        }
        None
    }

    /// Hint shown after `name(`: the rest of the signature and the summary.
    pub fn hint_for(&self, line: &str) -> Option<String> {
        let name = trailing_ident(line.strip_suffix('(')?);
        let d = self
            .docs
            .iter()
            .find(|d| d.name == name && matches!(d.kind, Kind::Function))?;
        let sig = d.signature();
        let rest = sig.strip_prefix(&format!("{name}("))?;
        Some(format!("{rest}  — {}", d.summary))
    }
}

impl Completer for ReplHelper {
    type Candidate = Pair;
    fn complete(
        &self,
        line: &str,
        pos: usize,
        _: &Context<'_>,
    ) -> rustyline::Result<(usize, Vec<Pair>)> {
        let (start, c) = self.candidates(line, pos);
        Ok((
            start,
            c.into_iter()
                .map(|(display, replacement)| Pair {
                    display,
                    replacement,
                })
                .collect(),
        ))
    }
}

impl Hinter for ReplHelper {
    type Hint = String;
    fn hint(&self, line: &str, pos: usize, _: &Context<'_>) -> Option<String> {
        (pos == line.len()).then(|| self.hint_for(line)).flatten()
    }
}

impl Validator for ReplHelper {
    fn validate(&self, ctx: &mut ValidationContext) -> rustyline::Result<ValidationResult> {
        // The prompt loop itself continues unfinished entries under a `...> ` prompt (the
        // same at a terminal and through a pipe), so every line is accepted here.
        let _ = (&self.parser, ctx.input());
        Ok(ValidationResult::Valid(None))
    }
}

impl Highlighter for ReplHelper {}
impl Helper for ReplHelper {}

/// `~/.bfpscope_history`.
pub fn default_history() -> Option<PathBuf> {
    std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".bfpscope_history"))
}

/// Run the prompt until Ctrl-D / end of input. Returns the process exit code (0).
pub fn run(mut wb: Workbench, history: Option<PathBuf>) -> i32 {
    let tty = std::io::stdin().is_terminal();
    let config = rustyline::Config::builder()
        .auto_add_history(false)
        .completion_type(rustyline::CompletionType::List)
        .max_history_size(10_000)
        .map(|b| b.build())
        .unwrap_or_default();
    let mut rl: Editor<ReplHelper, DefaultHistory> = match Editor::with_config(config) {
        Ok(e) => e,
        Err(e) => {
            eprintln!("error: cannot start the prompt: {e}");
            return 1;
        }
    };
    let helper = ReplHelper::new(wb.docs.clone());
    let user = helper.user.clone();
    let types = helper.types.clone();
    rl.set_helper(Some(helper));
    if let Some(h) = history.as_ref().filter(|_| tty) {
        let _ = rl.load_history(h);
    }
    if tty {
        wb.ctx.set_pause_question(Some(Arc::new(ask_paused)));
        wb.ctx.set_pager(Some(Arc::new(page)));
    }
    if tty {
        println!("bfpscope {} — help() lists the bindings, help(\"name\") explains one; Tab completes; Ctrl-C interrupts, Ctrl-D exits.", env!("CARGO_PKG_VERSION"));
        println!("{}", connected_banner(&wb.ctx));
    }
    let parser = Engine::new_raw();
    let mut buffer = String::new();
    loop {
        let prompt = if buffer.is_empty() { "bfp> " } else { "...> " };
        match rl.readline(prompt) {
            Ok(line) => {
                if !buffer.is_empty() {
                    buffer.push('\n');
                }
                buffer.push_str(&line);
                if is_incomplete(&parser, &buffer) {
                    continue;
                }
                let entry = std::mem::take(&mut buffer);
                if entry.trim().is_empty() {
                    continue;
                }
                let _ = rl.add_history_entry(entry.as_str());
                if is_exit(&entry) {
                    break;
                }
                evaluate(&mut wb, &entry);
                if let Ok(mut u) = user.lock() {
                    *u = wb.user_names();
                }
                if let Ok(mut t) = types.lock() {
                    *t = wb.user_types();
                }
            }
            Err(ReadlineError::Interrupted) => {
                buffer.clear();
                println!("^C  (Ctrl-D exits)");
            }
            Err(ReadlineError::Eof) => break,
            Err(e) => {
                eprintln!("error: {e}");
                break;
            }
        }
    }
    if !buffer.trim().is_empty() {
        evaluate(&mut wb, &buffer); // unfinished entry at end of input: report its error
    }
    if let Some(h) = history.as_ref().filter(|_| tty) {
        let _ = rl.save_history(h);
    }
    0
}

/// Ctrl-C during a scan at the terminal: the scan waits between points or raster lines (the
/// stage at rest, nothing commanded) and asks, with the answers of the stop rule
/// (`acquire::stop_rule`); the count is of pixels, in either mode. Scripts run without a
/// terminal keep Ctrl-C = abort.
fn ask_paused(p: &crate::script::ctx::Paused) -> bool {
    eprintln!(
        "{} paused after {} of {} pixels; the stage waits at x = {:.3}, y = {:.3}, z = {:.3} µm.\n  {}; aborted, {}.",
        p.kind,
        p.measured,
        p.total,
        p.at[0],
        p.at[1],
        p.at[2],
        crate::script::stop_rule::PAUSE_ANSWERS,
        crate::script::stop_rule::ON_ABORT
    );
    let Ok(mut ed) = rustyline::DefaultEditor::new() else {
        return false;
    };
    loop {
        match ed.readline("paused> ") {
            Ok(l) => match l.trim() {
                "" | "r" | "resume" => return true,
                "a" | "abort" => return false,
                other => eprintln!("`{other}`: Enter or r resumes the scan, a aborts it"),
            },
            Err(_) => return false,
        }
    }
}

/// The banner's second line: what is connected and from which config, so the operator sees at
/// once whether the prompt drives the simulator or the hardware the config names.
fn connected_banner(ctx: &crate::script::Ctx) -> String {
    let what = ctx
        .with_instrument("banner", |i| {
            Ok(format!("{}, {}", i.stage.name(), i.qpd.name()))
        })
        .ok();
    let from = match &ctx.settings.config_path {
        Some(p) => format!("config {}", p.display()),
        None => "no config file: the simulated instrument".to_string(),
    };
    match (ctx.backend(), what) {
        (Some(b), Some(w)) => format!("connected {b}: {w} ({from})"),
        _ => format!("nothing connected ({from}); connect() connects what the config names"),
    }
}

/// Long text (`help()`) a screen at a time at the terminal: a page fills the screen but one line,
/// then `-- more --` waits: Enter (or space) shows the next page, `q` (or Ctrl-C, Ctrl-D) stops.
fn page(text: &str) {
    let lines: Vec<&str> = text.lines().collect();
    let Ok(mut ed) = rustyline::DefaultEditor::new() else {
        println!("{text}");
        return;
    };
    // rows the terminal reports (24 when it reports none)
    let rows = match ed.dimensions() {
        Some((_, r)) if r > 0 => usize::from(r).max(6),
        _ => 24,
    };
    if lines.len() < rows {
        println!("{text}");
        return;
    }
    let mut at = 0;
    while at < lines.len() {
        let end = (at + rows - 1).min(lines.len());
        for l in &lines[at..end] {
            println!("{l}");
        }
        at = end;
        if at == lines.len() {
            break;
        }
        let more = format!(
            "-- more: {at} of {} lines; Enter: next page, q: stop -- ",
            lines.len()
        );
        match ed.readline(&more) {
            Ok(a) if a.trim().is_empty() => {}
            _ => {
                println!("({} lines not shown)", lines.len() - at);
                break;
            }
        }
    }
}

/// The REPL's `_` (the last result) becomes the variable `_last` (Rhai has no variable `_`):
/// a lone `_` outside strings and comments, not a `switch` arm's `_ =>`.
pub fn subst_last(entry: &str) -> String {
    let c: Vec<char> = entry.chars().collect();
    let mut out = String::with_capacity(entry.len() + 8);
    let mut i = 0;
    let ident = |ch: char| ch.is_alphanumeric() || ch == '_';
    while i < c.len() {
        let ch = c[i];
        if ch == '"' || ch == '`' || ch == '\'' {
            // copy the string literal
            out.push(ch);
            i += 1;
            while i < c.len() {
                out.push(c[i]);
                if c[i] == '\\' && i + 1 < c.len() {
                    out.push(c[i + 1]);
                    i += 2;
                    continue;
                }
                if c[i] == ch {
                    break;
                }
                i += 1;
            }
            i += 1;
            continue;
        }
        if ch == '/' && c.get(i + 1) == Some(&'/') {
            while i < c.len() && c[i] != '\n' {
                out.push(c[i]);
                i += 1;
            }
            continue;
        }
        if ch == '_' && (i == 0 || !ident(c[i - 1])) && c.get(i + 1).is_none_or(|n| !ident(*n)) {
            let rest: String = c[i + 1..].iter().collect();
            if !rest.trim_start().starts_with("=>") {
                out.push_str("_last");
                i += 1;
                continue;
            }
        }
        out.push(ch);
        i += 1;
    }
    out
}

/// `exit`, `quit` (with or without `()` and `;`) end the session.
pub fn is_exit(entry: &str) -> bool {
    let e = entry.trim().trim_end_matches(';').trim();
    matches!(e, "exit" | "quit" | "exit()" | "quit()")
}

/// Append to the session log (`session.log` in the session folder): the entry and what it gave.
fn log_session(wb: &Workbench, entry: &str, out: &str) {
    use std::io::Write;
    let p = wb.ctx.store.dir().join("session.log");
    let _ = std::fs::create_dir_all(wb.ctx.store.dir());
    if let Ok(mut f) = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(p)
    {
        let mut s = String::new();
        for (i, l) in entry.lines().enumerate() {
            s.push_str(if i == 0 { "bfp> " } else { "...> " });
            s.push_str(l);
            s.push('\n');
        }
        if !out.is_empty() {
            s.push_str(out);
            if !out.ends_with('\n') {
                s.push('\n');
            }
        }
        let _ = f.write_all(s.as_bytes());
    }
}

fn evaluate(wb: &mut Workbench, entry: &str) {
    // everything printed while the entry runs goes to the session log too
    wb.ctx.start_transcript();
    let result = wb.eval_line(&subst_last(entry));
    let printed = wb.ctx.take_transcript();
    let out = match result {
        Ok(v) => {
            let text = if v.is_unit() { String::new() } else { show(&v) };
            if !v.is_unit() {
                out_line(&text);
                // `_` is the last result
                wb.set_var("_last", v);
            }
            text
        }
        Err(e) if e.interrupted => {
            let m = "interrupted (Ctrl-C); the prompt is still here".to_string();
            err_line(&m);
            m
        }
        Err(e) => {
            let mut m = format!("error: {e}");
            err_line(&m);
            if let Some(note) = bind_partial(wb, entry) {
                err_line(&note);
                m.push('\n');
                m.push_str(&note);
            }
            m
        }
    };
    log_session(wb, entry, &format!("{printed}{out}"));
}

/// The scan bindings whose result a partial scan stands in for.
const SCAN_CALLS: &[&str] = &[
    "scan_line",
    "scan_xy",
    "scan_xz",
    "scan_yz",
    "ascan",
    "dscan",
    "mesh",
    "dmesh",
    "lup",
    "a2scan",
    "d2scan",
];

/// `let NAME = scan_xy(…)` / `NAME = scan_xy(…)`: the variable a scan call was assigned to.
pub fn assigned_scan_variable(entry: &str) -> Option<String> {
    let t = entry.trim_start();
    let t = t.strip_prefix("let ").map(str::trim_start).unwrap_or(t);
    let name: String = t
        .chars()
        .take_while(|c| c.is_alphanumeric() || *c == '_')
        .collect();
    if name.is_empty() || name.starts_with(|c: char| c.is_ascii_digit()) {
        return None;
    }
    let rest = t[name.len()..].trim_start();
    let rhs = rest
        .strip_prefix('=')
        .filter(|r| !r.starts_with('='))?
        .trim_start();
    let call: String = rhs
        .chars()
        .take_while(|c| c.is_alphanumeric() || *c == '_')
        .collect();
    let after = rhs[call.len()..].trim_start();
    (SCAN_CALLS.contains(&call.as_str()) && after.starts_with('(')).then_some(name)
}

/// After a scan ended early (Ctrl-C, a device fault), bind its partial scan to `_` and to the
/// variable the entry was assigning it to; the note says where it went.
fn bind_partial(wb: &mut Workbench, entry: &str) -> Option<String> {
    let scan = wb.ctx.take_partial()?;
    let status = scan.scan.status;
    let measured = scan.scan.meta["points_measured"].as_u64().unwrap_or(0);
    let total = scan.scan.meta["points_total"].as_u64().unwrap_or(0);
    let unsaved = scan.path.is_none();
    wb.set_var("_last", rhai::Dynamic::from(scan.clone()));
    let var = assigned_scan_variable(entry);
    if let Some(v) = &var {
        wb.set_var(v, rhai::Dynamic::from(scan));
    }
    let what = if status.to_string() == "complete" {
        "the scan".to_string()
    } else {
        format!("the partial scan ({status}, {measured} of {total} points)")
    };
    let name = var.clone().unwrap_or_else(|| "_".into());
    let target = if unsaved { ", NOT on disk" } else { "" };
    let mut note = format!(
        "{what} is in {}_{target}",
        var.map(|v| format!("`{v}` and ")).unwrap_or_default()
    );
    if unsaved {
        note.push_str(&format!(
            "; save it elsewhere: {name}.save(\"/a/writable/folder/scan.npz\")"
        ));
    }
    Some(note)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_variable_a_scan_is_assigned_to() {
        assert_eq!(
            assigned_scan_variable("let s = scan_xy(#{x: [0, 1]})").as_deref(),
            Some("s")
        );
        assert_eq!(
            assigned_scan_variable("  big2 = ascan(\"x\", 0, 1, 4, 0.01)").as_deref(),
            Some("big2")
        );
        assert_eq!(assigned_scan_variable("let r = focus::search(#{})"), None);
        assert_eq!(assigned_scan_variable("s == scan_xy(#{})"), None);
        assert_eq!(assigned_scan_variable("scan_xy(#{})"), None);
        assert_eq!(assigned_scan_variable("let n = scan_xy"), None);
    }

    #[test]
    fn underscore_is_the_last_result() {
        assert_eq!(subst_last("_ * 10"), "_last * 10");
        assert_eq!(subst_last("let a = _.sx;"), "let a = _last.sx;");
        assert_eq!(subst_last(r#"print("_"); // _"#), r#"print("_"); // _"#);
        assert_eq!(
            subst_last("switch x { 1 => 2, _ => 3 }"),
            "switch x { 1 => 2, _ => 3 }"
        );
        assert_eq!(subst_last("let _x = 1; a_b"), "let _x = 1; a_b");
    }

    #[test]
    fn exit_and_quit_end_the_session() {
        for e in ["exit", "quit", " quit() ", "exit;"] {
            assert!(is_exit(e), "{e}");
        }
        assert!(!is_exit("exits"));
        assert!(!is_exit("let quit = 1"));
    }

    #[test]
    fn incomplete_entries_are_detected() {
        let p = Engine::new_raw();
        assert!(is_incomplete(&p, "fn sq(x) {"));
        assert!(is_incomplete(&p, "let a = [1, 2,"));
        assert!(is_incomplete(&p, "mv(#{x: 1.0,"));
        assert!(!is_incomplete(&p, "fn sq(x) { x * x }"));
        assert!(!is_incomplete(&p, "let a = 1 +* 2;"));
        assert!(!is_incomplete(&p, ""));
    }

    #[test]
    fn completion_of_names_methods_and_map_keys() {
        let h = ReplHelper::new(crate::script::all_docs());
        let (s, c) = h.candidates("scan_x", 6);
        assert_eq!(s, 0);
        assert!(c.iter().any(|c| c.1 == "scan_xy("), "{c:?}");
        assert!(c.iter().any(|c| c.1 == "scan_xz("), "{c:?}");
        let line = "scan_xy(#{x: [0, 1], n";
        let (s, c) = h.candidates(line, line.len());
        assert_eq!(s, line.len() - 1);
        let reps: Vec<&str> = c.iter().map(|c| c.1.as_str()).collect();
        assert_eq!(reps, vec!["nx: ", "ny: "]);
        let line = "let m = s.sx.ab";
        let (_, c) = h.candidates(line, line.len());
        assert!(c.iter().any(|c| c.1 == "abs_max("), "{c:?}");
        let line = "focus::se";
        let (s, c) = h.candidates(line, line.len());
        assert_eq!(s, 7);
        assert_eq!(
            c.iter().map(|c| c.1.as_str()).collect::<Vec<_>>(),
            vec!["search("]
        );
        let (_, c) = h.candidates("beads::", 7);
        let reps: Vec<&str> = c.iter().map(|c| c.1.as_str()).collect();
        assert!(
            reps.contains(&"multi(") && reps.contains(&"sizes(") && reps.contains(&"help("),
            "{reps:?}"
        );
        assert_eq!(
            h.hint_for("mv(").unwrap().split("  —").next().unwrap(),
            "#{x, y, z})"
        );
        // keys of a map that is not the first argument
        let line = "plot(sc, \"f.png\", #{ti";
        let (_, c) = h.candidates(line, line.len());
        assert_eq!(
            c.iter().map(|c| c.1.as_str()).collect::<Vec<_>>(),
            vec!["title: "]
        );
        assert_eq!(
            call_and_argument("f(a, [1, 2], g(3, 4), "),
            Some(("f".into(), 3))
        );
        assert_eq!(call_and_argument("let m = [1, "), None);
        assert_eq!(trailing_ident("let x = abc_1"), "abc_1");
        assert_eq!(trailing_ident("f(µm"), "µm");
        assert_eq!(trailing_ident("f("), "");
    }

    #[test]
    fn completion_after_a_dot_knows_the_variables_type() {
        let h = ReplHelper::new(crate::script::all_docs());
        h.types
            .lock()
            .unwrap()
            .insert("t".into(), ("Template".into(), vec![]));
        h.types.lock().unwrap().insert(
            "r".into(),
            (
                "map".into(),
                vec!["angle_deg".into(), "angle_err_deg".into(), "n".into()],
            ),
        );
        // `t.` offers what a Template has, not an Image's methods
        let (_, c) = h.candidates("t.", 2);
        let reps: Vec<&str> = c.iter().map(|c| c.1.as_str()).collect();
        assert!(reps.contains(&"save("), "{reps:?}");
        assert!(!reps.contains(&"abs_max("), "{reps:?}");
        // an unknown receiver: every method
        let (_, c) = h.candidates("q.ab", 4);
        assert!(c.iter().any(|c| c.1 == "abs_max("), "{c:?}");
        // a map: its keys
        let (_, c) = h.candidates("r.an", 4);
        assert_eq!(
            c.iter().map(|c| c.1.as_str()).collect::<Vec<_>>(),
            vec!["angle_deg", "angle_err_deg"]
        );
    }
}
