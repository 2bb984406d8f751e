//! `drivescript convert`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use drivescript::io::scene_output::SceneOutput;
use drivescript::io::{check_output_not_input, output_stem};

#[derive(clap::Args)]
pub struct Args {
    /// The scene file or directory.
    scene: PathBuf,
    /// Which scene of a multi-scene source.
    #[arg(long, default_value_t = 0)]
    index: usize,
    /// Output: .yaml (map + agents), .json (rollout of the recorded trajectories) or .tfrecord.
    #[arg(short, long)]
    output: PathBuf,
    /// Move the current step (history before it, future after): cuts several evaluation
    /// instances from one long recording.
    #[arg(long)]
    current_step: Option<usize>,
    /// New scenario id (instances of one recording need distinct ids for `eval --rollouts`).
    #[arg(long)]
    id: Option<String>,
}

pub fn run(args: Args) -> Result<ExitCode> {
    // Writing over the input would replace a many-scene file with one scene, or a compact
    // YAML with its explicit form: refuse before reading anything.
    check_output_not_input(&args.output, &[&args.scene], "-o")?;
    let format = SceneOutput::from_path(&args.output).with_context(|| {
        format!(
            "{}: unknown output format; use .yaml, .json or .tfrecord",
            args.output.display()
        )
    })?;
    // Nor any existing file but an earlier output of the same format, one scenario.
    format.check_replaces_own(&args.output, "-o")?;
    // An id that cannot name output files would be written here and refused by every command
    // that reads the file back.
    if let Some(id) = &args.id {
        output_stem(id)?;
    }
    let mut scene = super::load_indexed(&args.scene, args.index)?;
    if let Some(c) = args.current_step {
        scene = scene
            .at_step(c)
            .with_context(|| format!("{}: --current-step", args.scene.display()))?;
    }
    if let Some(id) = &args.id {
        scene.meta.scenario_id = id.clone();
    }
    format.write(&args.output, &scene)?;
    super::print_wrote(&args.output);
    // What the format cannot hold, so that a round trip that changes the scene says so.
    for lost in format.left_out(&scene) {
        eprintln!("note: {} does not hold {lost}", super::shown(&args.output));
    }
    Ok(ExitCode::SUCCESS)
}
