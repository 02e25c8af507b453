//! The program suite: the binary as a user runs it (command line, the prompt in a pty, the
//! README's tour, the live view in a browser), the workbench's scripts, files, figures,
//! provenance and golden traces, and the house's architecture.
//!
//! Each module is one file of `tests/`; run one with `cargo test --test program <module>::`.

mod support;

mod architecture;
mod cli;
mod console;
mod data_files;
mod golden;
mod plots;
mod provenance;
mod readme_tour;
mod scans;
mod session_optics;
mod view;
mod workbench;
