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
  drivescript inspect ~/womd/validation/   # every shard, every scenario")]
    Inspect(inspect::Args),
    /// Draw a scene (or a rollout on its map) as SVG, PNG or animated GIF.
    #[command(after_help = "Examples:
  drivescript render data/samples/commonroad/USA_Lanker-1_1_T-1.xml -o lanker.png
  drivescript render scene.yaml --rollout sim.json -o sim.gif
  drivescript render training.tfrecord-00000-of-01000 --index 3 --step 0 -o s3.svg")]
    Render(render::Args),
    /// Convert a scene to YAML (map and agents) or TFRecord, or its trajectories to rollout JSON.
    #[command(after_help = "Examples:
  drivescript convert data/samples/av2/ -o av2.yaml
  drivescript convert data/samples/commonroad/USA_US101-3_3_T-1.xml -o us101.tfrecord
  drivescript convert scene.yaml -o recorded.json")]
    Convert(convert::Args),
    /// Evaluate a cost script on a scene's recorded future (or a rollout): per-term values and gradients.
    #[command(after_help = "Examples:
  drivescript cost data/samples/yaml/highway_cut_in.yaml --script scripts/cut_in.rhai --param cutter=2 victim=1
  drivescript cost scene.xml --script my.rhai --rollout sim.json --json")]
    Cost(cost::Args),
    /// Training windows a corpus gives (for the diffusion model) and PCA reconstruction errors.
    #[command(after_help = "Examples:
  drivescript dataset ../shared/data/commonroad-ngsim
  drivescript dataset data/samples --history 11 --future 30")]
    Dataset(dataset::Args),
    /// Sample futures of a scene with the diffusion model, guided by cost scripts.
    #[command(after_help = "Examples:
  drivescript simulate scene.yaml --checkpoint runs/ngsim --script scripts/cut_in.rhai --param cutter=2 victim=1 -o out/sim
  drivescript simulate scene.xml --checkpoint runs/ngsim --task unconditional --samples 4 -o out/uncond")]
    Simulate(simulate::Args),
    /// Train the diffusion model (EDM) on scenes; checkpoints as safetensors + JSON.
    #[command(after_help = "Examples:
  drivescript train --data ../shared/data/commonroad-ngsim --out runs/ngsim --steps 20000
  drivescript train --data scripts/scenes --out /tmp/tiny --steps 50 --batch 4")]
    Train(train::Args),
    /// Score baselines or rollouts: conditional, unconditional or behaviour tables.
    #[command(after_help = "Examples:
  drivescript eval ../shared/data/commonroad-ngsim --task conditional
  drivescript eval scenes/ --task unconditional --baseline cv
  drivescript eval scene.yaml --task behaviour --behaviour cut_in --param cutter=2 victim=1 --rollouts sims/
  drivescript eval data/samples --task conditional --rollouts sims/ --samples 4 --json out/eval.json")]
    Eval(eval::Args),
    /// The product in one command: `ask` with the rules planner on a US-101 sample ("vehicle 401
    /// cuts in front of vehicle 405, vehicle 389 drives off the road"), every phase printed, a
    /// repair round, and out/demo/final.gif with the named agents highlighted.
    #[command(after_help = "Examples:
  drivescript demo
  drivescript demo -o /tmp/demo --samples 8 --seed 2
  drivescript demo --scene data/samples/commonroad/USA_US101-3_3_T-1.xml --request \"vehicle 401 cuts in front of vehicle 399\"")]
    Demo(demo::Args),
    /// Words → cost script → guided samples → repaired script: the LLM in the loop.
    #[command(
        after_help = "Backends: an OpenAI-compatible server (DRIVESCRIPT_LLM_URL, DRIVESCRIPT_LLM_MODEL,
DRIVESCRIPT_LLM_KEY where needed; --llm-url and --model override), --llm manual (prompts
as files, --resume after saving each reply), or --llm rules (a fixed vocabulary, the default
when no LLM is configured). Exit status: 0 accepted (or a manual round waiting), 2 not
accepted or gave up, 1 an error.

Examples:
  drivescript ask data/samples/commonroad/USA_US101-3_3_T-1.xml \\
      \"vehicle 401 cuts in front of vehicle 399, vehicle 405 drives off the road\" -o runs/ask1
  drivescript ask --continue runs/ask1 \"make the cut-in more abrupt\"
  drivescript ask scene.xml \"vehicle 3 yields to vehicle 5\" --llm manual -o runs/m1
  drivescript ask --resume runs/m1"
    )]
    Ask(ask::Args),
    /// Show the prompts `ask` sends.
    #[command(after_help = "Examples:
  drivescript prompt show data/samples/commonroad/USA_US101-3_3_T-1.xml \"vehicle 401 cuts in front of vehicle 399\"")]
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
  drivescript bench io --data ../shared/data/commonroad-ngsim")]
    Bench(bench::Args),
}

/// Parses the command line and runs the subcommand; errors are printed with their causes.
pub fn run() -> ExitCode {
    let cli = Cli::parse();
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
        Command::Ask(a) => ask::run(a),
        Command::Prompt(a) => prompt::run(a),
        Command::StdlibDoc(a) => stdlib_doc::run(a),
        Command::TestScripts(a) => test_scripts::run(a),
        Command::Bench(a) => bench::run(a),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Prints one sample's outcome: the checker's verdict (when there is one), each term's first
/// estimate and final value, and the implausible motion of any vehicle.
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
        println!("  implausible: {who}{} {}", e.agent, e.text);
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
