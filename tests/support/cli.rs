//! Shared helpers of the command-line tests: a scratch directory and a run of the binary.

use std::path::PathBuf;
use std::process::{Command, Output};

/// A fresh empty directory for one test.
pub fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("hexcal-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Run `hexcal` with `args`.
#[allow(dead_code)] // Not every test file runs the binary the same way.
pub fn hexcal(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_hexcal"))
        .args(args)
        .output()
        .unwrap()
}
