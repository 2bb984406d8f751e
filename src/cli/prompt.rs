//! `drivescript prompt show`: the exact first prompt `ask` would send.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use drivescript::io::{load_scene, LoadOptions};
use drivescript::llm::session::{first_messages, render_messages};
use drivescript::llm::SessionConfig;

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
    /// Checkpoint whose horizon the summary states (default: data/checkpoint).
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    #[command(flatten)]
    prompt: super::ask::PromptFlags,
}

pub fn run(args: Args) -> Result<ExitCode> {
    let Sub::Show(a) = args.command;
    let trained = super::ask::checkpoint(a.checkpoint.as_deref())?;
    let raw = load_scene(&a.scene, 0, &LoadOptions::default())
        .with_context(|| format!("loading {}", a.scene.display()))?;
    let prompts = a.prompt.load()?;
    let cfg = SessionConfig {
        prompt: a.prompt.options(),
        max_agents: a.prompt.max_agents,
        // The reply's share as ask's default --max-tokens leaves it.
        context: a.prompt.window(4096),
        ..SessionConfig::default()
    };
    let m = first_messages(
        &prompts,
        &cfg,
        &raw,
        &[a.request],
        trained.meta.config.window.future,
    )?;
    print!("{}", render_messages(&m.messages));
    if !m.left_out.is_empty() {
        eprintln!(
            "fitted to --context {}: left out {}",
            a.prompt.context.unwrap_or_default(),
            m.left_out.join("; ")
        );
    }
    Ok(ExitCode::SUCCESS)
}
