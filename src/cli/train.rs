//! `drivescript train`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use drivescript::train::{
    check_export_dir, check_out_dir, load_for_training, train_from, ComponentScale, Corpus,
    Holdout, SplitBy, TrainConfig, WindowSource, WindowStore,
};
use indicatif::{ProgressBar, ProgressStyle};

/// Window sizes and network of a new run.
#[derive(Clone, Copy, clap::ValueEnum)]
enum Setting {
    /// 4 s futures, vehicles only (the NGSIM checkpoint's setting).
    Ngsim,
    /// 8 s futures, with each agent's type and size as inputs: highways and cities.
    Cities,
}

#[derive(clap::Args)]
pub struct Args {
    /// Scene files or directories to train on; about 10 % of their scenes are held out, by
    /// scene id (for recordings of a few long roads, such as NGSIM).
    #[arg(long, num_args = 1..)]
    data: Vec<PathBuf>,
    /// Scene files or directories of many towns or cities (CommonRoad ids, `DEU_Flensburg-…`):
    /// held out a town at a time, so that validation measures places the model never saw.
    #[arg(long, num_args = 1..)]
    urban: Vec<PathBuf>,
    /// Window sizes and network of a new run (default ngsim; a resumed run keeps its
    /// checkpoint's, and refuses another).
    // No clap default: a resumed run must tell a setting given from none (`--setting cities`
    // beside an ngsim checkpoint was ignored without a word).
    #[arg(long, value_enum)]
    setting: Option<Setting>,
    /// Checkpoint directory (model.safetensors + config.json, written at every validation).
    #[arg(long, required_unless_present = "export")]
    out: Option<PathBuf>,
    /// Instead of training: write every window, encoded as the --resume checkpoint's network
    /// reads it, into this new or empty directory (safetensors files of 1,024 windows, with a
    /// loss check and the checkpoint's config): what `benches/torch/train.py` trains the same
    /// network from on an accelerator.
    // Only the corpora, --resume and --cache bear on an export: the windows are cut and held
    // out as the checkpoint's config says and nothing is trained, so a training flag beside
    // it is refused (--val-fold 3 was ignored without a word, and fold 0 exported).
    #[arg(
        long,
        conflicts_with = "out",
        requires = "resume",
        conflicts_with_all = [
            "setting", "steps", "batch", "lr", "seed", "eval_every", "val_fold", "val_town",
            "ema_half_life", "component_scale", "scale_cap", "p_mean", "p_std",
            "nearest_lane_pose", "route_times", "goals", "route_frame", "across_weight",
            "force",
        ]
    )]
    export: Option<PathBuf>,
    /// Directory for the training windows, cut from the scenes once and read back a batch at
    /// a time (default: OUT/windows, or a temporary directory with --export; rewritten at
    /// every start).
    #[arg(long)]
    cache: Option<PathBuf>,
    /// Optimiser steps.
    #[arg(long, default_value_t = 2000)]
    steps: usize,
    /// Windows per batch.
    #[arg(long, default_value_t = 8)]
    batch: usize,
    /// Learning rate, at least 1e-8.
    #[arg(long, value_parser = super::ask::float, default_value_t = 3e-4)]
    lr: f64,
    /// Seed (initialisation, batches, noise, augmentation; default 1). A resumed run keeps its
    /// checkpoint's, and refuses another.
    #[arg(long)]
    seed: Option<u64>,
    /// Validation (and checkpoint) every this many steps.
    #[arg(long, default_value_t = 100)]
    eval_every: usize,
    /// Which tenth of the scenes to hold out for validation (0-9, by a hash of the scene id):
    /// models trained on different folds cross-validate each other. Default 0, or the resumed
    /// checkpoint's fold.
    #[arg(long, value_parser = clap::value_parser!(u64).range(0..10))]
    val_fold: Option<u64>,
    /// A town or city of the --urban corpora to hold out besides the fold's (repeatable;
    /// the name before the first `-` of its scene ids, e.g. DEU_Reutlingen).
    #[arg(long)]
    val_town: Vec<String>,
    /// Continue from this checkpoint (its sizes, PCA basis and seed are kept; `--steps` is the
    /// total to reach). May be the `--out` directory itself.
    #[arg(long)]
    resume: Option<PathBuf>,
    /// Half-life, in steps, of the moving average of the weights that the checkpoint samples
    /// with (0: the last step's weights; at most 10^8). Default: the setting's (cities 500,
    /// ngsim 0), or the resumed checkpoint's.
    #[arg(long, value_parser = super::ask::float)]
    ema_half_life: Option<f64>,
    /// How a new run scales the PCA components: `common` (one scale for all) or `capped`
    /// (each its own spread, at most the common one). Default: the setting's (cities capped,
    /// ngsim common); a resumed run keeps its checkpoint's.
    #[arg(long, value_enum)]
    component_scale: Option<ScaleArg>,
    /// With `capped` scales: the cap as a fraction of the common scale, in (0, 1] (default 1).
    /// A resumed run keeps its checkpoint's.
    #[arg(long, value_parser = super::ask::float)]
    scale_cap: Option<f64>,
    /// A new run draws its training noise levels with ln σ ~ N(P_MEAN, P_STD²) (EDM's P_mean;
    /// default -1.2). Higher trains the levels where the sampler places a car on its route more
    /// often; the validation loss is drawn the same way, so it compares only runs of one
    /// P_MEAN and P_STD. A resumed run keeps its checkpoint's.
    #[arg(long, value_parser = super::ask::float)]
    p_mean: Option<f64>,
    /// EDM's P_std for a new run (default 1.2; see --p-mean).
    #[arg(long, value_parser = super::ask::float)]
    p_std: Option<f64>,
    /// A new run gives every agent-lane pair the pose of the lane's point nearest to the agent
    /// besides its first point's (`nearest_lane_pose` in the checkpoint's window; a resumed run
    /// keeps its checkpoint's).
    #[arg(long)]
    nearest_lane_pose: bool,
    /// A new run measures each agent's noisy future against the lanes at this many future
    /// times (`route_times` in the checkpoint's window and model; 0 for none, the default; a
    /// resumed run keeps its checkpoint's).
    #[arg(long)]
    route_times: Option<usize>,
    /// A new run gives the network each agent's recorded end point as an input, for half the
    /// agents of each training batch (`goals` in the checkpoint's window and model): its
    /// conditional simulation then samples futures that end there instead of pulling
    /// unconditional ones to it. A resumed run keeps its checkpoint's.
    #[arg(long)]
    goals: bool,
    /// A new run tells each vehicle's future against a route of the lane graph (the distance
    /// along it beyond constant speed, the offset across it, the heading beyond the route's)
    /// and gives the route ahead as an input (`route_frame` in the checkpoint's window and
    /// model), so that a future with no offset follows its lanes. A resumed run keeps its
    /// checkpoint's.
    #[arg(long)]
    route_frame: bool,
    /// A new run weighs the part of each position error across the recorded path this many
    /// times the rest, 1 to 1000 (default 1, the plain error; `across_weight` in the
    /// checkpoint's config). Validation losses then compare only runs of one weight. A resumed
    /// run keeps its checkpoint's.
    #[arg(long, value_parser = super::ask::float)]
    across_weight: Option<f64>,
    /// Train from scratch into an --out directory that already holds a checkpoint (which is
    /// replaced at the first validation). Without it, that is refused.
    #[arg(long)]
    force: bool,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum ScaleArg {
    Common,
    Capped,
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
    let base = match args.setting.unwrap_or(Setting::Ngsim) {
        Setting::Ngsim => TrainConfig::ngsim(),
        Setting::Cities => TrainConfig::cities(),
    };
    let mut cfg = TrainConfig {
        steps: args.steps,
        batch: args.batch,
        lr: args.lr,
        seed: args.seed.unwrap_or(base.seed),
        eval_every: args.eval_every,
        val_fold: args.val_fold.unwrap_or(0),
        val_towns: args.val_town.clone(),
        ema_half_life: args.ema_half_life.unwrap_or(base.ema_half_life),
        component_scale: match args.component_scale {
            Some(ScaleArg::Common) => ComponentScale::Common,
            Some(ScaleArg::Capped) => ComponentScale::Capped,
            None => base.component_scale,
        },
        scale_cap: args.scale_cap.unwrap_or(base.scale_cap),
        across_weight: args.across_weight.unwrap_or(base.across_weight),
        ..base
    };
    cfg.edm.p_mean = args.p_mean.unwrap_or(cfg.edm.p_mean);
    cfg.edm.p_std = args.p_std.unwrap_or(cfg.edm.p_std);
    if args.nearest_lane_pose {
        cfg.window.nearest_lane_pose = true;
        cfg.model.agent_lane_features = cfg.window.agent_lane_features();
    }
    if let Some(t) = args.route_times {
        cfg.window.route_times = t;
        cfg.model.route_times = t;
    }
    if args.goals {
        cfg.window.goals = true;
        cfg.model.goals = true;
    }
    if args.route_frame {
        cfg.window.route_frame = true;
        cfg.model.route_frame = true;
    }
    if args.data.is_empty() && args.urban.is_empty() {
        anyhow::bail!("nothing to train on: give --data or --urban (or both)");
    }
    let corpora: Vec<Corpus> = args
        .data
        .iter()
        .map(|p| (p, SplitBy::Scene))
        .chain(args.urban.iter().map(|p| (p, SplitBy::Town)))
        .map(|(p, split)| Corpus {
            path: p.clone(),
            split,
        })
        .collect();
    if let Some(dir) = &args.export {
        return export_run(&args, dir, &corpora);
    }
    let out = args
        .out
        .clone()
        .expect("clap requires --out without --export");
    // Before anything is read or written: a checkpoint among the scenes it learns from.
    check_out_dir(&out, &corpora)?;
    // A good checkpoint is never overwritten by accident, by a new run or another's resume.
    drivescript::train::check_replaces_checkpoint(&out, args.resume.as_deref(), args.force)?;
    // Before any data is read: --steps, --batch, --lr and --eval-every.
    if let Err(e) = cfg.validate().and_then(|()| cfg.check_batch_memory()) {
        match drivescript::train::trainer::flag_of(&e) {
            Some(flag) => anyhow::bail!("training settings: {flag}: {e}"),
            None => anyhow::bail!("training settings: {e}"),
        }
    }
    let resume = match &args.resume {
        Some(dir) => {
            let r = load_for_training(dir)
                .with_context(|| format!("resuming from {}", dir.display()))?;
            drivescript::train::trainer::check_steps_left(&r, cfg.steps)?;
            if args.ema_half_life.is_none() {
                cfg.ema_half_life = r.meta.config.ema_half_life;
            }
            let fold = r.meta.config.val_fold;
            let kept = &r.meta.config;
            if let Some(seed) = args.seed.filter(|s| *s != kept.seed) {
                anyhow::bail!(
                    "--seed {seed}: {} was trained with seed {}; a resumed run keeps its seed \
                     (each step's batch and noise come from it and the step number)",
                    dir.display(),
                    kept.seed
                );
            }
            if args.setting.is_some()
                && (base.window.future != kept.window.future
                    || base.model.attrs != kept.model.attrs)
            {
                anyhow::bail!(
                    "--setting: {} has {}-step futures {} the agents' types and sizes as \
                     inputs, the other setting's network; a resumed run keeps its setting",
                    dir.display(),
                    kept.window.future,
                    if kept.model.attrs > 0 {
                        "and"
                    } else {
                        "without"
                    }
                );
            }
            if args.val_fold.is_some_and(|f| f != fold) {
                anyhow::bail!(
                    "--val-fold {}: {} held out fold {fold}; a resumed run keeps its fold",
                    args.val_fold.unwrap_or_default(),
                    dir.display()
                );
            }
            if args.component_scale.is_some()
                && cfg.component_scale != r.meta.config.component_scale
            {
                // Named as the flag spells it: `{:?}` printed Rust's `Common`.
                anyhow::bail!(
                    "--component-scale: {} scales its PCA components as `--component-scale \
                     {}`; a resumed run keeps its scales",
                    dir.display(),
                    match r.meta.config.component_scale {
                        ComponentScale::Common => "common",
                        ComponentScale::Capped => "capped",
                    }
                );
            }
            if args.nearest_lane_pose && !r.meta.config.window.nearest_lane_pose {
                anyhow::bail!(
                    "--nearest-lane-pose: {} was trained without the lanes' nearest points; a \
                     resumed run keeps its inputs",
                    dir.display()
                );
            }
            if args.route_frame && !r.meta.config.window.route_frame {
                anyhow::bail!(
                    "--route-frame: {} was trained with futures told along each agent's \
                     heading; a resumed run keeps its form of the future",
                    dir.display()
                );
            }
            if args.goals && !r.meta.config.window.goals {
                anyhow::bail!(
                    "--goals: {} was trained without agents' end points; a resumed run keeps \
                     its inputs",
                    dir.display()
                );
            }
            if let Some(t) = args
                .route_times
                .filter(|t| *t != r.meta.config.window.route_times)
            {
                anyhow::bail!(
                    "--route-times {t}: {} measures futures against the lanes at {} times; a \
                     resumed run keeps its inputs",
                    dir.display(),
                    r.meta.config.window.route_times
                );
            }
            for (flag, given, kept) in [
                ("--p-mean", args.p_mean, r.meta.config.edm.p_mean),
                ("--p-std", args.p_std, r.meta.config.edm.p_std),
            ] {
                if let Some(v) = given.filter(|v| *v != kept) {
                    anyhow::bail!(
                        "{flag} {}: {} drew its noise levels with {} {}; a resumed run keeps them",
                        drivescript::geom::num(v),
                        dir.display(),
                        flag.trim_start_matches("--").replace('-', "_"),
                        drivescript::geom::num(kept)
                    );
                }
            }
            if let Some(w) = args
                .across_weight
                .filter(|w| *w != r.meta.config.across_weight)
            {
                anyhow::bail!(
                    "--across-weight {}: {} weighs the error across the path {} times; a \
                     resumed run keeps its loss",
                    drivescript::geom::num(w),
                    dir.display(),
                    drivescript::geom::num(r.meta.config.across_weight)
                );
            }
            if args.scale_cap.is_some_and(|c| c != r.meta.config.scale_cap) {
                anyhow::bail!(
                    "--scale-cap: {} caps its PCA scales at {} of the common scale; a resumed \
                     run keeps its scales",
                    dir.display(),
                    r.meta.config.scale_cap
                );
            }
            if !args.val_town.is_empty() && args.val_town != r.meta.config.val_towns {
                let towns = |t: &[String]| {
                    let shown: Vec<String> = t
                        .iter()
                        .map(|t| format!("\"{}\"", drivescript::io::name::shown_counted(t)))
                        .collect();
                    if shown.is_empty() {
                        "none".to_string()
                    } else {
                        shown.join(" ")
                    }
                };
                anyhow::bail!(
                    "--val-town {}: {} held out {}; a resumed run keeps its towns",
                    towns(&args.val_town),
                    dir.display(),
                    towns(&r.meta.config.val_towns)
                );
            }
            println!(
                "resuming from {} at step {}{}",
                super::shown(&dir),
                r.meta.steps_done,
                if r.optimizer.is_some() {
                    ""
                } else {
                    " (no optimiser state saved with it: AdamW's moments restart)"
                }
            );
            match (&r.ema, cfg.ema_half_life > 0.0) {
                (None, true) => println!(
                    "a moving average of the weights (half-life {} steps) starts here",
                    cfg.ema_half_life
                ),
                (Some(_), false) => println!(
                    "--ema-half-life 0: the moving average of the weights is dropped; \
                     training goes on from the last step's weights"
                ),
                _ => {}
            }
            Some(r)
        }
        None => None,
    };
    // The windows are cut with the sizes and the fold training will use: a resumed run's own.
    if let Some(r) = &resume {
        cfg.window = r.meta.config.window;
        cfg.val_fold = r.meta.config.val_fold;
        cfg.val_towns = r.meta.config.val_towns.clone();
    }
    let cache = args.cache.clone().unwrap_or_else(|| out.join("windows"));
    // Before --out is made for the lock: a cache refused leaves nothing behind.
    drivescript::train::store::check_cache_dir(&cache, &corpora)?;
    drivescript::train::check_cache_beside_checkpoint(&cache, &out)?;
    // Held to the end: a second run into this --out is refused, not mixed with this one.
    let _lock = drivescript::train::store::lock_out_dir(&out)?;
    let started = std::time::Instant::now();
    let holdout = Holdout {
        fold: cfg.val_fold,
        towns: cfg.val_towns.clone(),
    };
    let store = WindowStore::build(&corpora, &cfg.window, &holdout, &cache, |n, w| {
        if n % 100 == 0 {
            eprintln!("  {n} scenes read, {w} windows");
        }
    })?;
    for w in store.repeated_scenarios() {
        eprintln!("warning: {}", drivescript::io::name::terminal_safe(&w));
    }
    println!(
        "{} training and {} validation windows ({} and {} scenes) in {} ({:.0} s); window {} + {} steps, {} agents, {} lanes",
        store.train_len(),
        store.val_len(),
        store.train_scenes().len(),
        store.val_scenes().len(),
        super::shown(&cache),
        started.elapsed().as_secs_f64(),
        cfg.window.history,
        cfg.window.future,
        cfg.window.max_agents,
        cfg.window.max_lanes
    );
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
        &store,
        cfg,
        resume,
        Some(&out),
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
        super::shown(&out)
    );
    Ok(ExitCode::SUCCESS)
}

/// `train --export DIR`: the windows of the corpora, encoded for the --resume checkpoint.
fn export_run(args: &Args, dir: &std::path::Path, corpora: &[Corpus]) -> Result<ExitCode> {
    check_export_dir(dir, corpora)?;
    if let Some(cache) = &args.cache {
        drivescript::train::store::check_cache_apart_from_export(cache, dir)?;
    }
    let from = args
        .resume
        .as_ref()
        .expect("clap requires --resume with --export");
    let trained =
        load_for_training(from).with_context(|| format!("exporting for {}", from.display()))?;
    let cfg = &trained.meta.config;
    let holdout = Holdout {
        fold: cfg.val_fold,
        towns: cfg.val_towns.clone(),
    };
    // A cache of the user's is kept; the default one is this run's scratch space.
    let (cache, scratch) = match &args.cache {
        Some(c) => (c.clone(), false),
        None => (
            drivescript::train::store::scratch_dir("drivescript-export")?,
            true,
        ),
    };
    if let Err(e) = drivescript::train::store::check_cache_dir(&cache, corpora) {
        if scratch {
            let _ = std::fs::remove_dir(&cache);
        }
        return Err(e.into());
    }
    let started = std::time::Instant::now();
    let built = WindowStore::build(corpora, &cfg.window, &holdout, &cache, |n, w| {
        if n % 100 == 0 {
            eprintln!("  {n} scenes read, {w} windows");
        }
    });
    let result = built.map_err(anyhow::Error::from).and_then(|store| {
        for w in store.repeated_scenarios() {
            eprintln!("warning: {}", drivescript::io::name::terminal_safe(&w));
        }
        drivescript::train::export(&store, &trained, dir, 1024, |done, total| {
            eprintln!("  {done}/{total} files written");
        })
        .map_err(anyhow::Error::from)
    });
    if scratch {
        let _ = std::fs::remove_dir_all(&cache);
    }
    let e = result.with_context(|| format!("exporting into {}", dir.display()))?;
    println!(
        "wrote {} training and {} validation windows in {} files to {} ({:.0} s)",
        e.train,
        e.val,
        e.shards,
        super::shown(&dir),
        started.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}
