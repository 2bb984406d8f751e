//! `drivescript inspect`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use drivescript::io::{discover, read_each, LoadOptions};
use drivescript::scene::{describe, DescribeOptions};
use drivescript::train::val_fold;

#[derive(clap::Args)]
pub struct Args {
    /// Scene files or directories (directories are searched for every readable scene).
    #[arg(required = true)]
    scenes: Vec<PathBuf>,
    /// Print a JSON array of summaries instead of text.
    #[arg(long)]
    json: bool,
    /// Describe the agents instead: each one's lane, Frenet position, speed, the agents ahead,
    /// behind and beside it, and the lanes around them (what the LLM prompt shows).
    #[arg(long)]
    agents: bool,
    /// With --agents: most agents listed, nearest the ego (or the first --keep) first.
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..=100000), requires = "agents")]
    max_agents: u64,
    /// With --agents: agents always listed, whatever the cap (each must be in every scene).
    #[arg(long, num_args = 1.., value_parser = super::agent_id_value, requires = "agents")]
    keep: Vec<i64>,
    /// With --agents: future steps the sampler simulates (the shipped model's 40).
    #[arg(long, default_value_t = 40, value_parser = clap::value_parser!(u64).range(1..=10000), requires = "agents")]
    horizon: u64,
}

/// One scene's JSON record with --agents.
#[derive(serde::Serialize)]
#[serde(untagged)]
enum Record {
    Summary(Entry),
    Agents(drivescript::scene::SceneDescription),
}

/// One scene's JSON record: its summary and validation fold.
#[derive(serde::Serialize)]
struct Entry {
    #[serde(flatten)]
    sum: drivescript::scene::SceneSummary,
    val_fold: u64,
    /// The fold of its town, as `train --urban` holds scenes out.
    town_fold: u64,
}

pub fn run(args: Args) -> Result<ExitCode> {
    // Accepted without a word: `--keep 1 1` listed agent 1 once.
    if let Some((k, id)) = args
        .keep
        .iter()
        .enumerate()
        .find(|(k, id)| args.keep[..*k].contains(id))
    {
        anyhow::bail!(
            "--keep names agent {id} twice (value {} of the list)",
            k + 1
        );
    }
    let opts = LoadOptions::default();
    let mut summaries = Vec::new();
    let mut failures = 0usize;
    for root in &args.scenes {
        let sources = match discover(root) {
            Ok(s) => s,
            Err(e) => {
                super::print_error(&e.to_string());
                failures += 1;
                continue;
            }
        };
        for src in sources {
            // A bad WOMD record is reported among the good ones, which are still printed.
            for item in read_each(&src, &opts) {
                match item {
                    Ok(s) => {
                        if args.agents {
                            if let Some(absent) =
                                drivescript::scene::description::absent_kept(&s, &args.keep)
                            {
                                super::print_error(&format!(
                                    "{}: scene {}: --keep names agents it does not hold: {absent}",
                                    src.display(),
                                    s.meta.scenario_id,
                                ));
                                failures += 1;
                                continue;
                            }
                            let d = describe(
                                &s,
                                &DescribeOptions {
                                    max_agents: args.max_agents as usize,
                                    keep: args.keep.clone(),
                                    horizon: args.horizon as usize,
                                },
                            );
                            if !args.json {
                                println!("{d}");
                            }
                            summaries.push(Record::Agents(d));
                            continue;
                        }
                        let sum = s.summary();
                        // Which checkpoints never trained on it (`train --val-fold`), so that
                        // held-out evaluation sets can be cut without recomputing the hash.
                        let fold = val_fold(&s.meta.scenario_id);
                        let town = drivescript::train::store::town(&s.meta.scenario_id);
                        let town_fold = val_fold(town);
                        if !args.json {
                            let text = sum.to_string();
                            let nl = if text.ends_with('\n') { "" } else { "\n" };
                            println!(
                                "{text}{nl}fold        {fold} (held out by `train --val-fold {fold}` from --data)\n\
                                 town fold   {town_fold} ({town}: held out by `train --val-fold {town_fold}` from --urban)\n"
                            );
                        }
                        summaries.push(Record::Summary(Entry {
                            sum,
                            val_fold: fold,
                            town_fold,
                        }));
                    }
                    Err(e) => {
                        super::print_error(&e.to_string());
                        failures += 1;
                    }
                }
            }
        }
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summaries)?);
    } else {
        println!("{} scenes read, {} failed", summaries.len(), failures);
    }
    if summaries.is_empty() && failures == 0 {
        eprintln!(
            "error: no scene found (scene files: *.xml, *.xml.gz, *.yaml, *.yml, *.tfrecord*, an AV2 scenario directory)"
        );
        return Ok(ExitCode::FAILURE);
    }
    Ok(if failures == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}
