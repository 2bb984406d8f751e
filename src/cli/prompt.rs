//! `drivescript prompt show`: the exact first prompt `ask` would send.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use drivescript::io::{load_scene, LoadOptions};
use drivescript::llm::session::{first_messages, render_messages};
use drivescript::llm::{Prompts, SessionConfig};

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    command: Sub,
}

#[derive(clap::Subcommand)]
enum Sub {
    /// Print the system prompt and the first user message for SCENE and REQUEST.
    Show(ShowArgs),
}

#[derive(clap::Args)]
struct ShowArgs {
    /// Scene file.
    scene: PathBuf,
    /// The request, in quotes.
    request: String,
    /// Prompt templates (default: prompts/).
    #[arg(long)]
    prompts: Option<PathBuf>,
    /// Checkpoint whose horizon the summary states (default: data/checkpoint).
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    /// Most agents in the scene summary.
    #[arg(long, default_value_t = 30)]
    max_agents: usize,
    /// As `ask --no-cot`.
    #[arg(long, conflicts_with = "zero_shot_cot")]
    no_cot: bool,
    /// As `ask --zero-shot-cot`.
    #[arg(long)]
    zero_shot_cot: bool,
    /// As `ask --no-frenet`.
    #[arg(long)]
    no_frenet: bool,
}

pub fn run(args: Args) -> Result<ExitCode> {
    let Sub::Show(a) = args.command;
    let trained = super::ask::checkpoint(a.checkpoint.as_deref())?;
    let raw = load_scene(&a.scene, 0, &LoadOptions::default())
        .with_context(|| format!("loading {}", a.scene.display()))?;
    let prompts = Prompts::load(&a.prompts.unwrap_or_else(Prompts::default_dir))?;
    let cfg = SessionConfig {
        prompt: super::ask::prompt_options(a.no_cot, a.zero_shot_cot, a.no_frenet),
        max_agents: a.max_agents,
        ..SessionConfig::default()
    };
    let m = first_messages(
        &prompts,
        &cfg,
        &raw,
        &[a.request],
        trained.meta.config.window.future,
    );
    print!("{}", render_messages(&m));
    Ok(ExitCode::SUCCESS)
}
