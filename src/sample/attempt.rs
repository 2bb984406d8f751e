//! One attempt at a request: compile and validate the cost scripts on the scene the sampler
//! will use, sample (open or closed loop), and report per sample each term's first estimate and
//! final value, the behaviour checker's verdict and every vehicle's implausible motion.
//!
//! `demo`, `simulate` and the LLM loop all run [`attempt`], so scripts are compiled under one
//! set of rules ([`ScriptSpec`] carries its [`Limits`]) and validated once before any sampling,
//! whichever loop samples them.

use std::path::Path;
use std::rc::Rc;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use serde::Serialize;

use super::closed_loop::closed_loop_until;
use super::config::{SampleConfig, SampleError, Task};
use super::guided::{prepare_for, sample_until, sampled_horizon, Sample};
use crate::cost::ScriptSpec;
use crate::cost::{check_params, CostError, CostReport, CostScript, Params};
use crate::eval::asked::{self, requested, verdicts};
use crate::eval::behaviors::{Behavior, CheckError, Verdict};
use crate::eval::kinematic::{judge, KinematicLimits, Violation};
use crate::eval::metrics::{road_departure, RoadDeparture};
use crate::io::rollout::{Allowance, AllowedMotion, Rollout};
use crate::io::{output_stem, write_atomic, IoError};
use crate::scene::Scene;
use crate::train::Trained;

/// What to attempt on one scene.
#[derive(Debug, Clone)]
pub struct AttemptSpec {
    /// The cost scripts, each with its parameters and limits.
    pub scripts: Vec<ScriptSpec>,
    /// The independent checkers that judge the result, each with its parameters (agent roles):
    /// one per event of the request that is a known behaviour. A sample passes when every
    /// checker passes it.
    pub checks: Vec<(Behavior, Params)>,
    /// Sampler settings.
    pub cfg: SampleConfig,
    /// Closed loop: steps executed before re-planning (5 = 2 Hz at 10 Hz); `None` samples the
    /// whole horizon at once.
    pub replan: Option<usize>,
    /// What a term that no probe moves ([`crate::cost::CostScript::dead_terms`]) does: refuse
    /// the attempt before sampling, as a validation error (the LLM loop: the model wrote it for
    /// this request and repairs it for the price of a reply, not of a sampling round), or go
    /// into [`AttemptReport::warnings`] (`simulate`: the user chose the script, perhaps as a
    /// guard against something the probes do not try, so it is said, not refused).
    pub refuse_dead_terms: bool,
}

/// Why an attempt did not produce samples.
#[derive(Debug, thiserror::Error)]
pub enum AttemptError {
    /// A script failed to compile or validate on the scene (the message names the script,
    /// line and term); nothing was sampled.
    #[error("{0}")]
    Script(CostError),
    /// Sampling failed.
    #[error(transparent)]
    Sample(#[from] SampleError),
    /// The checker cannot judge this scene with these parameters.
    #[error(transparent)]
    Check(#[from] CheckError),
}

/// One term of one sample.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TermOutcome {
    /// The script that declares it.
    pub script: String,
    /// Its name.
    pub term: String,
    /// Line of its `term(...)` call.
    pub line: usize,
    /// Its weight.
    pub weight: f64,
    /// Unweighted value on the first denoised estimate, before any guidance (absent in closed
    /// loop when the term appears only later).
    #[serde(serialize_with = "crate::io::json::opt_f64_explicit")]
    pub initial: Option<f64>,
    /// Unweighted value on the final trajectories.
    #[serde(rename = "final", serialize_with = "crate::io::json::f64_explicit")]
    pub value: f64,
    /// The script's tolerance for it, when it gives one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<f64>,
    /// For a script term over many agents (it reads three or more, or one the script does
    /// not name) that pulls on some: the agents that carry it ([`Carried`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub carried_by: Option<Carried>,
}

/// The most agents [`Carried::top`] names: enough to point a repair at the agents that
/// matter, few enough to keep a line of feedback a line.
pub const CARRIERS_SHOWN: usize = 3;

/// The agents that carry a term over many agents, by their share of its gradient
/// ([`crate::cost::attribution`]: how much of the term's fall moving that agent alone down
/// its gradient would bring).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Carried {
    /// Agents the term reads.
    pub reads: usize,
    /// The agents with the largest shares, largest first, at most [`CARRIERS_SHOWN`].
    pub top: Vec<AgentShare>,
    /// Agents with a share beyond those.
    pub others: usize,
}

/// One agent's share of a term ([`Carried`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct AgentShare {
    /// The agent's id.
    pub agent: i64,
    /// Its share, 0 to 1.
    #[serde(serialize_with = "crate::io::json::f64_explicit")]
    pub share: f64,
}

/// Who carries `term`, evaluated on `scene`'s agents laid out as `layout`, when it is a term
/// over many agents (it reads three or more, or one not in `named`, the ids the script
/// names) and it pulls on any; `None` otherwise.
fn carried(
    term: &crate::cost::TermReport,
    layout: &crate::cost::VarLayout,
    scene: &Scene,
    named: &[i64],
) -> Option<Carried> {
    let at = crate::cost::attribution::attribute(term, layout);
    let id = |i: usize| scene.agents.get(i).map(|a| a.id);
    let many = at.reads.len() >= 3
        || at
            .reads
            .iter()
            .any(|&i| id(i).is_some_and(|a| !named.contains(&a)));
    if !many || at.shares.is_empty() {
        return None;
    }
    let top: Vec<AgentShare> = at
        .shares
        .iter()
        .filter_map(|&(i, share)| {
            Some(AgentShare {
                agent: id(i)?,
                share,
            })
        })
        .take(CARRIERS_SHOWN)
        .collect();
    Some(Carried {
        reads: at.reads.len(),
        others: at.shares.len() - top.len(),
        top,
    })
}

/// One vehicle's implausible motion in a sample.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RealismEvent {
    /// The agent.
    pub agent: i64,
    /// Its role in the checked behaviour, when it has one.
    pub role: Option<String>,
    /// Which violation ([`crate::eval::kinematic::Violation::name`]).
    pub kind: &'static str,
    /// Seconds after the current step.
    pub time: f64,
    /// The offending value in SI units.
    #[serde(serialize_with = "crate::io::json::f64_explicit")]
    pub value: f64,
    /// In words (`reverses at -9.3 m/s at t = 3.9 s`).
    pub text: String,
    /// Whether the request asks this of the agent: a checked behaviour asks it of an agent it
    /// names (`reverse`'s backing up, [`Behavior::allowed_motion`]), or a script allows it
    /// (`allow(a, "reverse")`). Reported, but no fault.
    pub requested: bool,
}

/// One sample's outcome.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SampleOutcome {
    /// Index in the batch.
    pub sample: usize,
    /// Weighted total of every term (realism's included) on the final trajectories.
    #[serde(serialize_with = "crate::io::json::f64_explicit")]
    pub total: f64,
    /// Every term of every script, in script then declaration order, then realism's terms
    /// (script `realism`) when realism guided.
    pub terms: Vec<TermOutcome>,
    /// Each checker's verdict, in [`AttemptSpec::checks`] order.
    pub verdicts: Vec<Verdict>,
    /// Implausible motion of any sampled vehicle (named or not), worst event per kind.
    pub realism: Vec<RealismEvent>,
    /// How far the agents that a script or checker names leave the road, those that do
    /// ([`road_departure`]).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub off_road: Vec<RoadDeparture>,
    /// The motion its scripts allowed (`allow(a, "reverse")`), which its verdicts count as
    /// asked; its rollout carries it for `eval` ([`Rollout::allowed`]).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub allowed: Vec<Allowance>,
}

impl SampleOutcome {
    /// Whether every checker passed it (`None` without checkers).
    pub fn passed(&self) -> Option<bool> {
        (!self.verdicts.is_empty()).then(|| self.verdicts.iter().all(|v| v.passed))
    }

    /// Implausible motion of the given agents (the ones a script names, say), less what the
    /// request asks of them: a checked behaviour or the script's `allow`
    /// ([`RealismEvent::requested`]).
    pub fn implausible<'a>(&'a self, agents: &'a [i64]) -> impl Iterator<Item = &'a RealismEvent> {
        self.realism
            .iter()
            .filter(move |e| !e.requested && agents.contains(&e.agent))
    }
}

/// An attempt's report: settings and per-sample outcomes. Serialises to the `*_costs.json`
/// files that `demo`, `simulate` and `ask` write.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AttemptReport {
    /// The scene.
    pub scenario: String,
    /// The checkers, in [`AttemptSpec::checks`] order.
    pub checks: Vec<CheckSpec>,
    /// The scripts, by name.
    pub scripts: Vec<String>,
    /// The agents the scripts name with `agent(id)`, in first-lookup order.
    pub named: Vec<i64>,
    /// Sampler settings in words: task, guidance, λ and its schedule, steps, seed, loop.
    pub settings: Settings,
    /// Seconds spent sampling.
    pub seconds: f64,
    /// Per sample.
    pub samples: Vec<SampleOutcome>,
    /// Agents the model does not move (types it never saw), as `type id`.
    pub not_sampled: Vec<String>,
    /// CRC-32C of the scene as read ([`scene_crc32c`]): a resumed run tells by it whether the
    /// scene's file changed since these samples were drawn.
    pub scene_crc32c: String,
    /// What validation found worth saying without refusing: terms that can never steer
    /// ([`AttemptSpec::refuse_dead_terms`]), each naming its script, line and term.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

impl AttemptReport {
    /// The agents the checked behaviours name, with their roles (`[(401, "cutter"), ...]`;
    /// a behaviour's lone `vehicle` is named by the behaviour, `off_road`; an agent with two
    /// roles has them joined by `/`): what pictures highlight.
    pub fn roles(&self) -> Vec<(i64, String)> {
        roles(
            self.checks
                .iter()
                .filter_map(|c| Some((Behavior::from_name(c.behaviour)?, &c.params))),
        )
    }
}

/// One checker of an attempt, for reports.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CheckSpec {
    /// The behaviour's name.
    pub behaviour: &'static str,
    /// Its parameters.
    pub params: Params,
}

/// The motion `reports`' scripts allow (`allow(a, "reverse")`), by agent id. `compiled_on` is
/// the scene the scripts were compiled on (their agent indices are its).
fn script_allowances(compiled_on: &Scene, reports: &[CostReport]) -> Vec<Allowance> {
    let mut out = Vec::new();
    for r in reports {
        for &i in &r.may_reverse {
            if let Some(a) = compiled_on.agents.get(i) {
                let x = Allowance {
                    agent: a.id,
                    motion: AllowedMotion::Reverse,
                };
                if !out.contains(&x) {
                    out.push(x);
                }
            }
        }
    }
    out
}

/// Every vehicle's implausible motion in `scene` (worst event per kind), with its role among
/// `roles` and whether the request asks it ([`requested`]).
fn realism_events(
    scene: &Scene,
    checks: &[(Behavior, Params)],
    roles: &[(i64, String)],
    allowed: &[(i64, Violation)],
) -> Vec<RealismEvent> {
    let judged = judge(scene, &KinematicLimits::default());
    let mut realism = Vec::new();
    for (a, j) in scene.agents.iter().zip(&judged) {
        for e in j.iter().flat_map(|j| &j.events) {
            realism.push(RealismEvent {
                agent: a.id,
                role: roles
                    .iter()
                    .find(|(id, _)| *id == a.id)
                    .map(|(_, r)| r.clone()),
                kind: e.kind.name(),
                time: e.time,
                value: e.value,
                text: e.to_string(),
                requested: requested(checks, allowed, a.id, e.kind),
            });
        }
    }
    realism
}

fn roles<'a>(checks: impl Iterator<Item = (Behavior, &'a Params)>) -> Vec<(i64, String)> {
    let mut out: Vec<(i64, String)> = Vec::new();
    for (b, p) in checks {
        for r in b.roles() {
            let Some(id) = p.number(r) else { continue };
            let id = id as i64;
            // "vehicle" says nothing in a picture; the behaviour does.
            let r = &if *r == "vehicle" { b.name() } else { r };
            match out.iter_mut().find(|(a, _)| *a == id) {
                Some((_, have)) if !have.split('/').any(|h| h == *r) => {
                    have.push('/');
                    have.push_str(r);
                }
                Some(_) => {}
                None => out.push((id, r.to_string())),
            }
        }
    }
    out
}

/// The sampler settings of an attempt, for reports.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Settings {
    /// `conditional` or `unconditional`.
    pub task: &'static str,
    /// `denoiser` or `output`.
    pub guidance: &'static str,
    /// Guidance strength.
    pub lambda: f64,
    /// Heun steps.
    pub steps: usize,
    /// Samples.
    pub samples: usize,
    /// Seed of the initial noise.
    pub seed: u64,
    /// Weight of the realism terms (0: off).
    pub realism: f64,
    /// Steps executed per re-plan in closed loop (absent in open loop).
    pub replan: Option<usize>,
}

/// The sampled scenes with their report.
#[derive(Debug, Clone)]
pub struct Attempt {
    /// The samples, as the sampler returned them.
    pub samples: Vec<Sample>,
    /// The same samples drawn unguided (same seed, so the same noise), against which the
    /// verdicts judged the rest of the scene; absent when nothing was guided or checked.
    pub unguided: Option<Vec<Sample>>,
    /// What happened.
    pub report: AttemptReport,
}

impl Attempt {
    /// The sample to show: the first that passes every checker, else the one with the lowest
    /// total cost (the first of equals).
    pub fn best(&self) -> usize {
        let o = &self.report.samples;
        o.iter()
            .position(|s| s.passed() == Some(true))
            .or_else(|| {
                (0..o.len()).min_by(|&a, &b| o[a].total.total_cmp(&o[b].total).then(a.cmp(&b)))
            })
            .unwrap_or(0)
    }

    /// Writes into `dir` (created if needed), each file atomically: `STEM_K.json` per sample
    /// (the rollout `eval --rollouts` reads, with each term's final value),
    /// `unguided/STEM_K.json` per unguided twin (what `eval --unguided` reads, so that `eval`
    /// judges the rest of the scene as these verdicts did) and `STEM_costs.json` (this
    /// report). A stem that cannot name a file (a scenario id read from an untrusted scene,
    /// say) is an error ([`output_stem`]).
    pub fn write(
        &self,
        dir: &Path,
        stem: &str,
        run: Option<&serde_json::Value>,
    ) -> Result<(), IoError> {
        let id = output_stem(stem)?;
        for (k, s) in self.samples.iter().enumerate() {
            let mut r = Rollout::from_scene(&s.scene);
            r.run = run.cloned();
            r.allowed = self.report.samples[k].allowed.clone();
            for t in &self.report.samples[k].terms {
                r.costs.insert(t.term.clone(), t.value);
            }
            r.write(&dir.join(format!("{id}_{k}.json")))?;
        }
        for (k, s) in self.unguided.iter().flatten().enumerate() {
            let mut r = Rollout::from_scene(&s.scene);
            r.run = run.cloned();
            r.write(&dir.join("unguided").join(format!("{id}_{k}.json")))?;
        }
        let text = serde_json::to_string_pretty(&self.report).expect("reports serialise");
        write_atomic(&dir.join(format!("{id}_costs.json")), text.as_bytes())
    }
}

/// The file that says a run left scene `stem` out on purpose (no agents suited to the
/// behaviour it asks for): `STEM_skipped.json`, beside the rollouts and their unguided twins,
/// so that `eval` over the same scene list counts the scene as skipped, as the run did,
/// rather than as a missing rollout.
pub fn skipped_file(dir: &Path, stem: &str) -> std::path::PathBuf {
    dir.join(format!("{stem}_skipped.json"))
}

/// CRC-32C of a scene as read (its map, agents and time grid, as `convert` writes them to
/// YAML), 8 hex digits: the same whatever format or file it was read from.
pub fn scene_crc32c(scene: &Scene) -> String {
    super::provenance::text_crc32c(crate::io::yaml::yaml_document(scene).as_bytes())
}

/// A resumed run's scene whose outputs were drawn from another version of it.
#[derive(Debug, thiserror::Error)]
#[error(
    "{stem}: the scene is not the one its outputs in {dir} were sampled from (scene checksum \
     {then} then, {now} now: its file changed since); simulate it into another -o, or remove \
     {file} there to sample it again"
)]
pub struct SceneChanged {
    /// The scene's output stem.
    pub stem: String,
    /// The run directory.
    pub dir: String,
    /// The checksum its cost report records.
    pub then: String,
    /// The scene's checksum now.
    pub now: String,
    /// The file in `dir` that records the checksum then (the cost report, or the file that
    /// says the scene was skipped), to remove for sampling the scene again.
    pub file: String,
}

/// Whether `dir` holds scene `stem` finished by a run of `samples` samples, for `simulate
/// --resume`: every sample's rollout reads back as one of that scenario, and the cost report
/// and the picture (written last) are there; or the scene was left out on purpose
/// ([`skipped_file`]). Outputs are written atomically, so a killed run leaves none
/// half-written; one damaged since (truncated by a full disk elsewhere, edited) made the scene
/// "already complete" for good, and `eval` failed on it later. Finished outputs of another
/// version of the scene (its file edited since) are an error: they were taken for this
/// scene's, and the table over them was of a scene no longer there. Reports written before
/// they recorded the scene's checksum are taken as they were.
pub fn outputs_complete(
    dir: &Path,
    stem: &str,
    scene: &Scene,
    samples: usize,
) -> Result<bool, SceneChanged> {
    // Ok(true) where the scene is the one the record was written for (or the record, from
    // before checksums were kept, says nothing).
    let judged = |record: &Path, cap: u64, what: &str, file: String| {
        let then = crate::io::read_regular_text(record, cap, what)
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
            .and_then(|v| v["scene_crc32c"].as_str().map(str::to_string));
        let now = scene_crc32c(scene);
        match then {
            Some(then) if then != now => Err(SceneChanged {
                stem: stem.into(),
                dir: dir.display().to_string(),
                then,
                now,
                file,
            }),
            _ => Ok(true),
        }
    };
    let skipped = skipped_file(dir, stem);
    if skipped.is_file() {
        // A scene skipped then and edited since (agents suited to the behaviour added) was
        // taken as skipped for good: the marker records the checksum of the scene it judged.
        return judged(
            &skipped,
            1 << 20,
            "a skipped-scene file",
            format!("{stem}_skipped.json and unguided/{stem}_skipped.json"),
        );
    }
    let rollouts_read = (0..samples).all(|k| {
        crate::io::rollout::Rollout::read(&dir.join(format!("{stem}_{k}.json")))
            .is_ok_and(|r| r.scene_id == scene.meta.scenario_id)
    });
    let costs = dir.join(format!("{stem}_costs.json"));
    if !(rollouts_read && costs.is_file() && dir.join(format!("{stem}_0.gif")).is_file()) {
        return Ok(false);
    }
    judged(
        &costs,
        64 << 20,
        "a cost report",
        format!("{stem}_costs.json"),
    )
}

/// Writes [`skipped_file`] into `dir` and, where `twins` is true, into `dir/unguided`, with the
/// reason and `scene`'s checksum ([`scene_crc32c`]); atomically, as every output.
pub fn write_skipped(
    dir: &Path,
    stem: &str,
    scene: &Scene,
    reason: &str,
    twins: bool,
) -> Result<(), IoError> {
    let stem = output_stem(stem)?;
    let text = serde_json::to_string_pretty(&serde_json::json!({
        "scenario_id": stem,
        "skipped": reason,
        // What `simulate --resume` compares the scene with ([`outputs_complete`]).
        "scene_crc32c": scene_crc32c(scene),
    }))
    .expect("a JSON object serialises");
    let mut dirs = vec![dir.to_path_buf()];
    if twins {
        dirs.push(dir.join("unguided"));
    }
    for d in dirs {
        std::fs::create_dir_all(&d).map_err(|e| IoError::read(&d, e))?;
        write_atomic(&skipped_file(&d, stem), text.as_bytes())?;
    }
    Ok(())
}

/// Runs `spec` on `raw` (a scene as read): every script is compiled and validated on the scene
/// cut to the model's horizon before anything is sampled, then the samples are scored and
/// judged.
pub fn attempt(
    trained: &Trained,
    raw: &Scene,
    spec: &AttemptSpec,
) -> Result<Attempt, AttemptError> {
    attempt_until(trained, raw, spec, &AtomicBool::new(false))
}

/// [`attempt`] that another thread may stop by setting `stop` (Python's Ctrl-C): sampling,
/// the unguided twins' included, ends within one denoising step or polish iteration with
/// [`SampleError::Stopped`].
pub fn attempt_until(
    trained: &Trained,
    raw: &Scene,
    spec: &AttemptSpec,
    stop: &AtomicBool,
) -> Result<Attempt, AttemptError> {
    let cfg = &spec.cfg;
    cfg.validate().map_err(SampleError::Settings)?;
    let scene = prepare_for(raw, sampled_horizon(trained, cfg)?)?;
    let shared = Rc::new(scene.clone());
    let sources: Vec<&str> = spec.scripts.iter().map(|t| t.source.as_str()).collect();
    for s in &spec.scripts {
        check_params(&sources, &s.params).map_err(AttemptError::Script)?;
    }
    let mut warnings = Vec::new();
    let scripts = spec
        .scripts
        .iter()
        .map(|s| {
            let c = CostScript::compile(&s.source, &s.name, shared.clone(), &s.params, &s.limits)?;
            let checked = c.validate()?;
            // Sampling evaluates a script hundreds of times and shows none of its prints: a
            // user debugging with `print` under `simulate` saw nothing and no word why.
            if !checked.prints.is_empty() {
                warnings.push(format!(
                    "script {} prints: sampling does not show what it prints; `drivescript cost` \
                     on the scene with this script does",
                    s.name
                ));
            }
            let dead = c.dead_terms();
            if spec.refuse_dead_terms {
                if let Some(first) = dead.first() {
                    return Err(match first.to_error() {
                        CostError::Term {
                            script,
                            term,
                            line,
                            message,
                        } if dead.len() > 1 => CostError::Term {
                            script,
                            term,
                            line,
                            message: format!(
                                "{message}; so are {}",
                                dead[1..]
                                    .iter()
                                    .map(|d| format!("{:?} (line {})", d.term, d.line))
                                    .collect::<Vec<_>>()
                                    .join(", ")
                            ),
                        },
                        e => e,
                    });
                }
            }
            warnings.extend(dead.iter().map(|d| d.to_string()));
            Ok(c)
        })
        .collect::<Result<Vec<_>, CostError>>()
        .map_err(AttemptError::Script)?;
    let t0 = Instant::now();
    let samples = match spec.replan {
        Some(every) => closed_loop_until(trained, raw, &spec.scripts, cfg, every, stop)?,
        None => sample_until(trained, &scene, &scripts, cfg, stop)?,
    };
    let seconds = t0.elapsed().as_secs_f64();
    // The rest of the scene is judged against the same samples drawn unguided (same seed, so
    // the same noise): a sample whose guidance wrecked the cars it does not name has not shown
    // the behaviour (`eval::collateral`).
    let twins = if spec.checks.is_empty() || spec.scripts.is_empty() {
        None
    } else {
        Some(match spec.replan {
            Some(every) => closed_loop_until(trained, raw, &[], cfg, every, stop)?,
            None => sample_until(trained, &scene, &[], cfg, stop)?,
        })
    };
    let roles = roles(spec.checks.iter().map(|(b, p)| (*b, p)));
    let mut outcomes = Vec::with_capacity(samples.len());
    for (k, s) in samples.iter().enumerate() {
        let mut terms = Vec::new();
        let mut total = 0.0;
        for (i, rep) in s.reports.iter().enumerate() {
            total += rep.total;
            for t in &rep.terms {
                terms.push(TermOutcome {
                    script: spec.scripts[i].name.clone(),
                    term: t.name.clone(),
                    line: t.line,
                    weight: t.weight,
                    initial: s
                        .initial_reports
                        .get(i)
                        .and_then(|r| r.term(&t.name))
                        .map(|x| x.value),
                    value: t.value,
                    tolerance: t.tolerance,
                    carried_by: carried(t, &rep.layout, &scene, &rep.named),
                });
            }
        }
        if let Some((first, fin)) = &s.realism {
            total += fin.total;
            for t in &fin.terms {
                terms.push(TermOutcome {
                    script: "realism".into(),
                    term: t.name.clone(),
                    line: 0,
                    weight: t.weight,
                    initial: first.term(&t.name).map(|x| x.value),
                    value: t.value,
                    tolerance: None,
                    carried_by: None,
                });
            }
        }
        let twin = twins.as_ref().and_then(|t| t.get(k));
        let allowed = script_allowances(&scene, &s.reports);
        let kinds = asked::kinds(&allowed);
        let verdicts = verdicts(&spec.checks, &s.scene, twin.map(|u| &u.scene), &kinds)?;
        let realism = realism_events(&s.scene, &spec.checks, &roles, &kinds);
        let off_road = s
            .scene
            .agents
            .iter()
            .filter(|a| {
                roles.iter().any(|(id, _)| *id == a.id)
                    || s.reports.iter().any(|r| r.named.contains(&a.id))
            })
            .filter_map(|a| road_departure(&s.scene, a))
            .collect();
        outcomes.push(SampleOutcome {
            sample: k,
            total,
            terms,
            verdicts,
            realism,
            off_road,
            allowed,
        });
    }
    let report = AttemptReport {
        scenario: raw.meta.scenario_id.clone(),
        checks: spec
            .checks
            .iter()
            .map(|(b, p)| CheckSpec {
                behaviour: b.name(),
                params: p.clone(),
            })
            .collect(),
        scripts: spec.scripts.iter().map(|s| s.name.clone()).collect(),
        named: {
            let mut named: Vec<i64> = Vec::new();
            for r in samples.iter().flat_map(|s| &s.reports) {
                for id in &r.named {
                    if !named.contains(id) {
                        named.push(*id);
                    }
                }
            }
            named
        },
        settings: Settings {
            task: match cfg.task {
                Task::Conditional => "conditional",
                Task::Unconditional => "unconditional",
            },
            guidance: cfg.guidance.name(),
            lambda: cfg.lambda,
            steps: cfg.steps,
            samples: cfg.samples,
            seed: cfg.seed,
            realism: cfg.realism.weight,
            replan: spec.replan,
        },
        seconds,
        not_sampled: samples
            .first()
            .map(|s| {
                s.fixed
                    .iter()
                    .map(|(a, t)| format!("{} {a}", t.name()))
                    .collect()
            })
            .unwrap_or_default(),
        samples: outcomes,
        warnings,
        scene_crc32c: scene_crc32c(raw),
    };
    Ok(Attempt {
        samples,
        unguided: twins,
        report,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cost::Limits;
    use crate::eval::check_against_unguided;
    use crate::io::{load_scene, LoadOptions};
    use crate::sample::{closed_loop, sample};
    use crate::train::train;
    use std::path::Path;

    fn root() -> &'static Path {
        Path::new(env!("CARGO_MANIFEST_DIR"))
    }

    fn setup() -> (Trained, Scene) {
        let dir = root().join("scripts/scenes");
        let scenes: Vec<Scene> = ["highway.yaml", "highway_cut_in.yaml"]
            .iter()
            .map(|f| load_scene(&dir.join(f), 0, &LoadOptions::default()).unwrap())
            .collect();
        let cfg = crate::train::trainer::tiny_config(20, 3, 40);
        let t = train(&scenes, cfg, None, None, |_, _, _| {}).unwrap();
        (t, scenes[1].clone())
    }

    fn cut_in(params: &Params) -> ScriptSpec {
        let src = std::fs::read_to_string(root().join("scripts/cut_in.rhai")).unwrap();
        ScriptSpec::new(src, "scripts/cut_in.rhai", params.clone())
    }

    fn cfg() -> SampleConfig {
        SampleConfig {
            steps: 8,
            samples: 2,
            ..SampleConfig::default()
        }
    }

    #[test]
    fn an_attempt_reports_terms_verdicts_and_realism_per_sample_and_writes_them() {
        let (t, scene) = setup();
        let p = Params::numbers(&[("cutter", 2.0), ("victim", 1.0)]);
        let spec = AttemptSpec {
            scripts: vec![cut_in(&p)],
            checks: vec![(Behavior::CutIn, p.clone())],
            cfg: cfg(),
            replan: None,
            refuse_dead_terms: true,
        };
        let a = attempt(&t, &scene, &spec).unwrap();
        let r = &a.report;
        assert_eq!((a.samples.len(), r.samples.len()), (2, 2));
        assert_eq!(r.checks[0].behaviour, "cut_in");
        assert_eq!(r.named, vec![2, 1]);
        assert_eq!(r.roles(), vec![(2, "cutter".into()), (1, "victim".into())]);
        // The same samples drawn unguided, drawn here independently of the attempt.
        let prepared = crate::sample::prepare(&scene, &t).unwrap();
        let twins = sample(&t, &prepared, &[], &cfg()).unwrap();
        for (k, o) in r.samples.iter().enumerate() {
            // The totals and verdicts are those of the scored scenes, not copies of one.
            let rep = &a.samples[k].reports[0];
            assert_eq!(o.total, rep.total);
            assert_eq!(o.terms.len(), rep.terms.len());
            for (x, y) in o.terms.iter().zip(&rep.terms) {
                assert_eq!(
                    (x.term.as_str(), x.value, x.weight),
                    (y.name.as_str(), y.value, y.weight)
                );
                assert!(x.initial.is_some(), "{} has no first estimate", x.term);
            }
            // Judged with the rest of the scene against the same sample drawn unguided.
            let v = check_against_unguided(
                Behavior::CutIn,
                &a.samples[k].scene,
                &twins[k].scene,
                &p,
                &[],
            )
            .unwrap();
            assert!(v.collateral.is_some());
            assert_eq!(o.verdicts, vec![v.clone()]);
            assert_eq!(o.passed(), Some(v.passed));
            let judged = judge(&a.samples[k].scene, &KinematicLimits::default());
            let events: usize = judged.iter().flatten().map(|j| j.events.len()).sum();
            assert_eq!(o.realism.len(), events);
            for e in &o.realism {
                let role = match e.agent {
                    2 => Some("cutter"),
                    1 => Some("victim"),
                    _ => None,
                };
                assert_eq!(e.role.as_deref(), role);
            }
        }
        let best = a.best();
        match r.samples.iter().position(|o| o.passed() == Some(true)) {
            Some(k) => assert_eq!(best, k),
            None => assert!(r.samples.iter().all(|o| o.total >= r.samples[best].total)),
        }
        let dir = tempfile::tempdir().unwrap();
        a.write(dir.path(), "run", None).unwrap();
        for f in [
            "run_0.json",
            "run_1.json",
            "unguided/run_0.json",
            "unguided/run_1.json",
            "run_costs.json",
        ] {
            assert!(dir.path().join(f).exists(), "{f} missing");
        }
        // The twins written are those the verdicts were judged against.
        let written = Rollout::read(&dir.path().join("unguided/run_1.json"))
            .unwrap()
            .apply_to(&prepared, Path::new("unguided/run_1.json"))
            .unwrap();
        // Read back, they move as they did in memory: the same positions, and velocities
        // from them by the same rule, up to the last step.
        let c = scene.meta.current_step;
        for (w, u) in written.agents.iter().zip(&twins[1].scene.agents) {
            for t in c + 1..u.states.len() {
                let (p, q) = (w.states[t], u.states[t]);
                assert_eq!(p.valid, q.valid);
                let close = |a: f64, b: f64| (a - b).abs() < 1e-3;
                assert!(
                    close(p.x, q.x) && close(p.y, q.y) && close(p.vx, q.vx) && close(p.vy, q.vy),
                    "agent {} step {t}: {p:?} vs {q:?}",
                    w.id
                );
            }
        }
        let json: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.path().join("run_costs.json")).unwrap(),
        )
        .unwrap();
        assert_eq!(json["checks"][0]["params"]["cutter"], 2);
        assert_eq!(
            json["samples"][1]["terms"][0]["final"],
            r.samples[1].terms[0].value
        );
        let e = a
            .write(dir.path(), "../escape", None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("cannot name an output file"), "{e}");
        // With realism on, its terms follow the script's and count in the total.
        let mut spec = spec;
        spec.cfg.realism.weight = 2.0;
        let a = attempt(&t, &scene, &spec).unwrap();
        for (k, o) in a.report.samples.iter().enumerate() {
            let real: Vec<&TermOutcome> =
                o.terms.iter().filter(|t| t.script == "realism").collect();
            let names: Vec<&str> = real.iter().map(|t| t.term.as_str()).collect();
            assert_eq!(names, crate::cost::REALISM_TERMS);
            assert!(real.iter().all(|t| t.weight == 2.0 && t.initial.is_some()));
            let (_, fin) = a.samples[k].realism.as_ref().unwrap();
            assert_eq!(o.total, a.samples[k].reports[0].total + fin.total);
        }
    }

    #[test]
    fn what_a_checked_behaviour_asks_of_its_agents_is_not_implausible() {
        let checks = vec![
            (Behavior::Reverse, Params::numbers(&[("vehicle", 3.0)])),
            (
                Behavior::CutIn,
                Params::numbers(&[("cutter", 2.0), ("victim", 1.0)]),
            ),
        ];
        assert!(requested(&checks, &[], 3, Violation::Reverse));
        assert!(!requested(&checks, &[], 3, Violation::Sprint));
        assert!(
            !requested(&checks, &[], 1, Violation::Reverse),
            "a victim reversing"
        );
        assert!(
            !requested(&checks, &[], 4, Violation::Reverse),
            "a car not named"
        );
        let event = |agent, requested| RealismEvent {
            agent,
            role: None,
            kind: Violation::Reverse.name(),
            time: 1.0,
            value: -2.0,
            text: "reverses".into(),
            requested,
        };
        let o = SampleOutcome {
            sample: 0,
            total: 0.0,
            terms: Vec::new(),
            verdicts: Vec::new(),
            realism: vec![event(3, true), event(1, false)],
            off_road: Vec::new(),
            allowed: Vec::new(),
        };
        let flagged: Vec<i64> = o.implausible(&[1, 3]).map(|e| e.agent).collect();
        assert_eq!(flagged, vec![1]);
    }

    #[test]
    fn what_a_script_allows_counts_as_requested_and_not_implausible() {
        // Vehicle 4 of highway_stop backs up at 3 m/s in its recorded future; reverse.rhai
        // allows it with allow(a, "reverse"), and no checker asks for reversing.
        let scene = load_scene(
            &root().join("scripts/scenes/highway_stop.yaml"),
            0,
            &LoadOptions::default(),
        )
        .unwrap();
        let src = std::fs::read_to_string(root().join("scripts/reverse.rhai")).unwrap();
        let script = CostScript::compile(
            &src,
            "reverse.rhai",
            Rc::new(scene.clone()),
            &Params::numbers(&[("vehicle", 4.0)]),
            &Limits::default(),
        )
        .unwrap();
        let report = script
            .evaluate(&crate::cost::Trajectories::recorded(&scene))
            .unwrap();
        let allowed = script_allowances(&scene, &[report]);
        assert_eq!(
            allowed,
            vec![Allowance {
                agent: 4,
                motion: AllowedMotion::Reverse
            }]
        );
        let allowed = asked::kinds(&allowed);
        assert_eq!(allowed, vec![(4, Violation::Reverse)]);
        let checks = vec![(Behavior::SpeedLimit, Params::numbers(&[("vehicle", 1.0)]))];
        let outcome = |realism| SampleOutcome {
            sample: 0,
            total: 0.0,
            terms: Vec::new(),
            verdicts: Vec::new(),
            realism,
            off_road: Vec::new(),
            allowed: Vec::new(),
        };
        // Without the allowance the backing up is implausible motion of a named agent ...
        let bare = outcome(realism_events(&scene, &checks, &[], &[]));
        assert!(
            bare.implausible(&[4]).any(|e| e.kind == "reverse"),
            "{:?}",
            bare.realism
        );
        // ... with it, reported but requested, so no fault.
        let allowed = outcome(realism_events(&scene, &checks, &[], &allowed));
        let backing: Vec<&RealismEvent> = allowed
            .realism
            .iter()
            .filter(|e| e.agent == 4 && e.kind == "reverse")
            .collect();
        assert!(!backing.is_empty() && backing.iter().all(|e| e.requested));
        assert!(
            allowed.implausible(&[4]).all(|e| e.kind != "reverse"),
            "{:?}",
            allowed.realism
        );
    }

    #[test]
    fn a_term_over_many_agents_is_carried_by_the_ones_it_pulls_and_a_pair_term_is_not_attributed() {
        // Highway: vehicle 2 driven 5 m behind vehicle 1, in its lane: the one overlapping pair.
        let mut scene = load_scene(
            &root().join("scripts/scenes/highway.yaml"),
            0,
            &LoadOptions::default(),
        )
        .unwrap();
        let c = scene.meta.current_step;
        let one = scene.agents.iter().find(|a| a.id == 1).unwrap().clone();
        let two = scene.agents.iter_mut().find(|a| a.id == 2).unwrap();
        for t in c + 1..two.states.len() {
            two.states[t] = one.states[t];
            two.states[t].x -= 5.0;
        }
        let src = "let a = agent(1);\nlet b = agent(2);\n\
                   term(\"apart\", no_collision_cost(vehicles(), 1.0));\n\
                   term(\"pair\", relu(20.0 - distance(a, b)).mean());\n";
        let script = CostScript::compile(
            src,
            "t.rhai",
            Rc::new(scene.clone()),
            &Params::default(),
            &Limits::default(),
        )
        .unwrap();
        let r = script
            .evaluate(&crate::cost::Trajectories::recorded(&scene))
            .unwrap();
        let apart = carried(r.term("apart").unwrap(), &r.layout, &scene, &r.named).unwrap();
        assert_eq!((apart.reads, apart.others), (4, 0));
        let mut ids: Vec<i64> = apart.top.iter().map(|a| a.agent).collect();
        ids.sort();
        assert_eq!(ids, vec![1, 2]);
        // Two agents, both named: the motion tables already show them.
        assert_eq!(
            carried(r.term("pair").unwrap(), &r.layout, &scene, &r.named),
            None
        );
    }

    #[test]
    fn a_checker_does_not_fail_a_car_for_the_reversing_its_script_allows() {
        // "Vehicle 4 reverses and leaves the road" (issue 31: 2976 came back three times as
        // "reverses at -1.4 m/s"). Vehicle 4 of highway_stop backs up at 3 m/s; here it also
        // drifts 4 m right, past the road's edge. reverse.rhai allows it to reverse.
        let mut scene = load_scene(
            &root().join("scripts/scenes/highway_stop.yaml"),
            0,
            &LoadOptions::default(),
        )
        .unwrap();
        let c = scene.meta.current_step;
        let n = scene.num_steps();
        let a = scene.agents.iter_mut().find(|a| a.id == 4).unwrap();
        for t in c + 1..n {
            a.states[t].y -= 4.0 * (t - c) as f64 / (n - 1 - c) as f64;
        }
        let allowed = vec![(4, Violation::Reverse)];
        let off_road = vec![(Behavior::OffRoad, Params::numbers(&[("vehicle", 4.0)]))];
        // Without the allowance the off_road checker sees it leave the road, and fails it for
        // reversing.
        let bare = verdicts(&off_road, &scene, None, &[]).unwrap();
        assert!(bare[0].achieved && !bare[0].passed, "{:?}", bare[0]);
        assert!(
            bare[0].reason.contains("vehicle 4 reverses"),
            "{}",
            bare[0].reason
        );
        // With it, the reversing was asked for: the verdict passes.
        let v = verdicts(&off_road, &scene, None, &allowed).unwrap();
        assert!(v[0].passed && v[0].violations.is_empty(), "{:?}", v[0]);
        // Judged against an unguided twin, as an agent the checker does not name, its
        // allowed reversing is no collateral implausibility either (in the twin it backs up
        // on the road).
        let twin = load_scene(
            &root().join("scripts/scenes/highway_stop.yaml"),
            0,
            &LoadOptions::default(),
        )
        .unwrap();
        let speed = vec![(
            Behavior::SpeedLimit,
            Params::numbers(&[("vehicle", 2.0), ("limit", 40.0)]),
        )];
        let implausible = |allowed: &[(i64, Violation)]| {
            let v = verdicts(&speed, &scene, Some(&twin), allowed).unwrap();
            let c = v[0].collateral.unwrap();
            (c.implausible, c.implausible_unguided)
        };
        assert_eq!(implausible(&[]), (1, 1));
        assert_eq!(implausible(&allowed), (0, 0));
    }

    #[test]
    fn roles_of_several_checkers_join_and_name_lone_vehicles_by_behaviour() {
        let cut = Params::numbers(&[("cutter", 2.0), ("victim", 1.0)]);
        let off = Params::numbers(&[("vehicle", 2.0)]);
        let stop = Params::numbers(&[("vehicle", 3.0)]);
        let got = roles(
            [
                (Behavior::CutIn, &cut),
                (Behavior::OffRoad, &off),
                (Behavior::Stop, &stop),
            ]
            .into_iter(),
        );
        assert_eq!(
            got,
            vec![
                (2, "cutter/off_road".to_string()),
                (1, "victim".to_string()),
                (3, "stop".to_string())
            ]
        );
    }

    #[test]
    fn scripts_are_validated_before_sampling_and_closed_loop_keeps_their_limits() {
        let (t, scene) = setup();
        // An agent the scene lacks: an error naming the script, and nothing sampled.
        let spec = AttemptSpec {
            scripts: vec![cut_in(&Params::numbers(&[
                ("cutter", 2.0),
                ("victim", 77.0),
            ]))],
            checks: Vec::new(),
            cfg: cfg(),
            replan: Some(5),
            refuse_dead_terms: true,
        };
        let e = attempt(&t, &scene, &spec).unwrap_err();
        assert!(matches!(e, AttemptError::Script(_)), "{e}");
        assert!(e.to_string().contains("scripts/cut_in.rhai"), "{e}");
        // A term no probe moves: refused before sampling where the caller refuses it (the LLM
        // loop), else sampled and reported, naming script, line and term. A guard that is 0 on
        // the log (no collision there) but wakes when cars meet is neither.
        let dead = ScriptSpec::new(
            "term(\"guard\", no_collision_cost(vehicles(), 0.5));\n\
             term(\"never\", relu(agent(1).speed - 60.0).mean());\n\
             term(\"nil\", 0.0 * agent(2).x.last());\n"
                .to_string(),
            "dead.rhai",
            Params::default(),
        );
        let mut spec = AttemptSpec {
            scripts: vec![dead],
            checks: Vec::new(),
            cfg: cfg(),
            replan: None,
            refuse_dead_terms: true,
        };
        let e = attempt(&t, &scene, &spec).unwrap_err().to_string();
        assert!(
            e.starts_with("dead.rhai:2: term \"never\": it is 0 with a zero gradient")
                && e.contains("can never steer sampling")
                && e.contains("so are \"nil\" (line 3)")
                && !e.contains("guard"),
            "{e}"
        );
        spec.refuse_dead_terms = false;
        let a = attempt(&t, &scene, &spec).unwrap();
        let w = &a.report.warnings;
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(
            w[0].starts_with("dead.rhai:2: term \"never\"")
                && w[1].starts_with("dead.rhai:3: term \"nil\""),
            "{w:?}"
        );
        let json = serde_json::to_value(&a.report).unwrap();
        assert_eq!(json["warnings"][1], w[1].as_str());
        // Closed loop compiles with the script's own limits, not the defaults.
        let mut s = cut_in(&Params::numbers(&[("cutter", 2.0), ("victim", 1.0)]));
        s.limits = Limits {
            max_operations: 50,
            ..Limits::default()
        };
        let e = closed_loop(&t, &scene, &[s], &cfg(), 5)
            .unwrap_err()
            .to_string();
        assert!(e.contains("limit exceeded: operations (max 50)"), "{e}");
    }
}
