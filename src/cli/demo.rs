//! `drivescript demo`: a cut-in simulated with the shipped checkpoint, guided by
//! scripts/cut_in.rhai, judged by the independent cut-in checker.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result};
use drivescript::cost::Realism;
use drivescript::eval::behaviors::{suggest, Behavior};
use drivescript::io::{load_scene, LoadOptions};
use drivescript::render::RenderOptions;
use drivescript::sample::{
    attempt, AttemptSpec, Guidance, LambdaSchedule, SampleConfig, ScriptSpec, Task,
};
use drivescript::train::load;

use super::render::write_picture;

#[derive(clap::Args)]
pub struct Args {
    /// Scene to simulate (default: a US-101 scene from data/samples).
    #[arg(long)]
    scene: Option<PathBuf>,
    /// Checkpoint directory (default: the one shipped in data/checkpoint).
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    /// Samples (one batch); the animation shows the first that passes the checker, else the
    /// one with the lowest cost.
    #[arg(long, default_value_t = 4)]
    samples: usize,
    /// Seed of the initial noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Where to write the animation; the rollouts (demo_K.json) and the cost report
    /// (demo_costs.json) go next to it.
    #[arg(short, long, default_value = "out/demo.gif")]
    output: PathBuf,
}

/// Guidance settings of the demo: the sampler's defaults for behaviours (see README,
/// "Diffusion model").
const LAMBDA: f64 = drivescript::sample::BEHAVIOUR_LAMBDA;

pub fn run(args: Args) -> Result<ExitCode> {
    let cfg = SampleConfig {
        samples: args.samples,
        seed: args.seed,
        lambda: LAMBDA,
        task: Task::Unconditional,
        guidance: Guidance::OutputSpace,
        schedule: LambdaSchedule::Fading,
        realism: Realism {
            weight: drivescript::sample::REALISM_WEIGHT,
            ..Realism::default()
        },
        ..SampleConfig::default()
    };
    if let Err(e) = cfg.validate() {
        anyhow::bail!("sampler settings: {e}");
    }
    let samples = super::samples_dir();
    let ckpt = args
        .checkpoint
        .unwrap_or_else(|| samples.join("../checkpoint"));
    let trained = load(&ckpt)
        .with_context(|| format!("loading the diffusion checkpoint {}", ckpt.display()))?;
    let scene_path = args
        .scene
        .unwrap_or_else(|| samples.join("commonroad/USA_US101-4_1_T-1.xml"));
    let raw = load_scene(&scene_path, 0, &LoadOptions::default())
        .with_context(|| format!("loading the demo scene {}", scene_path.display()))?;
    println!("{}\n", raw.summary());
    let future = trained.meta.config.window.future;
    let behaviour = Behavior::CutIn;
    let chosen = suggest(behaviour, &raw.with_horizon(future), future).with_context(|| {
        format!(
            "{}: no pair of vehicles in adjacent lanes for a cut-in",
            scene_path.display()
        )
    })?;
    println!(
        "cut-in: vehicle {} cuts in front of vehicle {} (chosen by eval::behaviors::suggest)",
        chosen.get("cutter").expect("suggest names the cutter"),
        chosen.get("victim").expect("suggest names the victim")
    );
    let script_path = samples.join("../../scripts/cut_in.rhai");
    let source = std::fs::read_to_string(&script_path)
        .with_context(|| format!("reading {}", script_path.display()))?;
    let spec = AttemptSpec {
        scripts: vec![ScriptSpec::new(
            source,
            "scripts/cut_in.rhai",
            chosen.clone(),
        )],
        checks: vec![(behaviour, chosen)],
        cfg,
        replan: None,
    };
    let done = attempt(&trained, &raw, &spec)?;
    let report = &done.report;
    println!(
        "{} samples, {} Heun steps, guided in output space (fading λ = {LAMBDA}), in {:.1} s\n",
        report.samples.len(),
        cfg.steps,
        report.seconds
    );
    let dir = args
        .output
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."))
        .to_path_buf();
    for o in &report.samples {
        super::print_outcome(&format!("sample {}", o.sample), o);
    }
    done.write(&dir, "demo")?;
    let k = done.best();
    let opts = RenderOptions {
        width: 900,
        roles: report.roles(),
        ..RenderOptions::default()
    };
    write_picture(&done.samples[k].scene, &args.output, &opts)?;
    let passed = report
        .samples
        .iter()
        .filter(|o| o.passed() == Some(true))
        .count();
    println!(
        "\n{passed} of {} samples pass the cut-in checker; wrote {} (sample {k}), demo_K.json and demo_costs.json in {}",
        report.samples.len(),
        args.output.display(),
        dir.display()
    );
    Ok(ExitCode::SUCCESS)
}
