//! `bfpscope emulate …` as a separate process, as a user starts it in a second terminal: started,
//! read until it serves, and stopped with Ctrl-C (SIGINT). Shared by the command-line and
//! prompt tests and the link benches (`#[path = "../support/emulate.rs"]`).

#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// How long an emulator may take to start serving (a loaded machine, a debug build).
const START: Duration = Duration::from_secs(60);

/// A running `bfpscope emulate` process; dropped, it gets Ctrl-C (and is killed after 5 s).
pub struct Emulator {
    child: Child,
    /// Everything it printed up to and including "Serving until Ctrl-C".
    pub text: String,
}

impl Emulator {
    /// Start `bfpscope emulate ARGS…` and wait until it prints "Serving until Ctrl-C".
    pub fn start(args: &[&str]) -> Emulator {
        let mut child = Command::new(env!("CARGO_BIN_EXE_bfpscope"))
            .arg("emulate")
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("bfpscope emulate starts");
        let (tx, rx) = std::sync::mpsc::channel();
        let out = child.stdout.take().expect("its stdout");
        std::thread::spawn(move || {
            for l in BufReader::new(out).lines() {
                let Ok(l) = l else { break };
                if tx.send(l).is_err() {
                    break;
                }
            }
        });
        let mut text = String::new();
        let t0 = Instant::now();
        while !text.contains("Serving until Ctrl-C") {
            match rx.recv_timeout(Duration::from_millis(100)) {
                Ok(l) => {
                    text.push_str(&l);
                    text.push('\n');
                }
                Err(_) if t0.elapsed() > START => {
                    let _ = child.kill();
                    panic!(
                        "`bfpscope emulate {}` did not serve within {START:?}:\n{text}",
                        args.join(" ")
                    );
                }
                Err(_) => {}
            }
        }
        Emulator { child, text }
    }

    /// The `bfpscope.toml` snippet it printed for its emulators.
    pub fn toml(&self) -> &str {
        self.text
            .split("# bfpscope.toml for these emulators:\n")
            .nth(1)
            .and_then(|t| t.split("Serving until").next())
            .unwrap_or_else(|| panic!("no config snippet:\n{}", self.text))
    }

    /// The first printed line that starts with `prefix` (e.g. "stage:").
    pub fn line(&self, prefix: &str) -> &str {
        self.text
            .lines()
            .find(|l| l.starts_with(prefix))
            .unwrap_or_else(|| panic!("no line starting with {prefix:?}:\n{}", self.text))
    }

    /// Where the device of the line starting with `prefix` is served: what follows the line's
    /// last " on " (a pseudo-terminal path or `tcp://HOST:PORT`).
    pub fn path_of(&self, prefix: &str) -> String {
        let line = self.line(prefix);
        line.rsplit(" on ").next().unwrap_or(line).to_string()
    }

    /// Ctrl-C (SIGINT); its exit code once it has stopped (10 s at most).
    pub fn interrupt(mut self) -> Option<i32> {
        self.sigint();
        let t0 = Instant::now();
        loop {
            if let Some(s) = self.child.try_wait().expect("its status") {
                return s.code();
            }
            if t0.elapsed() > Duration::from_secs(10) {
                let _ = self.child.kill();
                panic!("emulate did not stop on SIGINT");
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn sigint(&self) {
        // SAFETY: kill(2) on our own child's pid.
        unsafe {
            libc::kill(self.child.id() as i32, libc::SIGINT);
        }
    }
}

impl Drop for Emulator {
    fn drop(&mut self) {
        if let Ok(Some(_)) = self.child.try_wait() {
            return;
        }
        self.sigint();
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(5) {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
