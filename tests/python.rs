//! The Python package's test suite (python/tests), run by `cargo test`.
//!
//! It builds the binding crate (python/, a member of this workspace) with a nested `cargo
//! build -p drivescript-python` on this target directory: the library it links was compiled
//! by this very `cargo test` with the same features (see Cargo.toml), so only the binding
//! compiles, in seconds, where a wheel built apart compiled candle and parquet again for half
//! an hour. The extension module goes beside a copy of the package's Python sources in a
//! temporary directory, named as maturin names it, and pytest runs against that with the
//! interpreter of a virtual environment cached outside the clone
//! (`$DRIVESCRIPT_VENV`, else `~/.cache/drivescript/python-venv`), which holds pytest, numpy
//! and torch from the package registry, installed on the first run.
//!
//! Its own harness (tests/common/harness.rs): without Python 3.9+ with venv and ensurepip it
//! reports "skipped". Where torch cannot be installed (or `DRIVESCRIPT_TEST_TORCH=0`), pytest
//! lists the torch tests as skipped with the reason.

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Output};
use std::time::Instant;

mod common;
use common::harness::{single, Outcome};

const NAME: &str = "python_package_suite";

/// What pytest and the package need in the cached environment (as python/pyproject.toml).
const REQUIREMENTS: [&str; 2] = ["pytest>=7", "numpy>=1.21"];

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// A Python 3.9+ interpreter with venv: $DRIVESCRIPT_PYTHON, else python3 on the PATH.
fn python() -> Result<String, String> {
    let py = std::env::var("DRIVESCRIPT_PYTHON").unwrap_or_else(|_| "python3".into());
    let ok = Command::new(&py)
        .args([
            "-c",
            "import sys, venv, ensurepip; sys.exit(sys.version_info < (3, 9))",
        ])
        .output()
        .map_err(|e| format!("no Python interpreter ({py}: {e})"))?;
    if ok.status.success() {
        Ok(py)
    } else {
        Err(format!(
            "{py} is older than 3.9 or lacks venv/ensurepip {}",
            String::from_utf8_lossy(&ok.stderr).trim()
        ))
    }
}

/// The tail of a command's output, for a failure message.
fn tail(out: &Output) -> String {
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(40)..].join("\n")
}

/// Runs `cmd`, printing how long `what` took; an error carries its output's tail.
fn run(what: &str, cmd: &mut Command) -> Result<Output, String> {
    let t = Instant::now();
    let out = cmd.output().map_err(|e| format!("{what}: {e}"))?;
    println!("  {what}: {:.0} s", t.elapsed().as_secs_f64());
    if out.status.success() {
        Ok(out)
    } else {
        Err(format!("{what} failed ({}):\n{}", out.status, tail(&out)))
    }
}

/// The cached virtual environment's directory.
fn venv_dir() -> Result<PathBuf, String> {
    if let Some(dir) = std::env::var_os("DRIVESCRIPT_VENV") {
        return Ok(PathBuf::from(dir));
    }
    let cache = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
        .ok_or("neither HOME nor XDG_CACHE_HOME is set: set DRIVESCRIPT_VENV to a directory")?;
    Ok(cache.join("drivescript/python-venv"))
}

fn venv_python(venv: &Path) -> PathBuf {
    if cfg!(windows) {
        venv.join("Scripts/python.exe")
    } else {
        venv.join("bin/python")
    }
}

/// Whether `python` imports `modules` (a comma-separated list).
fn imports(python: &Path, modules: &str) -> bool {
    Command::new(python)
        .args(["-c", &format!("import {modules}")])
        .output()
        .is_ok_and(|o| o.status.success())
}

/// The cached environment's interpreter, with pytest and numpy (and torch where it can be
/// installed). A new environment is made beside the cache and moved into place once it has
/// pytest and numpy, so that a run cut short, or one beside it, never leaves a half-made one
/// there.
fn environment(py: &str) -> Result<PathBuf, String> {
    let venv = venv_dir()?;
    if !imports(&venv_python(&venv), "pytest, numpy") {
        let parent = venv.parent().ok_or("the venv directory has no parent")?;
        std::fs::create_dir_all(parent).map_err(|e| format!("{}: {e}", parent.display()))?;
        let name = venv.file_name().unwrap_or_default().to_string_lossy();
        let fresh = parent.join(format!("{name}.{}.tmp", std::process::id()));
        run(
            &format!("{py} -m venv {}", fresh.display()),
            Command::new(py).args(["-m", "venv", "--clear"]).arg(&fresh),
        )?;
        if let Err(e) = run(
            "pip install pytest numpy",
            pip(&venv_python(&fresh)).args(REQUIREMENTS),
        ) {
            let _ = std::fs::remove_dir_all(&fresh);
            return Err(e);
        }
        // One that lacks them, or no longer runs (its base interpreter is gone), is replaced.
        if venv.exists() {
            std::fs::remove_dir_all(&venv).map_err(|e| format!("{}: {e}", venv.display()))?;
        }
        if let Err(e) = std::fs::rename(&fresh, &venv) {
            // Another run put its environment there first: use that one.
            let _ = std::fs::remove_dir_all(&fresh);
            if !imports(&venv_python(&venv), "pytest, numpy") {
                return Err(format!("{}: {e}", venv.display()));
            }
        }
    }
    let python = venv_python(&venv);
    // torch is optional: where it cannot be installed its tests say "skipped" with the
    // reason, and the rest of the suite still runs.
    if std::env::var("DRIVESCRIPT_TEST_TORCH").as_deref() != Ok("0") && !imports(&python, "torch") {
        if let Err(e) = run("pip install torch", pip(&python).arg("torch")) {
            println!("  torch not installed, its tests will be skipped: {e}");
        }
    }
    Ok(python)
}

fn pip(python: &Path) -> Command {
    let mut c = Command::new(python);
    c.args(["-m", "pip", "install", "-q", "--disable-pip-version-check"]);
    c
}

/// Builds the binding crate; returns the extension module it made. Fails where the build
/// compiled the library again: the binding's features and this test's have drifted apart
/// (Cargo.toml lists the ones declared to keep them together), and the suite would cost a
/// second build of candle and parquet.
fn build_extension() -> Result<PathBuf, String> {
    let profile = if cfg!(debug_assertions) {
        "dev"
    } else {
        "release"
    };
    let mut cargo = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
    cargo
        .args(["build", "--profile", profile, "-p", "drivescript-python"])
        .arg("--message-format=json-render-diagnostics")
        .current_dir(root());
    // Cargo sets these for the test it runs, not for the build it runs in. Build scripts that
    // read them (ring's) would see them change, run again, and take the library with them.
    for (key, _) in std::env::vars_os() {
        let key = key.to_string_lossy();
        let set_by_cargo = ["CARGO_PKG_", "CARGO_MANIFEST_", "CARGO_BIN_", "CARGO_CFG_"]
            .iter()
            .any(|p| key.starts_with(p))
            || [
                "CARGO_CRATE_NAME",
                "CARGO_PRIMARY_PACKAGE",
                "CARGO_TARGET_TMPDIR",
            ]
            .contains(&key.as_ref())
            || key == "OUT_DIR";
        if set_by_cargo {
            cargo.env_remove(key.as_ref());
        }
    }
    let out = run(
        &format!("cargo build --profile {profile} -p drivescript-python"),
        &mut cargo,
    )?;
    let library = root().join("Cargo.toml");
    let mut module = None;
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let Ok(msg) = serde_json::from_str::<serde_json::Value>(line) else {
            continue;
        };
        if msg["reason"] != "compiler-artifact" {
            continue;
        }
        let target = &msg["target"];
        let kinds = target["kind"].as_array().cloned().unwrap_or_default();
        if target["name"] == "drivescript"
            && kinds.iter().any(|k| k == "lib")
            && msg["manifest_path"].as_str().map(Path::new) == Some(library.as_path())
            && msg["fresh"] == false
        {
            return Err(format!(
                "`cargo build -p drivescript-python` compiled the drivescript library again: \
                 the binding's dependencies turn on features that `cargo test` does not (or \
                 the reverse); declare them in both Cargo.toml files (compare `cargo tree -e \
                 features -p drivescript-python` with `-p drivescript`), or a build script \
                 reads a variable that differs here (CARGO_LOG=cargo::core::compiler::\
                 fingerprint=info on that build says which)"
            ));
        }
        if target["name"] == "_native" && kinds.iter().any(|k| k == "cdylib") {
            module = msg["filenames"]
                .as_array()
                .and_then(|f| f.first())
                .and_then(|f| f.as_str())
                .map(PathBuf::from);
        }
    }
    module.ok_or_else(|| "the build made no _native extension module".into())
}

/// The package as maturin lays it out: python/drivescript's files and the extension module
/// named as CPython's abi3 import looks for it, in `dir`/drivescript.
fn package(dir: &Path, module: &Path) -> Result<(), String> {
    let err = |p: &Path, e: std::io::Error| format!("{}: {e}", p.display());
    let pkg = dir.join("drivescript");
    std::fs::create_dir(&pkg).map_err(|e| err(&pkg, e))?;
    let src = root().join("python/drivescript");
    for entry in std::fs::read_dir(&src).map_err(|e| err(&src, e))? {
        let path = entry.map_err(|e| err(&src, e))?.path();
        if path.is_file() {
            let to = pkg.join(path.file_name().unwrap_or_default());
            std::fs::copy(&path, &to).map_err(|e| err(&path, e))?;
        }
    }
    let name = if cfg!(windows) {
        "_native.pyd"
    } else {
        "_native.abi3.so"
    };
    std::fs::copy(module, pkg.join(name)).map_err(|e| err(module, e))?;
    Ok(())
}

fn suite() -> Result<Outcome, String> {
    let py = match python() {
        Ok(py) => py,
        Err(why) => return Ok(Outcome::Skipped(why)),
    };
    let t = Instant::now();
    let python = environment(&py)?;
    let module = build_extension()?;
    let dir = tempfile::tempdir().map_err(|e| format!("temporary directory: {e}"))?;
    package(dir.path(), &module)?;
    let out = Command::new(&python)
        .args([
            "-m",
            "pytest",
            "python/tests",
            "-rs",
            "-q",
            "-p",
            "no:cacheprovider",
        ])
        .current_dir(root())
        .env("PYTHONPATH", dir.path())
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .env("DRIVESCRIPT_BIN", env!("CARGO_BIN_EXE_drivescript"))
        .output()
        .map_err(|e| format!("pytest: {e}"))?;
    for line in String::from_utf8_lossy(&out.stdout)
        .lines()
        .chain(String::from_utf8_lossy(&out.stderr).lines())
    {
        println!("  | {line}");
    }
    if !out.status.success() {
        return Err(format!("pytest failed ({})", out.status));
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let summary = stdout.lines().last().unwrap_or_default().trim();
    Ok(Outcome::Passed(format!(
        "pytest: {summary}; {:.0} s in all",
        t.elapsed().as_secs_f64()
    )))
}

fn main() -> ExitCode {
    single(NAME, suite)
}
