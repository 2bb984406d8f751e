//! `drivescript demo`: the product in one command. `ask` with the rules planner on a sample
//! scene and a two-event request: plan, script, validation, sampling, per-term costs, verdicts,
//! the planner's answer (accept, or repair while no sample meets the request), and the GIF with
//! the named agents highlighted.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use drivescript::io::{load_scene, LoadOptions};
use drivescript::llm::{Backend, Outcome, Prompts, Session, SessionConfig};

/// The demo's scene and request: a cut-in that needs the cutter to gain 5 m on the victim
/// within 4 s, beside a road departure. Without polish every sample of the first script ends
/// the cut-in a few metres short and the loop repairs it; with it (the default) three of the
/// four meet the request.
const SCENE: &str = "commonroad/USA_US101-4_1_T-1.xml";
const REQUEST: &str = "vehicle 401 cuts in front of vehicle 405, vehicle 389 drives off the road";

#[derive(clap::Args)]
pub struct Args {
    /// Scene (default: a US-101 scene from data/samples).
    #[arg(long)]
    scene: Option<PathBuf>,
    /// Request, in the rules planner's vocabulary (default: a cut-in and a road departure).
    #[arg(long)]
    request: Option<String>,
    /// Checkpoint directory (default: the one shipped in data/checkpoint).
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    /// Samples per round, 1 to 1024.
    #[arg(long, default_value_t = 4, value_parser = super::ask::usize_in(1, drivescript::sample::MAX_SAMPLES))]
    samples: usize,
    /// Seed of the initial noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Where the guidance gradient is taken (as `simulate` and `ask` take it).
    #[arg(long, value_enum, default_value = "output")]
    guidance: super::GuidanceArg,
    /// Run directory; an earlier demo run there is replaced. The picture is DIR/final.gif.
    #[arg(short, long, default_value = "out/demo")]
    output: PathBuf,
}

pub fn run(args: Args) -> Result<ExitCode> {
    let request = args.request.unwrap_or_else(|| REQUEST.to_string());
    // Refused before the scene and the request are printed: a request the planner cannot run
    // was echoed whole first.
    drivescript::llm::session::check_rules_request(&request)?;
    let trained = super::ask::checkpoint(args.checkpoint.as_deref())?;
    let scene_path = args
        .scene
        .unwrap_or_else(|| super::samples_dir().join(SCENE));
    let raw = load_scene(&scene_path, 0, &LoadOptions::default())
        .with_context(|| format!("loading the demo scene {}", scene_path.display()))?;
    println!("{}\n", raw.summary());
    println!(
        "request: {}",
        drivescript::io::name::terminal_safe(&request)
    );
    println!("LLM: the rules planner (a fixed vocabulary, not a language model); `drivescript ask` takes any OpenAI-compatible server\n");
    let config = SessionConfig {
        samples: args.samples,
        seed: args.seed,
        guidance: args.guidance.into(),
        ..SessionConfig::default()
    };
    // Before the previous run is cleared away.
    config.validate()?;
    let prompts = Prompts::load(&Prompts::default_dir())?;
    // The previous demo run there goes, under the run's lock (an `ask` going on there keeps
    // its files).
    let mut session = Session::replace(
        &args.output,
        &scene_path,
        raw,
        &request,
        &trained,
        Backend::Rules,
        prompts,
        config,
        None,
    )?;
    for (b, p) in session.checks() {
        println!("checker: {} ({p}): {}", b.name(), b.definition());
    }
    let outcome =
        session.run(&mut |line| println!("{}", drivescript::io::name::terminal_safe(line)))?;
    let dir = super::shown(&args.output);
    // As `ask` says it: a run that sampled no round wrote no final picture or script, and the
    // line named them anyway (a --scene without the request's agents).
    if session.verdict().round.is_some() {
        println!(
            "\nwrote {dir}/final.gif (named agents highlighted), {dir}/final.rhai, {dir}/report.md, every round in {dir}/round_N/ and {dir}/transcript.json"
        );
    } else {
        println!("\nwrote {dir}/report.md and {dir}/transcript.json (no round was sampled)");
    }
    if let Outcome::Accepted { round, .. } | Outcome::RoundsUsed { round, .. } = &outcome {
        println!(
            "rollouts of the final round, in {dir}: {}",
            session.rollout_files(*round)
        );
        for (b, p) in session.checks() {
            println!(
                "  score them: drivescript eval {} --task behaviour --behaviour {} --param {p} --rollouts {dir}/round_{round} --unguided {dir}/round_{round}/unguided --samples {}",
                super::shown(&scene_path),
                b.name(),
                args.samples
            );
        }
    }
    // As `ask` exits: by the run's verdict.
    Ok(if session.verdict().succeeded {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(2)
    })
}
