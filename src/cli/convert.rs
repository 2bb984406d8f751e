//! `drivescript convert`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Result};
use drivescript::io::{load_scene, rollout::Rollout, womd, write_atomic, yaml, LoadOptions};

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
}

pub fn run(args: Args) -> Result<ExitCode> {
    let scene = load_scene(&args.scene, args.index, &LoadOptions::default())?;
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
