//! Every scene of the development corpus in ../shared/data reads. The corpus is not part of the
//! repository, so this test has its own harness: without the corpus it reports "skipped", not
//! "ok" (libtest can only say ok, FAILED or ignored).

use std::path::PathBuf;
use std::process::ExitCode;

use drivescript::io::{discover, load_scenes, LoadOptions};

const NAME: &str = "every_shared_scene_reads";

/// The problems found, or the number of scenes read.
fn check(root: &PathBuf) -> Result<usize, Vec<String>> {
    let mut n = 0;
    let mut failures = Vec::new();
    let sources = discover(root).map_err(|e| vec![e.to_string()])?;
    for src in sources {
        match load_scenes(&src, &LoadOptions::default()) {
            Ok(scenes) => {
                for s in &scenes {
                    if s.num_steps() == 0 || s.agents.is_empty() {
                        failures.push(format!("{}: no steps or no agents", src.display()));
                    }
                    if s.map.lanes().is_empty() || s.map.road_edges().is_empty() {
                        failures.push(format!("{}: no lanes or no road edges", src.display()));
                    }
                }
                n += scenes.len();
            }
            Err(e) => failures.push(e.to_string()),
        }
    }
    if n < 113 {
        failures.push(format!("only {n} scenes found under {}", root.display()));
    }
    if failures.is_empty() {
        Ok(n)
    } else {
        Err(failures)
    }
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
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
    if !root.exists() {
        println!(
            "test {NAME} ... skipped: {} not found (development corpus only)\n",
            root.display()
        );
        println!("test result: skipped. 0 passed; 0 failed; 1 skipped\n");
        return ExitCode::SUCCESS;
    }
    match check(&root) {
        Ok(n) => {
            println!("test {NAME} ... ok ({n} scenes)\n");
            println!("test result: ok. 1 passed; 0 failed\n");
            ExitCode::SUCCESS
        }
        Err(failures) => {
            println!("test {NAME} ... FAILED");
            for f in &failures {
                println!("  {f}");
            }
            println!("\ntest result: FAILED. 0 passed; 1 failed\n");
            ExitCode::FAILURE
        }
    }
}
