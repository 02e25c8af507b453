//! Helpers shared by the test suites (`crate::support::…` from any test file).

pub mod cleanup;
pub mod emulate;
pub mod fakebench;
pub mod pty;
pub mod webdriver;
