//! `drivescript convert`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Result};
use drivescript::io::{
    check_output_not_input, load_scene, output_stem, rollout::Rollout, womd, write_atomic, yaml,
    LoadOptions,
};

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
    // An id that cannot name output files would be written here and refused by every command
    // that reads the file back.
    if let Some(id) = &args.id {
        output_stem(id)?;
    }
    let mut scene = load_scene(&args.scene, args.index, &LoadOptions::default())?;
    if let Some(c) = args.current_step {
        if c + 1 >= scene.num_steps() {
            bail!(
                "{}: --current-step {c} leaves no future (the scene has {} steps)",
                args.scene.display(),
                scene.num_steps()
            );
        }
        if !scene.agents.iter().any(|a| a.is_valid(c)) {
            bail!("{}: no agent is observed at step {c}", args.scene.display());
        }
        scene.meta.current_step = c;
    }
    if let Some(id) = &args.id {
        scene.meta.scenario_id = id.clone();
    }
    let name = args.output.to_string_lossy().to_lowercase();
    if name.ends_with(".yaml") || name.ends_with(".yml") {
        write_atomic(&args.output, yaml::to_yaml(&scene).as_bytes())?;
    } else if name.ends_with(".json") {
        Rollout::from_scene(&scene).write(&args.output)?;
    } else if name.ends_with(".tfrecord") || name.contains(".tfrecord-") {
        womd::write_file(&args.output, std::slice::from_ref(&scene))?;
    } else {
        bail!(
            "{}: unknown output format; use .yaml, .json or .tfrecord",
            args.output.display()
        );
    }
    println!("wrote {}", args.output.display());
    Ok(ExitCode::SUCCESS)
}
