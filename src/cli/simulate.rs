//! `drivescript simulate`.

use std::path::PathBuf;
use std::process::ExitCode;
use std::rc::Rc;

use anyhow::{Context, Result};
use drivescript::cost::{CostScript, Limits, Params};
use drivescript::io::{load_scene, rollout::Rollout, LoadOptions};
use drivescript::render::RenderOptions;
use drivescript::sample::{prepare, sample, Guidance, SampleConfig, Task};
use drivescript::train::load;

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum TaskArg {
    /// History and recorded end points known.
    Conditional,
    /// History only.
    Unconditional,
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum GuidanceArg {
    /// Cost gradient pulled back through the denoiser (the paper's rule).
    Denoiser,
    /// Cost gradient at the denoised output (cheaper).
    Output,
}

#[derive(clap::Args)]
pub struct Args {
    /// The scene file or directory.
    scene: PathBuf,
    /// Which scene of a multi-scene source.
    #[arg(long, default_value_t = 0)]
    index: usize,
    /// Conditioning.
    #[arg(long, value_enum, default_value = "conditional")]
    task: TaskArg,
    /// Cost scripts guiding the sampler (repeatable).
    #[arg(long = "script")]
    scripts: Vec<PathBuf>,
    /// Script parameters, name=value.
    #[arg(long = "param", num_args = 1..)]
    params: Vec<String>,
    /// Samples (one batch).
    #[arg(long, default_value_t = 1)]
    samples: usize,
    /// Seed of the initial noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Heun steps.
    #[arg(long, default_value_t = 32)]
    steps: usize,
    /// Guidance strength.
    #[arg(long, default_value_t = 0.05)]
    lambda: f64,
    /// Where the guidance gradient is taken.
    #[arg(long, value_enum, default_value = "denoiser")]
    guidance: GuidanceArg,
    /// Checkpoint directory (model.safetensors + config.json).
    #[arg(long)]
    checkpoint: PathBuf,
    /// Output directory: sample_K.json, sample_0.gif, costs.json.
    #[arg(short, long)]
    output: PathBuf,
}

pub fn run(args: Args) -> Result<ExitCode> {
    let trained = load(&args.checkpoint)?;
    let raw = load_scene(&args.scene, args.index, &LoadOptions::default())?;
    let scene = prepare(&raw, &trained)?;
    let params = Params::parse(&args.params)?;
    let shared = Rc::new(scene.clone());
    let scripts = args
        .scripts
        .iter()
        .map(|p| {
            let src =
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            let s = CostScript::compile(
                &src,
                &p.display().to_string(),
                shared.clone(),
                &params,
                &Limits::default(),
            )?;
            s.validate()?;
            Ok(s)
        })
        .collect::<Result<Vec<_>>>()?;
    let cfg = SampleConfig {
        steps: args.steps,
        samples: args.samples,
        seed: args.seed,
        lambda: args.lambda,
        task: if args.task == TaskArg::Conditional {
            Task::Conditional
        } else {
            Task::Unconditional
        },
        guidance: if args.guidance == GuidanceArg::Denoiser {
            Guidance::Denoiser
        } else {
            Guidance::OutputSpace
        },
        known_weight: 1.0,
    };
    let t0 = std::time::Instant::now();
    let samples = sample(&trained, &scene, &scripts, &cfg)?;
    let secs = t0.elapsed().as_secs_f64();
    std::fs::create_dir_all(&args.output)
        .with_context(|| format!("creating {}", args.output.display()))?;
    let mut report = Vec::new();
    for (k, s) in samples.iter().enumerate() {
        let mut r = Rollout::from_scene(&s.scene);
        for rep in &s.reports {
            for t in &rep.terms {
                r.costs.insert(t.name.clone(), t.value);
            }
        }
        r.write(&args.output.join(format!("sample_{k}.json")))?;
        let terms: Vec<serde_json::Value> = s
            .reports
            .iter()
            .zip(
                s.initial_reports
                    .iter()
                    .map(Some)
                    .chain(std::iter::repeat(None)),
            )
            .flat_map(|(fin, ini)| {
                fin.terms.iter().map(move |t| {
                    let before = ini.and_then(|i| i.term(&t.name)).map(|x| x.value);
                    serde_json::json!({"term": t.name, "initial": before, "final": t.value})
                })
            })
            .collect();
        for t in &terms {
            println!(
                "sample {k}  {:<28} initial {:>10}  final {:>10.4}",
                t["term"].as_str().unwrap_or(""),
                t["initial"]
                    .as_f64()
                    .map_or("-".into(), |v| format!("{v:.4}")),
                t["final"].as_f64().unwrap_or(f64::NAN)
            );
        }
        report.push(serde_json::json!({"sample": k, "terms": terms}));
    }
    drivescript::io::write_atomic(
        &args.output.join("costs.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    super::render::write_picture(
        &samples[0].scene,
        &args.output.join("sample_0.gif"),
        &RenderOptions {
            width: 800,
            ..Default::default()
        },
    )?;
    println!(
        "{} samples in {secs:.2} s; wrote {}",
        samples.len(),
        args.output.display()
    );
    Ok(ExitCode::SUCCESS)
}
