//! The stop rule of every scan, every mode, in words: the one source of its prose. The engine
//! (`engine.rs`) applies the rule; this file says it — in every scan binding's help
//! ([`STOP_RULE`]), in the question a paused scan asks at the prompt ([`PAUSE_ANSWERS`],
//! [`ON_ABORT`]) and in the docs: `bfpscope docs` writes the rule between the markers
//! `<!-- stop-rule:full -->` / `<!-- stop-rule:short -->` and `<!-- /stop-rule -->` in
//! [`STOP_RULE_DOCS`], and `bfpscope docs --check` (and a test) fails when a copy is stale.

/// The answers to the pause question (the prompt prints them, the rule states them).
macro_rules! pause_answers {
    () => {
        "Enter (or `r`) resumes (a raster re-arms and continues with the next row), `a` (or Ctrl-C, Ctrl-D) aborts"
    };
}

/// What an abort does.
macro_rules! on_abort {
    () => {
        "a relative scan returns to its start and the partial scan (unmeasured pixels NaN) is saved with status \"aborted\""
    };
}

/// The answers to the pause question, as the prompt prints them.
pub const PAUSE_ANSWERS: &str = pause_answers!();

/// What an abort does, as the prompt prints it.
pub const ON_ABORT: &str = on_abort!();

/// The stop rule of every scan, every mode (the engine's, `acquire::engine`), for the help and
/// the guide.
pub const STOP_RULE: &str = concat!(
    "Stop rule (every mode): Ctrl-C at the prompt pauses the scan — point by point at the next \
     point; a raster after the line being swept (the line is finished, the digitiser stopped, the \
     wave generator off, the stage at rest where the line ended) — and asks: ",
    pause_answers!(),
    ". Aborted (or Ctrl-C in a script run): ",
    on_abort!(),
    ", and the call fails with a message naming the file. A device error ends the scan with \
     status \"failed\" and the device's words, the partial scan saved: after a stage error the \
     stage gets a stop command and nothing else (no return, no further motion); after any other \
     error (QPD, digitiser) a relative scan returns to its start."
);

/// The rule in one sentence, for the README and the hardware notes.
pub const STOP_RULE_SHORT: &str = concat!(
    "Ctrl-C pauses a running scan between steps (a raster after the line being swept), the stage \
     at rest and nothing commanded, and asks: ",
    pause_answers!(),
    "; aborted, ",
    on_abort!(),
    "; a device error saves the partial scan with status \"failed\", and after a stage error the \
     stage gets a stop command and nothing else."
);

/// The documents that carry the rule, relative to the repository root, and how many copies
/// each must hold (a copy removed with its markers is a failure too).
pub const STOP_RULE_DOCS: [(&str, usize); 3] = [
    ("README.md", 1),
    ("docs/guide.md", 2),
    ("docs/hardware.md", 3),
];

const END: &str = "<!-- /stop-rule -->";

/// `markdown` with every marked copy of the rule rewritten from this file, and the number of
/// copies. A copy is the lines between `<!-- stop-rule:full -->` (or `:short`) and
/// `<!-- /stop-rule -->`; the text is wrapped at 100 columns and indented as its opening marker.
/// Errors: an unknown kind or an opening marker without its end.
pub fn with_stop_rule(markdown: &str) -> Result<(String, usize), String> {
    let mut out = String::with_capacity(markdown.len());
    let mut lines = markdown.split_inclusive('\n');
    let mut copies = 0;
    while let Some(line) = lines.next() {
        out.push_str(line);
        let t = line.trim();
        let Some(kind) = t
            .strip_prefix("<!-- stop-rule:")
            .and_then(|r| r.strip_suffix("-->"))
        else {
            continue;
        };
        let text = match kind.trim() {
            "full" => STOP_RULE,
            "short" => STOP_RULE_SHORT,
            k => {
                return Err(format!(
                    "stop-rule marker `{t}`: unknown kind `{k}` (full or short)"
                ))
            }
        };
        let indent = &line[..line.len() - line.trim_start().len()];
        let mut closed = false;
        for l in lines.by_ref() {
            if l.trim() == END {
                out.push_str(&wrap(text, indent, 100));
                out.push_str(l);
                closed = true;
                break;
            }
        }
        if !closed {
            return Err(format!("stop-rule marker `{t}` without its `{END}`"));
        }
        copies += 1;
    }
    Ok((out, copies))
}

/// `text` wrapped at `width` columns (counted in characters), each line starting with `indent`.
fn wrap(text: &str, indent: &str, width: usize) -> String {
    let mut out = String::new();
    let mut line = String::from(indent);
    for w in text.split_whitespace() {
        if line.len() > indent.len() && line.chars().count() + 1 + w.chars().count() > width {
            out.push_str(&line);
            out.push('\n');
            line = String::from(indent);
        }
        if line.len() > indent.len() {
            line.push(' ');
        }
        line.push_str(w);
    }
    out.push_str(&line);
    out.push('\n');
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rule_states_the_prompts_answers_and_the_abort() {
        assert!(STOP_RULE.contains(PAUSE_ANSWERS) && STOP_RULE_SHORT.contains(PAUSE_ANSWERS));
        assert!(STOP_RULE.contains(ON_ABORT) && STOP_RULE_SHORT.contains(ON_ABORT));
    }

    #[test]
    fn marked_copies_are_rewritten_and_counted() {
        let md = "# T\n  <!-- stop-rule:short -->\n  stale words\n  <!-- /stop-rule -->\nafter\n";
        let (out, n) = with_stop_rule(md).unwrap();
        assert_eq!(n, 1);
        assert!(
            out.starts_with("# T\n  <!-- stop-rule:short -->\n  Ctrl-C pauses"),
            "{out}"
        );
        assert!(out.ends_with("  <!-- /stop-rule -->\nafter\n"), "{out}");
        assert!(!out.contains("stale"));
        let body: Vec<&str> = out
            .lines()
            .skip(2)
            .take_while(|l| !l.contains("/stop"))
            .collect();
        assert!(body
            .iter()
            .all(|l| l.starts_with("  ") && l.chars().count() <= 100));
        assert_eq!(
            body.iter().map(|l| l.trim()).collect::<Vec<_>>().join(" "),
            STOP_RULE_SHORT
        );
        // rewriting is idempotent
        assert_eq!(with_stop_rule(&out).unwrap(), (out.clone(), 1));
        let e = with_stop_rule("<!-- stop-rule:long -->\n<!-- /stop-rule -->\n").unwrap_err();
        assert!(e.contains("unknown kind `long`"), "{e}");
        let e = with_stop_rule("<!-- stop-rule:full -->\ntext\n").unwrap_err();
        assert!(e.contains("without its `<!-- /stop-rule -->`"), "{e}");
    }
}
