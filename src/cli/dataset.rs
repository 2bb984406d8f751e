//! `drivescript dataset`: what training windows a corpus gives, and how well PCA holds them.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use drivescript::io::{discover, read_each, LoadOptions};
use drivescript::model::Pca;
use drivescript::train::{windows, WindowConfig};

#[derive(clap::Args)]
pub struct Args {
    /// Scene files or directories.
    #[arg(required = true)]
    scenes: Vec<PathBuf>,
    /// History steps, current included.
    #[arg(long, default_value_t = 11)]
    history: usize,
    /// Future steps.
    #[arg(long, default_value_t = 40)]
    future: usize,
    /// Steps between windows of a scene.
    #[arg(long, default_value_t = 10)]
    stride: usize,
}

pub fn run(args: Args) -> Result<ExitCode> {
    let cfg = WindowConfig {
        history: args.history,
        future: args.future,
        stride: args.stride,
        ..WindowConfig::ngsim()
    };
    if let Err(e) = cfg.validate() {
        let flag = e.split(' ').next().unwrap_or_default();
        anyhow::bail!("--{flag}: {e}");
    }
    let (mut scenes, mut used, mut wins, mut agents, mut lanes) = (0, 0, 0, 0usize, 0usize);
    let mut futures = Vec::new();
    // A bad file is reported and the others still counted, as `inspect` does: the first one
    // stopped the whole corpus.
    let mut failures = 0usize;
    let mut copies = drivescript::io::copies::ScenarioCopies::new();
    for root in &args.scenes {
        let files = match discover(root) {
            Ok(f) => f,
            Err(e) => {
                super::print_error(&e.to_string());
                failures += 1;
                continue;
            }
        };
        // An empty folder was reported as "0 complete agent futures ... PCA needs at least 50".
        if files.is_empty() {
            anyhow::bail!(
                "{}: no scene file in it (supported: {})",
                root.display(),
                drivescript::io::SUPPORTED_FORMATS
            );
        }
        for src in files {
            for s in read_each(&src, &LoadOptions::default()) {
                let s = match s {
                    Ok(s) => s,
                    Err(e) => {
                        super::print_error(&e.to_string());
                        failures += 1;
                        continue;
                    }
                };
                if let Some(m) = drivescript::train::dataset::step_mismatch(&s) {
                    super::print_error(&m);
                    failures += 1;
                    continue;
                }
                scenes += 1;
                copies.add(&s.meta.scenario_id, &src);
                let w = windows(&s, &cfg);
                if !w.is_empty() {
                    used += 1;
                }
                for win in &w {
                    wins += 1;
                    agents += win.agents.len();
                    lanes += win.lane_ids.len();
                    futures.extend((0..win.agents.len()).filter_map(|k| win.agent_future(&cfg, k)));
                }
            }
        }
    }
    for w in copies.warnings() {
        eprintln!("warning: {}", drivescript::io::name::terminal_safe(&w));
    }
    if failures > 0 {
        println!("{failures} sources or records could not be read (above); the rest:");
    }
    println!(
        "{scenes} scenes, {used} long enough for {} + {} steps; {wins} windows; {:.1} agents and {:.1} lanes per window; {} complete agent futures",
        cfg.history,
        cfg.future,
        agents as f64 / wins.max(1) as f64,
        lanes as f64 / wins.max(1) as f64,
        futures.len()
    );
    // The table is what the command is for: without it the run has not done its job. Its
    // variance is out of a basis of every component, which needs as many futures as a future
    // holds numbers: 76 futures of 40 steps (`--stride 100000`) passed the check of 50, printed
    // the table's header, then stopped at "PCA needs at least 120 samples", naming no cause.
    let needed = 50.max(3 * cfg.future);
    if futures.len() < needed {
        anyhow::bail!(
            "{} complete agent futures of {} steps: PCA needs at least {needed} (at least 50, \
             and one per number of a future, which holds {}; more scenes, a smaller --stride, or \
             a shorter --future / --history)",
            futures.len(),
            cfg.future,
            3 * cfg.future
        );
    }
    println!("\n| PCA components | position RMSE (m) | variance kept |");
    println!("|---|---|---|");
    let total = Pca::fit(&futures, futures[0].len())?
        .variances
        .iter()
        .sum::<f64>();
    let dim = futures[0].len();
    let ks: Vec<usize> = [4, 8, 12, 16, 24, 32]
        .into_iter()
        .filter(|k| *k < dim)
        .collect();
    for &k in &ks {
        let p = Pca::fit(&futures, k)?;
        println!(
            "| {k} | {:.3} | {:.5} |",
            p.position_rmse(&futures),
            p.variances.iter().sum::<f64>() / total
        );
    }
    if ks.len() < 6 {
        // Rows at or past the dimension would all read "1.00000 variance kept" and say
        // nothing about how many a model needs.
        println!(
            "\nA future of {} steps holds {dim} numbers (x, y, heading per step): {dim} \
             components keep it exactly, so the rows from {dim} on are left out.",
            cfg.future
        );
    }
    Ok(if failures > 0 {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    })
}
