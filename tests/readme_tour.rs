//! The README's prompt tour, typed line by line into the real binary through a pseudo-terminal
//! (the REPL sees a terminal, as a person at the instrument); every output line the README shows
//! must appear, in order.

use crate::support::cleanup;

use crate::support::pty;

use pty::Prompt;
use std::time::Duration;

/// (input lines, expected output lines) of the tour block.
fn tour() -> (Vec<String>, Vec<String>) {
    let readme =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md")).unwrap();
    let start = readme
        .find("## A 30-second tour of the prompt")
        .expect("tour section");
    let block = &readme[start..];
    let b0 = block.find("```text\n").unwrap() + 8;
    let b1 = b0 + block[b0..].find("```").unwrap();
    let mut inputs = vec![];
    let mut outputs = vec![];
    for l in block[b0..b1].lines() {
        if let Some(i) = l.strip_prefix("bfp> ").or_else(|| l.strip_prefix("...> ")) {
            inputs.push(i.to_string());
        } else if !l.trim().is_empty() {
            outputs.push(l.split('…').next().unwrap().trim_end().to_string());
        }
    }
    (inputs, outputs)
}

#[test]
fn readme_tour_runs_at_the_prompt() {
    let (inputs, expected) = tour();
    assert!(inputs.len() > 10 && expected.len() > 10);
    let dir = std::env::temp_dir().join(format!("bfpscope-tour-{}", std::process::id()));
    cleanup::at_exit(&dir);
    let mut p = Prompt::start(&dir, &[]);
    for line in inputs.iter().take_while(|l| *l != "quit") {
        p.enter_line(line, Duration::from_secs(60));
    }
    let out = p.quit();
    let text = out.replace('\r', "");
    let mut at = 0;
    for e in &expected {
        match text[at..].find(e.as_str()) {
            Some(i) => at += i + e.len(),
            None => {
                panic!("README output line not printed (in order): {e:?}\n--- session:\n{text}")
            }
        }
    }
    assert!(!text.contains("syntax error"), "{text}");
    let _ = std::fs::remove_dir_all(&dir);
}
