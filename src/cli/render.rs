//! `drivescript render`.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Result};
use drivescript::io::{load_scene, rollout::Rollout, write_atomic, LoadOptions};
use drivescript::render::{render_gif, render_png, render_svg, RenderOptions, MAX_GIF_FRAMES};
use drivescript::scene::Scene;

#[derive(clap::Args)]
pub struct Args {
    /// The scene file or directory.
    scene: PathBuf,
    /// Draw this rollout's trajectories instead of the recorded ones.
    #[arg(long)]
    rollout: Option<PathBuf>,
    /// Which scene of a multi-scene source (WOMD files hold many).
    #[arg(long, default_value_t = 0)]
    index: usize,
    /// Step whose boxes are drawn in SVG/PNG (default: the current step).
    #[arg(long)]
    step: Option<usize>,
    /// Image width in pixels.
    #[arg(long, default_value_t = 1000)]
    width: u32,
    /// Highlight an agent and label it with a role, ID=ROLE (e.g. 389=cutter); repeatable.
    #[arg(long = "role", value_parser = parse_role)]
    roles: Vec<(i64, String)>,
    /// Output: .svg, .png or .gif.
    #[arg(short, long)]
    output: PathBuf,
}

fn parse_role(s: &str) -> Result<(i64, String), String> {
    let (id, role) = s
        .split_once('=')
        .ok_or_else(|| format!("{s:?}: expected ID=ROLE"))?;
    let id = id
        .trim()
        .parse()
        .map_err(|_| format!("{s:?}: {id:?} is not an agent id"))?;
    let role = role.trim();
    if role.is_empty() || role.len() > 32 || role.chars().any(char::is_control) {
        return Err(format!(
            "{s:?}: the role must be 1 to 32 printable characters"
        ));
    }
    Ok((id, role.to_string()))
}

/// Writes `scene` as SVG, PNG or GIF by the output's extension.
pub fn write_picture(scene: &Scene, output: &Path, opts: &RenderOptions) -> Result<()> {
    let ext = output
        .extension()
        .map(|e| e.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    let bytes = match ext.as_str() {
        "svg" => render_svg(scene, opts)?.into_bytes(),
        "png" => render_png(scene, opts)?,
        "gif" => render_gif(scene, opts)?,
        _ => bail!(
            "{}: unknown picture format; use .svg, .png or .gif",
            output.display()
        ),
    };
    write_atomic(output, &bytes)?;
    Ok(())
}

pub fn run(args: Args) -> Result<ExitCode> {
    let mut scene = load_scene(&args.scene, args.index, &LoadOptions::default())?;
    if let Some(r) = &args.rollout {
        let rollout = Rollout::read(r)?;
        // The error names the rollout and what in it does not fit the scene.
        scene = rollout.apply_to(&scene, r)?;
    }
    if let Some(step) = args.step {
        if step >= scene.num_steps() {
            bail!("--step {step}: the scene has {} steps", scene.num_steps());
        }
    }
    // Asked for in so many words, a GIF is all the steps or nothing (`simulate`'s own
    // pictures show the last frames of a longer scene).
    let gif = args
        .output
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("gif"));
    if gif && scene.num_steps() > MAX_GIF_FRAMES {
        bail!(
            "a GIF of {} steps is more than {MAX_GIF_FRAMES} frames; draw one step (--step N, as \
             SVG or PNG) or cut the scene first (convert --current-step)",
            scene.num_steps()
        );
    }
    let opts = RenderOptions {
        width: args.width,
        step: args.step,
        roles: args.roles.clone(),
        ..RenderOptions::default()
    };
    write_picture(&scene, &args.output, &opts)?;
    println!("wrote {}", args.output.display());
    Ok(ExitCode::SUCCESS)
}
