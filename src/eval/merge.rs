//! `eval --merge`: the `--json` files of an evaluation's shards read back, every figure in
//! them checked, and combined into the accumulators a single run would have had.
//!
//! A shard file is a user's file like any other: a count edited to wrap when summed, a
//! negative distance, a rate over 1 or more samples passed than checked would otherwise come
//! out as a table that looks like a result. Each is an error naming the file and the field.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use super::behaviors::Behavior;
use super::tally::{Tally, Task};
use crate::io::shard::MAX_SHARDS;

/// Why shard files cannot be merged.
#[derive(Debug, thiserror::Error)]
pub enum MergeError {
    /// A file cannot be read (missing, not a regular file, too large).
    #[error(transparent)]
    Io(#[from] crate::io::IoError),
    /// A file holds what no `eval --json` writes.
    #[error("{}: {message}", path.display())]
    Shard {
        /// The file.
        path: PathBuf,
        /// What is wrong, naming the field.
        message: String,
    },
    /// The files are not the shards of one evaluation, each once.
    #[error("{0}")]
    Shards(String),
}

fn bad(path: &Path, message: impl Into<String>) -> MergeError {
    MergeError::Shard {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// Where a scene's horizon (the future steps every method is scored over) came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HorizonFrom {
    /// `--horizon`.
    Flag,
    /// The longest of the scene's rollouts.
    Rollouts,
    /// The recorded future (no flag, no rollouts read).
    Recording,
}

/// How many scenes were scored over each horizon, for the line that says which was used.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Horizons(pub Vec<HorizonCount>);

/// Scenes scored over one horizon.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HorizonCount {
    /// Future steps scored after the current step.
    pub steps: usize,
    /// Where that number came from.
    pub from: HorizonFrom,
    /// How many scenes.
    pub scenes: usize,
}

impl Horizons {
    /// Counts one scene scored over `steps` from `from`.
    pub fn count(&mut self, steps: usize, from: HorizonFrom) {
        // A count of one per scene read cannot reach usize::MAX.
        let _ = self.add(steps, from, 1);
    }

    /// Adds `scenes` scored over `steps` from `from`; `None` (nothing added) where the count
    /// would overflow.
    pub fn add(&mut self, steps: usize, from: HorizonFrom, scenes: usize) -> Option<()> {
        match self
            .0
            .iter_mut()
            .find(|c| c.steps == steps && c.from == from)
        {
            Some(c) => c.scenes = c.scenes.checked_add(scenes)?,
            None => self.0.push(HorizonCount {
                steps,
                from,
                scenes,
            }),
        }
        self.0.sort_by_key(|c| (c.from, c.steps));
        Some(())
    }

    /// `horizon: 40 steps after the current step, the rollouts' own (3 scenes)`; None when
    /// nothing was scored.
    pub fn line(&self) -> Option<String> {
        let parts: Vec<String> = self
            .0
            .iter()
            .map(|c| {
                let from = match c.from {
                    HorizonFrom::Flag => "--horizon",
                    HorizonFrom::Rollouts => "the rollouts' own",
                    HorizonFrom::Recording => "the recorded future",
                };
                let s = if c.scenes == 1 { "" } else { "s" };
                format!("{} steps, {from} ({} scene{s})", c.steps, c.scenes)
            })
            .collect();
        (!parts.is_empty()).then(|| {
            let hint = if self.0.iter().any(|c| c.from != HorizonFrom::Flag) {
                "; --horizon H scores every scene over H steps"
            } else {
                ""
            };
            format!(
                "horizon (future steps scored after the current step): {}{hint}",
                parts.join("; ")
            )
        })
    }
}

/// What a shard's `--json` carries for `--merge` besides the accumulators (`merge.run`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunRecord {
    /// Everything the shards must agree on: task, methods, behaviour, parameters, horizon,
    /// samples, the number of shards.
    pub settings: Value,
    /// The shard indices combined (empty: an unsharded run).
    pub shards: Vec<usize>,
    /// Scenes skipped: no agents for which the behaviour is meaningful.
    pub skipped: usize,
    /// Scenes that failed.
    pub failures: usize,
    /// Scenes the rollouts' run left out.
    #[serde(default)]
    pub run_skipped: usize,
    /// The horizons the scenes were scored over (absent in files written before).
    #[serde(default)]
    pub horizons: Horizons,
}

/// What every shard of one evaluation read, whichever shard it scored: how many scenes and a
/// checksum of their scenario ids (sorted, CRC-32C), for `merge.run.settings.scenes`. Each
/// shard reads every scene to learn which are its own, so the shards of one run agree on it,
/// on any machine and under any path; the shards of two corpora do not. Without it, shard
/// 0/2 of one corpus and shard 1/2 of another merged into one table, exit 0.
pub fn corpus(ids: &[String]) -> Value {
    let mut sorted: Vec<&str> = ids.iter().map(String::as_str).collect();
    sorted.sort_unstable();
    let joined = sorted.join("\n");
    json!({
        "count": sorted.len(),
        "crc32c": crate::io::tfrecord::crc32c(joined.as_bytes()),
    })
}

/// The `merge` object of an `eval --json` file: what [`merge`] reads back.
pub fn record_json(accumulators: &[Tally], run: &RunRecord) -> Value {
    json!({"accumulators": accumulators, "run": run})
}

/// Shards combined: the table of a single run.
#[derive(Debug)]
pub struct Merged {
    /// The task.
    pub task: Task,
    /// The behaviour of a behaviour task.
    pub behaviour: Option<Behavior>,
    /// The methods, one per accumulator.
    pub methods: Vec<String>,
    /// One per method.
    pub accumulators: Vec<Tally>,
    /// The shards' settings, the shards combined and the summed counts.
    pub run: RunRecord,
    /// How many shards the evaluation was split into.
    pub shards: usize,
}

/// The most steps `eval --horizon` takes.
pub const MAX_HORIZON_FLAG: usize = 10_000;

/// The whole numbers of a file's `merge.run`, and of each accumulator (and group).
const RUN_COUNTS: &[&str] = &["skipped", "failures", "run_skipped"];
const TALLY_COUNTS: &[&str] = &["scenes", "passed", "achieved", "checked"];

/// `v[key]`, where present, as a whole number; else the message names `at.key`.
fn whole(v: &Value, key: &str, at: &str) -> Result<(), String> {
    match v.get(key) {
        None => Ok(()),
        Some(n) if n.as_u64().is_some() => Ok(()),
        Some(n) => Err(format!(
            "{at}.{key} is {n}: must be a whole number, 0 or more"
        )),
    }
}

/// The counts of an accumulator and its groups, before they are read as unsigned numbers
/// (whose error would not say which).
fn tally_counts(v: &Value, at: &str) -> Result<(), String> {
    for key in TALLY_COUNTS {
        whole(v, key, at)?;
    }
    if let Some(groups) = v.get("groups").and_then(Value::as_object) {
        for (label, g) in groups {
            tally_counts(g, &format!("{at}.groups[{label:?}]"))?;
        }
    }
    Ok(())
}

/// The settings every shard repeats, checked: a known task (and behaviour), the methods, and
/// a number of shards [`merge`] can count to.
struct Settings {
    task: Task,
    behaviour: Option<Behavior>,
    methods: Vec<String>,
    shards: usize,
}

fn settings(s: &Value) -> Result<Settings, String> {
    let task = s
        .get("task")
        .and_then(Value::as_str)
        .and_then(Task::from_name)
        .ok_or_else(|| {
            format!(
                "merge.run.settings.task is {}: must be conditional, unconditional or behaviour",
                s.get("task").unwrap_or(&Value::Null)
            )
        })?;
    let behaviour = match s.get("behaviour") {
        None | Some(Value::Null) => None,
        Some(b) => Some(b.as_str().and_then(Behavior::from_name).ok_or_else(|| {
            format!("merge.run.settings.behaviour is {b}: not a behaviour eval knows")
        })?),
    };
    let methods: Vec<String> = s
        .get("methods")
        .and_then(|m| serde_json::from_value(m.clone()).ok())
        .filter(|m: &Vec<String>| !m.is_empty())
        .ok_or("merge.run.settings.methods: must be a list of the methods' names")?;
    // The names start the table's rows: an escape sequence in one (a file's, not the user's)
    // was printed to the terminal as it was, and a line break split a row in two.
    for (i, m) in methods.iter().enumerate() {
        if let Err(c) = crate::io::name::check_name(m) {
            return Err(format!(
                "merge.run.settings.methods[{i}] is \"{}\": holds {c}; a method's name starts \
                 a row of the table",
                crate::io::name::shown(m)
            ));
        }
    }
    let shards = match s.get("shards") {
        // Files written before shards were counted are whole runs.
        None => 1,
        Some(n) => n
            .as_u64()
            .filter(|n| (1..=MAX_SHARDS as u64).contains(n))
            .ok_or_else(|| format!("merge.run.settings.shards is {n}: must be 1 to {MAX_SHARDS}"))?
            as usize,
    };
    Ok(Settings {
        task,
        behaviour,
        methods,
        shards,
    })
}

/// One shard file, read and checked: its record, settings and accumulators.
fn read_shard(path: &Path) -> Result<(RunRecord, Settings, Vec<Tally>), MergeError> {
    let text =
        crate::io::read_regular_text(path, crate::io::MAX_SCENE_BYTES, "an `eval --json` file")?;
    // A key named twice (a group, a method) was read as its last copy without a word.
    let mut v: Value =
        crate::io::json::parse_json(&text).map_err(|e| bad(path, format!("not JSON ({e})")))?;
    let no_record = || {
        bad(
            path,
            "no shard record (write one with `eval ... --shard I/N --json FILE`)",
        )
    };
    let run = v
        .pointer_mut("/merge/run")
        .map(Value::take)
        .filter(Value::is_object)
        .ok_or_else(no_record)?;
    for key in RUN_COUNTS {
        whole(&run, key, "merge.run").map_err(|m| bad(path, m))?;
    }
    if let Some(h) = run.get("horizons").and_then(Value::as_array) {
        for (i, c) in h.iter().enumerate() {
            for key in ["steps", "scenes"] {
                whole(c, key, &format!("merge.run.horizons[{i}]")).map_err(|m| bad(path, m))?;
            }
        }
    }
    if let Some(shards) = run.get("shards").and_then(Value::as_array) {
        if let Some((i, s)) = shards
            .iter()
            .enumerate()
            .find(|(_, s)| s.as_u64().is_none())
        {
            return Err(bad(
                path,
                format!("merge.run.shards[{i}] is {s}: must be a whole number, 0 or more"),
            ));
        }
    }
    let run: RunRecord = serde_json::from_value(run)
        .map_err(|e| bad(path, format!("merge.run is damaged ({e})")))?;
    let s = settings(&run.settings).map_err(|m| bad(path, m))?;
    if let Some(i) = run.shards.iter().find(|i| **i >= s.shards) {
        return Err(bad(
            path,
            format!(
                "merge.run.shards holds {i}: not a shard of {} (0 to {})",
                s.shards,
                s.shards - 1
            ),
        ));
    }
    let accs = v
        .pointer_mut("/merge/accumulators")
        .map(Value::take)
        .ok_or_else(no_record)?;
    let list = accs
        .as_array()
        .ok_or_else(|| bad(path, "merge.accumulators: must be a list, one per method"))?;
    if list.len() != s.methods.len() {
        return Err(bad(
            path,
            format!(
                "merge.accumulators holds {}, and the settings name {} methods: one per method",
                list.len(),
                s.methods.len()
            ),
        ));
    }
    for (i, a) in list.iter().enumerate() {
        tally_counts(a, &format!("merge.accumulators[{i}]")).map_err(|m| bad(path, m))?;
    }
    let accs: Vec<Tally> = serde_json::from_value(accs)
        .map_err(|e| bad(path, format!("merge.accumulators are damaged ({e})")))?;
    for (i, a) in accs.iter().enumerate() {
        a.check().map_err(|m| {
            bad(
                path,
                format!("merge.accumulators[{i}] ({}): {m}", s.methods[i]),
            )
        })?;
    }
    check_horizons(&run).map_err(|m| bad(path, m))?;
    Ok((run, s, accs))
}

/// Refuses horizons no evaluation scores over, and more scenes scored than the run read: a
/// shard saying `steps: 0` or a million, or 5 scenes of a run of 2, was merged and its line
/// printed ("horizon: 0 steps, ... (6 scenes)") under a table of 2 scenes, exit 0.
fn check_horizons(run: &RunRecord) -> Result<(), String> {
    for (i, c) in run.horizons.0.iter().enumerate() {
        if !(1..=crate::io::MAX_STEPS).contains(&c.steps) {
            return Err(format!(
                "merge.run.horizons[{i}].steps is {}: must be 1 to {} future steps",
                c.steps,
                crate::io::MAX_STEPS
            ));
        }
    }
    // `--horizon H` scores every scene over H steps from the flag, and without it no scene's
    // horizon is the flag's: a shard saying `horizon: 40` in its settings and 80 steps (or
    // the recording's) in its horizon line was merged and both printed, exit 0.
    match run.settings.get("horizon") {
        // Files written before the setting was recorded say nothing to check against.
        None => {}
        Some(Value::Null) => {
            if let Some((i, c)) = run
                .horizons
                .0
                .iter()
                .enumerate()
                .find(|(_, c)| c.from == HorizonFrom::Flag)
            {
                return Err(format!(
                    "merge.run.horizons[{i}] says {} steps from --horizon, but \
                     merge.run.settings.horizon is null (no --horizon given)",
                    c.steps
                ));
            }
        }
        Some(h) => {
            let flag = h
                .as_u64()
                .filter(|h| (1..=MAX_HORIZON_FLAG as u64).contains(h))
                .ok_or_else(|| {
                    format!(
                        "merge.run.settings.horizon is {h}: must be null or 1 to \
                         {MAX_HORIZON_FLAG} steps (eval --horizon's range)"
                    )
                })? as usize;
            if let Some((i, c)) = run
                .horizons
                .0
                .iter()
                .enumerate()
                .find(|(_, c)| (c.steps, c.from) != (flag, HorizonFrom::Flag))
            {
                let from = match c.from {
                    HorizonFrom::Flag => "--horizon",
                    HorizonFrom::Rollouts => "the rollouts",
                    HorizonFrom::Recording => "the recording",
                };
                return Err(format!(
                    "merge.run.horizons[{i}] says {} steps from {from}, but \
                     merge.run.settings.horizon is {flag}: with --horizon every scene is \
                     scored over its {flag} steps",
                    c.steps
                ));
            }
        }
    }
    let read = run
        .settings
        .get("scenes")
        .and_then(|c| c.get("count"))
        .and_then(Value::as_u64);
    let scored = run
        .horizons
        .0
        .iter()
        .try_fold(0u64, |t, c| t.checked_add(c.scenes as u64));
    if let (Some(read), Some(scored)) = (read, scored) {
        if scored > read {
            return Err(format!(
                "merge.run.horizons count {scored} scenes scored, but the run read {read} \
                 (merge.run.settings.scenes.count)"
            ));
        }
    }
    Ok(())
}

/// The scenes a shard scored, by name, sorted: its first method's per-scene rows (every
/// method scores the same scenes).
fn accs_scenes(accs: &[Tally]) -> Vec<String> {
    let mut names: Vec<String> = accs
        .first()
        .map(|t| {
            t.per_scene
                .iter()
                .filter_map(|r| r.get("scene").and_then(Value::as_str))
                .map(str::to_string)
                .collect()
        })
        .unwrap_or_default();
    names.sort_unstable();
    names
}

fn sum(a: usize, b: usize, what: &str, path: &Path) -> Result<usize, MergeError> {
    a.checked_add(b).ok_or_else(|| {
        bad(
            path,
            format!("merge.run.{what} is {b}: summed with the shards before, it overflows"),
        )
    })
}

/// Reads the `--json` files of an evaluation's shards, each checked ([`Tally::check`]), and
/// combines them. Refused: files of different settings (task, methods, behaviour, horizon,
/// number of shards), a shard given twice, a whole run given twice, a shard missing, and sums
/// that overflow.
pub fn merge(files: &[PathBuf]) -> Result<Merged, MergeError> {
    let mut first: Option<(PathBuf, RunRecord, Settings)> = None;
    let mut accs: Vec<Tally> = Vec::new();
    let mut seen: Vec<(usize, PathBuf)> = Vec::new();
    let mut scenes: Vec<(String, PathBuf)> = Vec::new();
    let (mut skipped, mut failures, mut run_skipped) = (0usize, 0usize, 0usize);
    let mut horizons = Horizons::default();
    for f in files {
        let (run, s, a) = read_shard(f)?;
        let mut own = accs_scenes(&a);
        own.dedup();
        scenes.extend(own.into_iter().map(|n| (n, f.clone())));
        match &first {
            None => {
                accs = a;
            }
            Some((f0, r0, _)) => {
                let (c0, c1) = (r0.settings.get("scenes"), run.settings.get("scenes"));
                if c0 != c1 {
                    let count = |c: &Value| c.get("count").map_or(Value::Null, Value::clone);
                    let why = match (c0, c1) {
                        (Some(a), Some(b)) if count(a) == count(b) => {
                            format!("both read {} scenes, but with other scenario ids", count(a))
                        }
                        (Some(a), Some(b)) => {
                            format!("{} scenes read against {}", count(a), count(b))
                        }
                        // One of the two has no record (they differ, so not both).
                        _ => format!(
                            "{} was written by an earlier drivescript, which did not record \
                             the scenes it read: run that shard again",
                            if c0.is_none() { f0 } else { f }.display()
                        ),
                    };
                    return Err(MergeError::Shards(format!(
                        "{} and {}: shards of evaluations of different scenes ({why}): merge \
                         the shards of one run, each run over the same scenes",
                        f0.display(),
                        f.display(),
                    )));
                }
                if run.settings != r0.settings {
                    return Err(MergeError::Shards(format!(
                        "{} and {}: not shards of one evaluation (settings {} against {})",
                        f0.display(),
                        f.display(),
                        r0.settings,
                        run.settings
                    )));
                }
                for (acc, o) in accs.iter_mut().zip(a) {
                    acc.absorb(o).map_err(|m| {
                        bad(
                            f,
                            format!("merge.accumulators: {m}, summed with the shards before"),
                        )
                    })?;
                }
            }
        }
        skipped = sum(skipped, run.skipped, "skipped", f)?;
        failures = sum(failures, run.failures, "failures", f)?;
        run_skipped = sum(run_skipped, run.run_skipped, "run_skipped", f)?;
        for (i, c) in run.horizons.0.iter().enumerate() {
            horizons.add(c.steps, c.from, c.scenes).ok_or_else(|| {
                bad(
                    f,
                    format!(
                        "merge.run.horizons[{i}].scenes is {}: summed with the shards before, it \
                         overflows",
                        c.scenes
                    ),
                )
            })?;
        }
        // An unsharded run is all of one evaluation: shard 0 of 1, so that merging it twice
        // (or with a copy) is refused rather than counting its scenes twice.
        let shards = if run.shards.is_empty() {
            vec![0]
        } else {
            run.shards.clone()
        };
        seen.extend(shards.iter().map(|&i| (i, f.clone())));

        if first.is_none() {
            first = Some((f.clone(), run, s));
        }
    }
    let (f0, r0, s) =
        first.ok_or_else(|| MergeError::Shards("--merge needs at least one file".into()))?;
    let n = s.shards;
    seen.sort();
    for w in seen.windows(2) {
        if w[0].0 == w[1].0 && n <= 1 {
            return Err(MergeError::Shards(format!(
                "{} and {} are both the whole of one evaluation (not shards of it): merging \
                 would count its scenes twice",
                w[0].1.display(),
                w[1].1.display()
            )));
        }
        if w[0].0 == w[1].0 {
            return Err(MergeError::Shards(format!(
                "shard {}/{n} is in both {} and {}: each shard once",
                w[0].0,
                w[0].1.display(),
                w[1].1.display()
            )));
        }
    }
    // Shards partition scenes by scenario id, so no scene is in two files; one that is (a
    // shard file relabelled, or one of no shard index beside a shard of the same run) would be
    // counted twice whatever the shard indices say.
    scenes.sort();
    for w in scenes.windows(2) {
        if w[0].0 == w[1].0 {
            return Err(MergeError::Shards(format!(
                "scene {} is in both {} and {}: each scene once (the shards of one evaluation \
                 hold different scenes)",
                crate::io::name::shown(&w[0].0),
                w[0].1.display(),
                w[1].1.display()
            )));
        }
    }
    // Every index is below n (read_shard), and each is there once: n of them is all.
    if n > 1 && seen.len() < n {
        let missing: Vec<String> = (0..n)
            .filter(|i| seen.binary_search_by_key(i, |s| s.0).is_err())
            .take(10)
            .map(|i| format!("{i}/{n}"))
            .collect();
        return Err(MergeError::Shards(format!(
            "{}: shards {}{} are missing: the merged table would leave their scenes out",
            f0.display(),
            missing.join(", "),
            if n - seen.len() > missing.len() {
                format!(" and {} more", n - seen.len() - missing.len())
            } else {
                String::new()
            }
        )));
    }
    Ok(Merged {
        task: s.task,
        behaviour: s.behaviour,
        methods: s.methods,
        accumulators: accs,
        run: RunRecord {
            settings: r0.settings,
            shards: seen.iter().map(|s| s.0).collect(),
            skipped,
            failures,
            run_skipped,
            horizons,
        },
        shards: n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{load_scene, LoadOptions};

    fn scene(name: &str) -> crate::scene::Scene {
        let p = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("scripts/scenes")
            .join(name);
        load_scene(&p, 0, &LoadOptions::default()).unwrap()
    }

    /// A conditional evaluation of one method (the log itself) over `scenes`.
    fn tally(scenes: &[&str]) -> Tally {
        let mut t = Tally::default();
        for name in scenes {
            let s = scene(name);
            t.score(
                Task::Conditional,
                &s,
                std::slice::from_ref(&s),
                None,
                None,
                &[],
            );
        }
        t
    }

    /// Shard `i` of 2 of a conditional evaluation of the log, as `eval --json` writes it.
    fn shard_file(i: usize, scenes: &[&str]) -> Value {
        let run = RunRecord {
            settings: json!({"task": "conditional", "methods": ["log"], "behaviour": null, "shards": 2}),
            shards: vec![i],
            skipped: 0,
            failures: 0,
            run_skipped: 0,
            horizons: Horizons::default(),
        };
        json!({"task": "conditional", "merge": record_json(&[tally(scenes)], &run)})
    }

    fn write(dir: &Path, name: &str, v: &Value) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, v.to_string()).unwrap();
        p
    }

    #[test]
    fn shards_merge_into_one_run_and_every_figure_is_checked_on_read() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (
            shard_file(0, &["highway.yaml"]),
            shard_file(1, &["crossroads.yaml", "highway_cut_in.yaml"]),
        );
        let fa = write(dir.path(), "a.json", &a);
        let fb = write(dir.path(), "b.json", &b);
        let m = merge(&[fa.clone(), fb.clone()]).unwrap();
        assert_eq!(m.accumulators[0].scenes, 3);
        assert_eq!(m.run.shards, vec![0, 1]);
        // Each edit of shard b, and what the error says of it.
        let edit = |pointer: &str, v: Value| {
            let mut e = b.clone();
            *e.pointer_mut(pointer).expect("a field shard files have") = v;
            let f = write(dir.path(), "edited.json", &e);
            match merge(&[fa.clone(), f]) {
                Ok(_) => format!("{pointer}: accepted"),
                Err(e) => e.to_string(),
            }
        };
        let acc = "/merge/accumulators/0";
        for (pointer, v, says) in [
            (format!("{acc}/scenes"), json!(u64::MAX), "merge.accumulators[0] (log): scenes is 18446744073709551615, but per_scene holds 2 scene rows"),
            (format!("{acc}/scenes"), json!(-2), "merge.accumulators[0].scenes is -2: must be a whole number"),
            (format!("{acc}/ade/0"), json!(-1.5), "merge.accumulators[0] (log): ade[0] is -1.5: must be a distance"),
            // Merged and printed in the table in 301 digits (issue 32).
            (format!("{acc}/ade/0"), json!(1e300), "merge.accumulators[0] (log): ade[0] is 1e300: must be a distance: finite, 0 to 3e7 m"),
            (format!("{acc}/collision/0"), json!(1.5), "collision[0] is 1.5: must be a rate: 0 to 1"),
            // Printed in 301 digits.
            (format!("{acc}/seconds"), json!(-1e300), "merge.accumulators[0] (log): seconds is -1e300: must be finite, not negative"),
            (format!("{acc}/sim_kin/speed/0"), json!(-3.0), "sim_kin.speed[0] is -3: must be a speed"),
            (format!("{acc}/achieved"), json!(1), "passed 0, achieved 1, checked 0"),
            (format!("{acc}/passed"), json!(2), "passed 2, achieved 0, checked 0: a sample passes only if"),
            (format!("{acc}/groups/urban/scenes"), json!(5), "groups[\"urban\"].scenes is 5: more than the whole row's 2"),
            (format!("{acc}/groups/urban/offroad"), json!([-0.5]), "groups[\"urban\"].offroad[0] is -0.5: must be a rate"),
            // A relabelled copy of a shard whose rows named no scene hid its scenes from the
            // check that refuses a scene in two files (issue 32).
            (format!("{acc}/per_scene/1/scene"), Value::Null, "merge.accumulators[0] (log): per_scene[1].scene is null: must be the scene's name"),
            (format!("{acc}/per_scene/0"), json!({}), "merge.accumulators[0] (log): per_scene[0] has no scene: each row names the scene it scores"),
            ("/merge/run/horizons".into(), json!([{"steps": 40, "from": "flag", "scenes": -1}]), "merge.run.horizons[0].scenes is -1: must be a whole number"),
            ("/merge/run/horizons".into(), json!([{"steps": 0, "from": "recording", "scenes": 1}]), "merge.run.horizons[0].steps is 0: must be 1 to 100000 future steps"),
            ("/merge/run/horizons".into(), json!([{"steps": 1000000, "from": "recording", "scenes": 1}]), "merge.run.horizons[0].steps is 1000000: must be 1 to"),
            ("/merge/run/skipped".into(), json!(-1), "merge.run.skipped is -1: must be a whole number"),
            ("/merge/run/shards/0".into(), json!(7), "merge.run.shards holds 7: not a shard of 2"),
            ("/merge/run/settings/shards".into(), json!(1e18), "must be 1 to 1000000"),
            ("/merge/run/settings/task".into(), json!("nonsense"), "merge.run.settings.task is \"nonsense\""),
            ("/merge/run/settings/methods/0".into(), json!("log\u{1b}]52;c;eA==\u{7}"), "merge.run.settings.methods[0] is \"log\\u{001B}]52;c;eA==\\u{0007}\": holds the control character U+001B"),
            ("/merge/run/settings/methods/0".into(), json!("log\n| ours | 0.0"), "merge.run.settings.methods[0] is \"log\\u{000A}| ours | 0.0\": holds the control character U+000A"),
        ] {
            let e = edit(&pointer, v);
            assert!(
                e.contains("edited.json: ") && e.contains(says),
                "{pointer}: {e}"
            );
        }
        // Counts that each fit, and whose sum does not.
        let mut big = a.clone();
        big["merge"]["run"]["skipped"] = json!(u64::MAX - 1);
        let fbig = write(dir.path(), "big.json", &big);
        let mut more = b.clone();
        more["merge"]["run"]["skipped"] = json!(2);
        let fmore = write(dir.path(), "more.json", &more);
        let e = merge(&[fbig, fmore]).unwrap_err().to_string();
        assert!(
            e.contains(
                "more.json: merge.run.skipped is 2: summed with the shards before, it overflows"
            ),
            "{e}"
        );
        let counted = |shard: usize, scenes: u64| {
            let mut v = b.clone();
            v["merge"]["run"]["shards"] = json!([shard]);
            v["merge"]["run"]["horizons"] =
                json!([{"steps": 40, "from": "flag", "scenes": scenes}]);
            v
        };
        let h0 = write(dir.path(), "h0.json", &counted(0, u64::MAX));
        let h1 = write(dir.path(), "h1.json", &counted(1, 1));
        let e = merge(&[h0, h1]).unwrap_err().to_string();
        assert!(
            e.contains(
                "h1.json: merge.run.horizons[0].scenes is 1: summed with the shards before, it \
                 overflows"
            ),
            "{e}"
        );
        // More scenes scored than the run read (a shard's line said 6 scenes under a table
        // of 2).
        let mut read = b.clone();
        read["merge"]["run"]["settings"]["scenes"] = json!({"count": 3, "crc32c": 1});
        read["merge"]["run"]["horizons"] = json!([{"steps": 40, "from": "recording", "scenes": 2}, {"steps": 80, "from": "recording", "scenes": 2}]);
        let f = write(dir.path(), "read.json", &read);
        let e = merge(&[f]).unwrap_err().to_string();
        assert!(
            e.contains("read.json: merge.run.horizons count 4 scenes scored, but the run read 3"),
            "{e}"
        );
        // A horizon line that contradicts the shard's own --horizon setting was merged and
        // printed under the table, exit 0.
        for (setting, horizons, says) in [
            (json!(40), json!([{"steps": 80, "from": "flag", "scenes": 1}]), "merge.run.horizons[0] says 80 steps from --horizon, but merge.run.settings.horizon is 40"),
            (json!(40), json!([{"steps": 40, "from": "recording", "scenes": 1}]), "merge.run.horizons[0] says 40 steps from the recording, but merge.run.settings.horizon is 40"),
            (Value::Null, json!([{"steps": 40, "from": "flag", "scenes": 1}]), "merge.run.horizons[0] says 40 steps from --horizon, but merge.run.settings.horizon is null"),
            (json!(0), json!([]), "merge.run.settings.horizon is 0: must be null or 1 to 10000"),
            (json!("40"), json!([]), "merge.run.settings.horizon is \"40\": must be null or 1 to 10000"),
            (json!(20000), json!([{"steps": 20000, "from": "flag", "scenes": 1}]), "merge.run.settings.horizon is 20000: must be null or 1 to 10000"),
        ] {
            let mut h = b.clone();
            h["merge"]["run"]["settings"]["horizon"] = setting.clone();
            h["merge"]["run"]["horizons"] = horizons;
            let f = write(dir.path(), "horizon.json", &h);
            let e = merge(&[f]).map(|_| "accepted".to_string()).unwrap_or_else(|e| e.to_string());
            assert!(e.contains("horizon.json: ") && e.contains(says), "{setting}: {e}");
        }
        let mut agree = b.clone();
        agree["merge"]["run"]["settings"]["horizon"] = json!(40);
        agree["merge"]["run"]["horizons"] = json!([{"steps": 40, "from": "flag", "scenes": 2}]);
        let f = write(dir.path(), "agree.json", &agree);
        read_shard(&f).unwrap();
        // One file twice, and one shard in two files.
        let e = merge(&[fa.clone(), fa.clone()]).unwrap_err().to_string();
        assert!(e.contains("shard 0/2 is in both"), "{e}");
        // A shard relabelled as the other, or stripped of its index (read as the whole of a
        // run): its scenes were counted twice.
        for shards in [json!([0]), json!([])] {
            let mut again = b.clone();
            again["merge"]["run"]["shards"] = shards.clone();
            let f = write(dir.path(), "again.json", &again);
            let e = merge(&[fb.clone(), f]).unwrap_err().to_string();
            assert!(
                e.contains("scene crossroads-straight is in both")
                    && e.contains("b.json")
                    && e.contains("again.json"),
                "{shards}: {e}"
            );
        }
        // A different evaluation.
        let mut other = b.clone();
        other["merge"]["run"]["settings"]["methods"] = json!(["cv"]);
        let fo = write(dir.path(), "other.json", &other);
        let e = merge(&[fa, fo]).unwrap_err().to_string();
        assert!(e.contains("not shards of one evaluation"), "{e}");
    }

    #[test]
    fn summed_counts_that_overflow_are_errors() {
        let mut a = Tally {
            checked: usize::MAX,
            ..Tally::default()
        };
        let b = Tally {
            checked: 1,
            ..Tally::default()
        };
        assert_eq!(
            a.absorb(b).unwrap_err(),
            "checked is 1, and the sum overflows"
        );
    }
}
