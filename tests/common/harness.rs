//! A harness for an integration test that needs something outside the repository (a corpus,
//! a Python interpreter): where that is missing it reports "skipped" with the reason, where
//! libtest could only say ok, FAILED or ignored. The test target sets `harness = false`.

use std::process::ExitCode;

/// How a test that ran ended, short of failing.
pub enum Outcome {
    /// It passed; the text says what it covered (e.g. "113 scenes").
    Passed(String),
    /// It could not run here; the text says why.
    Skipped(String),
}

/// Runs the one test `name` as libtest would print it, honouring `--list` and the name
/// filters that `cargo test -- FILTER` passes on. `Err` is a failure, with its text.
pub fn single(name: &str, test: impl FnOnce() -> Result<Outcome, String>) -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.iter().any(|a| a == "--list") {
        println!("{name}: test");
        return ExitCode::SUCCESS;
    }
    let filters: Vec<&String> = args.iter().filter(|a| !a.starts_with('-')).collect();
    if !filters.is_empty() && !filters.iter().any(|f| name.contains(f.as_str())) {
        println!("\nrunning 0 tests\n\ntest result: ok. 0 passed; 0 failed; 1 filtered out\n");
        return ExitCode::SUCCESS;
    }
    println!("\nrunning 1 test");
    match test() {
        Ok(Outcome::Passed(what)) => {
            println!("test {name} ... ok ({what})\n");
            println!("test result: ok. 1 passed; 0 failed\n");
            ExitCode::SUCCESS
        }
        Ok(Outcome::Skipped(why)) => {
            println!("test {name} ... skipped: {why}\n");
            println!("test result: skipped. 0 passed; 0 failed; 1 skipped\n");
            ExitCode::SUCCESS
        }
        Err(failure) => {
            println!("test {name} ... FAILED");
            for line in failure.lines() {
                println!("  {line}");
            }
            println!("\ntest result: FAILED. 0 passed; 1 failed\n");
            ExitCode::FAILURE
        }
    }
}
