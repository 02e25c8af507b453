//! The import graph of `src/` (issue 15): what each top-level module imports from the others,
//! read from the code (`crate::<module>` outside `#[cfg(test)]`), must equal the table in
//! docs/guide.md's architecture section and keep the layering rules.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

type Graph = BTreeMap<String, BTreeSet<String>>;

fn rs_files(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rs_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// `crate::name` references in `code`, comments and test modules removed.
fn crate_refs(code: &str) -> BTreeSet<String> {
    let code = code.split("#[cfg(test)]").next().unwrap_or("");
    let mut out = BTreeSet::new();
    for line in code.lines() {
        let line = line.split("//").next().unwrap_or("");
        let mut rest = line;
        while let Some(i) = rest.find("crate::") {
            rest = &rest[i + 7..];
            let name: String = rest
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            if !name.is_empty() {
                out.insert(name);
            }
        }
    }
    out
}

fn code_graph() -> Graph {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = vec![];
    rs_files(&src, &mut files);
    let mut g = Graph::new();
    for f in files {
        let rel = f.strip_prefix(&src).unwrap();
        let top = rel
            .components()
            .next()
            .unwrap()
            .as_os_str()
            .to_string_lossy()
            .trim_end_matches(".rs")
            .to_string();
        if top == "lib" || top == "main" {
            continue;
        }
        let refs = crate_refs(&std::fs::read_to_string(&f).unwrap());
        let e = g.entry(top.clone()).or_default();
        e.extend(refs.into_iter().filter(|r| *r != top));
    }
    g
}

fn doc_graph() -> Graph {
    let guide =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/guide.md"))
            .unwrap();
    let table = guide
        .split("<!-- import-graph -->")
        .nth(1)
        .and_then(|t| t.split("<!-- /import-graph -->").next())
        .expect("docs/guide.md has an <!-- import-graph --> table");
    let mut g = Graph::new();
    for row in table.lines().filter(|l| l.starts_with("| `")) {
        let cells: Vec<&str> = row.split('|').map(str::trim).collect();
        let name = cells[1].trim_matches('`').to_string();
        let deps = cells[2]
            .split(',')
            .map(|d| d.trim().trim_matches('`').to_string())
            .filter(|d| !d.is_empty() && d != "—")
            .collect();
        g.insert(name, deps);
    }
    g
}

#[test]
fn import_graph_matches_the_guide() {
    let (code, doc) = (code_graph(), doc_graph());
    assert_eq!(
        code, doc,
        "the import graph of src/ (left) differs from docs/guide.md's architecture table (right)"
    );
}

#[test]
fn layering_rules_hold() {
    let g = code_graph();
    let forbid = |m: &str, bad: &[&str]| {
        for b in bad {
            assert!(
                !g[m].contains(*b),
                "{m} must not import {b} (docs/guide.md, Architecture)"
            );
        }
    };
    forbid("optics", &["script", "acquire", "accuracy"]);
    forbid("analysis", &["script", "acquire", "accuracy"]);
    forbid("instrument", &["acquire", "script"]);
    for (m, deps) in &g {
        if m != "repl" {
            assert!(!deps.contains("script"), "{m} imports script");
        }
        for d in deps {
            assert!(
                !g.get(d).is_some_and(|dd| dd.contains(m)),
                "{m} and {d} import each other"
            );
        }
    }
}

/// Identifiers a path starting at `rest` names first: `name` or each item's first segment of a
/// `{a, b::c, …}` group (nested groups count by their first segment only).
fn path_heads(rest: &str) -> Vec<String> {
    let ident = |s: &str| -> String {
        s.trim_start()
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
            .collect()
    };
    if let Some(group) = rest.trim_start().strip_prefix('{') {
        let (mut depth, mut end) = (0usize, group.len());
        for (i, c) in group.char_indices() {
            match c {
                '{' => depth += 1,
                '}' if depth == 0 => {
                    end = i;
                    break;
                }
                '}' => depth -= 1,
                _ => {}
            }
        }
        let mut heads = vec![];
        let (mut depth, mut start) = (0usize, 0usize);
        let inner = &group[..end];
        for (i, c) in inner
            .char_indices()
            .chain(std::iter::once((inner.len(), ',')))
        {
            match c {
                '{' => depth += 1,
                '}' => depth -= 1,
                ',' if depth == 0 => {
                    let h = ident(&inner[start..i.min(inner.len())]);
                    if !h.is_empty() {
                        heads.push(h);
                    }
                    start = i + 1;
                }
                _ => {}
            }
        }
        heads
    } else {
        vec![ident(rest)]
    }
}

/// Code without comments and without what follows the first `#[cfg(test)]`.
fn code_only(text: &str) -> String {
    let code = text.split("#[cfg(test)]").next().unwrap_or("");
    code.lines()
        .map(|l| l.split("//").next().unwrap_or(""))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The `pub use child::{…};` statements of a `mod.rs`: re-exported name → the file defining it,
/// and the text without them (re-exports and `mod` declarations are the facade, not a use).
fn reexports(code: &str, files: &BTreeSet<String>) -> (BTreeMap<String, String>, String) {
    let mut map = BTreeMap::new();
    let mut rest = String::new();
    for stmt in code.split_inclusive(';') {
        let s = stmt.trim_start();
        let s = s.trim_start_matches("#[doc(inline)]").trim_start();
        if let Some(body) = s.strip_prefix("pub use ") {
            let child = path_heads(body).remove(0);
            if files.contains(&child) {
                let after = body.trim_start()[child.len()..].trim_start_matches("::");
                for name in path_heads(after) {
                    map.insert(name, child.clone());
                }
                continue;
            }
        }
        if s.starts_with("pub mod ") || s.starts_with("mod ") && !s.contains('{') {
            continue;
        }
        rest.push_str(stmt);
    }
    (map, rest)
}

/// The file graph inside `src/<dir>/`: each file (`mod` for mod.rs) → the files of the same
/// directory it uses (`super::x`, `crate::<dir>::x`, and in mod.rs `x::…`/`self::x`). A name that
/// is no file is an item of mod.rs, or of the file mod.rs re-exports it from.
fn inner_graph(dir: &str) -> Graph {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src").join(dir);
    let mut files = BTreeSet::new();
    for e in std::fs::read_dir(&root).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            // a sub-folder is a module of its own, checked by its own inner_graph (its files
            // reach this folder only through `super::super::`, which is not counted here)
            let name = p.file_name().unwrap().to_string_lossy().to_string();
            assert!(
                SUB_FOLDERS.contains(&format!("{dir}/{name}").as_str()),
                "{dir}/{name}/ is a sub-folder the cycle test does not check: add it to SUB_FOLDERS"
            );
            continue;
        }
        if p.extension().is_some_and(|x| x == "rs") {
            files.insert(p.file_stem().unwrap().to_string_lossy().to_string());
        }
    }
    // the folder's module file: `dir/mod.rs`, or `dir.rs` beside the folder
    let mod_path = if root.join("mod.rs").exists() {
        root.join("mod.rs")
    } else {
        files.insert("mod".into());
        root.with_extension("rs")
    };
    let mod_code = code_only(&std::fs::read_to_string(&mod_path).unwrap());
    let (reexported, mod_rest) = reexports(&mod_code, &files);
    let resolve = |name: &str| -> Option<String> {
        if name == "self" || name == "super" || name == "crate" || name.is_empty() {
            None
        } else if files.contains(name) {
            Some(name.to_string())
        } else {
            Some(reexported.get(name).cloned().unwrap_or("mod".into()))
        }
    };
    let mut g = Graph::new();
    for f in &files {
        let code = if f == "mod" {
            mod_rest.clone()
        } else {
            code_only(&std::fs::read_to_string(root.join(format!("{f}.rs"))).unwrap())
        };
        let mut prefixes = vec![format!("crate::{}::", dir.replace('/', "::"))];
        if f == "mod" {
            prefixes.push("self::".into());
        } else {
            prefixes.push("super::".into());
        }
        let mut deps = BTreeSet::new();
        for p in &prefixes {
            let mut at = 0;
            while let Some(i) = code[at..].find(p.as_str()) {
                // the character before the match, in the whole file (`super::super::…`: the
                // second `super::` follows the first's `:`)
                let before = code[..at + i].chars().last();
                at += i + p.len();
                let rest = &code[at..];
                if p == "super::" && (before == Some(':') || rest.starts_with("super::")) {
                    continue; // `super::super::…` leaves the directory
                }
                deps.extend(path_heads(rest).iter().filter_map(|h| resolve(h)));
            }
        }
        if f == "mod" {
            // mod.rs names its files directly: `child::item`.
            for child in files.iter().filter(|c| *c != "mod") {
                let pat = format!("{child}::");
                let mut rest = code.as_str();
                while let Some(i) = rest.find(&pat) {
                    let before = rest[..i].chars().last();
                    rest = &rest[i + pat.len()..];
                    if !before.is_some_and(|c| c.is_ascii_alphanumeric() || c == '_' || c == ':') {
                        deps.insert(child.clone());
                    }
                }
            }
        }
        deps.remove(f);
        g.insert(f.clone(), deps);
    }
    g
}

/// A cycle of `g`, if it has one (as the list of its nodes, first repeated at the end).
fn find_cycle(g: &Graph) -> Option<Vec<String>> {
    fn visit(
        n: &str,
        g: &Graph,
        state: &mut BTreeMap<String, u8>,
        stack: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        state.insert(n.into(), 1);
        stack.push(n.into());
        for d in g.get(n).into_iter().flatten() {
            match state.get(d.as_str()).copied().unwrap_or(0) {
                1 => {
                    let at = stack.iter().position(|s| s == d).unwrap();
                    let mut c = stack[at..].to_vec();
                    c.push(d.clone());
                    return Some(c);
                }
                0 => {
                    if let Some(c) = visit(d, g, state, stack) {
                        return Some(c);
                    }
                }
                _ => {}
            }
        }
        stack.pop();
        state.insert(n.into(), 2);
        None
    }
    let mut state = BTreeMap::new();
    for n in g.keys() {
        if !state.contains_key(n.as_str()) {
            if let Some(c) = visit(n, g, &mut state, &mut vec![]) {
                return Some(c);
            }
        }
    }
    None
}

#[test]
fn cycle_finder_finds_cycles() {
    let g = |edges: &[(&str, &str)]| {
        let mut g = Graph::new();
        for (a, b) in edges {
            g.entry(a.to_string()).or_default().insert(b.to_string());
            g.entry(b.to_string()).or_default();
        }
        g
    };
    assert_eq!(find_cycle(&g(&[("a", "b"), ("b", "c"), ("a", "c")])), None);
    assert_eq!(
        find_cycle(&g(&[("a", "b"), ("b", "c"), ("c", "a")])),
        Some(vec!["a".into(), "b".into(), "c".into(), "a".into()])
    );
    assert_eq!(
        path_heads(" {fit::{A, B}, peaks, Result};"),
        vec!["fit".to_string(), "peaks".into(), "Result".into()]
    );
}

/// The sub-folders of the checked folders, each checked in turn.
const SUB_FOLDERS: [&str; 1] = ["analysis/fit"];

#[test]
fn files_inside_analysis_and_script_import_no_cycle() {
    for dir in ["analysis", "script"].into_iter().chain(SUB_FOLDERS) {
        let g = inner_graph(dir);
        if let Some(c) = find_cycle(&g) {
            let table: Vec<String> = g
                .iter()
                .map(|(f, d)| {
                    format!(
                        "  {f}: {}",
                        d.iter().cloned().collect::<Vec<_>>().join(", ")
                    )
                })
                .collect();
            panic!(
                "files inside src/{dir}/ import each other in a cycle: {}\n{}",
                c.join(" → "),
                table.join("\n")
            );
        }
    }
}
