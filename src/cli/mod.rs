//! Command-line interface: argument definitions and dispatch.

mod ask;
mod bench;
mod convert;
mod cost;
mod dataset;
mod demo;
mod eval;
mod inspect;
mod prompt;
mod render;
mod simulate;
mod stdlib_doc;
mod test_scripts;
mod train;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// Controllable traffic simulation on real road maps.
#[derive(Parser)]
#[command(name = "drivescript", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Summarise scenes: format, scenario id, time grid, agents by type, map and lane graph.
    #[command(after_help = "Examples:
  drivescript inspect data/samples/commonroad/USA_US101-3_3_T-1.xml
  drivescript inspect data/samples --json
  drivescript inspect data/samples/commonroad/USA_US101-3_3_T-1.xml --agents --max-agents 5
  drivescript convert data/samples/commonroad/USA_US101-3_3_T-1.xml -o out/us101.tfrecord
  drivescript inspect out/us101.tfrecord   # WOMD: every scenario of a file (or of a directory)")]
    Inspect(inspect::Args),
    /// Draw a scene (or a rollout on its map) as SVG, PNG or animated GIF.
    #[command(after_help = "Examples:
  drivescript render data/samples/commonroad/USA_Lanker-1_1_T-1.xml -o out/lanker.png
  drivescript convert data/samples/yaml/highway_cut_in.yaml -o out/recorded.json
  drivescript render data/samples/yaml/highway_cut_in.yaml --rollout out/recorded.json \\
      -o out/recorded.gif
  drivescript convert data/samples/commonroad/USA_US101-3_3_T-1.xml -o out/us101.tfrecord
  drivescript render out/us101.tfrecord --index 0 --step 0 -o out/us101.svg")]
    Render(render::Args),
    /// Convert a scene to YAML (map and agents) or TFRecord, or its trajectories to rollout JSON.
    #[command(after_help = "Examples:
  drivescript convert data/samples/av2/ -o out/av2.yaml
  drivescript convert data/samples/commonroad/USA_US101-3_3_T-1.xml -o out/us101.tfrecord
  drivescript convert data/samples/yaml/highway_cut_in.yaml -o out/recorded.json")]
    Convert(convert::Args),
    /// Evaluate a cost script on a scene's recorded future (or a rollout): per-term values and gradients.
    #[command(after_help = "Examples:
  drivescript cost data/samples/yaml/highway_cut_in.yaml --script scripts/cut_in.rhai \\
      --param cutter=2 victim=1
  drivescript simulate data/samples/yaml/highway_cut_in.yaml --checkpoint data/checkpoint \\
      --script scripts/cut_in.rhai --param cutter=2 victim=1 -o out/sim
  drivescript cost data/samples/yaml/highway_cut_in.yaml --script scripts/cut_in.rhai \\
      --param cutter=2 victim=1 --rollout out/sim/highway-cut-in_0.json --json")]
    Cost(cost::Args),
    /// Training windows a corpus gives (for the diffusion model) and PCA reconstruction errors.
    #[command(after_help = "Examples:
  drivescript dataset data/samples
  drivescript dataset data/samples --history 11 --future 30")]
    Dataset(dataset::Args),
    /// Sample futures of a scene with the diffusion model, guided by cost scripts.
    #[command(after_help = "Examples:
  drivescript simulate data/samples/yaml/highway_cut_in.yaml --checkpoint data/checkpoint \\
      --script scripts/cut_in.rhai --param cutter=2 victim=1 -o out/sim
  drivescript simulate data/samples/commonroad/USA_US101-3_3_T-1.xml \\
      --checkpoint data/checkpoint --task unconditional --samples 4 -o out/uncond
  drivescript simulate data/samples/commonroad --checkpoint data/checkpoint \\
      --task unconditional --auto off_road -o out/off_road   # agents chosen per scene
  drivescript simulate data/samples --checkpoint data/checkpoint --shard 0/2 --resume -o out/s
  drivescript simulate data/samples --checkpoint data/checkpoint --shard 1/2 --resume -o out/s")]
    Simulate(simulate::Args),
    /// Train the diffusion model (EDM) on scenes; checkpoints as safetensors + JSON.
    #[command(after_help = "Examples:
  drivescript train --data data/samples --out out/tiny --steps 50 --batch 4
  drivescript train --data data/samples --out out/tiny --resume out/tiny --steps 100 --batch 4")]
    Train(train::Args),
    /// Score baselines or rollouts: conditional, unconditional or behaviour tables.
    #[command(after_help = "Examples:
  drivescript eval data/samples --task conditional
  drivescript eval data/samples --task unconditional --baseline cv
  drivescript simulate data/samples/yaml/highway_cut_in.yaml --checkpoint data/checkpoint \\
      --script scripts/cut_in.rhai --param cutter=2 victim=1 -o out/sim
  drivescript eval data/samples/yaml/highway_cut_in.yaml --task behaviour --behaviour cut_in \\
      --param cutter=2 victim=1 --rollouts out/sim
  drivescript simulate data/samples --checkpoint data/checkpoint --samples 4 -o out/cond
  drivescript eval data/samples --task conditional --rollouts out/cond --samples 4 \\
      --json out/eval.json")]
    Eval(eval::Args),
    /// The product in one command: `ask` with the rules planner on a US-101 sample ("vehicle 401
    /// cuts in front of vehicle 405, vehicle 389 drives off the road"), every phase printed, a
    /// repair round, and out/demo/final.gif with the named agents highlighted.
    #[command(after_help = "Examples:
  drivescript demo
  drivescript demo -o out/demo2 --samples 8 --seed 2
  drivescript demo --scene data/samples/commonroad/USA_US101-3_3_T-1.xml \\
      --request \"vehicle 401 cuts in front of vehicle 399\" -o out/demo399")]
    Demo(demo::Args),
    /// Words → cost script → guided samples → repaired script: the LLM in the loop.
    #[command(
        after_help = "Backends: an OpenAI-compatible server (DRIVESCRIPT_LLM_URL, DRIVESCRIPT_LLM_MODEL,
DRIVESCRIPT_LLM_KEY where needed; --llm-url and --model override), --llm manual (prompts
as files, --resume after saving each reply), or --llm rules (a fixed vocabulary, the default
when no LLM is configured). Exit status: 0 when the run succeeded (the final round passes
every checker, or meets the whole request where a clause has none: the judgement --batch
counts) or a manual round waits, 2 when it did not or nothing was sampled (a request no car
can meet in the horizon is not attempted), 1 an error.

Examples:
  drivescript ask data/samples/commonroad/USA_US101-3_3_T-1.xml \\
      \"vehicle 401 cuts in front of vehicle 399, vehicle 405 drives off the road\" -o out/ask1
  drivescript ask --continue out/ask1 \"vehicle 402 drives off the road\"
  drivescript ask data/samples/commonroad/USA_US101-3_3_T-1.xml \\
      \"vehicle 401 cuts in front of vehicle 399\" --llm manual -o out/m1
  (echo '```rhai'; cat out/ask1/final.rhai; echo '```') > out/m1/round_0/reply.md  # the reply
  drivescript ask --resume out/m1
  drivescript ask --batch data/requests/table1.yaml --scenes data/samples/commonroad \\
      --llm rules --rounds 1 -o out/batch"
    )]
    Ask(ask::Args),
    /// Show the prompts `ask` sends.
    #[command(after_help = "Examples:
  drivescript prompt show data/samples/commonroad/USA_US101-3_3_T-1.xml \\
      \"vehicle 401 cuts in front of vehicle 399\"")]
    Prompt(prompt::Args),
    /// Run cost-script unit tests (*.test.yaml) and print a pass/fail table.
    #[command(after_help = "Examples:
  drivescript test-scripts
  drivescript test-scripts scripts/cut_in.test.yaml -v")]
    TestScripts(test_scripts::Args),
    /// Print the cost-script reference (markdown), generated from what the engine registers.
    #[command(after_help = "Examples:
  drivescript stdlib-doc > reference.md
  drivescript stdlib-doc | grep frenet")]
    StdlibDoc(stdlib_doc::Args),
    /// Measure throughput and print a table.
    #[command(after_help = "Examples:
  drivescript bench io
  drivescript bench cost --seconds 0.2
  drivescript bench sample --only output --repeat 1")]
    Bench(bench::Args),
}

/// `--guidance denoiser|output`: one flag, with one default, on every command that samples.
#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum GuidanceArg {
    /// Cost gradient pulled back through the denoiser (the paper's rule; slower).
    Denoiser,
    /// Cost gradient at the denoised output (the default: sample::DEFAULT_GUIDANCE says why).
    Output,
}

impl From<GuidanceArg> for drivescript::sample::Guidance {
    fn from(g: GuidanceArg) -> Self {
        match g {
            GuidanceArg::Denoiser => drivescript::sample::Guidance::Denoiser,
            GuidanceArg::Output => drivescript::sample::Guidance::OutputSpace,
        }
    }
}

/// Parses the command line and runs the subcommand; errors are printed with their causes.
pub fn run() -> ExitCode {
    use clap::{CommandFactory, FromArgMatches};
    let matches = negatives_as_values(Cli::command())
        .try_get_matches()
        .unwrap_or_else(|e| quoted_cut(e).exit());
    let cli = Cli::from_arg_matches(&matches)
        .map_err(|e| e.format(&mut Cli::command()))
        .unwrap_or_else(|e| e.exit());
    let given = matches
        .subcommand()
        .map(|(_, m)| given(m))
        .unwrap_or_default();
    let result = match cli.command {
        Command::Inspect(a) => inspect::run(a),
        Command::Render(a) => render::run(a),
        Command::Convert(a) => convert::run(a),
        Command::Cost(a) => cost::run(a),
        Command::Eval(a) => eval::run(a),
        Command::Train(a) => train::run(a),
        Command::Simulate(a) => simulate::run(a),
        Command::Dataset(a) => dataset::run(a),
        Command::Demo(a) => demo::run(a),
        Command::Ask(a) => ask::run(a, &given),
        Command::Prompt(a) => prompt::run(a),
        Command::StdlibDoc(a) => stdlib_doc::run(a),
        Command::TestScripts(a) => test_scripts::run(a),
        Command::Bench(a) => bench::run(a),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            print_error(&describe(&e));
            ExitCode::FAILURE
        }
    }
}

/// `cmd` with every option that takes a value taking a negative number as one, in every
/// subcommand: clap otherwise reads `--lambda -1` (or `--index -1`, `--lr -1`) as the flag
/// `-1`, said "unexpected argument '-1' found" with the tip to write `-- -1`, which passes it
/// as a scene instead; read as the value, the flag's own check names it and its range.
fn negatives_as_values(cmd: clap::Command) -> clap::Command {
    cmd.mut_args(|a| {
        if !a.is_positional() && a.get_action().takes_values() {
            a.allow_negative_numbers(true)
        } else {
            a
        }
    })
    .mut_subcommands(negatives_as_values)
}

/// clap's error with every value and argument the user typed quoted as
/// [`drivescript::io::name::shown_counted`] shows it: clap echoes a bad value whole ("invalid
/// value '…'", "unexpected argument '…'", and again in its tip), and a 5000-character value made
/// a 5 to 10 KB message; escape sequences in one reached the terminal as they were.
fn quoted_cut(mut e: clap::Error) -> clap::Error {
    use clap::error::{ContextKind, ContextValue};
    use drivescript::io::name::shown_counted;
    let mut cut = Vec::new();
    for kind in [
        ContextKind::InvalidValue,
        ContextKind::InvalidArg,
        ContextKind::InvalidSubcommand,
    ] {
        if let Some(ContextValue::String(typed)) = e.get(kind) {
            let shown = shown_counted(typed);
            if shown != *typed {
                cut.push((typed.clone(), shown.clone()));
                e.insert(kind, ContextValue::String(shown));
            }
        }
    }
    if let Some(ContextValue::StyledStrs(tips)) = e.get(ContextKind::Suggested) {
        if !cut.is_empty() {
            let tips = tips
                .iter()
                .map(|t| {
                    let mut text = t.ansi().to_string();
                    for (typed, shown) in &cut {
                        text = text.replace(typed.as_str(), shown);
                    }
                    clap::builder::StyledStr::from(text)
                })
                .collect();
            e.insert(ContextKind::Suggested, ContextValue::StyledStrs(tips));
        }
    }
    e
}

/// The flags given on the command line (clap's ids: the field names), not those left at their
/// defaults: a flag typed with its default value is still one the user gave, and a command
/// that refuses a flag it would not read refuses that one too.
fn given(m: &clap::ArgMatches) -> Vec<String> {
    m.ids()
        .filter(|id| m.value_source(id.as_str()) == Some(clap::parser::ValueSource::CommandLine))
        .map(|id| id.as_str().to_string())
        .collect()
}

/// Prints `error: TEXT` on stderr as a terminal can show it: errors quote file names and what
/// files and servers hold, escape sequences included (`io::name::terminal_safe`).
pub(crate) fn print_error(text: &str) {
    eprintln!("error: {}", drivescript::io::name::terminal_safe(text));
}

/// A path on one line as a terminal can show it, for progress and `wrote` lines: an output
/// name holding an escape sequence (`-o $'x\e[2J.svg'`) cleared the screen, and one holding a
/// line break forged a line, where errors about the same name are escaped (`print_error`).
pub(crate) fn shown(path: &std::path::Path) -> String {
    drivescript::io::name::one_line(&path.display().to_string())
}

/// Prints `wrote PATH` on stdout as [`shown`] writes the path.
pub(crate) fn print_wrote(path: &std::path::Path) {
    println!("wrote {}", shown(path));
}

/// An error and its causes on one line, each cause once: many errors already quote their
/// source (`FILE: No such file or directory`), and anyhow's `{:#}` would repeat it.
pub(crate) fn describe(e: &anyhow::Error) -> String {
    let mut text = e.to_string();
    for cause in e.chain().skip(1) {
        let c = cause.to_string();
        if !text.contains(&c) {
            text.push_str(": ");
            text.push_str(&c);
        }
    }
    text
}

/// Prints one sample's outcome: the checker's verdict (when there is one), each term's first
/// estimate and final value, and the implausible motion of any vehicle (motion the checked
/// behaviour asks for, `reverse`'s backing up, as "asked for").
pub(crate) fn print_outcome(label: &str, o: &drivescript::sample::SampleOutcome) {
    if o.verdicts.is_empty() {
        println!("{label}: total cost {:.4}", o.total);
    }
    for v in &o.verdicts {
        let head = match (v.passed, v.achieved) {
            (true, _) => "PASS",
            (false, true) => "fail (achieved, implausibly)",
            (false, false) => "fail",
        };
        println!("{label}: {head}: {}", v.reason);
    }
    println!(
        "  {:<28} {:>7} {:>10} {:>10}",
        "term (unweighted)", "weight", "initial", "final"
    );
    for t in &o.terms {
        println!(
            "  {:<28} {:>7} {:>10} {:>10.4}",
            t.term,
            format!("{}", t.weight),
            t.initial.map_or("-".into(), |v| format!("{v:.4}")),
            t.value
        );
    }
    let shown = 4;
    for e in o.realism.iter().take(shown) {
        let who = e.role.as_deref().map_or(String::new(), |r| format!("{r} "));
        let what = if e.requested {
            "asked for"
        } else {
            "implausible"
        };
        println!("  {what}: {who}{} {}", e.agent, e.text);
    }
    if o.realism.len() > shown {
        println!(
            "  implausible: {} more events (all in the costs JSON)",
            o.realism.len() - shown
        );
    }
}

/// Where the repository's sample data lives (next to the binary's crate, or the working dir).
pub(crate) fn samples_dir() -> PathBuf {
    let here = PathBuf::from("data/samples");
    if here.exists() {
        return here;
    }
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("data/samples")
}

/// `--script-budget SECONDS` as the sampler takes it, or an error naming the flag and its range.
pub(crate) fn script_budget(seconds: f64) -> anyhow::Result<std::time::Duration> {
    let max = drivescript::sample::MAX_SCRIPT_BUDGET;
    // A positive budget below a nanosecond is 0 as a Duration: refused here, naming the flag,
    // not as the sampler's "script budget = 0 s".
    if !(seconds >= 1e-9 && seconds <= max.as_secs_f64()) {
        anyhow::bail!(
            "--script-budget {}: must be more than 0 and at most {} seconds",
            drivescript::geom::num(seconds),
            max.as_secs()
        );
    }
    Ok(std::time::Duration::from_secs_f64(seconds))
}

/// Scene `index` of `path`, as a command's `--index` asks for it: an index past the source's
/// last scene names the flag and the indices there are, not only "scene 7".
pub(crate) fn load_indexed(
    path: &std::path::Path,
    index: usize,
) -> anyhow::Result<drivescript::scene::Scene> {
    use drivescript::io::{load_scene, IoError, LoadOptions};
    match load_scene(path, index, &LoadOptions::default()) {
        Err(IoError::NoSuchScene { count, .. }) => anyhow::bail!(
            "--index {index}: {} holds {count} scene{}{}",
            path.display(),
            if count == 1 { "" } else { "s" },
            match count {
                0 => String::new(),
                1 => " (give --index 0, or leave it out)".into(),
                n => format!(" (give --index 0 to {})", n - 1),
            }
        ),
        r => Ok(r?),
    }
}

/// `--param`'s value parser: a value without `=` is refused at once. `--param` takes every value
/// up to the next flag, so `cost --param a=1 scene.yaml` read the scene as a parameter and said
/// only that `<SCENE>` was not given.
pub(crate) fn param_value(text: &str) -> Result<String, String> {
    if text.contains('=') {
        Ok(text.to_string())
    } else {
        // clap quotes the value before this message.
        Err(
            "not name=value: --param takes every value up to the next flag, so give the scenes \
             before --param, or end its list with `--`"
                .into(),
        )
    }
}

/// `--keep`'s value parser, for the same reason as [`param_value`]: `inspect --agents --keep 4
/// scene.yaml` read the scene as an agent id.
pub(crate) fn agent_id_value(text: &str) -> Result<i64, String> {
    text.parse().map_err(|_| {
        "not an agent id (a whole number): --keep takes every value up to the next flag, so \
         give the scenes before --keep, or end its list with `--`"
            .into()
    })
}
