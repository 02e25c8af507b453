//! The README's prompt tour, typed line by line into the real binary through a pseudo-terminal
//! (the REPL sees a terminal, as a person at the instrument); every output line the README shows
//! must appear, in order.

use serialport::{SerialPort, TTYPort};
use std::io::{Read, Write};
use std::os::fd::{FromRawFd, IntoRawFd, OwnedFd};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

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

fn read_until_prompt(m: &mut TTYPort, out: &mut String, deadline: Instant) {
    let mut buf = [0u8; 4096];
    while Instant::now() < deadline {
        match m.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => {
                out.push_str(&String::from_utf8_lossy(&buf[..n]));
                let t = out.trim_end_matches([' ', '\r', '\n']);
                if out.ends_with("bfp> ") || out.ends_with("...> ") || t.ends_with("exit") {
                    return;
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(_) => break,
        }
    }
}

#[test]
fn readme_tour_runs_at_the_prompt() {
    let (inputs, expected) = tour();
    assert!(inputs.len() > 10 && expected.len() > 10);
    let dir = std::env::temp_dir().join(format!("bfpscope-tour-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (mut master, slave) = TTYPort::pair().expect("pseudo-terminal");
    master.set_timeout(Duration::from_millis(200)).unwrap();
    let fd = unsafe { OwnedFd::from_raw_fd(slave.into_raw_fd()) };
    let mut child = Command::new(env!("CARGO_BIN_EXE_bfpscope"))
        .args(["--data", dir.to_str().unwrap(), "repl"])
        .env("TERM", "dumb")
        .env("HOME", &dir)
        .stdin(Stdio::from(fd.try_clone().unwrap()))
        .stdout(Stdio::from(fd.try_clone().unwrap()))
        .stderr(Stdio::from(fd))
        .spawn()
        .unwrap();
    let mut out = String::new();
    let deadline = Instant::now() + Duration::from_secs(60);
    read_until_prompt(&mut master, &mut out, deadline);
    for line in &inputs {
        master.write_all(line.as_bytes()).unwrap();
        master.write_all(b"\n").unwrap();
        if line == "quit" {
            break;
        }
        read_until_prompt(&mut master, &mut out, deadline);
    }
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        let mut buf = [0u8; 4096];
        if let Ok(n) = master.read(&mut buf) {
            out.push_str(&String::from_utf8_lossy(&buf[..n]));
        }
        assert!(
            Instant::now() < deadline,
            "the prompt did not exit on quit:\n{out}"
        );
    };
    assert!(status.success(), "{out}");
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
