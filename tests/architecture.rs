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
