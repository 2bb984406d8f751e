//! `drivescript train`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use drivescript::io::{discover, load_scenes, LoadOptions};
use drivescript::train::{load, train_from, TrainConfig};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(clap::Args)]
pub struct Args {
    /// Scene files or directories to train on (about 10 % of scenes are held out by id).
    #[arg(long, required = true, num_args = 1..)]
    data: Vec<PathBuf>,
    /// Checkpoint directory (model.safetensors + config.json, written at every validation).
    #[arg(long)]
    out: PathBuf,
    /// Optimiser steps.
    #[arg(long, default_value_t = 2000)]
    steps: usize,
    /// Windows per batch.
    #[arg(long, default_value_t = 8)]
    batch: usize,
    /// Learning rate.
    #[arg(long, default_value_t = 3e-4)]
    lr: f64,
    /// Seed (initialisation, batches, noise, augmentation).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Validation (and checkpoint) every this many steps.
    #[arg(long, default_value_t = 100)]
    eval_every: usize,
    /// Which tenth of the scenes to hold out for validation (0-9, by a hash of the scene id):
    /// models trained on different folds cross-validate each other. Default 0, or the resumed
    /// checkpoint's fold.
    #[arg(long, value_parser = clap::value_parser!(u64).range(0..10))]
    val_fold: Option<u64>,
    /// Continue from this checkpoint (its sizes, PCA basis and seed are kept; `--steps` is the
    /// total to reach). May be the `--out` directory itself.
    #[arg(long)]
    resume: Option<PathBuf>,
    /// Train from scratch into an --out directory that already holds a checkpoint (which is
    /// replaced at the first validation). Without it, that is refused.
    #[arg(long)]
    force: bool,
}

fn git_revision() -> Option<String> {
    let out = std::process::Command::new("git")
        .args(["rev-parse", "HEAD"])
        .output()
        .ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}

pub fn run(args: Args) -> Result<ExitCode> {
    let cfg = TrainConfig {
        steps: args.steps,
        batch: args.batch,
        lr: args.lr,
        seed: args.seed,
        eval_every: args.eval_every,
        val_fold: args.val_fold.unwrap_or(0),
        ..TrainConfig::ngsim()
    };
    // A good checkpoint is never overwritten by accident.
    if args.out.join("model.safetensors").exists() && args.resume.is_none() && !args.force {
        anyhow::bail!(
            "{} already holds a checkpoint: continue it with --resume {}, choose another --out, \
             or pass --force to replace it",
            args.out.display(),
            args.out.display()
        );
    }
    // Before any data is read: --steps, --batch, --lr and --eval-every.
    if let Err(e) = cfg.validate() {
        anyhow::bail!("training settings: {e}");
    }
    let mut scenes = Vec::new();
    for root in &args.data {
        for src in discover(root)? {
            scenes.extend(
                load_scenes(&src, &LoadOptions::default())
                    .with_context(|| format!("loading {}", src.display()))?,
            );
        }
    }
    println!(
        "{} scenes; window {} + {} steps, {} agents, {} lanes",
        scenes.len(),
        cfg.window.history,
        cfg.window.future,
        cfg.window.max_agents,
        cfg.window.max_lanes
    );
    let resume = match &args.resume {
        Some(dir) => {
            let r = load(dir).with_context(|| format!("resuming from {}", dir.display()))?;
            let fold = r.meta.config.val_fold;
            if args.val_fold.is_some_and(|f| f != fold) {
                anyhow::bail!(
                    "--val-fold {}: {} held out fold {fold}; a resumed run keeps its fold",
                    args.val_fold.unwrap_or_default(),
                    dir.display()
                );
            }
            println!(
                "resuming from {} at step {}{}",
                dir.display(),
                r.meta.steps_done,
                if r.optimizer.is_some() {
                    ""
                } else {
                    " (no optimiser state saved with it: AdamW's moments restart)"
                }
            );
            Some(r)
        }
        None => None,
    };
    let bar = ProgressBar::new(args.steps as u64);
    if let Some(r) = &resume {
        bar.set_position(r.meta.steps_done as u64);
    }
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} steps  {per_sec}  ETA {eta}  {msg}")
            .expect("valid template"),
    );
    let mut last_val = None;
    let mut avg = None::<f64>;
    let mut since = (0.0f64, 0usize);
    let t = train_from(
        &scenes,
        cfg,
        resume,
        Some(&args.out),
        git_revision(),
        |step, loss, val| {
            avg = Some(avg.map_or(loss, |a| 0.98 * a + 0.02 * loss));
            since.0 += loss;
            since.1 += 1;
            if val.is_some() {
                last_val = val;
            }
            // A line per checkpoint (the loss history's row), also where the bar is hidden
            // (a log file, CI) and its message never shows.
            if step % args.eval_every.max(1) == 0 || step == args.steps {
                bar.suspend(|| {
                    println!(
                        "step {step:>6}  train {:.4}  val {}",
                        since.0 / since.1.max(1) as f64,
                        val.map_or("-".into(), |v| format!("{v:.4}"))
                    )
                });
                since = (0.0, 0);
            }
            bar.set_message(format!(
                "loss {:.4}  val {}",
                avg.unwrap_or(loss),
                last_val.map_or("-".into(), |v| format!("{v:.4}"))
            ));
            bar.inc(1);
        },
    )?;
    bar.finish();
    println!(
        "trained {} steps on {} scenes ({} held out); PCA position RMSE {:.3} m; wrote {}",
        t.meta.steps_done,
        t.meta.train_scenes.len(),
        t.meta.val_scenes.len(),
        t.meta.pca_rmse_m,
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}
