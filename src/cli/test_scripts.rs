//! `drivescript test-scripts`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use drivescript::cost::script_test::{find_test_files, run_test_file};
use drivescript::io::name::terminal_safe;

#[derive(clap::Args)]
pub struct Args {
    /// Test files (*.test.yaml) or directories to search (default: scripts/).
    paths: Vec<PathBuf>,
    /// Print every case's measured values, not only the failures'.
    #[arg(short, long)]
    verbose: bool,
}

pub fn run(args: Args) -> Result<ExitCode> {
    let roots = if args.paths.is_empty() {
        vec![PathBuf::from("scripts")]
    } else {
        args.paths
    };
    let files = find_test_files(&roots)?;
    if files.is_empty() {
        let names: Vec<String> = roots.iter().map(|r| r.display().to_string()).collect();
        anyhow::bail!("no *.test.yaml files in {}", names.join(", "));
    }
    let (mut passed, mut failed) = (0, 0);
    println!("| {:<28} | {:<56} | result |", "test file", "case");
    println!("|{}|{}|--------|", "-".repeat(30), "-".repeat(58));
    for f in &files {
        let name = f
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        match run_test_file(f) {
            Ok(results) => {
                for r in results {
                    println!(
                        "| {:<28} | {:<56} | {:<6} |",
                        terminal_safe(&name),
                        r.case,
                        if r.passed { "pass" } else { "FAIL" }
                    );
                    if !r.passed || args.verbose {
                        println!("|   {}", terminal_safe(&r.detail));
                    }
                    if r.passed {
                        passed += 1;
                    } else {
                        failed += 1;
                    }
                }
            }
            Err(e) => {
                println!(
                    "| {:<28} | {:<56} | FAIL   |\n|   {}",
                    terminal_safe(&name),
                    "(file could not run)",
                    terminal_safe(&e.to_string())
                );
                failed += 1;
            }
        }
    }
    println!("{passed} passed, {failed} failed");
    Ok(if failed == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}
