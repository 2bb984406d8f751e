//! `drivescript render`.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use drivescript::io::name::shown_counted;
use drivescript::io::{check_output_not_input, check_replaces_own, rollout::Rollout, write_atomic};
use drivescript::render::{render_gif_with_progress, PictureFormat, RenderOptions, MAX_GIF_FRAMES};
use drivescript::scene::Scene;

/// The fewest frames of a GIF whose drawing is said as it goes (a few seconds' work).
const GIF_PROGRESS_FRAMES: usize = 200;

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
    /// Image width in pixels, 64 to 8192.
    #[arg(long, default_value_t = 1000, value_parser = clap::value_parser!(u32).range(64..=8192))]
    width: u32,
    /// Highlight an agent and label it with a role, ID=ROLE (e.g. 389=cutter); repeatable.
    #[arg(long = "role", value_parser = RoleParser)]
    roles: Vec<(i64, String)>,
    /// Output: .svg, .png or .gif.
    #[arg(short, long)]
    output: PathBuf,
}

/// Parses `--role` values. Not a plain function parser: clap quotes the whole value in its
/// "invalid value '…'" line, and a 5000-character value made a 10 KB message; this one says
/// what is wrong quoting at most [`drivescript::io::name::QUOTED_CHARS`] characters of it.
#[derive(Clone)]
struct RoleParser;

impl clap::builder::TypedValueParser for RoleParser {
    type Value = (i64, String);

    fn parse_ref(
        &self,
        cmd: &clap::Command,
        arg: Option<&clap::Arg>,
        value: &std::ffi::OsStr,
    ) -> Result<Self::Value, clap::Error> {
        parse_role(&value.to_string_lossy()).map_err(|e| {
            let flag = arg
                .map(|a| a.to_string())
                .unwrap_or_else(|| "--role".into());
            clap::Error::raw(
                clap::error::ErrorKind::ValueValidation,
                format!("invalid value for '{flag}': {e}\n"),
            )
            .with_cmd(cmd)
        })
    }
}

fn parse_role(s: &str) -> Result<(i64, String), String> {
    let q = |v: &str| format!("'{}'", shown_counted(v));
    let (id, role) = s
        .split_once('=')
        .ok_or_else(|| format!("{}: expected ID=ROLE", q(s)))?;
    let id = id
        .trim()
        .parse()
        .map_err(|_| format!("{}: {} is not an agent id", q(s), q(id)))?;
    let role = role.trim();
    // `--role 389=cutter,401=victim` labelled 389 "cutter,401=victim" and left 401 plain.
    if role.contains('=') {
        return Err(format!(
            "{}: a role cannot hold '=': give --role once per agent (--role 389=cutter --role \
             401=victim)",
            q(s)
        ));
    }
    if role.is_empty()
        || role.chars().count() > 32
        || role.chars().any(drivescript::io::name::unshowable)
    {
        return Err(format!(
            "{}: the role must be 1 to 32 printable characters",
            q(s)
        ));
    }
    Ok((id, role.to_string()))
}

/// The picture format `output`'s extension names, or an error saying which there are.
fn format_of(output: &Path) -> Result<PictureFormat> {
    PictureFormat::from_path(output).with_context(|| {
        // `-o .svg` names a hidden file with no extension, and was told only that its
        // format is unknown.
        let name = output
            .file_name()
            .map(|n| n.to_string_lossy().to_lowercase())
            .unwrap_or_default();
        if [".svg", ".png", ".gif"].contains(&name.as_str()) {
            format!(
                "{}: the name is only an extension (a hidden file with none); name the file \
                 before it, e.g. out{name}",
                output.display()
            )
        } else {
            format!(
                "{}: unknown picture format; use .svg, .png or .gif",
                output.display()
            )
        }
    })
}

/// Writes `scene` as SVG, PNG or GIF by the output's extension.
pub fn write_picture(scene: &Scene, output: &Path, opts: &RenderOptions) -> Result<()> {
    let bytes = format_of(output)?.render(scene, opts)?;
    write_atomic(output, &bytes)?;
    Ok(())
}

pub fn run(args: Args) -> Result<ExitCode> {
    // Refused before anything is read: -o replaces only an earlier picture of its format,
    // never an input or a file of the user's.
    let format = format_of(&args.output)?;
    let inputs: Vec<&Path> = std::iter::once(args.scene.as_path())
        .chain(args.rollout.as_deref())
        .collect();
    check_output_not_input(&args.output, &inputs, "-o")?;
    check_replaces_own(&args.output, "-o", format.what(), |p| format.holds_own(p))?;
    let mut scene = super::load_indexed(&args.scene, args.index)?;
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
    if format == PictureFormat::Gif && scene.num_steps() > MAX_GIF_FRAMES {
        bail!(
            "{}: a GIF of {} steps is more than {MAX_GIF_FRAMES} frames; draw one step (--step \
             N, as SVG or PNG) or cut the scene first (convert --current-step)",
            super::shown(&args.scene),
            scene.num_steps()
        );
    }
    let opts = RenderOptions {
        width: args.width,
        step: args.step,
        roles: args.roles.clone(),
        ..RenderOptions::default()
    };
    opts.check_roles(&scene)?;
    if format == PictureFormat::Gif {
        // A 2,000-frame GIF takes half a minute, which passed without a word: the frames
        // drawn are said on stderr at each tenth of a long one.
        let mut said = 0;
        let bytes = render_gif_with_progress(&scene, &opts, &mut |k, n| {
            if n >= GIF_PROGRESS_FRAMES && k * 10 / n > said {
                said = k * 10 / n;
                eprintln!("drew {k} of {n} frames");
            }
        })?;
        write_atomic(&args.output, &bytes)?;
    } else {
        write_picture(&scene, &args.output, &opts)?;
    }
    super::print_wrote(&args.output);
    Ok(ExitCode::SUCCESS)
}
