//! Helpers shared by the end-to-end tests.
#![allow(dead_code)]

pub mod harness;
pub mod llm_server;

use std::path::{Path, PathBuf};
use std::process::Output;

/// The repository's sample scenes.
pub fn samples() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("data/samples")
}

/// Runs the drivescript binary.
pub fn drivescript(args: &[&str]) -> Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_drivescript"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("the binary runs")
}

/// Runs it and asserts success; returns stdout.
pub fn ok(args: &[&str]) -> String {
    let out = drivescript(args);
    assert!(
        out.status.success(),
        "drivescript {args:?} failed ({:?}):\n{}",
        out.status.code(),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("UTF-8 output")
}

/// Runs it and asserts a clean failure (exit 1, not a panic); returns stderr.
pub fn fails(args: &[&str]) -> String {
    let out = drivescript(args);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(
        out.status.code(),
        Some(1),
        "drivescript {args:?} should fail cleanly:\n{err}"
    );
    assert!(
        !err.contains("panicked"),
        "panic in drivescript {args:?}:\n{err}"
    );
    err
}

/// A path as &str.
pub fn s(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}
