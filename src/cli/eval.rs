//! `drivescript eval`: the paper's tables for baselines and rollouts.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use drivescript::cost::Params;
use drivescript::eval::kinematic::Violation;
use drivescript::eval::merge::{record_json, HorizonFrom, Horizons, RunRecord};
use drivescript::eval::metrics::{self, JsdBins};
use drivescript::eval::tally::{group_order, Group, Task as EvalTask};
use drivescript::eval::{asked, check, Baseline, Behavior, Tally};
use drivescript::io::{
    check_output_not_input, check_replaces_own_json, discover, read_each, rollout::Rollout,
    write_atomic, LoadOptions, OutputNames,
};
use drivescript::scene::{AgentType, KinematicLimits, Scene};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Task {
    /// History + endpoint given: ADE/FDE, realism JSD, collision and off-road rates.
    Conditional,
    /// Only the current state given: scene collision rate and MMD of placements.
    Unconditional,
    /// Success rate of a behaviour's checker.
    Behaviour,
}

impl From<Task> for EvalTask {
    fn from(t: Task) -> Self {
        match t {
            Task::Conditional => EvalTask::Conditional,
            Task::Unconditional => EvalTask::Unconditional,
            Task::Behaviour => EvalTask::Behaviour,
        }
    }
}

impl From<EvalTask> for Task {
    fn from(t: EvalTask) -> Self {
        match t {
            EvalTask::Conditional => Task::Conditional,
            EvalTask::Unconditional => Task::Unconditional,
            EvalTask::Behaviour => Task::Behaviour,
        }
    }
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum BaselineArg {
    /// Log replay (the recorded future).
    Log,
    /// Constant velocity.
    Cv,
    /// Constant speed along the current lane.
    Lane,
}

#[derive(clap::Args)]
pub struct Args {
    /// Scene files or directories.
    #[arg(required_unless_present = "merge")]
    scenes: Vec<PathBuf>,
    /// What to evaluate.
    #[arg(long, value_enum, required_unless_present = "merge")]
    task: Option<Task>,
    /// Baselines to score (repeatable; default: all three unless --rollouts is given).
    #[arg(long = "baseline", value_enum)]
    baselines: Vec<BaselineArg>,
    /// Directory of rollout JSON files to score: SCENARIO_ID.json or SCENARIO_ID_K.json.
    #[arg(long)]
    rollouts: Option<PathBuf>,
    /// Samples per scene expected in --rollouts: minADE/minFDE over them (conditional), and
    /// every one judged, each against its own unguided twin (behaviour: rates per sample).
    #[arg(long, default_value_t = 1)]
    samples: usize,
    /// Behaviour for --task behaviour (a script name, e.g. cut_in).
    #[arg(long)]
    behaviour: Option<String>,
    /// Checker parameters for --task behaviour, name=value.
    #[arg(long = "param", num_args = 1.., value_parser = super::param_value)]
    params: Vec<String>,
    /// For --task behaviour: choose the agents of every scene automatically
    /// (`eval::suggest::suggest`); --param values override the suggestion.
    #[arg(long)]
    auto: bool,
    /// For --task behaviour with --rollouts: the same scenes sampled unguided (same seed and
    /// samples, e.g. `simulate` without a script). A sample then passes only when the vehicles
    /// the behaviour does not name collide and drive implausibly no more than in its unguided
    /// twin, within the tolerance in docs/evaluation.md.
    #[arg(long, value_name = "DIR", requires = "rollouts")]
    unguided: Option<PathBuf>,
    /// Score exactly this many future steps (a model's horizon): scenes are cut, or extended
    /// with unobserved steps, to current step + 1 + HORIZON before anything is simulated or
    /// scored, so that baselines simulate as far as a model does. Default: with --rollouts,
    /// each scene's rollouts' own length (the longest of its samples), else each scene's
    /// recorded future; the table says which was used.
    #[arg(long)]
    horizon: Option<usize>,
    /// Conditional task: score every simulated step, not only the steps where the agent is
    /// in the recording (by default an agent is scored while its recorded track lasts).
    #[arg(long)]
    all_steps: bool,
    /// Write the table and per-scene results as JSON (with what `--merge` needs to combine
    /// shards).
    #[arg(long)]
    json: Option<PathBuf>,
    /// Only the scenes of shard I of N (0 <= I < N, a stable partition by scenario id, the
    /// same as `simulate --shard`); write --json, then combine the shards with --merge.
    #[arg(long, value_name = "I/N")]
    shard: Option<drivescript::io::shard::Shard>,
    /// Combine the --json files of the shards of one evaluation (same task, methods,
    /// behaviour, parameters and horizon; every shard once) into the table a single run prints.
    // Every flag of a single run is refused beside it: the shards' files say how they were
    // made (--samples 3 was ignored without a word).
    #[arg(long, value_name = "JSON", num_args = 1.., conflicts_with_all = ["scenes", "task", "shard", "rollouts", "samples", "baselines", "behaviour", "params", "auto", "unguided", "horizon", "all_steps"])]
    merge: Vec<PathBuf>,
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// A number for --json: `null` where there is none, else as the library writes numbers
/// (`"NaN"` / `"inf"` rather than the `null` serde_json would make of them).
fn num(v: Option<f64>) -> serde_json::Value {
    v.map_or(serde_json::Value::Null, drivescript::io::json::number)
}

fn fmt(v: Option<f64>, prec: usize) -> String {
    v.map_or("-".into(), |x| format!("{x:.prec$}"))
}

/// A scene the run that wrote the rollouts left out on purpose (`simulate --auto` found no
/// agents for its behaviour): counted as skipped, as the run counted it.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
struct LeftOut(String);

/// What a sample's scripts allowed, as the checkers take it ([`asked::kinds`]).
type Allowed = Vec<(i64, Violation)>;

/// The rollouts of `scene` in `dir` (`ID.json` for one sample, `ID_K.json` for `k`), each
/// with the motion its scripts allowed ([`Rollout::allowed`]).
fn rollouts_for(dir: &Path, scene: &Scene, k: usize) -> Result<Vec<(Scene, Allowed)>> {
    let id = &scene.meta.scenario_id;
    let marker = drivescript::sample::attempt::skipped_file(dir, id);
    if marker.is_file() {
        return Err(LeftOut(format!("{}: the run skipped this scene", marker.display())).into());
    }
    let read = |p: &Path| -> Result<(Scene, Allowed)> {
        let r = Rollout::read(p)?;
        Ok((r.apply_to(scene, p)?, asked::kinds(&r.allowed)))
    };
    // The first numbered sample from `from` on that is there. Every number a run can make is
    // looked at, not only the next: with ID_1.json gone, ID_2.json was left out unsaid.
    let stray = |from: usize| {
        (from..drivescript::sample::MAX_SAMPLES)
            .map(|j| dir.join(format!("{id}_{j}.json")))
            .find(|p| p.exists())
    };
    let single = dir.join(format!("{id}.json"));
    if k == 1 && single.exists() {
        // Beside numbered samples, which of them is meant cannot be told: the numbered ones
        // were left out without a word (4 samples of a run, and a recording converted beside
        // them, scored as the recording).
        if let Some(first) = stray(0) {
            bail!(
                "{}: the rollouts hold both {id}.json and numbered samples ({id}_K.json): \
                 move one away, or give --samples with the number the run made",
                first.display()
            );
        }
        return Ok(vec![read(&single)?]);
    }
    let mut out = Vec::new();
    for i in 0..k {
        let p = dir.join(format!("{id}_{i}.json"));
        if !p.exists() {
            bail!(
                "{}: missing rollout for scene {id} (sample {i} of {k})",
                p.display()
            );
        }
        out.push(read(&p)?);
    }
    // Rollouts of 4 samples scored with the default --samples 1 gave minADE of one sample,
    // from a quarter of the run, and said nothing.
    if let Some(next) = stray(k) {
        bail!(
            "{}: the rollouts hold more samples of scene {id} than --samples {k}: give \
             --samples with the number the run made (`simulate --samples`)",
            next.display()
        );
    }
    Ok(out)
}

pub fn run(args: Args) -> Result<ExitCode> {
    if let Some(out) = &args.json {
        // Refused before any work: an evaluation can take hours.
        let inputs: Vec<&Path> = args
            .scenes
            .iter()
            .chain(&args.merge)
            .chain(&args.rollouts)
            .chain(&args.unguided)
            .map(|p| p.as_path())
            .collect();
        check_output_not_input(out, &inputs, "--json")?;
        check_replaces_own_json(out, "merge", "an `eval --json` file", "--json")?;
    }
    if !args.merge.is_empty() {
        return merge(&args.merge, args.json.as_deref());
    }
    let task = args.task.expect("clap requires --task without --merge");
    if !(1..=drivescript::sample::MAX_SAMPLES).contains(&args.samples) {
        anyhow::bail!(
            "--samples {}: must be 1 to {}",
            args.samples,
            drivescript::sample::MAX_SAMPLES
        );
    }
    // Every method is simulated over the horizon, so 10^8 steps aborted on allocation; a
    // horizon of 0 scores nothing.
    let max = drivescript::eval::merge::MAX_HORIZON_FLAG;
    if let Some(h) = args.horizon.filter(|h| !(1..=max).contains(h)) {
        anyhow::bail!("--horizon {h}: must be 1 to {max} steps");
    }
    // A flag of another task would be dropped without a word, and the table taken for what
    // the user asked.
    if task != Task::Behaviour {
        for (given, flag) in [
            (args.behaviour.is_some(), "--behaviour"),
            (!args.params.is_empty(), "--param"),
            (args.auto, "--auto"),
        ] {
            if given {
                bail!("{flag}: only --task behaviour takes it (a behaviour's checker and agents)");
            }
        }
    }
    if args.all_steps && task != Task::Conditional {
        bail!("--all-steps: only --task conditional scores steps against the recording");
    }
    if args.samples != 1 && args.rollouts.is_none() {
        bail!(
            "--samples {}: the number of samples per scene in --rollouts; baselines have one",
            args.samples
        );
    }
    // A baseline named twice was scored twice: two rows of one method, in the table and in
    // --json, as if they were two measurements.
    if let Some(b) = (1..args.baselines.len())
        .map(|i| args.baselines[i])
        .enumerate()
        .find(|(i, b)| args.baselines[..=*i].contains(b))
        .map(|(_, b)| b)
    {
        let name = clap::ValueEnum::to_possible_value(&b)
            .map(|v| v.get_name().to_string())
            .unwrap_or_default();
        bail!("--baseline {name}: given twice (each baseline is scored once)");
    }
    let mut methods: Vec<(String, Option<Baseline>)> = Vec::new();
    let baselines = if args.baselines.is_empty() && args.rollouts.is_none() {
        vec![BaselineArg::Log, BaselineArg::Cv, BaselineArg::Lane]
    } else {
        args.baselines.clone()
    };
    for b in baselines {
        let b = match b {
            BaselineArg::Log => Baseline::Log,
            BaselineArg::Cv => Baseline::ConstantVelocity,
            BaselineArg::Lane => Baseline::Lane,
        };
        methods.push((b.name().to_string(), Some(b)));
    }
    if let Some(d) = &args.rollouts {
        if !d.is_dir() {
            bail!("{}: --rollouts must be a directory", d.display());
        }
        // On one line: the name starts a row of the table (and of --json, which --merge
        // refuses with a line break or an escape sequence in it).
        methods.push((
            format!(
                "rollouts in {}",
                drivescript::io::name::one_line(&d.display().to_string())
            ),
            None,
        ));
        // Scoring the first of four samples, say, was a table of one sample per scene whose
        // only sign was the empty minADE column.
        if let Some(k) = drivescript::sample::provenance::recorded_samples(d) {
            if k != args.samples as u64 {
                bail!(
                    "--samples {}: the run in {} sampled {k} per scene (its run.json): pass \
                     --samples {k}",
                    args.samples,
                    d.display()
                );
            }
        }
    }
    if args.unguided.is_some() && task != Task::Behaviour {
        bail!("--unguided: only --task behaviour judges a sample against its unguided twin");
    }
    if let Some(d) = args.unguided.as_ref().filter(|d| !d.is_dir()) {
        bail!("{}: --unguided must be a directory", d.display());
    }
    let behaviour = match (task, &args.behaviour) {
        (Task::Behaviour, None) => bail!("--task behaviour needs --behaviour NAME"),
        (Task::Behaviour, Some(n)) => {
            let b = Behavior::parse(n).context("--behaviour")?;
            // Every parameter the loop's checkers take, words (`yielder_turn=left`) too: the
            // behaviour's own check says what is wrong with a value, on the first scene. A
            // name it does not read is refused here, before any scene is read.
            let params = Params::parse(&args.params).context("--param")?;
            b.check_param_names(&params).context("--param")?;
            Some((b, params))
        }
        _ => None,
    };
    let mut sources = Vec::new();
    for s in &args.scenes {
        sources.extend(discover(s)?);
    }
    let mut accs: Vec<Tally> = methods.iter().map(|_| Tally::default()).collect();
    let bar = ProgressBar::new(sources.len() as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{bar:40} {pos}/{len} sources  {elapsed_precise} elapsed, {eta} left  {msg}",
        )
        .expect("valid template"),
    );
    let mut failures = 0;
    let mut skipped = 0;
    // Scenes the rollouts' run left out (per method that reads rollouts).
    let mut run_skipped = 0;
    let mut names = OutputNames::default();
    let mut horizons = Horizons::default();
    // Every scene read, this shard's or not: the shards of one run agree on them.
    let mut read_ids: Vec<String> = Vec::new();
    let mut own_scenes = 0usize;
    for src in &sources {
        bar.set_message(
            src.file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
        );
        // A bad record is reported and the good ones of its file are scored; two scenes with
        // one name would be scored against the same rollouts, so the second is refused.
        let mut scenes = Vec::new();
        for item in read_each(src, &LoadOptions::default()) {
            let claimed = item.and_then(|s| {
                read_ids.push(s.meta.scenario_id.clone());
                if args
                    .shard
                    .is_some_and(|sh| !sh.contains(&s.meta.scenario_id))
                {
                    return Ok(None);
                }
                names.claim(&s.meta.scenario_id, src).map(|_| Some(s))
            });
            match claimed {
                Ok(Some(s)) => {
                    own_scenes += 1;
                    scenes.push(s)
                }
                Ok(None) => {}
                Err(e) => {
                    bar.suspend(|| super::print_error(&e.to_string()));
                    failures += 1;
                }
            }
        }
        for scene in &scenes {
            // The rollouts are read first: without --horizon, their own length is the horizon
            // every method is scored over (a rear-end at 3.9 s of a 40-step sample counted as
            // a miss where the recording held 3 s). Read against the recording, whose history
            // is all a rollout is checked against.
            let mut rolled = args
                .rollouts
                .as_ref()
                .map(|dir| rollouts_for(dir, scene, args.samples));
            let own = match &rolled {
                Some(Ok(samples)) => samples.iter().map(|s| s.0.num_future_steps()).max(),
                _ => None,
            };
            let (horizon, from) = match (args.horizon, own) {
                (Some(h), _) => (Some(h), HorizonFrom::Flag),
                (None, Some(h)) => (Some(h), HorizonFrom::Rollouts),
                (None, None) => (None, HorizonFrom::Recording),
            };
            let cut;
            let scene = match horizon {
                Some(h) => {
                    cut = scene.with_horizon(h);
                    &cut
                }
                None => scene,
            };
            let scene_params = match (&behaviour, args.auto) {
                (Some((b, given)), true) => {
                    match drivescript::eval::suggest::suggest(
                        *b,
                        scene,
                        horizon.unwrap_or(scene.num_future_steps()),
                    ) {
                        Some(p) => Some((*b, p.overridden_by(given))),
                        None => {
                            skipped += 1;
                            continue;
                        }
                    }
                }
                (Some((b, given)), false) => Some((*b, given.clone())),
                (None, _) => None,
            };
            // Agents are chosen on the recording (as `simulate --auto` chooses them); every
            // method then runs the whole horizon, past the end of a shorter recording.
            let extended;
            let scene = match horizon {
                Some(h) => {
                    extended = scene.over_horizon(h);
                    &extended
                }
                None => scene,
            };
            // Parameters that cannot be checked on this scene (an agent it lacks, say) are
            // said once here, not hidden in the JSON of every method's row.
            if let Some((b, p)) = &scene_params {
                if let Err(e) = check(*b, scene, p) {
                    bar.suspend(|| super::print_error(&format!("{}: {e}", scene.meta.scenario_id)));
                    failures += 1;
                    continue;
                }
            }
            // Counted once a method has scored the scene: a scene whose rollouts failed was
            // counted in the horizon line ("(2 scenes)") under a table of 1.
            let mut scored = false;
            // Every method, and the log it is compared with, loses its cars where they leave
            // the map.
            let reference = scene.retire_exited();
            for ((_, m), acc) in methods.iter().zip(accs.iter_mut()) {
                // Baselines follow no script: they were allowed nothing.
                let (sims, allowed): (Vec<Scene>, Vec<Allowed>) = match m {
                    Some(b) => (vec![b.simulate(scene)], Vec::new()),
                    None => match rolled.take().expect("a rollouts method reads them once") {
                        Ok(s) => s.into_iter().unzip(),
                        Err(e) if e.is::<LeftOut>() => {
                            run_skipped += 1;
                            continue;
                        }
                        Err(e) => {
                            bar.suspend(|| super::print_error(&super::describe(&e)));
                            failures += 1;
                            continue;
                        }
                    },
                };
                // Every method is scored over the scene's steps: a rollout may run longer
                // (a model's horizon, without --horizon).
                let fit = |s: &Scene| {
                    let s = s.with_horizon(scene.num_future_steps()).retire_exited();
                    if task == Task::Conditional && !args.all_steps {
                        s.with_lifetimes_of(&reference)
                    } else {
                        s
                    }
                };
                let sims: Vec<Scene> = sims.iter().map(fit).collect();
                // The rollouts' unguided twins (baselines have none: nothing guided them).
                let twins = match (m, &args.unguided) {
                    // A twin is judged with its guided sample's allowances (the collateral
                    // exempts them in both), not with any of its own.
                    (None, Some(dir)) => match rollouts_for(dir, scene, args.samples) {
                        Ok(u) => Some(u.iter().map(|(s, _)| fit(s)).collect::<Vec<_>>()),
                        Err(e) => {
                            bar.suspend(|| super::print_error(&super::describe(&e)));
                            failures += 1;
                            continue;
                        }
                    },
                    _ => None,
                };
                acc.score(
                    task.into(),
                    &reference,
                    &sims,
                    scene_params.as_ref().map(|(b, p)| (*b, p)),
                    twins.as_deref(),
                    &allowed,
                );
                scored = true;
            }
            if scored {
                horizons.count(scene.num_future_steps(), from);
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let settings = json!({
        "task": EvalTask::from(task).name(),
        "methods": methods.iter().map(|m| m.0.clone()).collect::<Vec<_>>(),
        "behaviour": behaviour.as_ref().map(|b| b.0.name()),
        "params": args.params,
        "auto": args.auto,
        "horizon": args.horizon,
        "samples": args.samples,
        "all_steps": args.all_steps,
        "unguided": args.unguided,
        "shards": args.shard.map_or(1, |s| s.count),
        "scenes": drivescript::eval::merge::corpus(&read_ids),
    });
    let shard = args.shard.map(|s| s.index);
    // A shard of an array job with more shards than scenes holds none: it says so and exits 0,
    // as `simulate --shard` does (it said "no scene ... was read from the given paths", exit 1).
    let empty_shard = args
        .shard
        .filter(|_| own_scenes == 0 && failures == 0 && !read_ids.is_empty())
        .map(|sh| (sh, read_ids.len()));
    report(
        task,
        &methods.iter().map(|m| m.0.clone()).collect::<Vec<_>>(),
        &accs,
        behaviour.as_ref().map(|b| b.0),
        args.json.as_deref(),
        &RunRecord {
            settings,
            shards: shard.into_iter().collect(),
            skipped,
            failures,
            run_skipped,
            horizons,
        },
        empty_shard,
    )
}

/// The table's header lines for `task`, with a group column when `grouped`.
fn header(task: Task, grouped: bool) -> String {
    let cols: &[&str] = match task {
        Task::Conditional => &[
            "scenes",
            "ADE (m)",
            "FDE (m)",
            "minADE",
            "minFDE",
            "JSD speed",
            "JSD ang. speed",
            "JSD accel",
            "JSD nearest",
            "JSD mean",
            "collision",
            "off-road",
            "implausible",
            "ms/scene",
        ],
        Task::Unconditional => &[
            "scenes",
            "scene collision rate",
            "MMD² nearest object",
            "MMD² road edge",
            "collided",
            "implausible",
            "ms/scene",
        ],
        Task::Behaviour => &[
            "behaviour",
            "samples checked",
            "achieved plausibly",
            "achieved",
            "collided",
            "implausible",
            "ms/scene",
        ],
    };
    let mut all = vec!["method"];
    if grouped {
        all.push("group");
    }
    all.extend(cols);
    format!("| {} |\n{}|", all.join(" | "), "|---".repeat(all.len()))
}

/// One method's row of the table (`group` names the group of a grouped table, and says
/// whether it holds whole scenes, as map kinds do, or one type's agents) and its JSON.
fn table_row(
    task: Task,
    name: &str,
    group: Option<(&str, bool)>,
    acc: &Tally,
    behaviour: Option<Behavior>,
    bins: &JsdBins,
) -> (String, serde_json::Value) {
    // No scene, no time per scene: `-` in the table and null in JSON, not a NaN.
    let ms = (acc.scenes > 0).then(|| 1000.0 * acc.seconds / acc.scenes as f64);
    let implausible = metrics::rate(&acc.implausible);
    let collided = metrics::rate(&acc.collided);
    let by_kind: serde_json::Map<String, serde_json::Value> = Violation::ALL
        .iter()
        .zip(&acc.by_kind)
        .map(|(v, f)| (v.name().to_string(), json!(metrics::rate(f))))
        .collect();
    // Time is spent on a scene, not on a group of its agents.
    let ms = ms.filter(|_| group.is_none());
    let ms_text = fmt(ms, 1);
    let lead = match group {
        Some((g, _)) => format!("| {name} | {g}"),
        None => format!("| {name}"),
    };
    let whole_scenes = group.is_none_or(|(_, whole)| whole);
    // Figures of whole scenes are not split by agent type: a dash in those rows.
    let (line, mut row) = match task {
        Task::Conditional => {
            let r = metrics::realism(&acc.sim_kin, &acc.log_kin, bins);
            (
                format!(
                    "{lead} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {ms_text} |",
                    acc.scenes,
                    fmt(mean(&acc.ade), 2),
                    fmt(mean(&acc.fde), 2),
                    fmt(mean(&acc.min_ade), 2),
                    fmt(mean(&acc.min_fde), 2),
                    fmt(r.map(|r| r.speed), 3),
                    fmt(r.map(|r| r.angular_speed), 3),
                    fmt(r.map(|r| r.accel), 3),
                    fmt(r.and_then(|r| r.nearest_vehicle), 3),
                    fmt(r.map(|r| r.mean), 3),
                    fmt(mean(&acc.collision), 3),
                    fmt(mean(&acc.offroad), 3),
                    fmt(implausible, 3),
                ),
                json!({"method": name, "scenes": acc.scenes, "ade": num(mean(&acc.ade)), "fde": num(mean(&acc.fde)),
                    "min_ade": num(mean(&acc.min_ade)), "min_fde": num(mean(&acc.min_fde)),
                    "jsd": r.map(|r| json!({"speed": num(Some(r.speed)), "angular_speed": num(Some(r.angular_speed)),
                        "accel": num(Some(r.accel)), "nearest_vehicle": num(r.nearest_vehicle), "mean": num(Some(r.mean))})),
                    "collision_rate": num(mean(&acc.collision)), "offroad_rate": num(mean(&acc.offroad)), "ms_per_scene": num(ms)}),
            )
        }
        Task::Unconditional => (
            format!(
                "{lead} | {} | {} | {} | {} | {} | {} | {ms_text} |",
                acc.scenes,
                fmt(mean(&acc.scr), 3),
                fmt(mean(&acc.mmd_near), 3),
                fmt(mean(&acc.mmd_edge), 3),
                fmt(collided, 3),
                fmt(implausible, 3)
            ),
            json!({"method": name, "scenes": acc.scenes, "scene_collision_rate": num(mean(&acc.scr)),
                "mmd2_nearest_object": num(mean(&acc.mmd_near)), "mmd2_road_edge": num(mean(&acc.mmd_edge)), "ms_per_scene": num(ms)}),
        ),
        Task::Behaviour => {
            let b = behaviour.expect("behaviour task");
            let of = |n: usize| (acc.checked > 0).then(|| n as f64 / acc.checked as f64);
            let (rate, achieved) = (of(acc.passed), of(acc.achieved));
            // A verdict is a scene's: a row of one agent type has none, not zero.
            let checked = whole_scenes.then_some(acc.checked);
            (
                format!(
                    "{lead} | {} | {} | {} | {} | {} | {} | {ms_text} |",
                    b.name(),
                    checked.map_or("-".to_string(), |n| n.to_string()),
                    fmt(rate, 2),
                    fmt(achieved, 2),
                    fmt(collided, 3),
                    fmt(implausible, 3)
                ),
                json!({"method": name, "behaviour": b.name(), "definition": b.definition(), "checked": checked,
                    "success_rate": rate, "achieved_rate": achieved, "ms_per_scene": num(ms)}),
            )
        }
    };
    row["implausible_rate"] = json!(implausible);
    if task != Task::Conditional {
        row["collided_rate"] = json!(collided);
    }
    row["implausible_by_kind"] = json!(by_kind);
    (line, row)
}

/// The legend of the implausible column; `others` are the road users besides vehicles that
/// the table scored, each judged by its own kind's limits.
fn implausible_legend(others: &[AgentType]) -> String {
    let car = "reversing, sprinting, braking or accelerating beyond 7 m/s², swerving, crabbing or \
               turning tighter than Waymax's curvature bound";
    let asked = "not counted: what a behaviour asks of the agents it names (the car reverse asks \
                 to back up)";
    if others.is_empty() {
        return format!(
            "implausible: fraction of vehicles (pooled over scenes and samples) whose future a \
             car cannot drive: {car} (docs/evaluation.md); {asked}"
        );
    }
    let limits: Vec<String> = others
        .iter()
        .filter_map(|t| {
            let l = KinematicLimits::default().for_type(*t)?;
            let mut s = format!(
                "{}s above {} m/s or beyond {} m/s²",
                t.name(),
                drivescript::geom::num(l.max_speed),
                drivescript::geom::num(l.max_accel)
            );
            if l.max_curvature.is_finite() {
                s += &format!(
                    ", turning tighter than {} 1/m",
                    drivescript::geom::num(l.max_curvature)
                );
            }
            Some(s)
        })
        .collect();
    format!(
        "implausible: fraction of road users (pooled over scenes and samples) whose future their \
         kind cannot move along, each by its own limits: vehicles {car}; {} (docs/evaluation.md); \
         {asked}",
        limits.join("; ")
    )
}

/// Prints the table over `accs` (one per method), writes --json, and says how the run went.
fn report(
    task: Task,
    methods: &[String],
    accs: &[Tally],
    behaviour: Option<Behavior>,
    json_out: Option<&Path>,
    merge: &RunRecord,
    empty_shard: Option<(drivescript::io::shard::Shard, usize)>,
) -> Result<ExitCode> {
    let (skipped, failures, run_skipped) = (merge.skipped, merge.failures, merge.run_skipped);
    let bins = JsdBins::default();
    let mut table = Vec::new();
    println!("{}", header(task, false));
    for (name, acc) in methods.iter().zip(accs) {
        let (line, row) = table_row(task, name, None, acc, behaviour, &bins);
        println!("{line}");
        table.push(json!({"summary": row, "scenes": acc.per_scene}));
    }
    // The same rows by map kind and agent type, where more than one kind or type was scored
    // (a single group repeats the table above).
    let present: Vec<(Group, String)> = group_order()
        .into_iter()
        .map(|g| (g, g.label()))
        .filter(|(_, l)| {
            accs.iter()
                .any(|a| a.groups.get(l).is_some_and(|t| t.scenes > 0))
        })
        .collect();
    // Cyclists and pedestrians scored: the implausible legend names their limits too.
    // Each type once, though it is scored both as a whole and within a map kind.
    let mut others: Vec<AgentType> = Vec::new();
    for t in present.iter().filter_map(|(g, _)| g.agent) {
        if t != AgentType::Vehicle && !others.contains(&t) {
            others.push(t);
        }
    }
    let kinds = present.iter().filter(|(g, _)| g.agent.is_none()).count();
    let types = present.iter().filter(|(g, _)| g.map.is_none()).count();
    // A group that is all of its parent repeats its row: map kinds only where there are two,
    // types only where there are two, and types within a kind only where both split.
    let present: Vec<(Group, String)> = present
        .into_iter()
        .filter(|(g, _)| match (g.map, g.agent) {
            (Some(_), None) => kinds > 1,
            (None, Some(_)) => types > 1,
            _ => kinds > 1 && types > 1,
        })
        .collect();
    let mut groups_json = Vec::new();
    if kinds > 1 || types > 1 {
        println!("\nby map kind (urban: two or more lanes turn, at junctions) and agent type:\n");
        println!("{}", header(task, true));
        for (group, g) in &present {
            for (name, acc) in methods.iter().zip(accs) {
                if let Some(t) = acc.groups.get(g).filter(|t| t.scenes > 0) {
                    let whole = group.agent.is_none();
                    let (line, mut row) =
                        table_row(task, name, Some((g, whole)), t, behaviour, &bins);
                    println!("{line}");
                    row["group"] = json!(g);
                    groups_json.push(row);
                }
            }
        }
    }
    if task != Task::Conditional {
        println!(
            "\ncollided: fraction of vehicles (pooled over scenes) whose box overlaps another agent's at some future step{}",
            if task == Task::Behaviour { " (an accident's own pair excepted)" } else { "" }
        );
    }
    println!("\n{}", implausible_legend(&others));
    if let Some(line) = merge.horizons.line() {
        println!("\n{line}");
    }
    if task == Task::Conditional {
        println!("\nJSD: Jensen-Shannon distance (natural log) of histograms pooled over agents, steps and scenes; bins {}", serde_json::to_string(&bins)?);
    }
    if let Some(out) = json_out {
        write_atomic(
            out,
            serde_json::to_string_pretty(&json!({
                "task": EvalTask::from(task).name(),
                "methods": table,
                "groups": groups_json,
                "merge": record_json(accs, merge),
            }))?
            .as_bytes(),
        )?;
        super::print_wrote(out);
    }
    if skipped > 0 {
        println!("{skipped} scenes skipped: no agents for which the behaviour is meaningful");
    }
    if run_skipped > 0 {
        println!(
            "{run_skipped} scenes skipped: the run that wrote --rollouts left them out (their _skipped.json says why)"
        );
    }
    if failures > 0 {
        eprintln!(
            "{failures} failed (the errors above): a file, a scene's rollouts or the behaviour's agents"
        );
        return Ok(ExitCode::FAILURE);
    }
    // A conditional table needs an agent with a recorded future to compare with: scenes read
    // but holding none printed a row of dashes and passed.
    let scored = accs.iter().any(|a| a.scored(task.into()));
    if let (false, Some((sh, n))) = (scored, empty_shard) {
        println!("shard {sh} holds none of the {n} scenes");
        return Ok(ExitCode::SUCCESS);
    }
    if !scored {
        eprintln!(
            "error: nothing was scored: no scene with agents and a {}{} was read from the given paths",
            if task == Task::Conditional {
                "recorded future to compare with"
            } else {
                "future"
            },
            if task == Task::Behaviour {
                " and agents for the behaviour"
            } else {
                ""
            }
        );
        return Ok(ExitCode::FAILURE);
    }
    Ok(ExitCode::SUCCESS)
}

/// `eval --merge`: the shards' --json files combined into the table of a single run.
fn merge(files: &[PathBuf], json_out: Option<&Path>) -> Result<ExitCode> {
    let m = drivescript::eval::merge::merge(files)?;
    println!(
        "merged {} of {} shard{} from {} file{}",
        m.run.shards.len().max(1),
        m.shards,
        if m.shards == 1 { "" } else { "s" },
        files.len(),
        if files.len() == 1 { "" } else { "s" }
    );
    report(
        m.task.into(),
        &m.methods,
        &m.accumulators,
        m.behaviour,
        json_out,
        &m.run,
        None,
    )
}
