//! The import graph of `src/`: what each top-level module imports from the others,
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
            let body = body.trim_start();
            let body = body.strip_prefix("self::").unwrap_or(body);
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

/// The `.rs` files of a module folder and of its sub-folders, each with its depth below
/// `dir`'s module: `dir/x.rs` and `dir/g/mod.rs` are 1 (modules `dir::x`, `dir::g`),
/// `dir/g/y.rs` is 2; `dir/mod.rs` is 0.
fn module_files(dir: &Path, depth: usize, out: &mut Vec<(std::path::PathBuf, usize)>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            module_files(&p, depth + 1, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            let is_mod = p.file_stem().is_some_and(|s| s == "mod");
            out.push((p, if is_mod { depth } else { depth + 1 }));
        }
    }
}

/// The folders under `src/` that hold a module's files (every folder with a `.rs` file in it
/// or below), as paths relative to `src/` with `/`.
fn module_folders() -> Vec<String> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<String>) {
        let mut has_rs = false;
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else if p.extension().is_some_and(|x| x == "rs") {
                has_rs = true;
            }
        }
        if has_rs && dir != root {
            let rel = dir
                .strip_prefix(root)
                .unwrap()
                .to_string_lossy()
                .replace('\\', "/");
            out.push(rel);
        }
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut out = vec![];
    walk(&root, &root, &mut out);
    out.sort();
    out
}

/// The graph inside the module folder `src/<dir>/`: its nodes are the folder's children — each
/// file (`mod` for the folder's own module file, `dir/mod.rs` or `dir.rs` beside the folder) and
/// each sub-folder (with its module file `g.rs` beside it, as one node `g`, all its files
/// included) — and child A → child B when code in A names B: `super::…` climbing exactly to
/// `dir`'s module (one `super::` from `dir/x.rs`, two from `dir/g/y.rs`), `crate::<dir>::…`,
/// and in the module file `self::…` and `child::…`. A name that is no child is an item of the
/// module file (`mod`), or of the child the module file re-exports it from.
fn inner_graph(dir: &str) -> Graph {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src").join(dir);
    // children: file stems and sub-folder names
    let mut children = BTreeSet::new();
    for e in std::fs::read_dir(&root).unwrap() {
        let p = e.unwrap().path();
        let stem = p.file_stem().unwrap().to_string_lossy().to_string();
        if p.is_dir() || p.extension().is_some_and(|x| x == "rs") {
            children.insert(stem);
        }
    }
    // the folder's module file: `dir/mod.rs`, or `dir.rs` beside the folder
    let mod_path = if root.join("mod.rs").exists() {
        root.join("mod.rs")
    } else {
        children.insert("mod".into());
        root.with_extension("rs")
    };
    let mod_code = code_only(&std::fs::read_to_string(&mod_path).unwrap());
    let (reexported, mod_rest) = reexports(&mod_code, &children);
    let resolve = |name: &str| -> Option<String> {
        if name == "self" || name == "super" || name == "crate" || name.is_empty() {
            None
        } else if children.contains(name) {
            Some(name.to_string())
        } else {
            Some(reexported.get(name).cloned().unwrap_or("mod".into()))
        }
    };
    // every file with the child it belongs to and its depth below `dir`'s module
    let mut files: Vec<(String, std::path::PathBuf, usize)> = vec![("mod".into(), mod_path, 0)];
    let mut inside = vec![];
    module_files(&root, 0, &mut inside);
    for (p, depth) in inside {
        if p.file_name().is_some_and(|n| n == "mod.rs") && p.parent() == Some(root.as_path()) {
            continue; // the module file itself
        }
        let first = p.strip_prefix(&root).unwrap().components().next().unwrap();
        let child = Path::new(first.as_os_str())
            .file_stem()
            .unwrap()
            .to_string_lossy()
            .to_string();
        files.push((child, p, depth));
    }
    // a sub-module's file beside its folder (`dir/g.rs` for `dir/g/`) is in `inside` already
    let crate_prefix = format!("crate::{}::", dir.replace('/', "::"));
    let mut g = Graph::new();
    for c in &children {
        g.insert(c.clone(), BTreeSet::new());
    }
    for (child, path, depth) in &files {
        let code = if child == "mod" {
            mod_rest.clone()
        } else {
            code_only(&std::fs::read_to_string(path).unwrap())
        };
        let mut deps = BTreeSet::new();
        // `crate::<dir>::child…`
        let mut at = 0;
        while let Some(i) = code[at..].find(crate_prefix.as_str()) {
            at += i + crate_prefix.len();
            deps.extend(path_heads(&code[at..]).iter().filter_map(|h| resolve(h)));
        }
        // a run of exactly `depth` `super::` (one starting a path, not inside `a::super::`)
        if *depth > 0 {
            let mut at = 0;
            while let Some(i) = code[at..].find("super::") {
                let start = at + i;
                let before = code[..start].chars().last();
                let mut end = start;
                let mut run = 0;
                while code[end..].starts_with("super::") {
                    end += "super::".len();
                    run += 1;
                }
                at = end;
                if before == Some(':') || run != *depth {
                    continue;
                }
                deps.extend(path_heads(&code[end..]).iter().filter_map(|h| resolve(h)));
            }
        } else {
            // the module file names its children `self::child…` or `child::…`
            let mut at = 0;
            while let Some(i) = code[at..].find("self::") {
                let before = code[..at + i].chars().last();
                at += i + "self::".len();
                if !before.is_some_and(|c| c.is_ascii_alphanumeric() || c == '_' || c == ':') {
                    deps.extend(path_heads(&code[at..]).iter().filter_map(|h| resolve(h)));
                }
            }
            for c in children.iter().filter(|c| *c != "mod") {
                let pat = format!("{c}::");
                let mut rest = code.as_str();
                while let Some(i) = rest.find(&pat) {
                    let before = rest[..i].chars().last();
                    rest = &rest[i + pat.len()..];
                    if !before.is_some_and(|c| c.is_ascii_alphanumeric() || c == '_' || c == ':') {
                        deps.insert(c.clone());
                    }
                }
            }
        }
        deps.remove(child);
        g.get_mut(child).unwrap().extend(deps);
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

/// Every module folder under `src/` (sub-folders included, e.g. `analysis/fit`,
/// `instrument/sim`): its children import each other without a cycle. (The modules of `src/`
/// itself: [`import_graph_has_no_cycle`].)
#[test]
fn files_inside_every_folder_import_no_cycle() {
    let folders = module_folders();
    for must in [
        "analysis",
        "analysis/fit",
        "acquire/strategy",
        "instrument/sim",
        "optics",
        "script",
    ] {
        assert!(
            folders.iter().any(|f| f == must),
            "{must} not found among {folders:?}"
        );
    }
    let mut cycles = vec![];
    for dir in &folders {
        let g = inner_graph(dir);
        if let Some(c) = find_cycle(&g) {
            let table: Vec<String> = g
                .iter()
                .map(|(f, d)| {
                    format!(
                        "    {f}: {}",
                        d.iter().cloned().collect::<Vec<_>>().join(", ")
                    )
                })
                .collect();
            cycles.push(format!(
                "src/{dir}/: {}\n{}",
                c.join(" → "),
                table.join("\n")
            ));
        }
    }
    assert!(
        cycles.is_empty(),
        "files inside these folders import each other in a cycle:\n{}",
        cycles.join("\n")
    );
}

/// The modules of `src/` import each other without a cycle of any length.
#[test]
fn import_graph_has_no_cycle() {
    let g = code_graph();
    assert_eq!(find_cycle(&g), None, "{g:?}");
}

/// The inner graph reads what it should: `super::super::` from a sub-folder's file is an edge
/// of the folder above, a sub-folder with its module file beside it is one node, `self::` and
/// re-exports in the module file.
#[test]
fn inner_graph_reads_sub_folders() {
    let g = inner_graph("acquire");
    assert!(g.contains_key("strategy"), "{g:?}");
    // strategy/stream.rs: `super::super::raster::…`
    assert!(g["strategy"].contains("raster"), "{g:?}");
    let i = inner_graph("instrument");
    // emulator/…: `crate::instrument::sim::…`
    assert!(i["emulator"].contains("sim"), "{i:?}");
    // optics/mie.rs with optics/mie/ beside it: one node
    let o = inner_graph("optics");
    assert!(o.contains_key("mie") && !o.contains_key("bessel"), "{o:?}");
    assert!(o["mie_beam"].contains("beam"), "{o:?}");
}

/// The device families `src/instrument/registry.rs` lists (`&super::NAME::FAMILY`).
fn registered_families() -> BTreeSet<String> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(root.join("src/instrument/registry.rs")).unwrap();
    let list = text
        .split("pub const FAMILIES")
        .nth(1)
        .and_then(|t| t.split("];").next())
        .expect("registry.rs has `pub const FAMILIES: … = &[…];`");
    list.lines()
        .filter_map(|l| {
            l.trim()
                .strip_prefix("&super::")
                .and_then(|r| r.strip_suffix("::FAMILY,"))
                .map(String::from)
        })
        .collect()
}

#[test]
fn every_instrument_folder_is_a_registered_family() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/instrument");
    let folders: BTreeSet<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_dir())
        .map(|p| p.file_name().unwrap().to_string_lossy().to_string())
        .collect();
    let listed = registered_families();
    assert_eq!(
        folders, listed,
        "folders of src/instrument (left) and the families of registry.rs (right) differ: a family \
         is one folder and one line of the registry"
    );
    for f in &listed {
        // the declaration sits in the folder's module file, or (a family the config names) in
        // its `config.rs` beside the section it refers to, re-exported by the module file
        let read = |file: &str| std::fs::read_to_string(dir.join(f).join(file)).unwrap_or_default();
        let (module, config) = (read("mod.rs"), read("config.rs"));
        // `name: "f"` in the literal, or `Family::new("f", …)` it takes the rest from
        let declared = |code: &str| {
            let code: String = code.split_whitespace().collect();
            code.contains(&format!("name:\"{f}\""))
                || code.contains(&format!("Family::new(\"{f}\","))
        };
        assert!(
            declared(&module) || declared(&config) && module.contains("pub use config::FAMILY;"),
            "src/instrument/{f}/ declares its FAMILY with name: \"{f}\" or Family::new(\"{f}\", …) \
             (mod.rs, or config.rs re-exported by mod.rs)"
        );
    }
}

#[test]
fn no_family_name_outside_the_instrument_folders() {
    // the names `connect` used to keep in string lists: the config and `connect` learn them
    // from the registry now (help text may name them, escaped inside a string)
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = vec![];
    rs_files(&root.join("config"), &mut files);
    files.push(root.join("script/motion.rs"));
    files.push(root.join("script/ctx.rs"));
    let mut hits = vec![];
    for f in files {
        let code = code_only(&std::fs::read_to_string(&f).unwrap());
        for (i, line) in code.lines().enumerate() {
            for name in ["thorlabs", "hardware", "bench", "emulated"] {
                let lit = format!("\"{name}\"");
                if line.contains(&lit) && !line.contains(&format!("\\{lit}")) {
                    hits.push(format!("{}:{}: {}", f.display(), i + 1, line.trim()));
                }
            }
        }
    }
    assert!(
        hits.is_empty(),
        "family names written outside src/instrument:\n{}",
        hits.join("\n")
    );
}

/// `text` with comments, string and character literals blanked (newlines kept), so braces
/// and `fn` are only the code's.
fn blank_literals(text: &str) -> String {
    let b = text.as_bytes();
    let mut out = b.to_vec();
    let blank = |out: &mut Vec<u8>, from: usize, to: usize| {
        for c in &mut out[from..to.min(b.len())] {
            if *c != b'\n' {
                *c = b' ';
            }
        }
    };
    let mut i = 0;
    while i < b.len() {
        let ident_before = i > 0 && (b[i - 1].is_ascii_alphanumeric() || b[i - 1] == b'_');
        if b[i..].starts_with(b"//") {
            let j = text[i..].find('\n').map_or(b.len(), |j| i + j);
            blank(&mut out, i, j);
            i = j;
        } else if b[i..].starts_with(b"/*") {
            let j = text[i..].find("*/").map_or(b.len(), |j| i + j + 2);
            blank(&mut out, i, j);
            i = j;
        } else if !ident_before && (b[i] == b'r' || b[i..].starts_with(b"br")) && {
            let k = i + if b[i] == b'b' { 2 } else { 1 };
            let hashes = b[k..].iter().take_while(|c| **c == b'#').count();
            b.get(k + hashes) == Some(&b'"')
        } {
            let k = i + if b[i] == b'b' { 2 } else { 1 };
            let hashes = b[k..].iter().take_while(|c| **c == b'#').count();
            let end = format!("\"{}", "#".repeat(hashes));
            let start = k + hashes + 1;
            let j = text[start..]
                .find(&end)
                .map_or(b.len(), |j| start + j + end.len());
            blank(&mut out, i, j);
            i = j;
        } else if b[i] == b'"' {
            let mut j = i + 1;
            while j < b.len() && b[j] != b'"' {
                j += if b[j] == b'\\' { 2 } else { 1 };
            }
            blank(&mut out, i, j + 1);
            i = j + 1;
        } else if b[i] == b'\'' {
            // a character literal ('{', '\n', '\u{7f}'), not a lifetime ('a)
            let rest = &text[i + 1..];
            let len = if rest.starts_with('\\') {
                rest.find('\'').map(|j| j + 2)
            } else {
                rest.chars()
                    .next()
                    .filter(|c| rest[c.len_utf8()..].starts_with('\''))
                    .map(|c| c.len_utf8() + 2)
            };
            match len {
                Some(l) => {
                    blank(&mut out, i, i + l);
                    i += l;
                }
                None => i += 1,
            }
        } else {
            i += 1;
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// Index of the brace closing the one at `open`.
fn closing_brace(code: &[u8], open: usize) -> usize {
    let mut depth = 0;
    for (k, c) in code.iter().enumerate().skip(open) {
        match c {
            b'{' => depth += 1,
            b'}' => {
                depth -= 1;
                if depth == 0 {
                    return k;
                }
            }
            _ => {}
        }
    }
    code.len()
}

/// Every function of `src/` outside test modules and test files: (lines from `fn` to its
/// closing brace, `file:line name`).
fn function_lengths() -> Vec<(usize, String)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = vec![];
    rs_files(&root.join("src"), &mut files);
    let mut out = vec![];
    for f in files.iter().filter(|f| !f.ends_with("tests.rs")) {
        let code = blank_literals(&std::fs::read_to_string(f).unwrap());
        let b = code.as_bytes();
        let line_of = |at: usize| code[..at].matches('\n').count() + 1;
        // test modules: `#[cfg(test)]` then `mod name {`
        let mut tests: Vec<(usize, usize)> = vec![];
        for (at, _) in code.match_indices("#[cfg(test)]") {
            let rest = code[at + 12..].trim_start();
            if rest.starts_with("mod ") || rest.starts_with("pub mod ") {
                if let Some(open) = code[at..].find('{').map(|o| at + o) {
                    tests.push((at, closing_brace(b, open)));
                }
            }
        }
        let mut from = 0;
        while let Some(k) = code[from..].find("fn ").map(|k| from + k) {
            from = k + 3;
            let word_start = k == 0 || !(b[k - 1].is_ascii_alphanumeric() || b[k - 1] == b'_');
            if !word_start || tests.iter().any(|(a, z)| (*a..=*z).contains(&k)) {
                continue;
            }
            let name: String = code[k + 3..]
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            // the body: the first `{` before any `;` (a declaration without a body)
            let Some(open) = code[k..].find(['{', ';']).map(|o| k + o) else {
                continue;
            };
            if b[open] == b';' || name.is_empty() {
                continue;
            }
            let close = closing_brace(b, open);
            let rel = f.strip_prefix(root).unwrap().display();
            out.push((
                line_of(close) - line_of(k) + 1,
                format!("{rel}:{} {name}", line_of(k)),
            ));
        }
    }
    out
}

/// Longest a production function of `src/` may be, lines.
const MAX_FN_LINES: usize = 150;

#[test]
fn no_production_function_is_over_150_lines() {
    let long: Vec<(usize, String)> = function_lengths()
        .into_iter()
        .filter(|(n, _)| *n > MAX_FN_LINES)
        .collect();
    let new: Vec<String> = long
        .iter()
        .map(|(n, s)| format!("{s}: {n} lines"))
        .collect();
    assert!(
        new.is_empty(),
        "functions over {MAX_FN_LINES} lines (split them into steps named after what they do):\n{}",
        new.join("\n")
    );
}

/// Longest a binding family's registration function may be: a screen. A family's `register`
/// lists its commands; each command (its declaration and its closure) is a unit of its own.
const MAX_REGISTER_LINES: usize = 60;

#[test]
fn binding_registration_functions_fit_on_a_screen() {
    let long: Vec<String> = function_lengths()
        .into_iter()
        .filter(|(n, s)| {
            let name = s.rsplit(' ').next().unwrap_or("");
            s.starts_with("src/script/") && name.starts_with("register") && *n > MAX_REGISTER_LINES
        })
        .map(|(n, s)| format!("{s}: {n} lines"))
        .collect();
    assert!(
        long.is_empty(),
        "registration functions over {MAX_REGISTER_LINES} lines (one function per command, the \
         family's `register` listing them):\n{}",
        long.join("\n")
    );
}

#[test]
fn function_lengths_count_from_fn_to_its_closing_brace() {
    let code = blank_literals("fn a() {\n    let s = \"}{\";\n    let c = '{';\n}\n// fn b() {\n");
    assert_eq!(code.matches('{').count(), 1, "{code}");
    assert_eq!(
        closing_brace(code.as_bytes(), code.find('{').unwrap()),
        code.rfind('}').unwrap()
    );
}

/// The option keys a binding family file writes as string literals where a key is declared
/// (`("key", "type", "unit", help)` in a `Doc::map`, `Opt::new("key", …)`) or read
/// (`o.f64_or("key", …)`, `m.get("key")`), each with its count.
fn option_key_literals(code: &str) -> BTreeMap<String, usize> {
    let mut n: BTreeMap<String, usize> = BTreeMap::new();
    let key_at = |rest: &str| -> Option<String> {
        let rest = rest.strip_prefix('"')?;
        let end = rest.find('"')?;
        let k = &rest[..end];
        (!k.is_empty()
            && k.bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_'))
        .then(|| k.to_string())
    };
    for line in code.lines() {
        let t = line.trim_start();
        // a declaration tuple on a line of its own: ("key", "type", "unit", help) (not a
        // property's ("name", "what it is"))
        if let Some(rest) = t.strip_prefix('(') {
            if let Some(k) = key_at(rest) {
                let after = &rest[k.len() + 2..];
                let strings = after.split(',').take(3).collect::<Vec<_>>();
                let quoted = |s: &str| s.trim().starts_with('"') && s.trim().ends_with('"');
                if strings.len() == 3 && quoted(strings[1]) && quoted(strings[2]) {
                    *n.entry(k).or_default() += 1;
                }
            }
        }
        let reads = [
            "Opt::new(",
            ".f64(",
            ".f64_or(",
            ".req_f64(",
            ".int(",
            ".req_int(",
            ".bool_or(",
            ".string(",
            ".axis_strings(",
            ".range(",
            ".req_range(",
            ".value(",
            ".has(",
            ".get(",
            ".contains_key(",
        ];
        for r in reads {
            let mut from = 0;
            while let Some(i) = line[from..].find(r) {
                let at = from + i + r.len();
                if let Some(k) = key_at(&line[at..]) {
                    *n.entry(k).or_default() += 1;
                }
                from = at;
            }
        }
    }
    n
}

#[test]
fn option_key_literals_are_counted_where_declared_and_read() {
    let code = "    (\"dwell\", \"float\", \"s\", \"optional\"),\n let d = o.f64_or(\"dwell\", 1.0)?;\nconst N: Opt = Opt::new(\"n_avg\", \"int\", \"\");\n        (\"sigma\", \"pixel noise used\"),\n";
    let n = option_key_literals(code);
    assert_eq!(n.get("dwell"), Some(&2));
    assert_eq!(n.get("sigma"), None, "a property's name and description");
    assert_eq!(n.get("n_avg"), Some(&1));
    assert_eq!(n.get("float"), None);
}

#[test]
fn no_binding_option_key_is_written_twice() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/script");
    let mut twice = vec![];
    let mut files = vec![];
    rs_files(&dir, &mut files);
    for f in files {
        let name = f.file_name().unwrap().to_string_lossy().to_string();
        let text = std::fs::read_to_string(&f).unwrap();
        let code = text.split("#[cfg(test)]").next().unwrap_or_default();
        let keys: Vec<String> = option_key_literals(code)
            .into_iter()
            .filter(|(_, c)| *c > 1)
            .map(|(k, c)| format!("{k} ×{c}"))
            .collect();
        if !keys.is_empty() {
            twice.push(format!("src/script/{name}: {}", keys.join(", ")));
        }
    }
    assert!(
        twice.is_empty(),
        "option keys written more than once (declare a `const K: Opt = Opt::new(\"key\", …)` and use K where the key is declared and read):\n{}",
        twice.join("\n")
    );
}
