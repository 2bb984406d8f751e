//! The Python package's test suite (python/tests), run by `cargo test`: builds the package
//! into a virtual environment under target/python (outside the tracked tree), installs
//! pytest, numpy and torch from the package registry (pip's cache, outside the clone, keeps
//! the next run from downloading them again), and runs pytest against the `drivescript`
//! binary of this build. Its own harness, so that a machine without Python 3.9+ reports
//! "skipped", not "ok"; torch tests that cannot run are listed by pytest as skipped, with
//! their reason.
//!
//! The wheel is built with its own CARGO_TARGET_DIR: `cargo test` holds the lock on target/
//! while it runs, and a nested build of the same directory would wait for it forever.

use std::path::PathBuf;
use std::process::{Command, ExitCode};
use std::time::Instant;

const NAME: &str = "python_package_suite";

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
        .map_err(|e| format!("{py}: {e}"))?;
    if ok.status.success() {
        Ok(py)
    } else {
        Err(format!(
            "{py} is older than 3.9 or lacks venv/ensurepip: {}",
            String::from_utf8_lossy(&ok.stderr).trim()
        ))
    }
}

/// Runs `cmd`, echoing what it is; an error carries its output's tail.
fn run(what: &str, cmd: &mut Command) -> Result<(), String> {
    let t = Instant::now();
    let out = cmd.output().map_err(|e| format!("{what}: {e}"))?;
    println!("  {what}: {:.0} s", t.elapsed().as_secs_f64());
    if out.status.success() {
        return Ok(());
    }
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let tail: Vec<&str> = text.lines().rev().take(40).collect();
    Err(format!(
        "{what} failed ({}):\n{}",
        out.status,
        tail.into_iter().rev().collect::<Vec<_>>().join("\n")
    ))
}

fn suite(py: &str) -> Result<(), String> {
    let root = root();
    let work = root.join("target/python");
    let venv = work.join("venv");
    let bin = |name: &str| venv.join("bin").join(name);
    if !bin("python").exists() {
        run(
            "python3 -m venv target/python/venv",
            Command::new(py).args(["-m", "venv"]).arg(&venv),
        )?;
    }
    let pip = |args: &[&str]| {
        let mut c = Command::new(bin("python"));
        c.args(["-m", "pip", "install", "--disable-pip-version-check"])
            .args(args);
        c
    };
    run("pip install pytest numpy", &mut pip(&["pytest", "numpy"]))?;
    // torch is optional: where it cannot be installed its tests say "skipped" with the
    // reason, and the rest of the suite still runs.
    if std::env::var("DRIVESCRIPT_TEST_TORCH").as_deref() != Ok("0") {
        if let Err(e) = run("pip install torch", &mut pip(&["torch"])) {
            println!("  torch not installed, its tests will be skipped: {e}");
        }
    }
    run(
        "pip install ./python",
        pip(&["--force-reinstall", "--no-deps", "./python"])
            .current_dir(&root)
            .env("CARGO_TARGET_DIR", work.join("build")),
    )?;
    let t = Instant::now();
    let out = Command::new(bin("python"))
        .args([
            "-m",
            "pytest",
            "python/tests",
            "-rs",
            "-q",
            "-p",
            "no:cacheprovider",
        ])
        .current_dir(&root)
        .env("DRIVESCRIPT_BIN", env!("CARGO_BIN_EXE_drivescript"))
        .output()
        .map_err(|e| format!("pytest: {e}"))?;
    print!("{}", indent(&String::from_utf8_lossy(&out.stdout)));
    print!("{}", indent(&String::from_utf8_lossy(&out.stderr)));
    println!("  pytest: {:.0} s", t.elapsed().as_secs_f64());
    if out.status.success() {
        Ok(())
    } else {
        Err(format!("pytest failed ({})", out.status))
    }
}

fn indent(s: &str) -> String {
    s.lines().map(|l| format!("  | {l}\n")).collect()
}

fn main() -> ExitCode {
    // `cargo test -- FILTER` passes the filter on: run only when it selects this test.
    let args: Vec<String> = std::env::args().skip(1).collect();
    let filters: Vec<&String> = args.iter().filter(|a| !a.starts_with('-')).collect();
    if args.iter().any(|a| a == "--list") {
        println!("{NAME}: test");
        return ExitCode::SUCCESS;
    }
    if !filters.is_empty() && !filters.iter().any(|f| NAME.contains(f.as_str())) {
        println!("\nrunning 0 tests\n\ntest result: ok. 0 passed; 0 failed; 1 filtered out\n");
        return ExitCode::SUCCESS;
    }
    println!("\nrunning 1 test");
    let py = match python() {
        Ok(py) => py,
        Err(why) => {
            println!("test {NAME} ... skipped: {why}\n");
            println!("test result: skipped. 0 passed; 0 failed; 1 skipped\n");
            return ExitCode::SUCCESS;
        }
    };
    let t = Instant::now();
    match suite(&py) {
        Ok(()) => {
            println!("test {NAME} ... ok ({:.0} s)\n", t.elapsed().as_secs_f64());
            println!("test result: ok. 1 passed; 0 failed\n");
            ExitCode::SUCCESS
        }
        Err(e) => {
            println!("test {NAME} ... FAILED\n{}", indent(&e));
            println!("\ntest result: FAILED. 0 passed; 1 failed\n");
            ExitCode::FAILURE
        }
    }
}
