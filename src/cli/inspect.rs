//! `drivescript inspect`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use drivescript::io::{discover, load_scenes, LoadOptions};
use drivescript::train::val_fold;

#[derive(clap::Args)]
pub struct Args {
    /// Scene files or directories (directories are searched for every readable scene).
    #[arg(required = true)]
    scenes: Vec<PathBuf>,
    /// Print a JSON array of summaries instead of text.
    #[arg(long)]
    json: bool,
}

/// One scene's JSON record: its summary and validation fold.
#[derive(serde::Serialize)]
struct Entry {
    #[serde(flatten)]
    sum: drivescript::scene::SceneSummary,
    val_fold: u64,
}

pub fn run(args: Args) -> Result<ExitCode> {
    let opts = LoadOptions::default();
    let mut summaries = Vec::new();
    let mut failures = 0usize;
    for root in &args.scenes {
        let sources = match discover(root) {
            Ok(s) => s,
            Err(e) => {
                eprintln!("error: {e}");
                failures += 1;
                continue;
            }
        };
        for src in sources {
            match load_scenes(&src, &opts) {
                Ok(scenes) => {
                    for s in scenes {
                        let sum = s.summary();
                        // Which checkpoints never trained on it (`train --val-fold`), so that
                        // held-out evaluation sets can be cut without recomputing the hash.
                        let fold = val_fold(&s.meta.scenario_id);
                        if !args.json {
                            let text = sum.to_string();
                            let nl = if text.ends_with('\n') { "" } else { "\n" };
                            println!(
                                "{text}{nl}fold        {fold} (held out by `train --val-fold {fold}`)\n"
                            );
                        }
                        summaries.push(Entry {
                            sum,
                            val_fold: fold,
                        });
                    }
                }
                Err(e) => {
                    eprintln!("error: {e}");
                    failures += 1;
                }
            }
        }
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summaries)?);
    } else {
        println!(
            "{} scenes read, {} sources failed",
            summaries.len(),
            failures
        );
    }
    Ok(if failures == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}
