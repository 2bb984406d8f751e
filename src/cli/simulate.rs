//! `drivescript simulate`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use drivescript::cost::{Params, Realism};
use drivescript::eval::behaviors::Behavior;
use drivescript::eval::suggest::suggest;
use drivescript::io::name::terminal_safe;
use drivescript::io::{discover, output_stem, read_each, LoadOptions, OutputNames};
use drivescript::render::RenderOptions;
use drivescript::sample::provenance::{file_crc32c, text_crc32c, RunRecord, RUN_FILE};
use drivescript::sample::{
    attempt, horizon_note, recorded_future, AttemptSpec, Clamp, LambdaSchedule, SampleConfig,
    ScriptSpec, Task,
};
use drivescript::train::load;

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum TaskArg {
    /// History and recorded end points known.
    Conditional,
    /// History only.
    Unconditional,
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum ClampArg {
    /// Each coefficient clipped on its own (the paper's rule).
    Coordinate,
    /// Each agent's gradient scaled as a whole until its largest entry is 1.
    Agent,
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum ScheduleArg {
    /// λ at every noise level.
    Constant,
    /// λ·σ/(σ + σ_data).
    Fading,
}

#[derive(clap::Args)]
pub struct Args {
    /// Scene files or directories (every scene of each is simulated).
    #[arg(required = true)]
    scenes: Vec<PathBuf>,
    /// Conditioning.
    #[arg(long, value_enum, default_value = "conditional")]
    task: TaskArg,
    /// Cost scripts guiding the sampler (repeatable).
    #[arg(long = "script")]
    scripts: Vec<PathBuf>,
    /// Script parameters, name=value.
    #[arg(long = "param", num_args = 1.., value_parser = super::param_value)]
    params: Vec<String>,
    /// Samples (one batch), 1 to 1024.
    #[arg(long, default_value_t = 1, value_parser = super::ask::usize_in(1, drivescript::sample::MAX_SAMPLES))]
    samples: usize,
    /// Seed of the initial noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Heun steps, 2 to 1000 and at least the fewest the checkpoint's noise schedule
    /// denoises with (8 for the shipped one): fewer leave noise in the trajectories.
    #[arg(long, default_value_t = 32, value_parser = super::ask::usize_in(drivescript::sample::MIN_HEUN_STEPS, drivescript::sample::MAX_HEUN_STEPS))]
    steps: usize,
    /// Future steps to sample, 1 up to the model's horizon (default: the model's horizon).
    #[arg(long, value_parser = super::ask::usize_in(1, drivescript::io::MAX_STEPS))]
    horizon: Option<usize>,
    /// Guidance strength of the scripts; default: the strength chosen for the checkpoint (its
    /// config.json's `guidance_lambda`), else 3 (chosen for the shipped NGSIM checkpoint with
    /// the fading schedule: data/checkpoint/README.md); above 0 only with --script or --auto.
    #[arg(long, value_parser = super::ask::float)]
    lambda: Option<f64>,
    /// Where the guidance gradient is taken: at the denoised output, or pulled back through
    /// the denoiser (the paper's rule, slower); the same flag and default as `ask`'s.
    #[arg(long, value_enum, default_value = "output")]
    guidance: super::GuidanceArg,
    /// Re-plan at 2 Hz: execute 0.5 s of each plan, then sample again from there. The scripts
    /// keep judging the horizon from the scene's current step (executed steps included), so a
    /// request keeps its deadline.
    #[arg(long)]
    closed_loop: bool,
    /// Choose each scene's agents for this behaviour (e.g. cut_in) the way `eval --task
    /// behaviour --auto` does, on the recording cut to the model's horizon; without --script
    /// the script is scripts/NAME.rhai. --param values override the choice. Scenes without
    /// suitable agents are skipped (and listed).
    #[arg(long)]
    auto: Option<String>,
    /// Weight of the realism terms that keep every sampled vehicle driving as a car can
    /// (speed, reversing, acceleration, lateral acceleration, crabbing) and clear of every
    /// other agent; 0 turns realism off. A script exempts an agent it asks to back up with
    /// `allow(a, "reverse")`, and two it asks to collide with `allow(a, "collide", b)`.
    #[arg(long, value_parser = super::ask::float, default_value_t = drivescript::sample::REALISM_WEIGHT)]
    realism: f64,
    /// Weight of the known-state cost (conditional end points), default 1; above 0 only with
    /// --task conditional.
    #[arg(long, value_parser = super::ask::float)]
    known_weight: Option<f64>,
    /// How λ varies with the noise level σ: constant or fading (λ·σ/(σ+σ_data)).
    #[arg(long, value_enum, default_value = "fading")]
    schedule: ScheduleArg,
    /// How the guidance gradient is kept within (-1, 1): per coefficient (the paper's rule)
    /// or per agent, scaled as a whole (keeps its direction).
    #[arg(long, value_enum, default_value = "coordinate")]
    clamp: ClampArg,
    /// Descent steps on the guidance cost after the last denoising step, 0 to 1000: what
    /// guidance planned, finished within realism's bounds; as many again with realism's
    /// collision term (0: none, and that term acts while denoising).
    #[arg(long, default_value_t = drivescript::sample::POLISH_STEPS, value_parser = super::ask::usize_in(0, 1000))]
    polish: usize,
    /// Seconds the cost scripts may take over one scene's sampling, every evaluation together
    /// (more than 0, at most 86400): past it the scene fails with an error that says how many
    /// evaluations ran and their mean time, instead of running for hours.
    #[arg(long, value_parser = super::ask::float, value_name = "SECONDS", default_value_t = drivescript::sample::DEFAULT_SCRIPT_BUDGET.as_secs_f64())]
    script_budget: f64,
    /// Checkpoint directory (model.safetensors + config.json).
    #[arg(long)]
    checkpoint: PathBuf,
    /// Output directory: SCENARIO_K.json per sample (what `eval --rollouts` reads),
    /// SCENARIO_0.gif and SCENARIO_costs.json, and run.json (what made them); with --auto
    /// also unguided/SCENARIO_K.json, the unguided twins the verdicts judged the rest of the
    /// scene against (`eval --unguided`). A directory holding another run is refused.
    #[arg(short, long)]
    output: PathBuf,
    /// Only the scenes of shard I of N (0 <= I < N), a stable partition by scenario id: run
    /// the N shards as an array job (Slurm, Kubernetes Indexed Job) into one -o with --resume.
    #[arg(long, value_name = "I/N")]
    shard: Option<drivescript::io::shard::Shard>,
    /// Continue the run in -o (same settings, checked against its run.json): scenes whose
    /// outputs are complete (every rollout reads back) are skipped; the rest are simulated
    /// again.
    #[arg(long)]
    resume: bool,
}

pub fn run(args: Args) -> Result<ExitCode> {
    let trained = load(&args.checkpoint)?;
    let auto = match &args.auto {
        Some(name) => Some(Behavior::parse(name).context("--auto")?),
        None => None,
    };
    let script_paths = match (auto, args.scripts.is_empty()) {
        (Some(b), true) => {
            vec![super::samples_dir().join(format!("../../scripts/{}.rhai", b.name()))]
        }
        _ => args.scripts.clone(),
    };
    // The same file twice would count its terms twice, silently doubling its weight.
    for (i, p) in script_paths.iter().enumerate() {
        let same = |q: &PathBuf| match (p.canonicalize(), q.canonicalize()) {
            (Ok(a), Ok(b)) => a == b,
            _ => p == q,
        };
        if let Some(q) = script_paths[..i].iter().find(|q| same(q)) {
            anyhow::bail!(
                "--script {}: the same file as --script {}; each script counts once (to weigh it more, raise --lambda)",
                terminal_safe(&p.display().to_string()),
                terminal_safe(&q.display().to_string())
            );
        }
    }
    // The horizon is checked against the model before anything is read or written.
    let future = match args.horizon {
        Some(h) if h > trained.meta.config.window.future => anyhow::bail!(
            "--horizon {h}: the model samples at most {} steps",
            trained.meta.config.window.future
        ),
        Some(h) => h,
        None => trained.meta.config.window.future,
    };
    let specs = script_paths
        .iter()
        .map(|p| {
            let source = drivescript::cost::read_script(p)?;
            Ok(ScriptSpec::new(
                source,
                p.display().to_string(),
                Params::default(),
            ))
        })
        .collect::<Result<Vec<_>>>()?;
    // Said once, before any scene is read or the output directory is claimed.
    for spec in &specs {
        spec.check_syntax()?;
    }
    // Said with the flag: the library's check names its settings, not the command line's.
    let max = drivescript::sample::MAX_WEIGHT;
    let lambda = args
        .lambda
        .unwrap_or_else(|| trained.meta.behaviour_lambda());
    let known_weight = args.known_weight.unwrap_or(1.0);
    for (flag, v) in [
        ("--lambda", lambda),
        ("--realism", args.realism),
        ("--known-weight", known_weight),
    ] {
        if !(v.is_finite() && (0.0..=max).contains(&v)) {
            anyhow::bail!("{flag} {}: must be 0 to {max}", drivescript::geom::num(v));
        }
    }
    // A weight with nothing to weigh was dropped without a word (0, "unguided", says
    // nothing wrong).
    if args.lambda.is_some_and(|l| l != 0.0) && specs.is_empty() {
        anyhow::bail!(
            "--lambda {}: no script to weigh (give --script or --auto)",
            drivescript::geom::num(lambda)
        );
    }
    if args.known_weight.is_some_and(|w| w != 0.0) && args.task != TaskArg::Conditional {
        anyhow::bail!(
            "--known-weight {}: only --task conditional knows end points to weigh",
            drivescript::geom::num(known_weight)
        );
    }
    let cfg = SampleConfig {
        steps: args.steps,
        samples: args.samples,
        seed: args.seed,
        lambda,
        task: if args.task == TaskArg::Conditional {
            Task::Conditional
        } else {
            Task::Unconditional
        },
        guidance: args.guidance.into(),
        known_weight,
        schedule: match args.schedule {
            ScheduleArg::Constant => LambdaSchedule::Constant,
            ScheduleArg::Fading => LambdaSchedule::Fading,
        },
        clamp: match args.clamp {
            ClampArg::Coordinate => Clamp::Coordinate,
            ClampArg::Agent => Clamp::Agent,
        },
        realism: Realism {
            weight: args.realism,
            ..Realism::default()
        },
        polish: args.polish,
        horizon: args.horizon,
        script_budget: super::script_budget(args.script_budget)?,
    };
    if let Err(e) = cfg.validate() {
        anyhow::bail!("sampler settings: {e}");
    }
    // Fewer steps wrote trajectories of kilometres a second without a word (and a closed
    // loop, which starts each round from them, failed on an "implausible heading").
    if let Some(why) = drivescript::sample::too_few_steps(&trained, args.steps) {
        anyhow::bail!("--steps {}: {why}", args.steps);
    }
    let explicit = Params::parse(&args.params)?;
    // With no script to read them, the values would be dropped without a word.
    if let Some(name) = explicit.names().next().filter(|_| specs.is_empty()) {
        anyhow::bail!(
            "parameter {name:?}: no script reads it; give the script it is for (--script or --auto)"
        );
    }
    let existed = args.output.exists();
    drivescript::io::create_output_dir(&args.output)?;
    let mut settings = serde_json::json!({
        "task": format!("{:?}", cfg.task),
        "samples": cfg.samples,
        "seed": cfg.seed,
        "steps": cfg.steps,
        "lambda": cfg.lambda,
        "guidance": format!("{:?}", cfg.guidance),
        "schedule": format!("{:?}", cfg.schedule),
        "clamp": format!("{:?}", cfg.clamp),
        "realism": cfg.realism.weight,
        "known_weight": cfg.known_weight,
        "polish": cfg.polish,
        "closed_loop": args.closed_loop,
        "auto": args.auto,
    });
    // A horizon shorter than the model's, recorded: `--resume --horizon 40` took the 20-step
    // rollouts of a `--horizon 20` run as complete. The model's own is left out, as runs
    // before the field recorded it, so that they resume as they were.
    if future != trained.meta.config.window.future {
        settings["horizon"] = future.into();
    }
    let record = RunRecord {
        command: "simulate".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        checkpoint: args.checkpoint.display().to_string(),
        weights_crc32c: file_crc32c(&args.checkpoint.join("model.safetensors"))?,
        config_crc32c: Some(file_crc32c(&args.checkpoint.join("config.json"))?),
        settings,
        scripts: specs
            .iter()
            .map(|s| (s.name.clone(), text_crc32c(s.source.as_bytes())))
            .collect(),
        params: explicit.to_string(),
    };
    let fresh = record.claim(&args.output, args.resume)?;
    if let Some(sh) = args.shard {
        drivescript::sample::provenance::claim_shards(&args.output, sh.count)?;
    }
    let run_value = serde_json::to_value(&record)?;
    let mut skipped = 0;
    let mut sources = Vec::new();
    for s in &args.scenes {
        sources.extend(discover(s)?);
    }
    // Said once per run, and counted at the end: scenes recording less or more than the
    // model's horizon, and agents of types the model never saw (agents, scenes).
    let horizons = std::cell::RefCell::new((0usize, 0usize));
    let fixed_total = std::cell::RefCell::new((0usize, 0usize));
    // Terms that can never steer, said once per run each (their scripts are the same for
    // every scene, and so is usually the reason).
    let warned = std::cell::RefCell::new(std::collections::BTreeSet::<String>::new());
    let started_writing = std::cell::Cell::new(false);
    // One scene's failure (a script error on its agents, say) is reported and the others go
    // on; the exit code says that something failed.
    let run_one = |raw: &drivescript::scene::Scene| -> Result<bool> {
        let id = raw.meta.scenario_id.clone();
        if let Some(note) = horizon_note(raw, future) {
            let mut h = horizons.borrow_mut();
            if h.0 + h.1 == 0 {
                println!("note: {note} (said once per run; the end of the run counts such scenes)");
            }
            if recorded_future(raw) < future {
                h.0 += 1;
            } else {
                h.1 += 1;
            }
        }
        // Suggested agents first, so that explicit --param values override them.
        let mut params = Params::default();
        if let Some(b) = auto {
            match suggest(b, &raw.with_horizon(future), future) {
                Some(p) => params = p,
                None => {
                    let reason = format!("no agents suited to {}", b.name());
                    drivescript::sample::attempt::write_skipped(
                        &args.output,
                        &id,
                        raw,
                        &reason,
                        true,
                    )?;
                    println!("{id}: {reason}; skipped");
                    return Ok(false);
                }
            }
            println!("{id}: {params}");
        }
        let params = params.overridden_by(&explicit);
        let spec = AttemptSpec {
            scripts: specs
                .iter()
                .map(|s| ScriptSpec {
                    params: params.clone(),
                    ..s.clone()
                })
                .collect(),
            checks: auto.map(|b| (b, params.clone())).into_iter().collect(),
            cfg,
            replan: args.closed_loop.then_some(5),
            // The user chose these scripts: a term the probes never wake is said, not refused.
            refuse_dead_terms: false,
        };
        let done = attempt(&trained, raw, &spec)?;
        let (samples, report) = (&done.samples, &done.report);
        for w in &report.warnings {
            if warned.borrow_mut().insert(w.clone()) {
                eprintln!(
                    "warning: {}",
                    terminal_safe(&format!("{id}: {w} (said once per run)"))
                );
            }
        }
        if !report.not_sampled.is_empty() {
            let mut total = fixed_total.borrow_mut();
            if total.0 == 0 {
                println!(
                    "note: the model has seen only {}, so agents of other types are not \
                     sampled: they {} (said once per run; {id}: {})",
                    trained.meta.seen_types(),
                    if cfg.task == Task::Conditional {
                        "follow their log"
                    } else {
                        "keep their current velocity"
                    },
                    report.not_sampled.join(", ")
                );
            }
            total.0 += report.not_sampled.len();
            total.1 += 1;
        }
        for o in &report.samples {
            super::print_outcome(&format!("{id} sample {}", o.sample), o);
        }
        // From here a failure (a full disk, a directory where the picture goes) leaves some
        // of the scene's outputs: the end of the run must not say that nothing was written.
        started_writing.set(true);
        done.write(&args.output, &id, Some(&run_value))?;
        super::render::write_picture(
            &samples[0].scene,
            &args.output.join(format!("{}_0.gif", output_stem(&id)?)),
            &RenderOptions {
                width: 800,
                roles: report.roles(),
                ..Default::default()
            },
        )?;
        println!("{id}: {} samples in {:.2} s", samples.len(), report.seconds);
        Ok(true)
    };
    let (mut failed, mut done, mut resumed, mut seen) = (0, 0, 0, 0);
    // Output names come from scenario ids: a second scene with the same name would overwrite
    // the first's rollouts.
    let mut names = OutputNames::default();
    for src in sources {
        for item in read_each(&src, &LoadOptions::default()) {
            let raw = match item {
                Ok(raw) => raw,
                Err(e) => {
                    super::print_error(&e.to_string());
                    failed += 1;
                    continue;
                }
            };
            seen += 1;
            if args
                .shard
                .is_some_and(|sh| !sh.contains(&raw.meta.scenario_id))
            {
                continue;
            }
            // An id that cannot name a file stops the run; a second scene of one name is
            // reported and left out.
            drivescript::io::output_stem_in(&raw.meta.scenario_id, &src)?;
            let stem = match names.claim(&raw.meta.scenario_id, &src) {
                Ok(stem) => stem,
                Err(e) => {
                    super::print_error(&e.to_string());
                    failed += 1;
                    continue;
                }
            };
            if args.resume {
                match drivescript::sample::attempt::outputs_complete(
                    &args.output,
                    &stem,
                    &raw,
                    cfg.samples,
                ) {
                    Ok(true) => {
                        resumed += 1;
                        continue;
                    }
                    Ok(false) => {}
                    Err(e) => {
                        super::print_error(&e.to_string());
                        failed += 1;
                        continue;
                    }
                }
            }
            // A bug that panics on one scene costs that scene, not the run.
            let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run_one(&raw)))
                .unwrap_or_else(|payload| {
                    Err(anyhow::anyhow!(drivescript::io::internal_error(
                        &*payload, "scene"
                    )))
                });
            match outcome {
                Ok(true) => done += 1,
                Ok(false) => skipped += 1,
                Err(e) => {
                    super::print_error(&format!(
                        "{}: {}",
                        raw.meta.scenario_id,
                        super::describe(&e)
                    ));
                    failed += 1;
                }
            }
        }
    }
    if skipped > 0 {
        println!("{skipped} scenes skipped (no agents suited to the behaviour)");
    }
    let plural = |n: usize, what: &str| format!("{n} {what}{}", if n == 1 { "" } else { "s" });
    let (shorter, longer) = horizons.into_inner();
    if shorter + longer > 0 {
        println!(
            "horizon: {future} steps sampled; {shorter} of the scenes recorded fewer, {longer} more"
        );
    }
    let (agents, scenes) = fixed_total.into_inner();
    if agents > 0 {
        println!(
            "{} in {} were not sampled (types the model never saw)",
            plural(agents, "agent"),
            plural(scenes, "scene")
        );
    }
    if resumed > 0 {
        println!(
            "{} already complete in {} (--resume): not simulated again",
            plural(resumed, "scene"),
            super::shown(&args.output)
        );
    }
    if done > 0 {
        println!(
            "wrote {} scene{} to {}",
            done,
            if done == 1 { "" } else { "s" },
            super::shown(&args.output)
        );
    } else if resumed == 0 {
        // A run that wrote nothing leaves nothing, not a record that would refuse the next
        // run's settings; shards share the record, so theirs stays, as does the record of
        // outputs left (`--resume` checks its settings against them).
        if fresh && args.shard.is_none() && !started_writing.get() {
            let _ = std::fs::remove_file(args.output.join(RUN_FILE));
            if !existed {
                let _ = std::fs::remove_dir(&args.output);
            }
        }
        if started_writing.get() {
            println!(
                "no scene simulated to the end: a scene that failed while its outputs were \
                 written left some of them in {} (`--resume` simulates it again)",
                super::shown(&args.output)
            );
        } else {
            println!("no scene simulated: nothing written");
        }
    }
    if failed > 0 {
        eprintln!("{failed} scenes failed");
        return Ok(ExitCode::FAILURE);
    }
    if done + resumed == 0 && seen > 0 && args.shard.is_some() {
        // Every scene fell in other shards: this shard's work is done.
        println!(
            "shard {} holds none of the {} scenes",
            args.shard.expect("checked"),
            seen
        );
        return Ok(ExitCode::SUCCESS);
    }
    if done + resumed == 0 {
        eprintln!(
            "error: no scene was simulated (none found, or none with agents suited to --auto)"
        );
        return Ok(ExitCode::FAILURE);
    }
    Ok(ExitCode::SUCCESS)
}
