//! Batch evaluation of the loop (the paper's Tables 1 and 3): many (scene, request) pairs from
//! a YAML file, each judged by independent checkers, summarised per behaviour before
//! refinement and after each round.
//!
//! ```yaml
//! # Paths are relative to this file. A directory means every scene in it.
//! scenes: ../runs/heldout/windows          # default for entries without their own
//! entries:
//!   - request: "vehicle {cutter} cuts in front of vehicle {victim}"
//!     behaviour: cut_in       # {role}s are chosen per scene by eval::suggest::suggest
//!   - scene: ../data/samples/commonroad/USA_US101-3_3_T-1.xml
//!     request: "vehicle 401 cuts in front of vehicle 399"
//!     behaviour: cut_in
//!     params: {cutter: 401, victim: 399}
//!   - request: "vehicle {vehicle} drives off the road"   # checker from the request's words
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::prompt::Prompts;
use super::rules::understand_request;
use super::session::{
    run_verdict, Backend, Outcome, RoundRecord, RunVerdict, Session, SessionConfig,
};
use super::LlmError;
use crate::cost::Params;
use crate::eval::behaviors::Behavior;
use crate::eval::suggest::suggest;
use crate::io::shard::Shard;
use crate::io::{discover, load_scenes, output_stem, write_atomic, LoadOptions};
use crate::scene::Scene;
use crate::train::Trained;

/// One line of a batch file.
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    /// Scene files or directories.
    pub scenes: Vec<PathBuf>,
    /// The request, with `{role}` placeholders where agents are chosen per scene.
    pub request: String,
    /// The checker, when given (else the rules planner's reading of the request, if any).
    pub behaviour: Option<Behavior>,
    /// The checker's parameters (the roles fill the placeholders).
    pub params: Option<Params>,
    /// The batch file it was read from, for messages.
    pub file: PathBuf,
    /// Line in the batch file, for messages.
    pub line: usize,
    /// Whether the scenes are the file's top-level `scenes:` (which `--scenes` replaces).
    pub default_scenes: bool,
}

/// One (scene, request) pair to run.
#[derive(Debug, Clone)]
pub struct Instance {
    /// Where the scene came from.
    pub scene_path: PathBuf,
    /// The scene.
    pub scene: Scene,
    /// The request with its agents filled in.
    pub request: String,
    /// Its checkers.
    pub checks: Vec<(Behavior, Params)>,
    /// The row of the summary it counts in: the behaviour, or `request` without checkers.
    pub label: String,
}

fn bad(path: &Path, message: String) -> LlmError {
    LlmError::Input {
        path: path.to_path_buf(),
        message,
    }
}

/// An error of entry `e` found on the scene file `scene`: named by the batch file and the
/// entry's line, then the scene. Named by the scene file alone, "entry on line 3" pointed
/// into a file that has no such entry (and "batch:" named no file at all).
fn entry_err(e: &Entry, scene: Option<&Path>, message: String) -> LlmError {
    let on = scene.map_or(String::new(), |f| format!(" ({})", f.display()));
    bad(&e.file, format!("entry on line {}{on}: {message}", e.line))
}

/// The most a batch file may hold (the paper's tables need a few hundred entries, a few
/// dozen KB).
pub const MAX_BATCH_BYTES: u64 = 4 << 20;

/// Reads a batch file.
pub fn read_batch(path: &Path) -> Result<Vec<Entry>, LlmError> {
    let text = crate::io::read_regular_text(path, MAX_BATCH_BYTES, "a batch file")
        .map_err(|e| bad(path, format!("cannot read the batch file: {}", e.reason())))?;
    crate::io::yaml::check_text(&text).map_err(|m| bad(path, m))?;
    let v: serde_yaml::Value =
        serde_yaml::from_str(&text).map_err(|e| bad(path, format!("not YAML: {e}")))?;
    if !v.is_mapping() {
        return Err(bad(
            path,
            "not a batch file: it holds `scenes:` and an `entries:` list, each entry with its \
             `request:`"
                .into(),
        ));
    }
    unknown_key(&v, &["scenes", "entries"]).map_err(|m| bad(path, m))?;
    let base = path.parent().unwrap_or(Path::new("."));
    let paths = |v: &serde_yaml::Value, what: &str| -> Result<Vec<PathBuf>, LlmError> {
        match v {
            serde_yaml::Value::String(s) => Ok(vec![base.join(s)]),
            serde_yaml::Value::Sequence(items) => items
                .iter()
                .map(|i| {
                    i.as_str()
                        .map(|s| base.join(s))
                        .ok_or_else(|| bad(path, format!("{what}: every item must be a path")))
                })
                .collect(),
            serde_yaml::Value::Null => Ok(Vec::new()),
            _ => Err(bad(
                path,
                format!("{what} must be a path or a list of paths"),
            )),
        }
    };
    let default_scenes = paths(&v["scenes"], "scenes")?;
    let entries = v["entries"]
        .as_sequence()
        .ok_or_else(|| bad(path, "no `entries:` list".into()))?;
    // Line numbers: the n-th "- " item under entries, found by scanning the text.
    let item_lines: Vec<usize> = {
        let mut lines = Vec::new();
        let mut inside = false;
        let mut indent = None;
        for (i, l) in text.lines().enumerate() {
            if l.trim_start().starts_with("entries:") {
                inside = true;
                continue;
            }
            if inside {
                let t = l.trim_start();
                if t.starts_with("- ") {
                    let ind = l.len() - t.len();
                    if indent.is_none() {
                        indent = Some(ind);
                    }
                    if Some(ind) == indent {
                        lines.push(i + 1);
                    }
                }
            }
        }
        lines
    };
    let mut out = Vec::new();
    for (k, e) in entries.iter().enumerate() {
        let line = item_lines.get(k).copied().unwrap_or(0);
        let at = |m: String| bad(path, format!("entry {} (line {line}): {m}", k + 1));
        unknown_key(e, &["request", "scene", "behaviour", "params"]).map_err(at)?;
        let request = e["request"]
            .as_str()
            .ok_or_else(|| at("`request:` (text) is missing".into()))?
            .trim()
            .to_string();
        if request.is_empty() {
            return Err(at(
                "`request:` is empty: say in words what should happen".into()
            ));
        }
        let (scenes, default) = match &e["scene"] {
            serde_yaml::Value::Null => (default_scenes.clone(), true),
            v => (paths(v, "scene")?, false),
        };
        if scenes.is_empty() && !default {
            return Err(at("no scene: give `scene:` or a top-level `scenes:`".into()));
        }
        let behaviour = match &e["behaviour"] {
            serde_yaml::Value::Null => None,
            serde_yaml::Value::String(s) => {
                Some(Behavior::parse(s).map_err(|e| at(e.to_string()))?)
            }
            _ => return Err(at("`behaviour:` must be a name".into())),
        };
        let params = match &e["params"] {
            serde_yaml::Value::Null => None,
            v => {
                let j = serde_json::to_value(v).map_err(|e| at(format!("params: {e}")))?;
                Some(Params::from_json(&j).map_err(|m| at(format!("params: {m}")))?)
            }
        };
        if params.is_some() && behaviour.is_none() {
            return Err(at("`params:` without `behaviour:`".into()));
        }
        out.push(Entry {
            scenes,
            request,
            behaviour,
            params,
            file: path.to_path_buf(),
            line,
            default_scenes: default,
        });
    }
    Ok(out)
}

/// A key of the mapping `v` that is not one of `known`, as an error naming it (and the key
/// meant, for the likely slips): a misspelt key was dropped without a word (`behavior:` ran the
/// entry without its checker, `parms:` with default parameters).
fn unknown_key(v: &serde_yaml::Value, known: &[&str]) -> Result<(), String> {
    let Some(map) = v.as_mapping() else {
        return Ok(());
    };
    for k in map.keys() {
        let name = match k {
            serde_yaml::Value::String(s) => s.clone(),
            other => serde_yaml::to_string(other)
                .unwrap_or_default()
                .trim()
                .to_string(),
        };
        if known.contains(&name.as_str()) {
            continue;
        }
        let meant = [
            ("behavior", "behaviour"),
            ("scene", "scenes"),
            ("scenes", "scene"),
            ("param", "params"),
            ("parameters", "params"),
            ("entry", "entries"),
            ("requests", "request"),
        ]
        .iter()
        .find(|(typo, fix)| *typo == name && known.contains(fix))
        .map_or(String::new(), |(_, fix)| {
            format!(" (did you mean `{fix}`?)")
        });
        return Err(format!(
            "unknown key `{}`{meant}; the keys are {}",
            crate::io::name::shown(&name),
            known
                .iter()
                .map(|k| format!("`{k}`"))
                .collect::<Vec<_>>()
                .join(", ")
        ));
    }
    Ok(())
}

/// Placeholders `{name}` in a request.
fn placeholders(request: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = request;
    while let Some(i) = rest.find('{') {
        let Some(j) = rest[i..].find('}') else { break };
        out.push(rest[i + 1..i + j].to_string());
        rest = &rest[i + j + 1..];
    }
    out
}

/// Braces in a request are placeholders only: `{name}`, a name of letters, digits and `_`.
/// `{{vehicle}}` was read as the placeholder `{vehicle`, and said as "no value for
/// {{vehicle}"; a lone brace went to the model as written.
fn check_braces(request: &str) -> Result<(), String> {
    let mut rest = request;
    while let Some(i) = rest.find(['{', '}']) {
        let problem = if rest[i..].starts_with('}') {
            Some("a `}` that closes no placeholder".to_string())
        } else {
            match rest[i + 1..].find(['{', '}']) {
                Some(j) if rest[i + 1..].as_bytes()[j] == b'}' => {
                    let name = &rest[i + 1..i + 1 + j];
                    rest = &rest[i + 1 + j + 1..];
                    if !name.is_empty()
                        && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
                    {
                        continue;
                    }
                    Some(format!(
                        "`{{{}}}`, whose name is not one of letters, digits and `_`",
                        crate::io::name::shown(name)
                    ))
                }
                _ => Some("a `{` that no `}` closes before the next brace".to_string()),
            }
        };
        if let Some(p) = problem {
            return Err(format!(
                "the request holds {p}: braces are placeholders only, `{{role}}`, and cannot be \
                 escaped"
            ));
        }
    }
    Ok(())
}

/// Every (scene, request) pair of `entries`, with agents chosen for `{role}` placeholders.
/// Pairs whose scene has no agents suited to the behaviour are returned as skip messages,
/// never dropped silently. `horizon` is the sampler's.
pub fn expand(entries: &[Entry], horizon: usize) -> Result<(Vec<Instance>, Vec<String>), LlmError> {
    let mut out = Vec::new();
    let mut skipped = Vec::new();
    // Where each pair's rollouts go (`rollouts/LABEL/STEM_K.json`), and the line of the entry
    // that wrote them: two pairs there replaced each other's files without a word (one
    // behaviour asked of two agents of one scene, two free-form requests on it), and `eval`
    // scored the last one's samples for both.
    let mut rollouts: BTreeMap<(String, String), usize> = BTreeMap::new();
    for e in entries {
        let mut files = Vec::new();
        for s in &e.scenes {
            // The reader's error names the file it could not read: named again in front, it
            // read "x.yaml: x.yaml: No such file or directory".
            files.extend(discover(s).map_err(|err| entry_err(e, None, err.to_string()))?);
        }
        if files.is_empty() {
            return Err(entry_err(
                e,
                None,
                "no scene (give `scene:`, a top-level `scenes:`, or --scenes)".into(),
            ));
        }
        files.sort();
        check_braces(&e.request).map_err(|m| entry_err(e, None, m))?;
        let holes = placeholders(&e.request);
        for f in files {
            for scene in load_scenes(&f, &LoadOptions::default())
                .map_err(|err| entry_err(e, None, err.to_string()))?
            {
                let id = scene.meta.scenario_id.clone();
                let mut params = e.params.clone().unwrap_or_default();
                if !holes.is_empty() {
                    let b = e.behaviour.ok_or_else(|| {
                        entry_err(
                            e,
                            Some(&f),
                            "{placeholders} need `behaviour:` to choose agents".into(),
                        )
                    })?;
                    if holes.iter().any(|h| params.get(h).is_none()) {
                        match suggest(b, &scene.with_horizon(horizon), horizon) {
                            Some(p) => params = p.overridden_by(&params),
                            None => {
                                skipped.push(format!(
                                    "{id}: no agents suited to {} (line {})",
                                    b.name(),
                                    e.line
                                ));
                                continue;
                            }
                        }
                    }
                }
                let mut request = e.request.clone();
                for h in &holes {
                    // Said with what could fill it: "no value for {foo}" left the user to
                    // guess the names the behaviour's agents go by.
                    let v = params.get(h).ok_or_else(|| {
                        let known: Vec<String> =
                            params.names().map(|n| format!("{{{n}}}")).collect();
                        entry_err(
                            e,
                            Some(&f),
                            format!(
                                "no value for {{{h}}}: {}",
                                if known.is_empty() {
                                    "neither `params:` nor the behaviour's agents give one"
                                        .to_string()
                                } else {
                                    format!(
                                        "the placeholders `params:` and the behaviour's agents \
                                         fill are {}",
                                        known.join(", ")
                                    )
                                }
                            ),
                        )
                    })?;
                    request = request.replace(&format!("{{{h}}}"), &v.to_string());
                }
                // A role the behaviour's checker judges, chosen per scene but named nowhere in
                // the request (`vehicle {cutter} cuts in front of vehicle {cutter}`: {victim}
                // left out): the request asked of one car what the checker judged against
                // another, and every pair counted as a failure of the loop.
                if let (Some(b), false) = (e.behaviour, holes.is_empty()) {
                    let given = |r: &str| e.params.as_ref().is_some_and(|p| p.get(r).is_some());
                    if let Some(role) = b
                        .roles()
                        .iter()
                        .find(|r| !given(r) && !holes.iter().any(|h| h == *r))
                    {
                        let roles: Vec<String> =
                            b.roles().iter().map(|r| format!("{{{r}}}")).collect();
                        return Err(entry_err(
                            e,
                            None,
                            format!(
                                "the request names no {{{role}}}, an agent {}'s checker \
                                 judges: it would be chosen for each scene and never named in \
                                 the request; write each of {} where the request names that \
                                 agent (or give it in `params:`)",
                                b.name(),
                                roles.join(", ")
                            ),
                        ));
                    }
                }
                let checks = match e.behaviour {
                    Some(b) => vec![(b, params.clone())],
                    None => understand_request(&request)
                        .map(|ev| ev.into_iter().map(|e| (e.behaviour, e.params)).collect())
                        .unwrap_or_default(),
                };
                // An agent the entry names that the scene lacks: every sample would fail its
                // checker, and the pair would count as a failure of the loop, not of the file.
                for (b, p) in &checks {
                    for role in b.roles() {
                        let Some(v) = p.get(role) else { continue };
                        let present = matches!(v, crate::cost::ParamValue::Int(id)
                            if scene.agents.iter().any(|a| a.id == *id));
                        if !present {
                            return Err(entry_err(
                                e,
                                Some(&f),
                                format!(
                                    "scene {id} has no agent {v} ({} {role}): name one of its \
                                     agents, or give its scenes their own entry",
                                    b.name()
                                ),
                            ));
                        }
                    }
                }
                // A parameter the checker cannot read (a limit given as a word, a required one
                // absent): every sample's verdict would be that error, and the pair counted a
                // failure of the loop, exit 0. Judged on the log, which has every agent.
                if let (Some(b), Some(given)) = (e.behaviour, &e.params) {
                    // As `eval --param`: a name the checker does not read is dropped and the
                    // pair judged on its default.
                    b.check_param_names(given)
                        .map_err(|err| entry_err(e, Some(&f), format!("params: {err}")))?;
                }
                for (b, p) in &checks {
                    use crate::eval::behaviors::CheckError as C;
                    match crate::eval::behaviors::check(*b, &scene, p) {
                        Err(
                            err @ (C::MissingParam { .. }
                            | C::NotANumber { .. }
                            | C::NotAnId { .. }
                            | C::NotAWord { .. }),
                        ) => return Err(entry_err(e, Some(&f), format!("scene {id}: {err}"))),
                        _ => {}
                    }
                }
                // A pair no car can meet in the horizon says nothing of the loop: it is left out
                // with the reason, as a scene without suitable agents is, before any round.
                let cannot: Vec<String> = checks
                    .iter()
                    .filter_map(|(b, p)| crate::eval::infeasible(*b, &scene, p, horizon))
                    .map(|i| i.to_string())
                    .collect();
                if !cannot.is_empty() {
                    skipped.push(format!(
                        "{id}: cannot be met within the horizon: {} (line {})",
                        cannot.join("; "),
                        e.line
                    ));
                    continue;
                }
                let label = match checks.as_slice() {
                    [] => "request".to_string(),
                    [(b, _)] => b.name().to_string(),
                    many => many
                        .iter()
                        .map(|(b, _)| b.name())
                        .collect::<Vec<_>>()
                        .join("+"),
                };
                if let Ok(stem) = output_stem(&id) {
                    let at = format!("rollouts/{}/{stem}_K.json", path_label(&label));
                    if let Some(first) = rollouts.insert((path_label(&label), stem.into()), e.line)
                    {
                        let other = if first == e.line {
                            "this entry's, for the scene given to it twice".to_string()
                        } else {
                            format!("those of the entry on line {first}")
                        };
                        return Err(entry_err(
                            e,
                            Some(&f),
                            format!(
                                "scene {id}: its rollouts ({at}) would replace {other}: run \
                                 each (scene, {label}) pair once per batch, or the others in \
                                 batches of their own"
                            ),
                        ));
                    }
                }
                out.push(Instance {
                    scene_path: f.clone(),
                    scene,
                    request,
                    checks,
                    label,
                });
            }
        }
    }
    Ok((out, skipped))
}

/// A pair's label as a file name: a request of many events has a label of many behaviours
/// (`off_road+off_road+...`), which as a name is too long for the file system (the error
/// then quoted a path of 19 KB). A long label is cut and given the checksum of the whole, so
/// that two labels never share a directory.
fn path_label(label: &str) -> String {
    if label.len() <= 80 {
        return label.to_string();
    }
    let cut: String = label.chars().take(64).collect();
    format!(
        "{cut}~{:08x}",
        crate::io::tfrecord::crc32c(label.as_bytes())
    )
}

/// One finished instance, for the summary.
#[derive(Debug, Clone, Serialize)]
pub struct InstanceResult {
    /// The summary row.
    pub label: String,
    /// The scene's id.
    pub scenario: String,
    /// The request as sent.
    pub request: String,
    /// The run directory.
    pub dir: PathBuf,
    /// Per sampling round.
    pub rounds: Vec<RoundRecord>,
    /// Calls to the LLM server.
    pub llm_calls: usize,
    /// Tokens they used.
    pub tokens: u64,
    /// How the run ended, in words.
    pub outcome: String,
    /// The run's verdict ([`super::session::run_verdict`]): what `ask` would exit with for
    /// this pair, and what the table's last column counts.
    pub verdict: RunVerdict,
}

/// One row of the summary.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    /// Behaviour (or `request`).
    pub label: String,
    /// Instances.
    pub n: usize,
    /// Per sampling round r (0 = before refinement): instances whose shown sample achieves
    /// the behaviour by round r, counting a run that stopped earlier with its last round.
    pub achieved: Vec<usize>,
    /// Per sampling round r: instances whose round r succeeded ([`RoundRecord::succeeded`],
    /// the judgement `ask` exits with: every checker passes, with plausible motion, where
    /// checkers judge the whole request; the whole request met otherwise), counting a run that
    /// stopped earlier with its last round.
    pub passed: Vec<usize>,
    /// Mean sampling rounds used.
    pub mean_rounds: f64,
    /// Mean LLM calls.
    pub mean_calls: f64,
    /// Mean tokens.
    pub mean_tokens: f64,
    /// Why the final shown samples fall short, by kind, with counts.
    pub failures: BTreeMap<String, usize>,
}

/// The summary table over `results`, with `rounds` refinement rounds.
pub fn summarise(results: &[InstanceResult], rounds: usize) -> Vec<Row> {
    let mut labels: Vec<String> = results.iter().map(|r| r.label.clone()).collect();
    labels.sort();
    labels.dedup();
    labels
        .into_iter()
        .map(|label| {
            let rs: Vec<&InstanceResult> = results.iter().filter(|r| r.label == label).collect();
            let n = rs.len();
            let at = |r: &InstanceResult, k: usize| -> Option<RoundRecord> {
                r.rounds
                    .get(k.min(r.rounds.len().saturating_sub(1)))
                    .cloned()
            };
            let achieved = (0..=rounds)
                .map(|k| {
                    rs.iter()
                        .filter(|r| at(r, k).is_some_and(|x| x.achieved))
                        .count()
                })
                .collect();
            // The same judgement as `ask`'s verdict ([`RoundRecord::succeeded`]), round by round.
            let passed = (0..=rounds)
                .map(|k| {
                    rs.iter()
                        .filter(|r| at(r, k).is_some_and(|x| x.succeeded()))
                        .count()
                })
                .collect();
            let mut failures = BTreeMap::new();
            for r in &rs {
                let last = r.rounds.last();
                let kinds: Vec<String> = match last {
                    None => vec![format!("no script sampled ({})", r.outcome)],
                    Some(x) => x
                        .reasons
                        .iter()
                        .map(|w| {
                            if let Some(rest) = w.strip_prefix("checker ") {
                                format!("checker {}", rest.split(':').next().unwrap_or(""))
                            } else if w.starts_with("term ") {
                                format!(
                                    "term {} above tolerance",
                                    w.split_whitespace().nth(1).unwrap_or("")
                                )
                            } else {
                                "implausible named agent".to_string()
                            }
                        })
                        .collect(),
                };
                let mut kinds = kinds;
                kinds.sort();
                kinds.dedup();
                for k in kinds {
                    *failures.entry(k).or_insert(0) += 1;
                }
            }
            let mean = |f: &dyn Fn(&InstanceResult) -> f64| {
                if n == 0 {
                    0.0
                } else {
                    rs.iter().map(|r| f(r)).sum::<f64>() / n as f64
                }
            };
            Row {
                label,
                n,
                achieved,
                passed,
                mean_rounds: mean(&|r| r.rounds.len() as f64),
                mean_calls: mean(&|r| r.llm_calls as f64),
                mean_tokens: mean(&|r| r.tokens as f64),
                failures,
            }
        })
        .collect()
}

/// The summary as markdown.
pub fn markdown(rows: &[Row], rounds: usize) -> String {
    let mut s = String::from("| behaviour | n |");
    for k in 0..=rounds {
        s.push_str(&format!(" round {k} |"));
    }
    s.push_str(" mean rounds | LLM calls | tokens | why the final sample falls short |\n|---|---|");
    for _ in 0..=rounds {
        s.push_str("---|");
    }
    s.push_str("---|---|---|---|\n");
    for r in rows {
        s.push_str(&format!("| {} | {} |", r.label, r.n));
        for k in 0..=rounds {
            let f = |x: usize| {
                if r.n == 0 {
                    "-".to_string()
                } else {
                    format!("{:.2}", x as f64 / r.n as f64)
                }
            };
            s.push_str(&format!(" {} ({}) |", f(r.passed[k]), f(r.achieved[k])));
        }
        let why: Vec<String> = r
            .failures
            .iter()
            .map(|(k, v)| format!("{k}: {v}"))
            .collect();
        s.push_str(&format!(
            " {:.2} | {:.1} | {:.0} | {} |\n",
            r.mean_rounds,
            r.mean_calls,
            r.mean_tokens,
            if why.is_empty() {
                "-".into()
            } else {
                why.join("; ")
            }
        ));
    }
    s.push_str(
        "\nRound k: the share of instances that succeed after k refinement rounds, as `ask` judges \
         a run (its verdict and exit status): the shown sample passes every checker with \
         plausible motion where checkers judge the whole request, else meets the whole request \
         (in brackets: the checkers' geometry alone). A run that stopped earlier counts with its \
         last round.\n",
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn long_labels_make_short_distinct_file_names() {
        assert_eq!(path_label("cut_in+off_road"), "cut_in+off_road");
        let a = path_label(&"off_road+".repeat(500));
        let b = path_label(&format!("{}stop", "off_road+".repeat(500)));
        assert!(a.len() <= 80 && b.len() <= 80, "{a} {b}");
        assert_ne!(a, b);
    }

    #[test]
    fn batch_files_resolve_paths_fill_roles_and_name_bad_entries() {
        let dir = tempfile::tempdir().unwrap();
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        let scenes = root.join("scripts/scenes");
        let f = dir.path().join("b.yaml");
        std::fs::write(
            &f,
            format!(
                "scenes: {}\nentries:\n  - request: \"vehicle {{cutter}} cuts in front of vehicle {{victim}}\"\n    behaviour: cut_in\n  - scene: {}\n    request: \"vehicle 2 drives off the road\"\n",
                scenes.join("highway_cut_in.yaml").display(),
                scenes.join("highway.yaml").display()
            ),
        )
        .unwrap();
        let e = read_batch(&f).unwrap();
        assert_eq!((e.len(), e[0].line, e[1].line), (2, 3, 5));
        let (inst, skipped) = expand(&e, 40).unwrap();
        assert!(skipped.is_empty(), "{skipped:?}");
        assert_eq!(inst.len(), 2);
        assert_eq!(inst[0].label, "cut_in");
        assert!(!inst[0].request.contains('{'), "{}", inst[0].request);
        assert_eq!(inst[1].label, "off_road");
        assert_eq!(inst[1].checks[0].1.to_string(), "vehicle=2");
        std::fs::write(
            &f,
            "entries:\n  - request: x\n    scene: a.yaml\n  - request: y\n    scene: a.yaml\n    behaviour: flying\n",
        )
        .unwrap();
        let err = read_batch(&f).unwrap_err().to_string();
        assert!(
            err.contains("entry 2 (line 4)") && err.contains("unknown behaviour \"flying\""),
            "{err}"
        );
    }

    #[test]
    fn unknown_keys_in_a_batch_file_are_named_not_dropped() {
        // `behavior:` ran the entry without its checker, `parms:` with default parameters,
        // a top-level `scene:` gave no scenes at all.
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("b.yaml");
        for (text, want) in [
            (
                "entries:\n  - request: x\n    scene: a.yaml\n    behavior: cut_in\n",
                "entry 1 (line 2): unknown key `behavior` (did you mean `behaviour`?); the keys \
                 are `request`, `scene`, `behaviour`, `params`",
            ),
            (
                "entries:\n  - request: x\n    scene: a.yaml\n  - request: y\n    scene: a.yaml\n    behaviour: cut_in\n    parms: {cutter: 1}\n",
                "entry 2 (line 4): unknown key `parms`",
            ),
            (
                "scene: a.yaml\nentries:\n  - request: x\n",
                "unknown key `scene` (did you mean `scenes`?)",
            ),
            ("- request: x\n", "not a batch file"),
            (
                "entries:\n  - request: \" \"\n    scene: a.yaml\n",
                "entry 1 (line 2): `request:` is empty",
            ),
        ] {
            std::fs::write(&f, text).unwrap();
            let err = read_batch(&f).unwrap_err().to_string();
            assert!(err.contains(want), "{text}: {err}");
        }
    }

    #[test]
    fn entry_errors_found_on_a_scene_name_the_batch_file() {
        // "scene.yaml: entry on line 3: no value for {x}" pointed into the scene file, and
        // "batch: entry on line 3: no scene" named no file (issue 32).
        let dir = tempfile::tempdir().unwrap();
        let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        let f = dir.path().join("b.yaml");
        std::fs::write(
            &f,
            format!(
                "scenes: {}\nentries:\n  - request: \"vehicle {{cutter}} passes {{nobody}}\"\n    behaviour: cut_in\n",
                scene.display()
            ),
        )
        .unwrap();
        let err = expand(&read_batch(&f).unwrap(), 40)
            .err()
            .unwrap()
            .to_string();
        assert!(
            err.starts_with(&format!("{}: entry on line 3 (", f.display()))
                && err.contains("no value for {nobody}: the placeholders `params:` and the behaviour's agents fill are {cutter}, {victim}"),
            "{err}"
        );
        std::fs::write(&f, "scenes: []\nentries:\n  - request: x\n").unwrap();
        let err = expand(&read_batch(&f).unwrap(), 40)
            .err()
            .unwrap()
            .to_string();
        assert!(
            err.starts_with(&format!("{}: entry on line 3: no scene", f.display())),
            "{err}"
        );
    }

    #[test]
    fn parameters_the_checker_cannot_read_refuse_the_entry_before_any_round() {
        let dir = tempfile::tempdir().unwrap();
        let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        let f = dir.path().join("b.yaml");
        for (params, says) in [
            (
                "{vehicle: 1, limit: fast}",
                "parameter \"limit\" = \"fast\" must be a number",
            ),
            ("{vehicle: 1}", "parameter \"limit\" is required"),
            (
                "{vehicle: 1, limit: 15, limt: 12}",
                "parameter \"limt\": the checker does not read it",
            ),
        ] {
            std::fs::write(
                &f,
                format!(
                    "scenes: {}\nentries:\n  - request: \"vehicle 1 keeps below 15 m/s\"\n    behaviour: speed_limit\n    params: {params}\n",
                    scene.display()
                ),
            )
            .unwrap();
            let err = expand(&read_batch(&f).unwrap(), 40)
                .err()
                .expect(params)
                .to_string();
            // Named by the batch file, whose line it is, and then the scene (issue 32: it
            // was named by the scene file alone).
            assert!(
                err.starts_with(&format!(
                    "{}: entry on line 3 ({}): ",
                    f.display(),
                    scene.display()
                )) && err.contains(says),
                "{params}: {err}"
            );
        }
    }

    #[test]
    fn braces_in_a_request_are_placeholders_or_an_error_naming_them() {
        for ok in ["vehicle {cutter} passes {victim_2}", "no braces", ""] {
            assert_eq!(check_braces(ok), Ok(()), "{ok}");
        }
        for (bad, says) in [
            (
                "vehicle {{vehicle}} brakes",
                "a `{` that no `}` closes before the next brace",
            ),
            ("vehicle {cutter passes", "a `{` that no `}` closes"),
            ("vehicle cutter} passes", "a `}` that closes no placeholder"),
            ("vehicle {a b} passes", "`{a b}`, whose name is not one of"),
            ("vehicle {} passes", "`{}`, whose name is not one of"),
        ] {
            let e = check_braces(bad).unwrap_err();
            assert!(
                e.contains(says) && e.contains("cannot be escaped"),
                "{bad}: {e}"
            );
        }
    }

    #[test]
    fn the_rules_planner_reads_every_shipped_request_as_its_behaviour() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/requests");
        for file in ["table1.yaml", "table3.yaml"] {
            let entries = read_batch(&root.join(file)).unwrap();
            assert_eq!(entries.len(), if file == "table1.yaml" { 4 } else { 9 });
            for e in entries {
                let mut req = e.request.clone();
                for (k, h) in placeholders(&e.request).iter().enumerate() {
                    let v = match h.as_str() {
                        "x" | "y" => format!("{}.5", 10 + k),
                        "limit" => "12.5".to_string(),
                        _ => (400 + k).to_string(),
                    };
                    req = req.replace(&format!("{{{h}}}"), &v);
                }
                let ev = understand_request(&req).unwrap_or_else(|err| panic!("{req}: {err}"));
                assert_eq!(ev.len(), 1, "{req}");
                assert_eq!(Some(ev[0].behaviour), e.behaviour, "{req}");
                for h in placeholders(&e.request) {
                    assert!(ev[0].params.get(&h).is_some(), "{req}: {h} not read");
                }
            }
        }
    }

    #[test]
    fn the_summary_carries_finished_runs_forward() {
        let rec = |achieved, passed| RoundRecord {
            exchange: 0,
            meets: passed,
            achieved,
            passed,
            reasons: if passed {
                vec![]
            } else {
                vec!["checker cut_in: short".into()]
            },
            success: None,
        };
        let r = |rounds: Vec<RoundRecord>| InstanceResult {
            label: "cut_in".into(),
            scenario: "s".into(),
            request: "r".into(),
            dir: PathBuf::new(),
            verdict: run_verdict(&rounds),
            rounds,
            llm_calls: 2,
            tokens: 100,
            outcome: "o".into(),
        };
        let rows = summarise(
            &[
                r(vec![rec(true, true)]),
                r(vec![rec(false, false), rec(true, false), rec(true, true)]),
            ],
            2,
        );
        assert_eq!(rows[0].passed, vec![1, 1, 2]);
        assert_eq!(rows[0].achieved, vec![1, 2, 2]);
        assert_eq!(rows[0].mean_rounds, 2.0);
        assert!(rows[0].failures.is_empty());
        let md = markdown(&rows, 2);
        assert!(
            md.contains("| cut_in | 2 | 0.50 (0.50) | 0.50 (1.00) | 1.00 (1.00) |"),
            "{md}"
        );
    }

    #[test]
    fn the_table_counts_a_pair_as_ask_s_verdict_judges_it() {
        use crate::llm::session::round_succeeded;
        // (meets, passed, fully checked): the checker passes and a term is over tolerance;
        // the same with a clause no checker reads; no checker, the terms met; nothing met.
        for (meets, passed, full) in [
            (false, true, true),
            (false, true, false),
            (true, false, false),
            (false, false, true),
        ] {
            let rounds = vec![RoundRecord {
                exchange: 0,
                meets,
                achieved: passed,
                passed,
                reasons: Vec::new(),
                success: Some(round_succeeded(meets, passed, full)),
            }];
            let result = InstanceResult {
                label: "speed_limit".into(),
                scenario: "s".into(),
                request: "r".into(),
                dir: PathBuf::new(),
                verdict: run_verdict(&rounds),
                rounds,
                llm_calls: 1,
                tokens: 10,
                outcome: "rounds ran out".into(),
            };
            let rows = summarise(std::slice::from_ref(&result), 0);
            assert_eq!(
                rows[0].passed[0] == 1,
                result.verdict.succeeded,
                "{meets} {passed} {full}: {:?}",
                result.verdict
            );
        }
    }
}

/// What the pair that stopped a batch had made: what [`Batch::run`] removes, or keeps.
#[derive(Default)]
struct Started {
    /// Its run directory, where this batch created it.
    fresh: Option<PathBuf>,
    /// Whether any pair received a reply from the model (work paid for, kept).
    replied: bool,
}

/// `e`, saying what of a failed batch's own files could not be removed (`left`).
fn undone(e: LlmError, left: Vec<String>) -> LlmError {
    if left.is_empty() {
        return e;
    }
    LlmError::Setup(format!(
        "{e} (the batch failed before any result, and could not remove what it had added: {})",
        left.join("; ")
    ))
}

/// A batch to run: its pairs and where the runs, rollouts and summary go.
pub struct Batch<'a> {
    /// The batch file (named in the summary).
    pub file: PathBuf,
    /// The pairs, from [`expand`].
    pub instances: Vec<Instance>,
    /// Pairs [`expand`] skipped, with why.
    pub skipped: Vec<String>,
    /// The output directory.
    pub out: PathBuf,
    /// The model.
    pub trained: &'a Trained,
    /// The backend every pair uses (not the manual one: nobody is there to paste).
    pub backend: Backend,
    /// The prompt templates.
    pub prompts: Prompts,
    /// The loop's settings (a resumed pair keeps those it was started with).
    pub config: SessionConfig,
    /// Only the pairs whose scene falls in this shard (pair numbers stay those of the whole
    /// batch, so shards share one output directory).
    pub shard: Option<Shard>,
}

/// What [`Batch::run`] reports as it goes.
pub enum Progress<'e> {
    /// The output directory is made, locked and holds nothing of another's: the pairs start,
    /// their runs in `runs`. Said here, not before [`Batch::run`], so a batch refused at
    /// these checks does not announce where its runs go.
    Ready {
        /// The directory of the pairs' run directories.
        runs: &'e Path,
    },
    /// A line of the current pair's session.
    Line(&'e str),
    /// A pair is finished (`resumed`: its run directory held a finished or stopped run).
    Done {
        /// Its position, from 0.
        k: usize,
        /// Its result.
        result: &'e InstanceResult,
        /// Whether it continued an earlier run instead of starting one.
        resumed: bool,
    },
}

impl Batch<'_> {
    /// The run directory of pair `k`.
    pub fn run_dir(&self, k: usize) -> Result<PathBuf, LlmError> {
        let inst = &self.instances[k];
        let stem = output_stem(&inst.scene.meta.scenario_id)
            .map_err(|e| bad(&inst.scene_path, e.to_string()))?;
        Ok(self
            .out
            .join("runs")
            .join(format!("{k:03}_{}_{stem}", path_label(&inst.label))))
    }

    /// Runs every pair in order, writing the summary after each. A pair whose run directory
    /// already holds a run of the same scene, request and backend continues it (a finished
    /// one is only read back), so a batch stopped by an error, a full disk or Ctrl-C is
    /// finished by running the same command again. An error in a pair stops the batch with
    /// the pair named; the pairs before it are in the summary. A batch that fails before any
    /// result (no pair done, no reply received) leaves `out` as it found it
    /// ([`super::rundir::Before`]): no lock file or run of its own marks it as a batch's.
    pub fn run(&self, progress: &mut dyn FnMut(Progress)) -> Result<Vec<InstanceResult>, LlmError> {
        if matches!(self.backend, Backend::Manual) {
            return Err(bad(
                &self.file,
                "a batch runs without a person: use the http or rules backend".into(),
            ));
        }
        self.check_samples_fit()?;
        let before = super::rundir::Before::of(&self.out, self.shard);
        crate::io::create_output_dir(&self.out).map_err(|e| bad(&self.out, e.reason()))?;
        // One process per batch (per shard: the shards of one batch share -o by design), no
        // single run beside it; the pairs' own run directories are locked too, should two
        // overlap.
        let locks = match super::rundir::lock_batch(&self.out, self.shard) {
            Ok(l) => l,
            Err(e) => return Err(undone(e, before.restore(None, None))),
        };
        let mut results = Vec::new();
        let mut started = Started::default();
        match self.run_pairs(&mut results, &mut started, progress) {
            Ok(()) => Ok(results),
            Err(e) if results.is_empty() && !started.replied => Err(undone(
                e,
                before.restore(started.fresh.as_deref(), Some(locks)),
            )),
            Err(e) => Err(e),
        }
    }

    /// Refuses, before anything is made or asked, a batch one of whose pairs to start would
    /// sample more than its scene's batch fits in memory ([`super::session::check_samples_fit`]):
    /// it stopped the batch at that pair's first round. A pair resumed keeps the samples its
    /// run recorded, and is not judged by this batch's.
    fn check_samples_fit(&self) -> Result<(), LlmError> {
        let mut seen = std::collections::HashSet::new();
        for (k, inst) in self.instances.iter().enumerate() {
            if self
                .shard
                .is_some_and(|sh| !sh.contains(&inst.scene.meta.scenario_id))
                || !seen.insert((&inst.scene_path, &inst.scene.meta.scenario_id))
                || self.run_dir(k)?.join("state.json").exists()
            {
                continue;
            }
            super::session::check_samples_fit(self.trained, &inst.scene, self.config.samples)
                .map_err(|e| {
                    bad(
                        &inst.scene_path,
                        format!(
                            "pair {} of {} ({}): {e}",
                            k + 1,
                            self.instances.len(),
                            inst.scene.meta.scenario_id
                        ),
                    )
                })?;
        }
        Ok(())
    }

    /// The pairs of [`Batch::run`], each result pushed to `results` as it is done; `started`
    /// says what the pair that stopped the batch made.
    fn run_pairs(
        &self,
        results: &mut Vec<InstanceResult>,
        started: &mut Started,
        progress: &mut dyn FnMut(Progress),
    ) -> Result<(), LlmError> {
        self.check_outputs_are_ours()?;
        progress(Progress::Ready {
            runs: &self.out.join("runs"),
        });
        for (k, inst) in self.instances.iter().enumerate() {
            if self
                .shard
                .is_some_and(|sh| !sh.contains(&inst.scene.meta.scenario_id))
            {
                continue;
            }
            let dir = self.run_dir(k)?;
            let stopped = |e: LlmError| {
                bad(
                    &dir,
                    format!(
                        "pair {} of {} ({}, {:?}) stopped the batch: {e}. The pairs finished before \
                         it are in the summary; run the same command again to continue from here",
                        k + 1,
                        self.instances.len(),
                        inst.scene.meta.scenario_id,
                        inst.request
                    ),
                )
            };
            // A pair's run this batch cannot continue (another request, settings or follow-up)
            // is refused as it is: running the same command again meets the same refusal.
            let refused = |e: LlmError| {
                bad(
                    &dir,
                    format!(
                        "pair {} of {} ({}, {:?}) cannot be continued: {e}. The pairs finished \
                         before it are in the summary",
                        k + 1,
                        self.instances.len(),
                        inst.scene.meta.scenario_id,
                        inst.request
                    ),
                )
            };
            let resumed = dir.join("state.json").exists();
            // A run directory this batch creates is its own to remove, should it fail first.
            started.fresh = (std::fs::symlink_metadata(&dir).is_err()).then(|| dir.clone());
            let session = if resumed {
                self.reopen(inst, &dir)
            } else {
                Session::start(
                    &dir,
                    &inst.scene_path,
                    inst.scene.clone(),
                    &inst.request,
                    self.trained,
                    self.backend.clone(),
                    self.prompts.clone(),
                    self.config.clone(),
                    Some(inst.checks.clone()),
                )
            };
            let result = match session {
                Err(LlmError::Rules(e)) => InstanceResult {
                    label: inst.label.clone(),
                    scenario: inst.scene.meta.scenario_id.clone(),
                    request: inst.request.clone(),
                    dir,
                    rounds: Vec::new(),
                    llm_calls: 0,
                    tokens: 0,
                    outcome: format!("not planned: {e}"),
                    verdict: run_verdict(&[]),
                },
                Err(e) if resumed => return Err(refused(e)),
                Err(e) => return Err(stopped(e)),
                Ok(mut session) => {
                    let outcome = session.run(&mut |l| progress(Progress::Line(l)));
                    started.replied |= session.replies() > 0;
                    let outcome = outcome.map_err(stopped)?;
                    self.copy_rollouts(k, &session).map_err(stopped)?;
                    let (llm_calls, tokens) = session.usage();
                    InstanceResult {
                        label: inst.label.clone(),
                        scenario: inst.scene.meta.scenario_id.clone(),
                        request: inst.request.clone(),
                        dir,
                        rounds: session.history().to_vec(),
                        llm_calls,
                        tokens,
                        outcome: match outcome {
                            Outcome::Accepted { round, .. } => format!("accepted in round {round}"),
                            Outcome::RoundsUsed { .. } => "rounds ran out".to_string(),
                            Outcome::GaveUp { reason } => format!("gave up: {reason}"),
                            Outcome::Infeasible { reasons } => {
                                format!("infeasible: {}", reasons.join("; "))
                            }
                            Outcome::Waiting { .. } => "waiting".to_string(),
                        },
                        verdict: session.verdict(),
                    }
                }
            };
            results.push(result);
            self.write_summary(results)?;
            progress(Progress::Done {
                k,
                result: results.last().expect("just pushed"),
                resumed,
            });
        }
        Ok(())
    }

    /// Reopens the run in `dir`, refusing one of another scene, request or backend.
    fn reopen(&self, inst: &Instance, dir: &Path) -> Result<Session<'_>, LlmError> {
        let other = |what: String| {
            bad(
                dir,
                format!("holds a run of {what}, not of this batch's pair: choose another -o"),
            )
        };
        let session = Session::resume(
            dir,
            self.trained,
            |name, _, _| {
                if name == self.backend.name() {
                    Ok(self.backend.clone())
                } else {
                    Err(other(format!("the {name} backend")))
                }
            },
            |path| {
                // Recorded absolute (runs before that as given): compared as such.
                if super::session::absolute(path) == super::session::absolute(&inst.scene_path) {
                    Ok(inst.scene.clone())
                } else {
                    Err(other(format!("the scene {}", path.display())))
                }
            },
        )?;
        if session.requests().first() != Some(&inst.request) {
            // Quoted as the request's words: `{:?}` of the Option printed `Some("...")`.
            return Err(other(match session.requests().first() {
                Some(r) => format!(
                    "the request \"{}\" (the batch file's entry said so when it ran)",
                    crate::io::name::shown(r)
                ),
                None => "no request".into(),
            }));
        }
        // A pair's run revised by hand (`ask --continue DIR "..."`) was read back as the
        // pair's: its follow-up rounds were counted as refinement rounds of the batch's
        // request, and the follow-up's samples copied as the pair's rollouts, exit 0.
        if let Some(follow) = session.requests().get(1) {
            return Err(bad(
                dir,
                format!(
                    "holds the pair's run revised with a follow-up request (`ask --continue`: \
                     \"{}\"): its rounds are no longer the batch's request alone; move the run \
                     directory away to run the pair again, or choose another -o",
                    crate::io::name::shown(follow)
                ),
            ));
        }
        // A run goes on with the settings it started with: a batch run again with another
        // --seed, --samples or --rounds reported the pairs finished before with the old ones
        // beside new pairs with the new, as one batch's summary, exit 0.
        let (then, now) = (
            serde_json::to_value(session.config()).unwrap_or_default(),
            serde_json::to_value(self.config.resolved(self.trained)).unwrap_or_default(),
        );
        if let (Some(then), Some(now)) = (then.as_object(), now.as_object()) {
            if let Some((key, was)) = then
                .iter()
                .find(|(k, v)| now.get(k.as_str()).is_some_and(|n| n != *v))
            {
                return Err(bad(
                    dir,
                    format!(
                        "holds the pair's run made with {key} = {was}, and this batch runs with \
                         {key} = {}: a run goes on with the settings it started with; give the \
                         batch its first run's settings, or choose another -o",
                        now[key.as_str()]
                    ),
                ));
            }
        }
        Ok(session)
    }

    /// The last sampled round's rollouts of pair `k`, and their unguided twins in
    /// `unguided/`, where `eval --task behaviour --rollouts OUT/rollouts/LABEL --unguided
    /// OUT/rollouts/LABEL/unguided` finds them.
    fn copy_rollouts(&self, k: usize, session: &Session) -> Result<(), LlmError> {
        let Some(last) = session.history().last() else {
            return Ok(());
        };
        let inst = &self.instances[k];
        let stem = output_stem(&inst.scene.meta.scenario_id)
            .map_err(|e| bad(&inst.scene_path, e.to_string()))?;
        let from = session.dir().join(format!("round_{}", last.exchange));
        let to = self.out.join("rollouts").join(path_label(&inst.label));
        std::fs::create_dir_all(&to).map_err(|e| bad(&to, format!("cannot create it: {e}")))?;
        for sub in ["", "unguided"] {
            for i in 0.. {
                let src = from.join(sub).join(format!("{stem}_{i}.json"));
                let Ok(bytes) =
                    crate::io::read_regular(&src, crate::io::MAX_SCENE_BYTES, "a rollout file")
                else {
                    break;
                };
                let dst = to.join(sub).join(format!("{stem}_{i}.json"));
                // Only a rollout (an earlier batch's) is replaced: a user's file at that name,
                // in an -o the batch made no claim on yet, was overwritten, exit 0.
                crate::io::check_replaces_own(
                    &dst,
                    "file",
                    "a rollout",
                    crate::io::is_rollout_file,
                )
                .map_err(LlmError::Io)?;
                write_atomic(&dst, &bytes).map_err(|e| bad(&dst, e.to_string()))?;
            }
        }
        Ok(())
    }

    /// Refuses an -o whose `summary.md` / `summary.json` a batch did not write (they would be
    /// replaced), or whose `runs` / `rollouts` is a link (the batch would write through it).
    fn check_outputs_are_ours(&self) -> Result<(), LlmError> {
        let read = |name: &str| {
            crate::io::read_regular_text(&self.out.join(name), MAX_BATCH_BYTES * 16, "a summary")
        };
        let theirs = |name: &str| {
            bad(
                &self.out.join(name),
                "it is not a summary an `ask --batch` wrote, and a batch would replace it: move \
                 it, or choose another -o"
                    .into(),
            )
        };
        if self.out.join("summary.md").exists()
            && !read("summary.md").is_ok_and(|t| t.starts_with("# drivescript ask --batch"))
        {
            return Err(theirs("summary.md"));
        }
        if self.out.join("summary.json").exists()
            && !read("summary.json")
                .ok()
                .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
                .is_some_and(|v| v.get("rows").is_some() && v.get("instances").is_some())
        {
            return Err(theirs("summary.json"));
        }
        for sub in ["runs", "rollouts"] {
            super::rundir::check_not_link(&self.out.join(sub))?;
        }
        self.check_same_batch()
    }

    /// Refuses an -o whose summary another batch file wrote: its runs would sit beside this
    /// batch's under `runs/`, and its summary would be replaced by one that lists only this
    /// batch's pairs. The file is the one recorded in `summary.json` (absolute), or for
    /// summaries written before that was recorded, the one in `summary.md`'s heading.
    fn check_same_batch(&self) -> Result<(), LlmError> {
        let read = |name: &str| {
            crate::io::read_regular_text(&self.out.join(name), MAX_BATCH_BYTES * 16, "a summary")
                .ok()
        };
        let recorded = read("summary.json")
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
            .and_then(|v| v.get("batch").and_then(|b| b.as_str()).map(PathBuf::from));
        let recorded = match recorded {
            Some(p) => p,
            None => match read("summary.md").and_then(|t| {
                t.lines()
                    .next()
                    .and_then(|l| l.strip_prefix("# drivescript ask --batch "))
                    .map(PathBuf::from)
            }) {
                Some(p) => p,
                None => return Ok(()),
            },
        };
        let ours = super::session::absolute(&self.file);
        if recorded == ours || recorded == self.file || super::session::absolute(&recorded) == ours
        {
            return Ok(());
        }
        Err(bad(
            &self.out,
            format!(
                "holds the runs and summary of another batch file ({}); this batch would mix its \
                 runs with those and replace their summary. Choose another -o for {}, or run {} \
                 again to continue that batch",
                recorded.display(),
                self.file.display(),
                recorded.display()
            ),
        ))
    }

    /// Writes `summary.md` and `summary.json` for the pairs done so far.
    fn write_summary(&self, results: &[InstanceResult]) -> Result<(), LlmError> {
        let rounds = self.config.rounds;
        let rows = summarise(results, rounds);
        let of = match self.shard {
            Some(sh) => format!(
                "{} pairs of shard {sh} done (the batch has {}; run it without --shard for the \
                 whole summary)",
                results.len(),
                self.instances.len()
            ),
            None => format!("{} of {} pairs done", results.len(), self.instances.len()),
        };
        let mut md = format!(
            "# drivescript ask --batch {}\n\n{of}; {} skipped (no suitable agents, or a request \
             no car can meet in the horizon).\n\n",
            self.file.display(),
            self.skipped.len()
        );
        md.push_str(&markdown(&rows, rounds));
        let json = serde_json::json!({
            "batch": super::session::absolute(&self.file),
            "rows": rows,
            "instances": results,
            "skipped": self.skipped
        });
        for (name, text) in [
            ("summary.md", md),
            (
                "summary.json",
                serde_json::to_string_pretty(&json).expect("summary serialises"),
            ),
        ] {
            let p = self.out.join(name);
            write_atomic(&p, text.as_bytes()).map_err(|e| bad(&p, e.to_string()))?;
        }
        Ok(())
    }
}
