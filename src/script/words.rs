//! Words for messages: edit distance and "did you mean", the script names of Rust types, and
//! numbers as the console prints them. A leaf: the registry, the types and the console (which
//! re-exports these) read them from here.

use rhai::Dynamic;

/// Levenshtein distance (small words: names of functions, keys, properties).
pub fn edit_distance(a: &str, b: &str) -> usize {
    let a: Vec<char> = a.chars().collect();
    let b: Vec<char> = b.chars().collect();
    let mut prev: Vec<usize> = (0..=b.len()).collect();
    for i in 1..=a.len() {
        let mut cur = vec![i; b.len() + 1];
        for j in 1..=b.len() {
            let sub = prev[j - 1] + usize::from(a[i - 1] != b[j - 1]);
            cur[j] = sub.min(prev[j] + 1).min(cur[j - 1] + 1);
        }
        prev = cur;
    }
    prev[b.len()]
}

/// The candidates closest to `word` (at most 2 edits for short words, a third of the length for
/// longer ones; a candidate that starts with `word` or contains it counts too), best first.
pub fn did_you_mean<'a>(word: &str, candidates: impl IntoIterator<Item = &'a str>) -> Vec<String> {
    let limit = (word.chars().count() / 3).max(2);
    let mut hits: Vec<(usize, String)> = candidates
        .into_iter()
        .filter(|c| *c != word)
        .filter_map(|c| {
            let d = edit_distance(&word.to_lowercase(), &c.to_lowercase());
            if d <= limit {
                Some((d, c.to_string()))
            } else if word.len() >= 3 && c.starts_with(word) {
                Some((limit + 1, c.to_string()))
            } else {
                None
            }
        })
        .collect();
    hits.sort();
    hits.dedup_by(|a, b| a.1 == b.1);
    let best = hits.first().map_or(0, |h| h.0);
    hits.into_iter()
        .take_while(|h| h.0 == best)
        .take(3)
        .map(|(_, c)| c)
        .collect()
}

/// ` (did you mean `a`, `b`?)` or nothing.
pub fn suggestion<'a>(word: &str, candidates: impl IntoIterator<Item = &'a str>) -> String {
    let v = did_you_mean(word, candidates);
    if v.is_empty() {
        String::new()
    } else {
        format!(
            "; did you mean {}?",
            v.iter()
                .map(|s| format!("`{s}`"))
                .collect::<Vec<_>>()
                .join(" or ")
        )
    }
}

/// The user's name of a Rust type name (`bfpscope::script::types::ScanRef` → `Scan`,
/// `ImmutableString` → `string`).
pub fn user_type(rust: &str) -> String {
    let t = rust.trim().trim_start_matches('&');
    let last = t.rsplit("::").next().unwrap_or(t);
    match last {
        "ImmutableString" | "str" | "String" => "string".into(),
        "i64" | "i32" | "INT" => "int".into(),
        "f64" | "f32" | "FLOAT" => "float".into(),
        "Map" | "BTreeMap<SmartString, Dynamic>" => "map".into(),
        "Array" | "Vec<Dynamic>" => "array".into(),
        "FitRef" => "FitResult".into(),
        "CurveRef" => "AngleCurve".into(),
        "FilamentRef" => "FilamentMeasurement".into(),
        "FnPtr" => "function".into(),
        "()" => "()".into(),
        other => other.strip_suffix("Ref").unwrap_or(other).to_string(),
    }
}

/// The user's name of a value's type.
pub fn user_type_name(v: &Dynamic) -> String {
    user_type(v.type_name())
}

/// Replace Rust type paths in an error message by the user's names
/// (`bfpscope::script::types::ScanRef` → `Scan`, `&str | ImmutableString | String` → `string`).
pub fn user_words(msg: &str) -> String {
    let mut s = msg
        .replace("&str | ImmutableString | String", "string")
        .replace("ImmutableString", "string")
        .replace("&mut ", "");
    // any path a::b::C
    let mut out = String::new();
    let mut rest = s.as_str();
    while let Some(i) = rest.find("::") {
        // start of the path token
        let start = rest[..i]
            .rfind(|c: char| !(c.is_alphanumeric() || c == '_' || c == ':'))
            .map_or(0, |j| j + 1);
        let end = rest[i..]
            .find(|c: char| !(c.is_alphanumeric() || c == '_' || c == ':'))
            .map_or(rest.len(), |j| i + j);
        let token = &rest[start..end];
        let is_rust = token.starts_with("bfpscope::")
            || token.starts_with("rhai::")
            || token.starts_with("alloc::")
            || token.starts_with("std::")
            || token.starts_with("core::");
        out.push_str(&rest[..start]);
        if is_rust {
            out.push_str(&user_type(token));
        } else {
            out.push_str(token);
        }
        rest = &rest[end..];
    }
    out.push_str(rest);
    s = out;
    for (from, to) in [
        ("RangeInclusive<i64>", "range"),
        ("Range<i64>", "range"),
        ("Vec<Dynamic>", "array"),
    ] {
        s = s.replace(from, to);
    }
    replace_words(
        &s,
        &[
            ("f64", "float"),
            ("f32", "float"),
            ("i64", "int"),
            ("i32", "int"),
            ("INT", "int"),
            ("FLOAT", "float"),
            ("Dynamic", "value"),
        ],
    )
}

/// Replace whole words (runs of letters, digits and `_`) found in `pairs`.
fn replace_words(s: &str, pairs: &[(&str, &str)]) -> String {
    let mut out = String::with_capacity(s.len());
    let mut word = String::new();
    let flush = |word: &mut String, out: &mut String| {
        match pairs.iter().find(|(f, _)| *f == word.as_str()) {
            Some((_, t)) => out.push_str(t),
            None => out.push_str(word),
        }
        word.clear();
    };
    for c in s.chars() {
        if c.is_alphanumeric() || c == '_' {
            word.push(c);
        } else {
            flush(&mut word, &mut out);
            out.push(c);
        }
    }
    flush(&mut word, &mut out);
    out
}

/// A number for messages: up to 6 significant digits, no trailing zeros.
pub fn fmt_num(x: f64) -> String {
    if x == 0.0 || !x.is_finite() {
        return format!("{x}");
    }
    let a = x.abs();
    if !(1e-5..1e6).contains(&a) {
        let s = format!("{x:.5e}");
        let (m, e) = s.split_once('e').unwrap_or((&s, "0"));
        let m = m.trim_end_matches('0').trim_end_matches('.');
        return format!("{m}e{e}");
    }
    let digits = (5 - a.log10().floor() as i32).max(0) as usize;
    let s = format!("{x:.digits$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// The words for a bead that was not found (weight not significantly positive), for the
/// prompt and for errors.
pub(crate) fn not_found_words(i: usize, b: &crate::analysis::fit::Bead) -> String {
    let err = b
        .weight_err
        .map(|e| format!(" ± {e:.3}"))
        .unwrap_or_default();
    format!(
        "bead {i} NOT FOUND: weight {:.3}{err} (reference-bead units) is not significantly positive (weight − {}σ ≤ 0); its position ({:.3}, {:.3}) µm means nothing",
        b.weight,
        crate::analysis::fit::FOUND_SIGMA,
        b.x,
        b.y
    )
}
