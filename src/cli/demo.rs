//! `drivescript demo`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use drivescript::io::{load_scene, LoadOptions};
use drivescript::render::RenderOptions;

use super::render::write_picture;

#[derive(clap::Args)]
pub struct Args {
    /// Scene to show (default: a Lankershim Boulevard scene from data/samples).
    #[arg(long)]
    scene: Option<PathBuf>,
    /// Where to write the animation.
    #[arg(short, long, default_value = "out/demo.gif")]
    output: PathBuf,
}

pub fn run(args: Args) -> Result<ExitCode> {
    let scene_path = args
        .scene
        .unwrap_or_else(|| super::samples_dir().join("commonroad/USA_Lanker-1_1_T-1.xml"));
    let scene = load_scene(&scene_path, 0, &LoadOptions::default())
        .with_context(|| format!("loading the demo scene {}", scene_path.display()))?;
    println!("{}\n", scene.summary());
    let opts = RenderOptions {
        width: 900,
        ..RenderOptions::default()
    };
    write_picture(&scene, &args.output, &opts)?;
    println!(
        "wrote {} ({} frames of recorded trajectories; no trained diffusion checkpoint ships yet)",
        args.output.display(),
        scene.num_steps()
    );
    Ok(ExitCode::SUCCESS)
}
