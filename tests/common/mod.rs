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

/// A fresh clone's view of this checkout: a temporary directory with its tracked data
/// (`data`, `scripts`, `prompts`, `stdlib`) linked in, and nothing a clone would not have
/// (`out/`, `runs/`).
pub fn fresh_clone() -> tempfile::TempDir {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let clone = tempfile::tempdir().expect("a temporary directory");
    for d in ["data", "scripts", "prompts", "stdlib"] {
        std::os::unix::fs::symlink(root.join(d), clone.path().join(d)).expect("a link");
    }
    clone
}

/// Runs `script` with `bash` (and `flags`, e.g. `-e`) in `dir`, as a user would: the built
/// `drivescript` first on the PATH and no language model configured.
pub fn bash_in(dir: &Path, flags: &[&str], script: &str) -> Output {
    let bin = Path::new(env!("CARGO_BIN_EXE_drivescript"));
    let path = format!(
        "{}:{}",
        bin.parent().expect("the binary's directory").display(),
        std::env::var("PATH").unwrap_or_default()
    );
    std::process::Command::new("bash")
        .args(flags)
        .args(["-c", script])
        .current_dir(dir)
        .env("PATH", &path)
        .env_remove("DRIVESCRIPT_LLM_URL")
        .env_remove("DRIVESCRIPT_LLM_MODEL")
        .output()
        .expect("bash runs")
}

/// A path as &str.
pub fn s(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

/// A YAML scene of 120 vehicles on a six-lane road (`crowd.yaml` in `dir`): many windows of
/// 24 agents, so that 1,024 samples of it are past the sampling batch's memory budget.
#[allow(dead_code)]
pub fn crowd_scene(dir: &Path) -> PathBuf {
    let mut yaml = String::from(
        "scenario_id: crowd\ndt: 0.1\nsteps: 51\ncurrent_step: 10\nroad:\n  lanes: 6\n  \
         lane_width: 3.6\n  length: 1500\n  segments: 1\n  speed_limit: 29\nagents:\n",
    );
    for lane in 0..6 {
        for k in 0..20 {
            let id = lane * 20 + k + 1;
            yaml += &format!(
                "  - {{id: {id}, lane: {lane}, s: {}, speed: 20}}\n",
                20 + k * 60
            );
        }
    }
    let scene = dir.join("crowd.yaml");
    std::fs::write(&scene, yaml).unwrap();
    scene
}

/// A copy of the shipped checkpoint (`config.json` and `model.safetensors`) in `dir/ck`, for a
/// test that edits its config.
#[allow(dead_code)]
pub fn checkpoint_copy(dir: &Path) -> PathBuf {
    let ck = dir.join("ck");
    std::fs::create_dir(&ck).unwrap();
    for f in ["config.json", "model.safetensors"] {
        std::fs::copy(Path::new("data/checkpoint").join(f), ck.join(f)).unwrap();
    }
    ck
}
