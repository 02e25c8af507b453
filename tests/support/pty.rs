#![allow(dead_code)]
//! The real binary's prompt in a pseudo-terminal, as a person at the instrument sees it: the REPL
//! finds a terminal on stdin (line editing, the pause question, Ctrl-C as the key sends it).

use serialport::{SerialPort, TTYPort};
use std::io::{Read, Write};
use std::os::fd::{FromRawFd, IntoRawFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub struct Prompt {
    master: TTYPort,
    child: Child,
    /// Everything the terminal showed so far (carriage returns removed).
    pub out: String,
    pub dir: PathBuf,
}

impl Prompt {
    /// `bfpscope --data DIR repl ARGS…` in a fresh pseudo-terminal, waiting for the first
    /// prompt. `DIR` (the session folders and `HOME`) is emptied first.
    pub fn start(dir: &Path, args: &[&str]) -> Prompt {
        let _ = std::fs::remove_dir_all(dir);
        std::fs::create_dir_all(dir).unwrap();
        let (mut master, slave) = TTYPort::pair().expect("pseudo-terminal");
        master.set_timeout(Duration::from_millis(100)).unwrap();
        let fd = unsafe { OwnedFd::from_raw_fd(slave.into_raw_fd()) };
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_bfpscope"));
        // a session of its own with the pty as its controlling terminal, so Ctrl-C typed into
        // the terminal reaches it as SIGINT (the line discipline signals the foreground group)
        unsafe {
            use std::os::unix::process::CommandExt;
            cmd.pre_exec(|| {
                if libc::setsid() < 0 || libc::ioctl(0, libc::TIOCSCTTY as _, 0) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                // a terminal as a login shell finds it (the pair is opened raw): line editing,
                // echo, Ctrl-C → SIGINT, CR → NL
                let mut t: libc::termios = std::mem::zeroed();
                if libc::tcgetattr(0, &mut t) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                t.c_lflag |= libc::ISIG | libc::ICANON | libc::ECHO | libc::ECHOE | libc::IEXTEN;
                t.c_iflag |= libc::ICRNL;
                t.c_oflag |= libc::OPOST | libc::ONLCR;
                t.c_cc[libc::VINTR] = 3;
                // a 40 × 120 window, as a terminal emulator reports it
                let ws = libc::winsize {
                    ws_row: 40,
                    ws_col: 120,
                    ws_xpixel: 0,
                    ws_ypixel: 0,
                };
                if libc::ioctl(0, libc::TIOCSWINSZ as _, &ws) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                if libc::tcsetattr(0, libc::TCSANOW, &t) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let child = cmd
            .args(["--data", dir.to_str().unwrap(), "repl"])
            .args(args)
            .env("TERM", "dumb")
            .env("HOME", dir)
            .stdin(Stdio::from(fd.try_clone().unwrap()))
            .stdout(Stdio::from(fd.try_clone().unwrap()))
            .stderr(Stdio::from(fd))
            .spawn()
            .unwrap();
        let _ = &mut master;
        let mut p = Prompt {
            master,
            child,
            out: String::new(),
            dir: dir.to_path_buf(),
        };
        p.wait_for("bfp> ", Duration::from_secs(60));
        p
    }

    /// Read until the terminal's output (since byte `from`) contains `what`; panics with the
    /// session so far after `timeout`.
    pub fn wait_for_from(&mut self, from: usize, what: &str, timeout: Duration) {
        self.wait_for_any_from(from, &[what], timeout)
    }

    /// As [`wait_for_from`](Self::wait_for_from), until any of `whats` shows.
    pub fn wait_for_any_from(&mut self, from: usize, whats: &[&str], timeout: Duration) {
        let deadline = Instant::now() + timeout;
        let mut buf = [0u8; 4096];
        while !whats
            .iter()
            .any(|w| self.out[from.min(self.out.len())..].contains(w))
        {
            assert!(
                Instant::now() < deadline,
                "waited {timeout:?} for {whats:?}; the session so far:\n{}",
                self.out
            );
            match self.master.read(&mut buf) {
                Ok(0) => {
                    if let Ok(Some(s)) = self.child.try_wait() {
                        panic!("the prompt ended ({s}) before {whats:?}:\n{}", self.out);
                    }
                }
                Ok(n) => self
                    .out
                    .push_str(&String::from_utf8_lossy(&buf[..n]).replace('\r', "")),
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                Err(e) => panic!("reading the terminal: {e}\n{}", self.out),
            }
        }
    }

    /// As [`wait_for_from`](Self::wait_for_from), from the start of the session.
    pub fn wait_for(&mut self, what: &str, timeout: Duration) {
        self.wait_for_from(0, what, timeout)
    }

    /// Type `line` and Enter; wait for the next prompt (`bfp> `) after it. Returns what the
    /// terminal showed for this entry (the echoed input, the output).
    pub fn enter(&mut self, line: &str, timeout: Duration) -> String {
        let from = self.out.len();
        self.type_line(line);
        self.wait_for_from(from, "bfp> ", timeout);
        self.out[from..].to_string()
    }

    /// Type one line of a possibly unfinished entry and Enter; wait for the next prompt, the
    /// entry's (`bfp> `) or a continuation (`...> `).
    pub fn enter_line(&mut self, line: &str, timeout: Duration) {
        let from = self.out.len();
        self.type_line(line);
        self.wait_for_any_from(from, &["bfp> ", "...> "], timeout);
    }

    /// Type `line` and Enter, without waiting.
    pub fn type_line(&mut self, line: &str) {
        self.master.write_all(line.as_bytes()).unwrap();
        self.master.write_all(b"\n").unwrap();
        self.master.flush().unwrap();
    }

    /// Send raw bytes (`b"\x03"` is Ctrl-C as the terminal's line discipline sees it).
    pub fn send(&mut self, bytes: &[u8]) {
        self.master.write_all(bytes).unwrap();
        self.master.flush().unwrap();
    }

    /// `quit` and wait for the process to end with success.
    pub fn quit(mut self) -> String {
        self.type_line("quit");
        let deadline = Instant::now() + Duration::from_secs(30);
        let status = loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                break s;
            }
            let mut buf = [0u8; 4096];
            if let Ok(n) = self.master.read(&mut buf) {
                self.out
                    .push_str(&String::from_utf8_lossy(&buf[..n]).replace('\r', ""));
            }
            assert!(
                Instant::now() < deadline,
                "the prompt did not exit on quit:\n{}",
                self.out
            );
        };
        assert!(status.success(), "{}", self.out);
        std::mem::take(&mut self.out)
    }
}

impl Drop for Prompt {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
