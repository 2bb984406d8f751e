//! The loop's state machine over a run directory.
//!
//! Every exchange with the model is a numbered `round_N/` holding `prompt.md` (the messages
//! sent, readable), `messages.json`, `reply.md`, and, as they happen, `script.rhai`,
//! `validation.txt` (or `budget.txt`, for a script that ran past `--script-budget`, or
//! `sampling.txt`, for one that failed while being sampled), the rollouts and cost report of the samples (`SCENARIO_K.json`,
//! `SCENARIO_costs.json`, named as `simulate` names them so that `eval --rollouts round_N`
//! scores them, and the unguided twins in `unguided/`), `feedback.md` and `sample.gif`. `state.json` is rewritten atomically
//! after every step, so a run stopped anywhere (a manual round waiting for its reply, a killed
//! process) continues from it with [`Session::resume`]; `transcript.json` records the
//! backend, the URL without credentials, every request body, token usage, latency, retries
//! and the time of every phase. When the loop ends, `final.rhai`, `final.gif` and `report.md`
//! are written next to them.

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use super::client::{redact_url, HttpClient, Message};
use super::feedback::{feedback, Acceptance};
use super::fit::{fit_conversation, fit_first, FirstTooLarge, Fitted};
use super::prompt::{PromptOptions, Prompts};
use super::reply::{parse_reply, Reply};
use super::rules::{self, Event, Tuning};
use super::LlmError;
use crate::cost::{Limits, ParamValue, Params};
use crate::eval::behaviors::Behavior;
use crate::io::{output_stem, write_atomic};
use crate::render::{render_gif, RenderOptions};
use crate::sample::{
    attempt, Attempt, AttemptError, AttemptSpec, SampleConfig, SampleError, ScriptSpec,
};
use crate::scene::description::{describe, DescribeOptions};
use crate::scene::Scene;
use crate::train::Trained;

/// Who answers.
#[derive(Clone)]
pub enum Backend {
    /// An OpenAI-compatible server.
    Http(HttpClient),
    /// A person: each round's prompt is written to a file and the run stops until the reply
    /// is saved next to it.
    Manual,
    /// The rules planner over `scripts/`.
    Rules,
    /// A recorded run's replies, in order (`ask --replay`): no server is asked.
    Replay(std::sync::Arc<super::replay::Recorded>),
}

impl Backend {
    /// `http`, `manual` or `rules`, as `--llm` and state.json name it.
    pub fn name(&self) -> &'static str {
        match self {
            Backend::Http(_) => "http",
            Backend::Manual => "manual",
            Backend::Rules => "rules",
            Backend::Replay(_) => "replay",
        }
    }

    /// The backend sending what the run with `config` recorded: its seed, and where it states
    /// a context window, the reply's share of it as the most tokens a reply may take. One
    /// path for a run started and a run taken up again (`--resume`, `--continue`, a batch's
    /// pair run again), whose flags (`--seed` at its default, `--max-tokens`) do not say
    /// what the run was started with; the sampler reads the same recorded seed.
    fn for_run(self, config: &SessionConfig) -> Self {
        match self {
            Backend::Http(c) => {
                let c = c.with_seed(Some(config.seed));
                Backend::Http(match config.context {
                    Some(w) => c.with_max_tokens(u32::try_from(w.reply).unwrap_or(u32::MAX)),
                    None => c,
                })
            }
            other => other,
        }
    }
}

/// Settings of a session.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SessionConfig {
    /// Refinement rounds after the first sampling (0: the first script is final).
    pub rounds: usize,
    /// Unusable replies, failed validations and rejected ACCEPTs allowed in a row before the
    /// run gives up.
    pub fixes: usize,
    /// Prompt options (the paper's ablations).
    pub prompt: PromptOptions,
    /// Largest unweighted script term a sample may keep and still meet the request.
    pub tolerance: f64,
    /// Most agents in the scene summary (the request's are always listed).
    pub max_agents: usize,
    /// Samples per round.
    pub samples: usize,
    /// Seed of the initial noise.
    pub seed: u64,
    /// Guidance strength; `None`: the checkpoint's ([`crate::train::CheckpointMeta::behaviour_lambda`]),
    /// which [`Session::start`] writes here, so that a resumed run keeps it.
    #[serde(default)]
    pub lambda: Option<f64>,
    /// Weight of the realism terms.
    pub realism: f64,
    /// Where the guidance gradient is taken (`--guidance`). Runs recorded before it was one
    /// setting stored `through_denoiser: true|false`, read as denoiser / output.
    #[serde(
        alias = "through_denoiser",
        deserialize_with = "guidance_or_legacy_flag",
        default = "default_guidance"
    )]
    pub guidance: crate::sample::Guidance,
    /// Descent steps on the guidance cost after the last denoising step
    /// ([`SampleConfig::polish`]); runs recorded before it existed had none.
    #[serde(default)]
    pub polish: usize,
    /// Seconds the cost script may take over one round's sampling, all its evaluations
    /// together ([`SampleConfig::script_budget`]); runs recorded before it existed get the
    /// default.
    #[serde(default = "default_script_budget")]
    pub script_budget: f64,
    /// Closed loop: steps executed per re-plan.
    pub replan: Option<usize>,
    /// The model's context window (`--context`): every request is fitted to it
    /// ([`super::fit`]); `None` sends the whole conversation.
    #[serde(default)]
    pub context: Option<super::fit::Window>,
}

/// The most refinement rounds a run may have (`--rounds`).
pub const MAX_ROUNDS: usize = 20;
/// The most unusable replies in a row a run may allow (`--fixes`).
pub const MAX_FIXES: usize = 20;
/// The most agents a scene summary may list (`--max-agents`).
pub const MAX_AGENTS: usize = 1000;

/// The largest tolerance (`--tolerance`) on an unweighted script term (0 where a sample meets
/// the request; the default tolerance is 0.05): `--tolerance 1e308` was taken, and any sample
/// met any request.
pub const MAX_TOLERANCE: f64 = 1000.0;

impl Default for SessionConfig {
    fn default() -> Self {
        Self {
            rounds: 3,
            fixes: 3,
            prompt: PromptOptions::default(),
            tolerance: Acceptance::default().tolerance,
            max_agents: 30,
            samples: 4,
            seed: 1,
            lambda: None,
            realism: crate::sample::REALISM_WEIGHT,
            guidance: crate::sample::DEFAULT_GUIDANCE,
            polish: crate::sample::POLISH_STEPS,
            script_budget: default_script_budget(),
            replan: None,
            context: None,
        }
    }
}

impl SessionConfig {
    /// Checks the loop's settings ([`SessionConfig::problem`]): done before a run writes
    /// anything, so that a bad setting does not fail after the first reply, with the run
    /// directory (or the demo's previous run) already replaced.
    pub fn validate(&self) -> Result<(), LlmError> {
        if let Some(m) = self.loop_problem() {
            return Err(LlmError::Setup(format!("session settings: {m}")));
        }
        self.sample_config().validate().map_err(|e| {
            LlmError::Attempt(crate::sample::AttemptError::Sample(
                crate::sample::SampleError::Settings(e),
            ))
        })
    }

    /// The first setting out of its range, named with its range: the loop's own (the ranges
    /// `ask`'s flags take) and the sampler's ([`SampleConfig::validate`]). `--resume` reads
    /// them back from `state.json`, where nothing but this check stands between an edited
    /// number and a huge allocation or a loop that never ends.
    pub fn problem(&self) -> Option<String> {
        self.loop_problem()
            .or_else(|| self.sample_config().validate().err())
    }

    fn loop_problem(&self) -> Option<String> {
        let range = |name: &str, v: usize, lo: usize, hi: usize| {
            (!(lo..=hi).contains(&v)).then(|| format!("{name} = {v}: must be {lo} to {hi}"))
        };
        range("rounds", self.rounds, 0, MAX_ROUNDS)
            .or_else(|| range("fixes", self.fixes, 0, MAX_FIXES))
            .or_else(|| range("max_agents", self.max_agents, 1, MAX_AGENTS))
            .or_else(|| {
                (!(self.tolerance.is_finite() && (0.0..=MAX_TOLERANCE).contains(&self.tolerance)))
                    .then(|| {
                        format!(
                            "tolerance = {}: must be finite and not negative, at most \
                             {MAX_TOLERANCE}",
                            crate::geom::num(self.tolerance)
                        )
                    })
            })
            .or_else(|| {
                let max = crate::sample::MAX_SCRIPT_BUDGET.as_secs_f64();
                (!(self.script_budget > 0.0 && self.script_budget <= max)).then(|| {
                    // In a few characters: an edited 1e308 was said in 309 digits.
                    format!(
                        "script_budget = {} s: must be more than 0 and at most {max} s",
                        crate::geom::num(self.script_budget)
                    )
                })
            })
            .or_else(|| {
                self.replan
                    .and_then(|r| range("replan", r, 1, crate::io::MAX_STEPS))
            })
            .or_else(|| {
                self.context.and_then(|w| {
                    (!(super::fit::MIN_CONTEXT..=super::fit::MAX_CONTEXT).contains(&w.tokens)
                        || w.reply >= w.tokens)
                        .then(|| {
                            format!(
                                "context = {} tokens with {} for the reply: must be {} to {} \
                                 tokens, the reply's share less than the whole",
                                w.tokens,
                                w.reply,
                                super::fit::MIN_CONTEXT,
                                super::fit::MAX_CONTEXT
                            )
                        })
                })
            })
    }

    /// These settings with what they leave to the checkpoint filled in from `trained` (the
    /// guidance strength): what a run stores, and what a batch compares with a run it goes on.
    pub fn resolved(&self, trained: &Trained) -> SessionConfig {
        let mut c = self.clone();
        c.lambda.get_or_insert(trained.meta.behaviour_lambda());
        c
    }

    /// The sampler settings: `simulate`'s defaults for behaviours.
    pub fn sample_config(&self) -> SampleConfig {
        SampleConfig {
            samples: self.samples,
            seed: self.seed,
            lambda: self.lambda.unwrap_or(crate::sample::BEHAVIOUR_LAMBDA),
            task: crate::sample::Task::Unconditional,
            guidance: self.guidance,
            schedule: crate::sample::LambdaSchedule::Fading,
            realism: crate::cost::Realism {
                weight: self.realism,
                ..crate::cost::Realism::default()
            },
            polish: self.polish,
            // Out of range, zero: refused by validate, after loop_problem has named it.
            script_budget: std::time::Duration::try_from_secs_f64(self.script_budget)
                .unwrap_or_default(),
            ..SampleConfig::default()
        }
    }
}

fn default_script_budget() -> f64 {
    crate::sample::DEFAULT_SCRIPT_BUDGET.as_secs_f64()
}

fn default_guidance() -> crate::sample::Guidance {
    crate::sample::DEFAULT_GUIDANCE
}

/// `guidance` as written now (`"denoiser"` / `"output"`), or the `through_denoiser` flag of
/// runs recorded before (`true` / `false`), so that `--resume` and `--replay` read them.
fn guidance_or_legacy_flag<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<crate::sample::Guidance, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Written {
        Flag(bool),
        Name(crate::sample::Guidance),
        // Anything else, to be named: untagged, serde said only "data did not match any
        // variant of untagged enum Written".
        Other(Value),
    }
    Ok(match Written::deserialize(d)? {
        Written::Flag(true) => crate::sample::Guidance::Denoiser,
        Written::Flag(false) => crate::sample::Guidance::OutputSpace,
        Written::Name(g) => g,
        Written::Other(v) => {
            return Err(serde::de::Error::custom(format!(
                "`guidance` is {}: it is \"denoiser\" or \"output\"",
                crate::io::name::shown_counted(&v.to_string())
            )))
        }
    })
}

/// A checker of the request, stored by name.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct StoredCheck {
    /// The behaviour's name.
    pub behaviour: String,
    /// Its parameters.
    pub params: Value,
}

/// How a run ended.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Outcome {
    /// A script whose samples meet the request, accepted.
    Accepted {
        /// The round whose samples were accepted.
        round: usize,
        /// The sample that meets the request.
        sample: usize,
    },
    /// The rounds ran out; the last valid script is final.
    RoundsUsed {
        /// The last sampled round.
        round: usize,
        /// A sample that meets the request, if one does (the model did not get to ACCEPT it).
        sample: Option<usize>,
    },
    /// The model could not produce a usable script.
    GaveUp {
        /// Why.
        reason: String,
    },
    /// The request asks what no plausible motion can do within the sampler's horizon
    /// ([`crate::eval::infeasible`]): said before any round, so that no reply or sampling is
    /// spent pretending it can be met.
    Infeasible {
        /// Why, one line per event that cannot be met.
        reasons: Vec<String>,
    },
    /// A manual round waits for its reply.
    Waiting {
        /// The prompt to paste.
        prompt: PathBuf,
        /// Where the reply goes.
        reply: PathBuf,
    },
}

/// One sampling round, judged on the sample it shows (the first that meets the request, else
/// the first that passes every checker, else the cheapest).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoundRecord {
    /// The exchange (`round_N`) whose script was sampled.
    pub exchange: usize,
    /// Whether a sample meets the request (terms, checkers, plausible named agents).
    pub meets: bool,
    /// Whether the shown sample's checkers all see the behaviour's geometry (false without
    /// checkers).
    pub achieved: bool,
    /// Whether they all pass it: geometry and plausible motion of the agents they name.
    pub passed: bool,
    /// Why the shown sample does not meet the request.
    pub reasons: Vec<String>,
    /// Whether the round succeeded ([`round_succeeded`]), as it was judged when sampled;
    /// absent in runs recorded before it was kept ([`RoundRecord::succeeded`] then judges).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub success: Option<bool>,
}

impl RoundRecord {
    /// Whether the round succeeded: the one judgement `ask` (its verdict and exit status)
    /// and `ask --batch` (its per-pair line and table) give ([`round_succeeded`]). A record
    /// from before it was kept is judged as if every clause had a checker (or none did).
    pub fn succeeded(&self) -> bool {
        self.success.unwrap_or(self.passed || self.meets)
    }

    /// The round's result in words, the same in `ask`'s report and `ask --batch`'s lines.
    pub fn verdict_words(&self) -> &'static str {
        match (self.succeeded(), self.meets, self.passed, self.achieved) {
            (true, true, _, _) => "met",
            (true, false, _, _) => "met by the checkers (script terms over tolerance)",
            (false, _, true, _) => "checkers pass, unchecked clauses not met",
            (false, _, false, true) => "achieved implausibly",
            (false, _, false, false) => "fail",
        }
    }
}

/// Whether a sampling round succeeded, from its shown sample: the one rule behind `ask`'s
/// verdict and exit status and `ask --batch`'s table.
///
/// Where checkers judge every clause of the request (`fully_checked`), success is theirs: the
/// sample passes every checker, with plausible motion of the agents they name and the rest of
/// the scene no worse than unguided (the paper's measure). Script terms above their tolerance
/// then mean that the script asks for more than the request: the loop goes on to relax them,
/// and an ACCEPT still needs them met, but the request is met. Without checkers, or where a
/// clause has none, the terms are the only judge of what no checker reads: success is
/// meeting the whole request (`meets`: terms within tolerance, checkers pass, named agents
/// plausible). `ask` once failed a run whose checker passed every sample while the batch
/// table counted it a success.
pub fn round_succeeded(meets: bool, passed: bool, fully_checked: bool) -> bool {
    if fully_checked {
        passed
    } else {
        meets
    }
}

/// A run's verdict: judged on its last sampling round (the final script's), whatever ended
/// the run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunVerdict {
    /// Whether the final round succeeded ([`RoundRecord::succeeded`]).
    pub succeeded: bool,
    /// That round's exchange (`round_N`), when something was sampled.
    pub round: Option<usize>,
    /// In words: the round's verdict, or why nothing was judged.
    pub text: String,
}

/// The verdict of a run with `history` (its sampling rounds, in order): what `ask` prints and
/// exits with and what `ask --batch` counts for the pair.
pub fn run_verdict(history: &[RoundRecord]) -> RunVerdict {
    match history.last() {
        None => RunVerdict {
            succeeded: false,
            round: None,
            text: "nothing was sampled".into(),
        },
        Some(r) => RunVerdict {
            succeeded: r.succeeded(),
            round: Some(r.exchange),
            text: format!(
                "{}: round {} {}",
                if r.succeeded() {
                    "succeeded"
                } else {
                    "not met"
                },
                r.exchange,
                r.verdict_words()
            ),
        },
    }
}

/// What persists between steps (`state.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
struct State {
    version: u32,
    scene: PathBuf,
    /// CRC-32C of the scene file when the run started (absent for a scene directory, and in
    /// runs written before it was kept): `--resume` refuses a scene that changed since.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    scene_crc32c: Option<u32>,
    /// The checkpoint the run samples with (absent in runs written before it was kept):
    /// `--resume` and `--continue` refuse another, which went on with the default one (or
    /// any given) without a word, the run's rounds sampled by two models.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    checkpoint: Option<crate::train::CheckpointOrigin>,
    requests: Vec<String>,
    backend: String,
    model: Option<String>,
    url: Option<String>,
    config: SessionConfig,
    prompts: PathBuf,
    checks: Vec<StoredCheck>,
    messages: Vec<Message>,
    /// Next exchange (`round_N`).
    exchange: usize,
    /// Sampling rounds done.
    sampled: usize,
    /// Unusable replies in a row.
    misses: usize,
    /// The last script that validated and was sampled, with its round.
    script: Option<(usize, String)>,
    /// Of the last sampling: a sample that meets the request.
    meets: Option<usize>,
    /// Rules planner: per event, its tuning and whether it passed / was achieved on the best
    /// sample of the last sampling.
    tunings: Vec<(f64, Vec<(String, f64)>)>,
    event_results: Vec<(bool, bool)>,
    /// Script terms above tolerance on that sample.
    #[serde(default)]
    failing_terms: Vec<String>,
    /// One record per sampling round, for batch tables.
    #[serde(default)]
    history: Vec<RoundRecord>,
    /// What the first prompt left out to fit the context window.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    left_out: Vec<String>,
    /// The last validation error, while the script that caused it is not yet repaired.
    #[serde(default)]
    last_error: Option<String>,
    /// What happened to that script, in words for the user (`last_error` is what the model
    /// was told): it failed validation, ran past the script budget, or failed while being
    /// sampled. What the rules planner says when it cannot go on; runs recorded before it was
    /// kept have only `last_error`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    last_failure: Option<String>,
    /// Who wrote that script ([`Backend::name`]): a run taken up with another backend
    /// (`--resume --llm rules` after the model's script failed) must not blame the one that
    /// did not write it. Runs recorded before it was kept: the run's backend.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    last_failure_by: Option<String>,
    /// The model's ACCEPT was refused since the last sampling: the script it sends next
    /// answers the refusal.
    #[serde(default)]
    accept_refused: bool,
    /// The rounds ran out on the script that answered a refused ACCEPT while one of its
    /// samples meets the request: the model has this one more turn, to ACCEPT it
    /// ([`Session::final_turn`]); nothing more is sampled.
    #[serde(default)]
    final_turn: bool,
    /// Set when the run is over.
    outcome: Option<Outcome>,
}

const STATE_VERSION: u32 = 1;

/// One record of `transcript.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct Record {
    round: usize,
    phase: String,
    seconds: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    detail: Option<Value>,
}

/// A run of the loop.
pub struct Session<'a> {
    dir: PathBuf,
    state: State,
    prompts: Prompts,
    backend: Backend,
    trained: &'a Trained,
    raw: Scene,
    transcript: Vec<Record>,
    /// Reopened from `state.json` (`--resume`, `--continue`, a batch's pair run again): its
    /// settings, the window among them, are the run's, which the flags cannot change, and
    /// advice says so rather than name a flag that would be refused.
    taken_up: bool,
    /// Held while the session lives: every way into a run directory takes it.
    _lock: super::rundir::RunLock,
}

/// The most a file of a run directory that drivescript reads back may hold (`state.json`
/// keeps every message of the run: a few hundred KB after many rounds).
pub const MAX_RUN_FILE_BYTES: u64 = 64 << 20;

/// Reads back a text file of a run directory: a planted FIFO or device must not hang `--resume`.
fn read_run_file(path: &Path) -> Result<String, crate::io::IoError> {
    crate::io::read_regular_text(path, MAX_RUN_FILE_BYTES, "a file of a run")
}

/// CRC-32C of a scene file (`None` for a directory, or a file that cannot be read: reading
/// the scene reports that).
fn scene_fingerprint(path: &Path) -> Option<u32> {
    crate::io::read_regular(path, crate::io::MAX_SCENE_BYTES, "a scene file")
        .ok()
        .map(|b| crate::io::tfrecord::crc32c(&b))
}

/// `path` made absolute against the working directory, as `state.json` records the scene and
/// the prompts: recorded as typed (`data/samples/x.xml`), they were looked for again under
/// the directory `--resume` ran in, and a run resumed from any other was refused as if its
/// scene had changed ("start a new run on it").
pub fn absolute(path: &Path) -> PathBuf {
    std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf())
}

/// Where a path the run recorded relative to the directory it started in (runs written before
/// paths were recorded absolute) is not found from this one: the words that say so.
fn relative_and_absent(path: &Path) -> Option<String> {
    if path.is_absolute() || std::fs::symlink_metadata(path).is_ok() {
        return None;
    }
    let here = std::env::current_dir()
        .map(|d| d.display().to_string())
        .unwrap_or_else(|_| "the current directory".into());
    Some(format!(
        "{} is not found from {here}: the run recorded it relative to the directory it was \
         started in; run the command from there",
        path.display()
    ))
}

fn run_err(dir: &Path, message: impl Into<String>) -> LlmError {
    LlmError::Run {
        dir: dir.to_path_buf(),
        message: message.into(),
    }
}

/// A file or directory inside the run directory, named itself.
fn file_err(path: &Path, message: impl Into<String>) -> LlmError {
    LlmError::RunFile {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// A file of the run that cannot be written, as the error that names it.
fn write_err(e: crate::io::IoError) -> LlmError {
    LlmError::Io(e)
}

fn write(dir: &Path, name: &str, text: &str) -> Result<(), LlmError> {
    write_bytes(dir, name, text.as_bytes())
}

/// Writes a file of the run, never through a link planted in its place.
fn write_bytes(dir: &Path, name: &str, bytes: &[u8]) -> Result<(), LlmError> {
    let p = dir.join(name);
    if let Some(parent) = p.parent() {
        std::fs::create_dir_all(parent).map_err(|e| {
            file_err(
                parent,
                format!("cannot create it (the run writes its files there): {e}"),
            )
        })?;
    }
    super::rundir::check_not_link(&p)?;
    write_atomic(&p, bytes).map_err(write_err)
}

/// Checkers as stored (by name), as the sampler takes them.
pub fn stored_checks(checks: &[StoredCheck]) -> Vec<(Behavior, Params)> {
    checks
        .iter()
        .filter_map(|c| {
            Some((
                Behavior::from_name(&c.behaviour)?,
                Params::from_json(&c.params).ok()?,
            ))
        })
        .collect()
}

/// The checkers of the events of `requests` that the rules planner recognises, clause by
/// clause: a part outside its vocabulary costs that part its checker, not the others theirs.
pub fn checks_for(requests: &[String]) -> Vec<(Behavior, Params)> {
    requests
        .iter()
        .flat_map(|r| rules::understand_partly(r).0)
        .map(|e| (e.behaviour, e.params))
        .collect()
}

/// The clauses of `requests` that have no checker (outside the rules planner's vocabulary, or
/// without the ids or numbers their behaviour needs), as the request words them.
pub fn unchecked_clauses(requests: &[String]) -> Vec<String> {
    requests
        .iter()
        .flat_map(|r| rules::understand_partly(r).1)
        .filter_map(|e| match e {
            rules::RulesError::NotUnderstood { clause, .. }
            | rules::RulesError::Missing { clause, .. } => Some(clause),
            rules::RulesError::TooLong { .. } => None,
        })
        .collect()
}

/// The whole numbers of `state.json` (JSON pointers) that the loop reads back as counts and
/// indices, with the largest each may be before its own range is checked.
const STATE_COUNTS: &[(&str, u64)] = &[
    ("/version", u32::MAX as u64),
    ("/scene_crc32c", u32::MAX as u64),
    ("/exchange", u64::MAX),
    ("/sampled", u64::MAX),
    ("/misses", u64::MAX),
    ("/meets", u64::MAX),
    ("/script/0", u64::MAX),
    ("/config/rounds", u64::MAX),
    ("/config/fixes", u64::MAX),
    ("/config/samples", u64::MAX),
    ("/config/max_agents", u64::MAX),
    ("/config/seed", u64::MAX),
    ("/config/polish", u64::MAX),
    ("/config/replan", u64::MAX),
    ("/config/context/tokens", u64::MAX),
    ("/config/context/reply", u64::MAX),
    ("/outcome/Accepted/round", u64::MAX),
    ("/outcome/Accepted/sample", u64::MAX),
    ("/outcome/RoundsUsed/round", u64::MAX),
    ("/outcome/RoundsUsed/sample", u64::MAX),
];

/// A JSON pointer as a field path: `/config/rounds` → `config.rounds`, `/script/0` →
/// `script[0]`.
fn field_name(pointer: &str) -> String {
    let mut out = String::new();
    for part in pointer.split('/').skip(1) {
        if part.bytes().all(|b| b.is_ascii_digit()) {
            out.push_str(&format!("[{part}]"));
        } else {
            if !out.is_empty() {
                out.push('.');
            }
            out.push_str(part);
        }
    }
    out
}

/// Reads a run's `state.json`: every count and index the loop reads back must be a whole
/// number in its range and agree with the rest of the file, or the message names the field.
/// An edited or damaged file must not wrap a counter (`exchange` at its largest once wrapped
/// to 0 and overwrote `round_0`), carry on past the rounds, or allocate what it says.
fn read_state(text: &str) -> Result<State, String> {
    let value: Value =
        serde_json::from_str(text).map_err(|e| format!("the file is damaged ({e})"))?;
    let edited = "the file was edited or damaged; start a new run";
    let mut pointers: Vec<(String, u64)> = STATE_COUNTS
        .iter()
        .map(|(p, max)| (p.to_string(), *max))
        .collect();
    let rounds = value
        .pointer("/history")
        .and_then(Value::as_array)
        .map_or(0, Vec::len);
    pointers.extend((0..rounds).map(|i| (format!("/history/{i}/exchange"), u64::MAX)));
    for (p, max) in &pointers {
        match value.pointer(p) {
            None | Some(Value::Null) => {}
            Some(v) if v.as_u64().is_some_and(|n| n <= *max) => {}
            Some(v) => {
                return Err(format!(
                    "`{}` is {v}: must be a whole number, {}; {edited}",
                    field_name(p),
                    if *max == u64::MAX {
                        "0 or more".to_string()
                    } else {
                        format!("0 to {max}")
                    }
                ))
            }
        }
    }
    let state: State = serde_json::from_value(value).map_err(|e| {
        format!(
            "the file is damaged ({})",
            crate::io::plain_types(&e.to_string())
        )
    })?;
    if state.version != STATE_VERSION {
        return Err(format!(
            "version {}: this drivescript reads {STATE_VERSION}",
            state.version
        ));
    }
    state.check().map_err(|m| format!("{m}; {edited}"))?;
    Ok(state)
}

impl State {
    /// The counts and indices against each other and the settings ([`read_state`]).
    fn check(&self) -> Result<(), String> {
        let c = &self.config;
        if let Some(m) = c.problem() {
            return Err(format!("`config`: {m}"));
        }
        // Every exchange adds the model's reply to the messages: the two counts are one.
        let replies = self
            .messages
            .iter()
            .filter(|m| m.role == "assistant")
            .count();
        if self.exchange != replies {
            return Err(format!(
                "`exchange` is {}, but `messages` holds {replies} replies of the model (one \
                 per exchange)",
                self.exchange
            ));
        }
        if self.sampled > c.rounds + 1 {
            return Err(format!(
                "`sampled` is {}: a run samples at most `config.rounds` + 1 = {} times",
                self.sampled,
                c.rounds + 1
            ));
        }
        if self.sampled > self.history.len() {
            return Err(format!(
                "`sampled` is {}, but `history` records {} sampling rounds",
                self.sampled,
                self.history.len()
            ));
        }
        if self.misses > c.fixes + 1 {
            return Err(format!(
                "`misses` is {}: a run gives up after `config.fixes` + 1 = {} in a row",
                self.misses,
                c.fixes + 1
            ));
        }
        if self.requests.is_empty() {
            return Err(
                "`requests` is empty: a run holds at least the request it started with".into(),
            );
        }
        // A checker that cannot be read was dropped without a word, and the run judged
        // without it ("Verdict: succeeded" with the request unchecked).
        for (i, c) in self.checks.iter().enumerate() {
            let b = Behavior::parse(&c.behaviour)
                .map_err(|e| format!("`checks[{i}].behaviour`: {e}"))?;
            let p =
                Params::from_json(&c.params).map_err(|m| format!("`checks[{i}].params`: {m}"))?;
            b.check_param_names(&p)
                .map_err(|e| format!("`checks[{i}].params`: {e}"))?;
        }
        let mut before = None;
        for (i, r) in self.history.iter().enumerate() {
            if r.exchange >= self.exchange || before.is_some_and(|b| r.exchange <= b) {
                return Err(format!(
                    "`history[{i}].exchange` is {}: the sampled exchanges must rise, each below \
                     `exchange` ({})",
                    r.exchange, self.exchange
                ));
            }
            before = Some(r.exchange);
        }
        let round = |name: &str, r: usize| {
            if r >= self.exchange {
                Err(format!(
                    "`{name}` is {r}: must be an exchange of the run, below `exchange` ({})",
                    self.exchange
                ))
            } else {
                Ok(())
            }
        };
        let sample = |name: &str, k: usize| {
            if k >= c.samples {
                Err(format!(
                    "`{name}` is {k}: must be a sample of the round, below `config.samples` ({})",
                    c.samples
                ))
            } else {
                Ok(())
            }
        };
        if let Some((r, _)) = &self.script {
            round("script[0]", *r)?;
        }
        if let Some(k) = self.meets {
            sample("meets", k)?;
        }
        match &self.outcome {
            Some(Outcome::Accepted {
                round: r,
                sample: k,
            }) => {
                round("outcome.Accepted.round", *r)?;
                sample("outcome.Accepted.sample", *k)?;
            }
            Some(Outcome::RoundsUsed {
                round: r,
                sample: k,
            }) => {
                round("outcome.RoundsUsed.round", *r)?;
                if let Some(k) = k {
                    sample("outcome.RoundsUsed.sample", *k)?;
                }
            }
            _ => {}
        }
        Ok(())
    }
}

/// Refuses a request (or follow-up) with no words: it started a run that asked the model
/// about nothing, and the rules planner answered that it did not understand `""`.
pub fn check_request(request: &str) -> Result<(), LlmError> {
    if request.trim().is_empty() {
        return Err(LlmError::Request(
            "the request is empty: say in words what should happen (\"vehicle 3 cuts in front \
             of vehicle 5\")"
                .into(),
        ));
    }
    Ok(())
}

/// Refuses a request the rules planner would refuse, before a run starts or anything is
/// printed: no words ([`check_request`]), or no clause in its vocabulary. `demo` printed the
/// scene and the whole request (12,000 characters of it) and only then said it could not run.
pub fn check_rules_request(request: &str) -> Result<(), LlmError> {
    check_request(request)?;
    super::rules::plan_request(request)?;
    Ok(())
}

/// Opens `dir` for a new run: refused before anything is written where `config` or the
/// scene's id cannot run, and where `dir` is not a directory; then locked, and refused where
/// it holds a batch or (unless `replace`, which removes it) another run, or files of the
/// user's that a run would replace.
fn open_new(
    dir: &Path,
    scene_path: &Path,
    raw: &Scene,
    config: &SessionConfig,
    replace: bool,
) -> Result<super::rundir::RunLock, LlmError> {
    let held = || {
        run_err(
            dir,
            "it already holds a run (state.json): continue it with --resume, revise it with \
             --continue, or choose another -o",
        )
    };
    if !replace && dir.join("state.json").exists() {
        return Err(held());
    }
    // Refused before anything is asked: the rollouts are named after the scenario.
    output_stem(&raw.meta.scenario_id).map_err(|e| LlmError::Input {
        path: scene_path.to_path_buf(),
        message: e.to_string(),
    })?;
    config.validate()?;
    crate::io::create_output_dir(dir).map_err(|e| LlmError::Input {
        path: dir.to_path_buf(),
        message: format!(
            "{}: -o names the run directory, where the run writes its rounds; give a new or \
             empty directory",
            match e {
                crate::io::IoError::Invalid { message, .. } => message,
                other => other.reason(),
            }
        ),
    })?;
    let lock = super::rundir::lock(dir)?;
    super::rundir::check_kind(
        dir,
        super::rundir::Kind::Run,
        "give this run a new or empty -o",
    )?;
    if replace {
        super::rundir::clear_run(dir)?;
    }
    // Checked again under the lock: another `ask` may have started here meanwhile.
    if dir.join("state.json").exists() {
        return Err(held());
    }
    super::rundir::check_fresh(dir)?;
    Ok(lock)
}

impl<'a> Session<'a> {
    /// Starts a run in `dir` (created; it must not hold another run).
    #[allow(clippy::too_many_arguments)]
    pub fn start(
        dir: &Path,
        scene_path: &Path,
        raw: Scene,
        request: &str,
        trained: &'a Trained,
        backend: Backend,
        prompts: Prompts,
        config: SessionConfig,
        checks: Option<Vec<(Behavior, Params)>>,
    ) -> Result<Self, LlmError> {
        check_request(request)?;
        // Before the directory is made: a request the planner refuses left an empty run
        // directory holding only its lock.
        if let Backend::Rules = backend {
            rules::plan_request(request)?;
        }
        check_scene_step(&raw)?;
        check_samples_fit(trained, &raw, config.samples)?;
        let lock = open_new(dir, scene_path, &raw, &config, false)?;
        Self::begin(
            lock, dir, scene_path, raw, request, trained, backend, prompts, config, checks,
        )
    }

    /// [`Session::start`] in a directory whose earlier run (only the files a run writes) is
    /// removed first, under the run's lock: `demo`, which is run again and again into one
    /// directory. Anything else there is left alone.
    #[allow(clippy::too_many_arguments)]
    pub fn replace(
        dir: &Path,
        scene_path: &Path,
        raw: Scene,
        request: &str,
        trained: &'a Trained,
        backend: Backend,
        prompts: Prompts,
        config: SessionConfig,
        checks: Option<Vec<(Behavior, Params)>>,
    ) -> Result<Self, LlmError> {
        check_request(request)?;
        // Before the directory is made: a request the planner refuses left an empty run
        // directory holding only its lock.
        if let Backend::Rules = backend {
            rules::plan_request(request)?;
        }
        check_scene_step(&raw)?;
        check_samples_fit(trained, &raw, config.samples)?;
        let lock = open_new(dir, scene_path, &raw, &config, true)?;
        Self::begin(
            lock, dir, scene_path, raw, request, trained, backend, prompts, config, checks,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn begin(
        lock: super::rundir::RunLock,
        dir: &Path,
        scene_path: &Path,
        raw: Scene,
        request: &str,
        trained: &'a Trained,
        backend: Backend,
        prompts: Prompts,
        mut config: SessionConfig,
        checks: Option<Vec<(Behavior, Params)>>,
    ) -> Result<Self, LlmError> {
        // Stored resolved: a resumed run keeps the strength it began with.
        config = config.resolved(trained);
        let requests = vec![request.trim().to_string()];
        let checks = checks.unwrap_or_else(|| checks_for(&requests));
        let backend = backend.for_run(&config);
        let (model, url) = match &backend {
            Backend::Http(c) => (
                Some(c.config().model.clone()),
                Some(redact_url(&c.config().endpoint())),
            ),
            _ => (None, None),
        };
        let mut s = Self {
            dir: dir.to_path_buf(),
            state: State {
                version: STATE_VERSION,
                scene: absolute(scene_path),
                scene_crc32c: scene_fingerprint(scene_path),
                checkpoint: trained.origin.clone(),
                requests,
                backend: backend.name().into(),
                model,
                url,
                config,
                prompts: absolute(prompts.dir()),
                checks: checks
                    .iter()
                    .map(|(b, p)| StoredCheck {
                        behaviour: b.name().into(),
                        params: serde_json::to_value(p).expect("params serialise"),
                    })
                    .collect(),
                messages: Vec::new(),
                exchange: 0,
                sampled: 0,
                misses: 0,
                script: None,
                meets: None,
                tunings: Vec::new(),
                event_results: Vec::new(),
                failing_terms: Vec::new(),
                history: Vec::new(),
                left_out: Vec::new(),
                last_error: None,
                last_failure: None,
                last_failure_by: None,
                accept_refused: false,
                final_turn: false,
                outcome: None,
            },
            prompts,
            backend,
            trained,
            raw,
            transcript: Vec::new(),
            taken_up: false,
            _lock: lock,
        };
        let first = first_messages(
            &s.prompts,
            &s.state.config,
            &s.raw,
            &s.state.requests,
            trained.meta.config.window.future,
        )?;
        s.state.messages = first.messages;
        s.state.left_out = first.left_out;
        s.save()?;
        Ok(s)
    }

    /// Reopens the run in `dir` where it stopped. `load` reads the scene the run recorded.
    pub fn resume(
        dir: &Path,
        trained: &'a Trained,
        backend: impl FnOnce(&str, Option<&str>, Option<&str>) -> Result<Backend, LlmError>,
        load: impl FnOnce(&Path) -> Result<Scene, LlmError>,
    ) -> Result<Self, LlmError> {
        let not_a_run = |what: &str| LlmError::Input {
            path: dir.to_path_buf(),
            message: format!(
                "{what}: --resume and --continue take the directory of a run, the -o DIR of \
                 `drivescript ask SCENE \"request\" -o DIR`"
            ),
        };
        match std::fs::metadata(dir) {
            Ok(m) if m.is_dir() => {}
            Ok(_) => return Err(not_a_run("is a file, not a run directory")),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(not_a_run("does not exist"))
            }
            Err(e) => return Err(not_a_run(&format!("cannot be read ({e})"))),
        }
        // Taken before state.json is read: a run still going there would go on writing it.
        let lock = super::rundir::lock(dir)?;
        super::rundir::check_kind(
            dir,
            super::rundir::Kind::Run,
            "run the batch's command again to continue it, or resume one of its pairs with \
             --resume DIR/runs/NNN_...",
        )?;
        let p = dir.join("state.json");
        if std::fs::symlink_metadata(&p).is_err() {
            return Err(not_a_run(
                "holds no run to resume (there is no state.json); start one with `drivescript \
                 ask SCENE \"request\" -o DIR`",
            ));
        }
        let text = read_run_file(&p).map_err(|e| {
            file_err(
                &p,
                format!(
                    "cannot read it ({}): a run keeps its state there, as a JSON file",
                    e.reason()
                ),
            )
        })?;
        let state = read_state(&text).map_err(|m| file_err(&p, m))?;
        if let Some(why) = relative_and_absent(&state.scene)
            .map(|w| format!("the scene {w}"))
            .or_else(|| relative_and_absent(&state.prompts).map(|w| format!("the prompts {w}")))
        {
            return Err(run_err(dir, why));
        }
        if let Some(was) = state.scene_crc32c {
            if scene_fingerprint(&state.scene) != Some(was) {
                return Err(run_err(
                    dir,
                    format!(
                        "the scene {} changed (or went) since the run started: its rounds were \
                         asked, sampled and judged on the old one; start a new run on it",
                        state.scene.display()
                    ),
                ));
            }
        }
        if let (Some(was), Some(now)) = (&state.checkpoint, &trained.origin) {
            if was.crc32c != now.crc32c {
                return Err(run_err(
                    dir,
                    format!(
                        "the run samples with the checkpoint {} (checksum {:08x}), and the one \
                         given, {}, is another (checksum {:08x}): its rounds would go on with \
                         another model; give --checkpoint {}",
                        crate::io::name::one_line(&was.dir.display().to_string()),
                        was.crc32c,
                        crate::io::name::one_line(&now.dir.display().to_string()),
                        now.crc32c,
                        crate::io::name::one_line(&was.dir.display().to_string()),
                    ),
                ));
            }
        }
        let prompts = Prompts::load(&state.prompts)?;
        let backend = backend(&state.backend, state.model.as_deref(), state.url.as_deref())?
            .for_run(&state.config);
        let raw = load(&state.scene)?;
        let transcript = read_run_file(&dir.join("transcript.json"))
            .ok()
            .and_then(|t| serde_json::from_str::<Value>(&t).ok())
            .and_then(|v| serde_json::from_value(v["records"].clone()).ok())
            .unwrap_or_default();
        Ok(Self {
            dir: dir.to_path_buf(),
            state,
            prompts,
            backend,
            trained,
            raw,
            transcript,
            taken_up: true,
            _lock: lock,
        })
    }

    /// Adds a follow-up request to a finished (or stopped) run: the model revises the last
    /// script instead of starting over. The rounds start counting again.
    pub fn follow_up(&mut self, request: &str) -> Result<(), LlmError> {
        check_request(request)?;
        let script = self
            .state
            .script
            .as_ref()
            .map(|(_, s)| s.clone())
            .ok_or_else(|| run_err(&self.dir, "the run has no sampled script to revise yet"))?;
        if let Backend::Rules = self.backend {
            rules::plan_request(request)?;
        }
        let before = self.state.clone();
        self.state.requests.push(request.trim().to_string());
        let added = checks_for(&self.state.requests[self.state.requests.len() - 1..]);
        for (b, p) in added {
            self.state.checks.push(StoredCheck {
                behaviour: b.name().into(),
                params: serde_json::to_value(&p).expect("params serialise"),
            });
        }
        self.state.messages.push(Message::new(
            "user",
            self.prompts.followup(request, &script),
        ));
        self.state.outcome = None;
        self.state.sampled = 0;
        self.state.misses = 0;
        self.state.accept_refused = false;
        self.state.final_turn = false;
        // Before anything is sent or saved: a conversation the run's window cannot hold is
        // refused now, the run left as it was, not after the first round was paid for.
        if let Err(e) = self.to_send(self.state.exchange, &mut |_| {}) {
            self.state = before;
            return Err(e);
        }
        self.save()
    }

    /// Why the sample the last sampling round shows does not meet the request.
    fn last_reasons(&self) -> &[String] {
        self.state
            .history
            .last()
            .map_or(&[], |h| h.reasons.as_slice())
    }

    /// The rollouts and cost report that sampling round `round` wrote, relative to the run
    /// directory, for messages: `round_1/ID_0.json … round_1/ID_3.json and round_1/ID_costs.json`.
    pub fn rollout_files(&self, round: usize) -> String {
        let id = &self.raw.meta.scenario_id;
        let last = self.state.config.samples.saturating_sub(1);
        let rollouts = if last == 0 {
            format!("round_{round}/{id}_0.json")
        } else {
            format!("round_{round}/{id}_0.json … round_{round}/{id}_{last}.json")
        };
        format!("{rollouts} and round_{round}/{id}_costs.json")
    }

    /// The settings the run was started with (read back from its `state.json` when it was
    /// taken up again).
    pub fn config(&self) -> &SessionConfig {
        &self.state.config
    }

    /// Replies received from the model so far (exchanges done), the run's paid-for work.
    pub fn replies(&self) -> usize {
        self.state.exchange
    }

    /// One record per sampling round so far.
    pub fn history(&self) -> &[RoundRecord] {
        &self.state.history
    }

    /// The run's verdict ([`run_verdict`] of its rounds): what `ask` exits with and what
    /// `ask --batch` counts.
    pub fn verdict(&self) -> RunVerdict {
        run_verdict(&self.state.history)
    }

    /// The events of the request no plausible motion can meet within the sampler's horizon,
    /// judged from the scene's current state ([`crate::eval::infeasible`]).
    pub fn infeasible(&self) -> Vec<crate::eval::Infeasible> {
        let horizon = self
            .state
            .config
            .sample_config()
            .horizon
            .unwrap_or(self.trained.meta.config.window.future);
        self.checks()
            .iter()
            .filter_map(|(b, p)| crate::eval::infeasible(*b, &self.raw, p, horizon))
            .collect()
    }

    /// Calls to the LLM server and the tokens they used (prompt + completion), from the
    /// transcript.
    pub fn usage(&self) -> (usize, u64) {
        let llm: Vec<&Record> = self
            .transcript
            .iter()
            .filter(|r| r.phase == "llm")
            .collect();
        let tokens = llm
            .iter()
            .filter_map(|r| r.detail.as_ref())
            // A hostile or broken server's counts must not wrap around into small ones.
            .map(|d| {
                d["usage"]["prompt_tokens"]
                    .as_u64()
                    .unwrap_or(0)
                    .saturating_add(d["usage"]["completion_tokens"].as_u64().unwrap_or(0))
            })
            .fold(0u64, u64::saturating_add);
        (llm.len(), tokens)
    }

    /// The requests of the run: the first, then each follow-up.
    pub fn requests(&self) -> &[String] {
        &self.state.requests
    }

    /// The run directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The clauses of the run's requests that no checker judges ([`unchecked_clauses`]).
    pub fn unchecked(&self) -> Vec<String> {
        unchecked_clauses(&self.state.requests)
    }

    /// The checkers of the request.
    pub fn checks(&self) -> Vec<(Behavior, Params)> {
        stored_checks(&self.state.checks)
    }

    /// What the first prompt left out to fit `--context` (empty when nothing was).
    pub fn left_out(&self) -> &[String] {
        &self.state.left_out
    }

    /// The first prompt, as `prompt show` prints it.
    pub fn first_prompt(&self) -> String {
        render_messages(&self.state.messages[..2.min(self.state.messages.len())])
    }

    fn save(&self) -> Result<(), LlmError> {
        let text = serde_json::to_string_pretty(&self.state).expect("state serialises");
        write(&self.dir, "state.json", &text)?;
        let t = json!({
            "backend": self.state.backend,
            "model": self.state.model,
            "url": self.state.url,
            "scene": self.state.scene,
            "requests": self.state.requests,
            "config": self.state.config,
            "records": self.transcript,
            "outcome": self.state.outcome,
        });
        write(
            &self.dir,
            "transcript.json",
            &serde_json::to_string_pretty(&t).expect("transcript serialises"),
        )
    }

    fn record(&mut self, round: usize, phase: &str, t0: Instant, detail: Option<Value>) {
        self.transcript.push(Record {
            round,
            phase: phase.into(),
            seconds: t0.elapsed().as_secs_f64(),
            detail,
        });
    }

    /// Runs until the loop ends or a manual round waits. `progress` receives one line per
    /// phase (the CLI prints them).
    pub fn run(&mut self, progress: &mut dyn FnMut(&str)) -> Result<Outcome, LlmError> {
        // A request no car can meet in the horizon is said before any round: asking the model
        // and sampling would only show, round after round, what the current state already
        // proves (a follow-up's new events are judged here too).
        if self.state.outcome.is_none() {
            let reasons: Vec<String> = self.infeasible().iter().map(|i| i.to_string()).collect();
            if !reasons.is_empty() {
                for r in &reasons {
                    progress(&format!("cannot be met within the horizon: {r}"));
                }
                return self.finish(Outcome::Infeasible { reasons }, progress);
            }
        }
        loop {
            if let Some(o) = &self.state.outcome {
                return Ok(o.clone());
            }
            let n = self.state.exchange;
            // A `round_N` link planted in the run directory must not take its files elsewhere.
            let rdir = super::rundir::own_subdir(&self.dir, &format!("round_{n}"))?;
            super::rundir::check_not_link(&rdir.join("unguided"))?;
            let last_user = self
                .state
                .messages
                .iter()
                .rposition(|m| m.role == "user")
                .unwrap_or(0);
            // The prompt of this exchange: everything sent (the manual backend's user pastes
            // the whole of it in a fresh chat, or the last message in the same one).
            if !rdir.join("prompt.md").exists() {
                let shown = if n == 0 {
                    render_messages(&self.state.messages)
                } else {
                    render_messages(&self.state.messages[last_user..])
                };
                write(&rdir, "prompt.md", &shown)?;
                write(
                    &rdir,
                    "messages.json",
                    &serde_json::to_string_pretty(&self.state.messages).expect("serialises"),
                )?;
            }
            // A run stopped after the reply came (killed while sampling, say) goes on with
            // that reply: the model is not asked, or paid, twice for one round.
            let received = match self.backend {
                Backend::Manual => None,
                _ => read_run_file(&rdir.join("reply.md"))
                    .ok()
                    .filter(|t| !t.trim().is_empty()),
            };
            let reply = match received {
                Some(t) => {
                    progress(&format!(
                        "round {n}: the reply received before the run stopped ({})",
                        rdir.join("reply.md").display()
                    ));
                    t
                }
                None => match self.get_reply(n, &rdir, progress)? {
                    Got::Text(t) => {
                        if !matches!(self.backend, Backend::Manual) {
                            write(&rdir, "reply.md", &t)?;
                            // Keeps the exchange's record (tokens, latency) if the run stops
                            // while sampling.
                            self.save()?;
                        }
                        t
                    }
                    Got::Wait(o) => {
                        self.save()?;
                        return Ok(o);
                    }
                    Got::GiveUp(reason) => {
                        return self.finish(Outcome::GaveUp { reason }, progress);
                    }
                },
            };
            self.state
                .messages
                .push(Message::new("assistant", reply.clone()));
            self.state.exchange = n + 1;
            if self.state.final_turn {
                let o = self.final_turn(n, &reply, progress);
                return self.finish(o, progress);
            }
            match parse_reply(&reply) {
                Err(e) => {
                    // A reply the token limit cut off is unusable for that reason, which the
                    // user (not the model) can fix.
                    let cut = match &self.backend {
                        Backend::Http(c) if self.last_reply_truncated(n) => format!(
                            " (the reply was cut off at the token limit, --max-tokens {}: {})",
                            c.config().max_tokens,
                            self.longer_reply_advice(c.config().max_tokens)
                        ),
                        _ => String::new(),
                    };
                    progress(&format!("round {n}: unusable reply: {e}{cut}"));
                    let msg = self.prompts.unusable(&e.to_string());
                    if let Some(o) = self.miss(msg)? {
                        return self.finish(o, progress);
                    }
                }
                Ok(Reply::Accept { .. }) => {
                    if let (Some(k), Some((round, _))) = (self.state.meets, &self.state.script) {
                        let round = *round;
                        progress(&format!(
                            "round {n}: ACCEPT (sample {k} of round {round} meets the request)"
                        ));
                        return self.finish(Outcome::Accepted { round, sample: k }, progress);
                    }
                    let reasons = if self.state.script.is_none() {
                        "nothing has been sampled yet: send a script first".to_string()
                    } else {
                        self.last_reasons()
                            .iter()
                            .map(|r| format!("- {r}"))
                            .collect::<Vec<_>>()
                            .join("\n")
                    };
                    progress(&format!(
                        "round {n}: ACCEPT not accepted: no sample meets the request"
                    ));
                    // Only a refusal of sampled numbers is answered by a script.
                    self.state.accept_refused = self.state.script.is_some();
                    let msg = self.prompts.accept_rejected(&reasons);
                    if let Some(o) = self.miss(msg)? {
                        return self.finish(o, progress);
                    }
                }
                Ok(Reply::Script { reasoning, source }) => {
                    if !reasoning.is_empty() {
                        progress(&format!("round {n}: plan:\n{}", indent(&reasoning)));
                    }
                    write(&rdir, "script.rhai", &source)?;
                    progress(&format!(
                        "round {n}: script ({} lines, {}):\n{}",
                        source.lines().count(),
                        rdir.join("script.rhai").display(),
                        indent(&source)
                    ));
                    progress(&format!(
                        "round {n}: validating on the sampler's horizon, then sampling {} ...",
                        self.state.config.samples
                    ));
                    let t1 = Instant::now();
                    match self.sample(&source) {
                        Err(AttemptError::Script(e)) => {
                            self.record(n, "validation failed", t1, None);
                            let err = e.to_string();
                            write(&rdir, "validation.txt", &err)?;
                            self.state.last_error = Some(err.clone());
                            self.state.last_failure = Some(format!("it failed validation: {err}"));
                            self.state.last_failure_by = Some(self.backend.name().into());
                            progress(&format!("round {n}: validation failed: {err}"));
                            let horizon = self.trained.meta.config.window.future;
                            let msg = self.prompts.validation(horizon, self.raw.meta.dt, &err);
                            if let Some(o) = self.miss(msg)? {
                                return self.finish(o, progress);
                            }
                        }
                        // A slow script is the model's mistake, as one that fails to
                        // validate: it goes back with the numbers, and the run goes on.
                        Err(AttemptError::Sample(SampleError::ScriptBudget { budget, used })) => {
                            self.record(
                                n,
                                "script over budget",
                                t1,
                                Some(json!({
                                    "evaluations": used.evaluations,
                                    "seconds": used.time.as_secs_f64(),
                                    "budget_seconds": budget.as_secs_f64(),
                                })),
                            );
                            let err = super::feedback::over_budget(budget, &used);
                            write(&rdir, "budget.txt", &err)?;
                            self.state.last_error = Some(err.clone());
                            self.state.last_failure_by = Some(self.backend.name().into());
                            self.state.last_failure = Some(format!(
                                "it ran past the script budget (--script-budget {} s) while \
                                 being sampled: {:.1} s over {} evaluations",
                                crate::geom::num(budget.as_secs_f64()),
                                used.time.as_secs_f64(),
                                used.evaluations
                            ));
                            progress(&format!("round {n}: script over budget: {err}"));
                            let msg = self.prompts.unusable(&err);
                            if let Some(o) = self.miss(msg)? {
                                return self.finish(o, progress);
                            }
                        }
                        // So is a script that validated but fails on what sampling gives
                        // it (an index only some trajectories reach, an error raised under
                        // guidance): the user did not write it, and another round can fix it.
                        Err(AttemptError::Sample(SampleError::Cost(e))) => {
                            self.record(
                                n,
                                "script failed in sampling",
                                t1,
                                Some(json!({"error": e.to_string()})),
                            );
                            let err = super::feedback::failed_in_sampling(&e);
                            write(&rdir, "sampling.txt", &err)?;
                            self.state.last_error = Some(err.clone());
                            self.state.last_failure_by = Some(self.backend.name().into());
                            self.state.last_failure = Some(format!(
                                "it passed validation but failed while being sampled: {e}"
                            ));
                            progress(&format!("round {n}: script failed in sampling: {e}"));
                            let msg = self.prompts.unusable(&err);
                            if let Some(o) = self.miss(msg)? {
                                return self.finish(o, progress);
                            }
                        }
                        Err(e) => return Err(e.into()),
                        Ok(done) => {
                            self.record(
                                n,
                                "sample",
                                t1,
                                Some(json!({"seconds_sampling": done.report.seconds})),
                            );
                            self.after_sampling(n, &rdir, &source, &done, progress)?;
                            if self.state.sampled > self.state.config.rounds
                                && !self.state.final_turn
                            {
                                let o = Outcome::RoundsUsed {
                                    round: n,
                                    sample: self.state.meets,
                                };
                                return self.finish(o, progress);
                            }
                        }
                    }
                }
            }
            self.save()?;
        }
    }

    /// Whether exchange `n`'s reply was stopped by the token limit, as its record says.
    fn last_reply_truncated(&self, n: usize) -> bool {
        self.transcript
            .iter()
            .rev()
            .find(|r| r.round == n && r.phase == "llm")
            .and_then(|r| r.detail.as_ref())
            .is_some_and(|d| d["truncated"] == true)
    }

    /// An unusable exchange: the message goes back, or the run gives up after too many.
    fn miss(&mut self, msg: String) -> Result<Option<Outcome>, LlmError> {
        self.state.misses += 1;
        if self.state.misses > self.state.config.fixes {
            return Ok(Some(Outcome::GaveUp {
                reason: format!(
                    "{} unusable replies in a row (--fixes {}); the last: {}",
                    self.state.misses,
                    self.state.config.fixes,
                    msg.lines().next().unwrap_or("")
                ),
            }));
        }
        self.state.messages.push(Message::new("user", msg));
        Ok(None)
    }

    fn sample(&self, source: &str) -> Result<Attempt, AttemptError> {
        let spec = AttemptSpec {
            scripts: vec![ScriptSpec {
                source: source.to_string(),
                name: "script.rhai".into(),
                params: Params::default(),
                limits: Limits::default(),
            }],
            checks: self.checks(),
            cfg: self.state.config.sample_config(),
            replan: self.state.config.replan,
            // Back to the model as a validation error, before any sampling.
            refuse_dead_terms: true,
        };
        attempt(self.trained, &self.raw, &spec)
    }

    fn after_sampling(
        &mut self,
        n: usize,
        rdir: &Path,
        source: &str,
        done: &Attempt,
        progress: &mut dyn FnMut(&str),
    ) -> Result<(), LlmError> {
        let acc = Acceptance {
            tolerance: self.state.config.tolerance,
        };
        done.write(rdir, &self.raw.meta.scenario_id, None)
            .map_err(write_err)?;
        let text = feedback(done, &acc);
        write(rdir, "feedback.md", &text)?;
        // Why each sample misses the request, computed once for the choice, the progress lines
        // and the round's record.
        let reasons: Vec<Vec<String>> = done
            .report
            .samples
            .iter()
            .map(|o| acc.reasons(o, &done.report))
            .collect();
        let meets = reasons.iter().position(Vec::is_empty);
        let best = meets.unwrap_or_else(|| done.best());
        let gif = render_gif(
            &done.samples[best].scene,
            &RenderOptions {
                width: 800,
                roles: self.roles(done),
                ..RenderOptions::default()
            },
        )
        .map_err(|e| file_err(&rdir.join("sample.gif"), format!("cannot render it: {e}")))?;
        write_bytes(rdir, "sample.gif", &gif)?;
        progress(&format!(
            "round {n}: {} samples in {:.1} s; terms (unweighted) over the samples:\n{}",
            done.report.samples.len(),
            done.report.seconds,
            indent(&super::feedback::term_table(&done.report, &acc))
        ));
        for (o, reasons) in done.report.samples.iter().zip(&reasons) {
            let verdicts: Vec<String> = o
                .verdicts
                .iter()
                .zip(&done.report.checks)
                .map(|(v, c)| format!("{} {}", c.behaviour, if v.passed { "PASS" } else { "fail" }))
                .collect();
            progress(&format!(
                "round {n}: sample {}: {}{}",
                o.sample,
                if reasons.is_empty() {
                    "meets the request".to_string()
                } else {
                    format!("{} reason(s) it does not: {}", reasons.len(), reasons[0])
                },
                if verdicts.is_empty() {
                    String::new()
                } else {
                    format!(" [{}]", verdicts.join(", "))
                }
            ));
        }
        self.state.sampled += 1;
        self.state.misses = 0;
        self.state.last_error = None;
        self.state.last_failure = None;
        self.state.last_failure_by = None;
        self.state.script = Some((n, source.to_string()));
        self.state.meets = meets;
        let shown = &done.report.samples[best];
        let passed = shown.passed() == Some(true);
        let fully_checked = !done.report.checks.is_empty() && self.unchecked().is_empty();
        self.state.history.push(RoundRecord {
            exchange: n,
            meets: meets.is_some(),
            achieved: !shown.verdicts.is_empty() && shown.verdicts.iter().all(|v| v.achieved),
            passed,
            reasons: reasons[best].clone(),
            success: Some(round_succeeded(meets.is_some(), passed, fully_checked)),
        });
        self.state.failing_terms = shown
            .terms
            .iter()
            .filter(|t| t.script != "realism" && !(t.value <= t.tolerance.unwrap_or(acc.tolerance)))
            .map(|t| t.term.clone())
            .collect();
        self.state.event_results = shown
            .verdicts
            .iter()
            .map(|v| (v.passed, v.achieved))
            .collect();
        let answered_refusal = std::mem::take(&mut self.state.accept_refused);
        if self.state.sampled <= self.state.config.rounds {
            let msg = self.prompts.refine(done.report.samples.len(), &text);
            self.state.messages.push(Message::new("user", msg));
        } else if let (true, Some(k)) = (answered_refusal, meets) {
            // The rounds ran out on the script that answered a refused ACCEPT, and it meets
            // the request: ending here would leave the model's answer unjudged by the model
            // and the run "not accepted" though a sample meets the request. One more turn,
            // to ACCEPT; nothing more is sampled.
            self.state.final_turn = true;
            progress(&format!(
                "round {n}: the rounds are used up, but this script answered a refused ACCEPT \
                 and its sample {k} meets the request: one more turn to accept it"
            ));
            let msg = format!(
                "{}\n\nThe rounds are used up (--rounds {}): this was the last sampling. Your \
                 script answered the refused ACCEPT, and sample {k} now meets the request. \
                 Reply ACCEPT to accept it; a new script would not be sampled, and the run \
                 ends with this script either way.",
                self.prompts.refine(done.report.samples.len(), &text),
                self.state.config.rounds
            );
            self.state.messages.push(Message::new("user", msg));
        } else if answered_refusal {
            progress(&format!(
                "round {n}: the rounds are used up; this script answered a refused ACCEPT, but \
                 none of its samples meets the request, so there is nothing left to accept"
            ));
        }
        Ok(())
    }

    /// The reply to the one more turn after the rounds ran out ([`State::final_turn`]): an
    /// ACCEPT of the sample that meets the request ends the run accepted; anything else ends
    /// it with the rounds used up, saying why (nothing more is sampled).
    fn final_turn(&mut self, n: usize, reply: &str, progress: &mut dyn FnMut(&str)) -> Outcome {
        self.state.final_turn = false;
        let round = self.state.script.as_ref().map_or(n, |(r, _)| *r);
        match (parse_reply(reply), self.state.meets) {
            (Ok(Reply::Accept { .. }), Some(k)) => {
                progress(&format!(
                    "round {n}: ACCEPT (sample {k} of round {round} meets the request)"
                ));
                Outcome::Accepted { round, sample: k }
            }
            (r, sample) => {
                progress(&format!(
                    "round {n}: {}; the rounds are used up, so nothing more is sampled and \
                     round {round}'s script is final",
                    match r {
                        Ok(Reply::Script { .. }) => "a new script, not ACCEPT".to_string(),
                        Ok(Reply::Accept { .. }) =>
                            "ACCEPT, but no sample meets the request".into(),
                        Err(e) => format!("unusable reply: {e}"),
                    }
                ));
                Outcome::RoundsUsed { round, sample }
            }
        }
    }

    fn roles(&self, done: &Attempt) -> Vec<(i64, String)> {
        let mut r = done.report.roles();
        for id in &done.report.named {
            if !r.iter().any(|(a, _)| a == id) {
                r.push((*id, "named".into()));
            }
        }
        r
    }

    fn finish(&mut self, o: Outcome, progress: &mut dyn FnMut(&str)) -> Result<Outcome, LlmError> {
        let mut report = String::new();
        report.push_str(&format!(
            "# drivescript ask\n\nScene: {}\n\nRequest{}:\n{}\n\nBackend: {}{}\n\n",
            self.state.scene.display(),
            if self.state.requests.len() > 1 {
                "s"
            } else {
                ""
            },
            self.state
                .requests
                .iter()
                .map(|r| format!("- {r}"))
                .collect::<Vec<_>>()
                .join("\n"),
            self.state.backend,
            self.state
                .model
                .as_ref()
                .map(|m| format!(" ({m})"))
                .unwrap_or_default()
        ));
        let sampled_rounds = self.state.sampled;
        match &o {
            Outcome::Accepted { round, sample } => report.push_str(&format!(
                "Outcome: accepted: sample {sample} of round {round} meets the request.\n"
            )),
            Outcome::RoundsUsed { round, sample } => report.push_str(&format!(
                "Outcome: the rounds ran out ({} sampled); round {round} is final; {}.\n",
                sampled_rounds,
                match sample {
                    Some(k) => format!("its sample {k} meets the request"),
                    None => "none of its samples meets the request".into(),
                }
            )),
            Outcome::GaveUp { reason } => report.push_str(&format!("Outcome: gave up: {reason}\n")),
            Outcome::Infeasible { reasons } => {
                report.push_str(
                    "Outcome: not attempted: no plausible motion meets the request within the \
                     sampler's horizon, so no round was asked or sampled:\n",
                );
                for r in reasons {
                    report.push_str(&format!("- {r}\n"));
                }
            }
            Outcome::Waiting { .. } => {}
        }
        // The one judgement `ask` exits with and `ask --batch` counts.
        report.push_str(&format!("Verdict: {}.\n", self.verdict().text));
        if let Some((round, script)) = &self.state.script {
            write(&self.dir, "final.rhai", script)?;
            let from = self.dir.join(format!("round_{round}"));
            if let Ok(bytes) =
                crate::io::read_regular(&from.join("sample.gif"), MAX_RUN_FILE_BYTES, "a picture")
            {
                write_bytes(&self.dir, "final.gif", &bytes)?;
            }
            report.push_str(&format!(
                "\nFinal script: final.rhai (round {round}); picture: final.gif; rollouts and costs: {}.\n",
                self.rollout_files(*round)
            ));
            let reasons = self.last_reasons().to_vec();
            if !reasons.is_empty() {
                report.push_str("\nWhy the best sample of that round falls short:\n");
                for r in &reasons {
                    report.push_str(&format!("- {r}\n"));
                }
            }
        }
        let calls = self.transcript.iter().filter(|r| r.phase == "llm").count();
        report.push_str(&format!(
            "\nExchanges: {}; sampling rounds: {}; LLM calls: {calls}.\n",
            self.state.exchange, sampled_rounds
        ));
        write(&self.dir, "report.md", &report)?;
        self.state.outcome = Some(o.clone());
        self.save()?;
        for line in report
            .lines()
            .filter(|l| l.starts_with("Outcome") || l.starts_with("Verdict"))
        {
            progress(line);
        }
        Ok(o)
    }

    /// What happened to the last script, while it is not yet repaired: in the words kept for
    /// the user, or for a run recorded before they were kept, the error the model was told.
    fn last_failure(&self) -> Option<String> {
        let e = self.state.last_error.as_ref()?;
        Some(self.state.last_failure.clone().unwrap_or_else(|| e.clone()))
    }

    /// Who wrote the script that last failed, as a possessive for messages ("the rules
    /// planner's", "the model's (qwen2.5-coder:32b)"), and whether it was the rules planner.
    fn failed_script_author(&self) -> (String, bool) {
        let by = self
            .state
            .last_failure_by
            .as_deref()
            .unwrap_or(&self.state.backend);
        let words = match by {
            "rules" => "the rules planner's".to_string(),
            "http" => match &self.state.model {
                Some(m) => format!("the model's ({})", crate::io::name::shown_counted(m)),
                None => "the model's".to_string(),
            },
            "manual" => "the pasted reply's".to_string(),
            "replay" => "the recorded model's".to_string(),
            other => format!("the {other} backend's"),
        };
        (words, by == Backend::Rules.name())
    }

    /// The rules planner's reply to the current state: a composed script first, ACCEPT when
    /// a sample meets the request, else the script with the failing events strengthened.
    fn rules_reply(&mut self) -> Result<String, String> {
        let events: Vec<Event> = self
            .state
            .requests
            .iter()
            .map(|r| rules::plan_request(r))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| e.to_string())?
            .into_iter()
            .flatten()
            .collect();
        let mut tunings: Vec<Tuning> = self
            .state
            .tunings
            .iter()
            .map(|(w, m)| Tuning {
                weight: *w,
                margins: Params(
                    m.iter()
                        .map(|(k, v)| (k.clone(), ParamValue::Float(*v)))
                        .collect(),
                ),
            })
            .collect();
        tunings.resize(events.len(), Tuning::default());
        let mut reasoning = String::new();
        if self.state.script.is_some() && self.state.sampled > 0 {
            if self.state.meets.is_some() && self.state.misses == 0 {
                return Ok(format!(
                    "ACCEPT\nA sample meets the request: every term is within tolerance, every checker passes and no named agent moves implausibly.\n"
                ));
            }
            if let Some(why) = self.last_failure() {
                let (author, own) = self.failed_script_author();
                let whose = if own { "its".to_string() } else { author };
                return Err(format!(
                    "the rules planner cannot repair {whose} last script: {why}"
                ));
            }
            // An event fails when its checker fails or one of its terms is above tolerance on
            // the best sample; only failing events change.
            let (_, terms) = rules::compose_with_terms(&events, &tunings);
            let mut changed = Vec::new();
            for (k, e) in events.iter().enumerate() {
                let (passed, achieved) = self
                    .state
                    .event_results
                    .get(k)
                    .copied()
                    .unwrap_or((true, true));
                let over: Vec<&String> = terms
                    .get(k)
                    .into_iter()
                    .flatten()
                    .filter(|t| self.state.failing_terms.contains(t))
                    .collect();
                if passed && over.is_empty() {
                    continue;
                }
                // A checker that passes with terms still short is a near miss: pull harder.
                let (t, why) = rules::retune(e, &tunings[k], !passed && achieved);
                tunings[k] = t;
                changed.push(if over.is_empty() {
                    why
                } else {
                    format!(
                        "{why} ({} above tolerance)",
                        over.iter()
                            .map(|s| s.as_str())
                            .collect::<Vec<_>>()
                            .join(", ")
                    )
                });
            }
            if changed.is_empty() {
                // Only a named agent's motion fails: every event pulls less hard.
                for (k, e) in events.iter().enumerate() {
                    let (t, why) = rules::retune(e, &tunings[k], true);
                    tunings[k] = t;
                    changed.push(why);
                }
            }
            reasoning.push_str(&format!(
                "Repair (rules planner): the best sample fails; {}.\n",
                changed.join("; ")
            ));
        } else if let Some(why) = self
            .last_failure()
            .filter(|_| self.failed_script_author().1)
        {
            // Its own first script failed: composed again, it would fail the same way. One
            // another backend wrote (a run taken up with `--llm rules`) is no reason to stop:
            // the rules planner's own has not been tried, and is written below.
            return Err(format!(
                "the rules planner's script does not fit this scene: {why}"
            ));
        } else {
            reasoning.push_str(&rules::plan_text(&events));
        }
        self.state.tunings = tunings
            .iter()
            .map(|t| {
                (
                    t.weight,
                    t.margins
                        .0
                        .iter()
                        .filter_map(|(k, v)| Some((k.clone(), v.as_f64()?)))
                        .collect(),
                )
            })
            .collect();
        Ok(format!(
            "{reasoning}\n```rhai\n{}```\n",
            rules::compose(&events, &tunings)
        ))
    }
}

enum Got {
    Text(String),
    Wait(Outcome),
    GiveUp(String),
}

impl Session<'_> {
    /// The messages to send for exchange `n`: the conversation, fitted to `--context` where
    /// it is set (saying what was left out).
    fn to_send(&self, n: usize, progress: &mut dyn FnMut(&str)) -> Result<Vec<Message>, LlmError> {
        Ok(match self.state.config.context {
            None => self.state.messages.clone(),
            Some(w) => {
                let refit = |tokens: u64| {
                    let config = SessionConfig {
                        context: Some(super::fit::Window {
                            tokens: tokens + w.reply,
                            reply: w.reply,
                        }),
                        ..self.state.config.clone()
                    };
                    let horizon = self.trained.meta.config.window.future;
                    first_prompt(
                        &self.prompts,
                        &config,
                        &self.raw,
                        &self.state.requests,
                        horizon,
                    )
                    .map_err(|e| e.smallest)
                };
                // Requests added by `--continue`: the first prompt of the run does not hold
                // them, and their messages must outlive the rounds summarised around them.
                let follow_ups = self.state.requests.get(1..).unwrap_or_default();
                let f = fit_conversation(&self.state.messages, w.prompt(), follow_ups, &refit)
                    .map_err(|fewest| {
                        let size = if fewest == u64::MAX {
                            String::new()
                        } else {
                            format!(": it takes about {fewest} tokens")
                        };
                        LlmError::Context(format!(
                            "round {n}: the conversation does not fit --context {} ({} tokens \
                             for the prompt after {} for the reply) even with the earlier \
                             rounds summarised or left out, the last feedback cut down and the \
                             first prompt at its smallest{size}; {}",
                            w.tokens,
                            w.prompt(),
                            w.reply,
                            self.larger_window_advice()
                        ))
                    })?;
                if !f.left_out.is_empty() {
                    progress(&format!(
                        "round {n}: fitted to --context {}: left out {}",
                        w.tokens,
                        f.left_out.join("; ")
                    ));
                }
                f.messages
            }
        })
    }

    /// What to do when the run's window is too small for what it must send: a run taken up
    /// again keeps its window (`--resume` and `--continue` refuse `--context` and
    /// `--max-tokens`), so only a new run can have a larger one.
    fn larger_window_advice(&self) -> &'static str {
        if self.taken_up {
            "the run keeps the window it started with: start a new run (-o NEWDIR) with a larger \
             --context (and the server's window)"
        } else {
            "raise --context (and the server's window) or lower --max-tokens"
        }
    }

    /// What to do about a reply cut off at `max_tokens`: raise `--max-tokens` where that gives
    /// the reply more; with a window, the reply's share is at most a quarter of it, and a run
    /// taken up again keeps its share.
    fn longer_reply_advice(&self, max_tokens: u32) -> String {
        match self.state.config.context {
            None => "raise --max-tokens".into(),
            Some(_) if self.taken_up => "the run keeps the reply's share of its --context \
                 window: start a new run (-o NEWDIR) with a larger --context (or --max-tokens)"
                .into(),
            Some(w) if u64::from(max_tokens) < w.tokens / 4 => format!(
                "raise --max-tokens (the reply may take up to a quarter of --context {}, {})",
                w.tokens,
                w.tokens / 4
            ),
            Some(w) => format!(
                "raise --context (and the server's window): the reply takes at most a quarter \
                 of it, {} of {}",
                w.tokens / 4,
                w.tokens
            ),
        }
    }

    fn get_reply(
        &mut self,
        n: usize,
        rdir: &Path,
        progress: &mut dyn FnMut(&str),
    ) -> Result<Got, LlmError> {
        let t0 = Instant::now();
        if let Backend::Http(c) = &self.backend {
            progress(&format!("round {n}: asking {} ...", c.config().model));
            let sent = self.to_send(n, progress)?;
            // A refusal ends the run as one that did not succeed, saying why: asked again it
            // was refused again (up to --fixes times), and as an error it stopped a batch at
            // the pair for good, however often the batch was run again.
            let ex = match c.complete(&sent) {
                Err(LlmError::Refused { url, message }) => {
                    progress(&format!("round {n}: {message}"));
                    // A call the server answered: unrecorded, the report said "LLM calls: 0"
                    // for a run that made one, and its replay had nothing to give up on.
                    let detail = serde_json::json!({
                        "url": url,
                        "request": c.body(&sent),
                        "refused": message,
                        "latency": t0.elapsed().as_secs_f64(),
                    });
                    self.record(n, "llm", t0, Some(detail));
                    return Ok(Got::GiveUp(message));
                }
                other => other?,
            };
            // Without usage the check that the server read the whole prompt cannot run:
            // said, not skipped in silence.
            let usage = ex.usage.map_or_else(
                || {
                    format!(
                        " (the server reported no token usage, so a prompt cut to its context \
                         window cannot be detected{})",
                        if ex.streamed {
                            "; with --no-stream most servers report it"
                        } else {
                            ""
                        }
                    )
                },
                |u| format!(", {} + {} tokens", u.prompt_tokens, u.completion_tokens),
            );
            progress(&format!(
                "round {n}: reply in {:.1} s{usage}{}",
                ex.latency,
                if ex.retries.is_empty() {
                    String::new()
                } else {
                    format!(" after {} retries", ex.retries.len())
                }
            ));
            if ex.truncated {
                progress(&format!(
                    "round {n}: the reply was cut off at the token limit (--max-tokens {}); \
                     if its script is incomplete, {}",
                    c.config().max_tokens,
                    self.longer_reply_advice(c.config().max_tokens)
                ));
            }
            let reply = ex.reply.clone();
            let detail = serde_json::to_value(&ex).expect("exchange serialises");
            self.record(n, "llm", t0, Some(detail));
            return Ok(Got::Text(reply));
        }
        if let Backend::Replay(rec) = &self.backend {
            let rec = rec.clone();
            let k = self.transcript.iter().filter(|r| r.phase == "llm").count();
            let Some(ex) = rec.exchanges.get(k) else {
                return Err(LlmError::Input {
                    path: rec.path.clone(),
                    message: format!(
                        "it records {} exchanges and the replay asks for another: its scripts \
                         or verdicts differ from the recorded run's",
                        rec.exchanges.len()
                    ),
                });
            };
            let sent = self.to_send(n, progress)?;
            progress(&format!(
                "round {n}: the recorded reply ({} of {}){}",
                k + 1,
                rec.exchanges.len(),
                match super::replay::first_difference(&sent, &ex.messages) {
                    Some(d) => format!(
                        "; the prompt differs from the recorded one at {d} (the prompts or the \
                         loop changed since)"
                    ),
                    None => String::new(),
                }
            ));
            let mut detail = ex.detail.clone();
            detail["replayed"] = true.into();
            self.record(n, "llm", t0, Some(detail));
            if let Some(message) = &ex.refused {
                progress(&format!("round {n}: {message}"));
                return Ok(Got::GiveUp(message.clone()));
            }
            return Ok(Got::Text(ex.reply.clone()));
        }
        if let Backend::Manual = self.backend {
            let reply = rdir.join("reply.md");
            // The round's directory is the run's own (`own_subdir`): a link planted there as
            // the reply had whatever it named (a key file) copied into state.json and every
            // later prompt, as a link planted as the round's directory would have.
            if reply
                .symlink_metadata()
                .is_ok_and(|m| m.file_type().is_symlink())
            {
                let to = std::fs::read_link(&reply)
                    .map(|t| {
                        format!(
                            " (to {})",
                            crate::io::name::one_line(&t.display().to_string())
                        )
                    })
                    .unwrap_or_default();
                return Err(file_err(
                    &reply,
                    format!(
                        "is a symbolic link{to}, not the reply: save the model's answer in this \
                         file itself, then --resume"
                    ),
                ));
            }
            // Held to a server's cap: every reply is kept in `state.json` and each round's
            // `messages.json` and sent again with every later round, so a pasted 4 MB file
            // went on into each, and state.json grew past what --resume reads back.
            let read = crate::io::read_regular_text(
                &reply,
                super::client::MAX_COMPLETION_BYTES as u64,
                "a model's reply",
            );
            return Ok(match read {
                Ok(t) if !t.trim().is_empty() => {
                    self.record(n, "manual reply read", t0, None);
                    Got::Text(t)
                }
                // A reply saved but unreadable (UTF-16 from an editor, a link to a device, too
                // large) is said: "waiting for a reply" would send the user to save it again.
                Err(e) if reply.symlink_metadata().is_ok() => {
                    return Err(file_err(
                        &reply,
                        format!(
                            "cannot read the reply ({}): save the model's answer there as UTF-8 \
                             text, then --resume",
                            e.reason()
                        ),
                    ))
                }
                _ => Got::Wait(Outcome::Waiting {
                    prompt: rdir.join("prompt.md"),
                    reply,
                }),
            });
        }
        let r = self.rules_reply();
        self.record(n, "rules", t0, None);
        Ok(match r {
            Ok(t) => Got::Text(t),
            Err(reason) => Got::GiveUp(reason),
        })
    }
}

/// Refuses, before the run directory is made or the model asked, a scene the sampler cannot
/// sample ([`crate::train::dataset::step_mismatch`]): a scene of 0.5-s steps got a request
/// and a reply before the first round's sampling refused it, each round of a batch again.
fn check_scene_step(raw: &Scene) -> Result<(), LlmError> {
    match crate::train::dataset::step_mismatch(raw) {
        Some(m) => Err(LlmError::Setup(m)),
        None => Ok(()),
    }
}

/// Refuses, before the run directory is made or the model asked, more samples a round than
/// the scene's sampling batch fits in memory ([`crate::sample::check_samples_fit`]): they were
/// refused only when round 0 began to sample, after a request was sent and paid for.
pub fn check_samples_fit(trained: &Trained, raw: &Scene, samples: usize) -> Result<(), LlmError> {
    crate::sample::check_samples_fit(trained, raw, samples).map_err(|e| match e {
        SampleError::Settings(m) => LlmError::Setup(format!("--samples {samples}: {m}")),
        e => LlmError::Setup(e.to_string()),
    })
}

/// The first two messages of a run: the system prompt and the scene summary with the request
/// (what `prompt show` prints), fitted to the context window when one is set. `horizon` is the
/// sampler's (the checkpoint's future steps).
pub fn first_messages(
    prompts: &Prompts,
    config: &SessionConfig,
    raw: &Scene,
    requests: &[String],
    horizon: usize,
) -> Result<Fitted, LlmError> {
    // `prompt show` comes here without `ask`'s checks: it showed the model a prompt asking
    // for nothing, which `ask` refuses.
    for r in requests {
        check_request(r)?;
    }
    first_prompt(prompts, config, raw, requests, horizon)
        .map_err(|e| LlmError::Context(e.to_string()))
}

/// [`first_messages`], its error the smallest size: what a later round fits it from.
fn first_prompt(
    prompts: &Prompts,
    config: &SessionConfig,
    raw: &Scene,
    requests: &[String],
    horizon: usize,
) -> Result<Fitted, FirstTooLarge> {
    let keep: Vec<i64> = requests
        .iter()
        .flat_map(|r| numbers(r))
        .filter(|id| raw.agent(*id).is_some())
        .collect();
    let scene = raw.with_horizon(horizon);
    let summary = |max_agents: usize| {
        describe(
            &scene,
            &DescribeOptions {
                max_agents,
                keep: keep.clone(),
                horizon,
            },
        )
        .to_string()
    };
    match config.context {
        None => Ok(Fitted {
            messages: vec![
                Message::new("system", prompts.system(&config.prompt)),
                Message::new(
                    "user",
                    prompts.request(&summary(config.max_agents), &requests.join("\n")),
                ),
            ],
            left_out: Vec::new(),
        }),
        Some(w) => fit_first(
            prompts,
            &config.prompt,
            requests,
            &summary,
            config.max_agents,
            keep.len(),
            w,
        ),
    }
}

/// Numbers in a request (candidate agent ids the summary keeps).
fn numbers(text: &str) -> Vec<i64> {
    text.split(|c: char| !c.is_ascii_digit())
        .filter_map(|w| w.parse().ok())
        .collect()
}

fn indent(t: &str) -> String {
    t.lines()
        .map(|l| format!("    {l}"))
        .collect::<Vec<_>>()
        .join("\n")
}

/// Messages as one markdown document: what a person pastes into a chat.
pub fn render_messages(messages: &[Message]) -> String {
    let mut s = String::new();
    for m in messages {
        s.push_str(&format!("<!-- {} -->\n\n{}\n\n", m.role, m.content.trim()));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The state of a run that sampled once (exchange 0) and was refined once (exchange 1),
    /// as `state.json` holds it.
    fn sampled_once() -> Value {
        let state = State {
            version: STATE_VERSION,
            scene: "scene.xml".into(),
            scene_crc32c: Some(7),
            checkpoint: None,
            requests: vec!["vehicle 401 cuts in front of vehicle 399".into()],
            backend: "rules".into(),
            model: None,
            url: None,
            config: SessionConfig::default(),
            prompts: "prompts".into(),
            checks: Vec::new(),
            messages: vec![
                Message::new("system", "s"),
                Message::new("user", "u"),
                Message::new("assistant", "a script"),
                Message::new("user", "feedback"),
                Message::new("assistant", "another script"),
                Message::new("user", "feedback"),
            ],
            exchange: 2,
            sampled: 2,
            misses: 0,
            script: Some((1, "term(\"x\", 0.0);".into())),
            meets: Some(3),
            tunings: Vec::new(),
            event_results: Vec::new(),
            failing_terms: Vec::new(),
            history: [0, 1]
                .map(|exchange| RoundRecord {
                    exchange,
                    meets: true,
                    achieved: true,
                    passed: true,
                    reasons: Vec::new(),
                    success: Some(true),
                })
                .to_vec(),
            left_out: Vec::new(),
            last_error: None,
            last_failure: None,
            last_failure_by: None,
            accept_refused: false,
            final_turn: false,
            outcome: Some(Outcome::Accepted {
                round: 1,
                sample: 3,
            }),
        };
        serde_json::to_value(state).unwrap()
    }

    #[test]
    fn state_json_counts_out_of_range_are_errors_naming_the_field() {
        read_state(&sampled_once().to_string()).unwrap();
        let edit = |pointer: &str, v: Value| {
            let mut state = sampled_once();
            *state.pointer_mut(pointer).unwrap() = v;
            read_state(&state.to_string()).unwrap_err()
        };
        for (pointer, v, says) in [
            // Once wrapped to 0 on the next reply, overwriting round_0.
            (
                "/exchange",
                json!(u64::MAX),
                "`exchange` is 18446744073709551615, but",
            ),
            (
                "/exchange",
                json!(-1),
                "`exchange` is -1: must be a whole number",
            ),
            (
                "/exchange",
                json!(1e30),
                "`exchange` is 1e+30: must be a whole number",
            ),
            (
                "/sampled",
                json!(-3),
                "`sampled` is -3: must be a whole number",
            ),
            // Once a silent carry-on: the next sampling ended the run at once.
            (
                "/sampled",
                json!(u64::MAX),
                "`sampled` is 18446744073709551615: a run samples at most `config.rounds` + 1 = 4",
            ),
            (
                "/misses",
                json!(50),
                "`misses` is 50: a run gives up after `config.fixes` + 1 = 4",
            ),
            (
                "/meets",
                json!(4),
                "`meets` is 4: must be a sample of the round, below `config.samples` (4)",
            ),
            (
                "/script/0",
                json!(2),
                "`script[0]` is 2: must be an exchange of the run",
            ),
            (
                "/history/1/exchange",
                json!(0),
                "`history[1].exchange` is 0",
            ),
            (
                "/history/0/exchange",
                json!(-2),
                "`history[0].exchange` is -2: must be a whole number",
            ),
            (
                "/outcome/Accepted/sample",
                json!(9),
                "`outcome.Accepted.sample` is 9",
            ),
            (
                "/config/samples",
                json!(1_000_000_000u64),
                "`config`: samples = 1000000000: must be 1 to 1024",
            ),
            (
                "/config/rounds",
                json!(1u64 << 40),
                "`config`: rounds = 1099511627776: must be 0 to 20",
            ),
            (
                "/config/max_agents",
                json!(0),
                "`config`: max_agents = 0: must be 1 to 1000",
            ),
            // Said in 309 digits (issue 32).
            (
                "/config/script_budget",
                json!(1e308),
                "`config`: script_budget = 1e308 s: must be more than 0 and at most 86400 s",
            ),
            (
                "/config/tolerance",
                json!(-1e300),
                "`config`: tolerance = -1e300: must be finite and not negative",
            ),
            ("/config/realism", json!(-1e300), "= -1e300: must be"),
        ] {
            let e = edit(pointer, v);
            assert!(e.contains(says), "{pointer}: {e}");
            assert!(
                e.contains("edited or damaged") || e.contains("damaged"),
                "{pointer}: {e}"
            );
        }
        let mut state = sampled_once();
        state["history"].as_array_mut().unwrap().pop();
        let e = read_state(&state.to_string()).unwrap_err();
        assert!(e.contains("`sampled` is 2, but `history` records 1"), "{e}");
        // A checker that cannot be read, or no request: the run went on without them, and
        // judged it "succeeded" (issue 32).
        let mut state = sampled_once();
        state["checks"] = json!([{"behaviour": "nope", "params": {}}]);
        let e = read_state(&state.to_string()).unwrap_err();
        assert!(
            e.contains("`checks[0].behaviour`") && e.contains("nope"),
            "{e}"
        );
        let mut state = sampled_once();
        state["checks"] = json!([{"behaviour": "off_road", "params": {"vehicle": 1, "typo": 2}}]);
        let e = read_state(&state.to_string()).unwrap_err();
        assert!(
            e.contains("`checks[0].params`") && e.contains("typo"),
            "{e}"
        );
        let mut state = sampled_once();
        state["requests"] = json!([]);
        let e = read_state(&state.to_string()).unwrap_err();
        assert!(e.contains("`requests` is empty"), "{e}");
    }

    #[test]
    fn guidance_is_one_setting_and_runs_recorded_with_the_old_flag_read_it() {
        let fresh = serde_json::to_value(SessionConfig::default()).unwrap();
        assert_eq!(fresh["guidance"], "output");
        assert!(fresh.get("through_denoiser").is_none(), "{fresh}");
        // state.json and transcript.json of runs before the flag was one setting.
        for (old, want) in [
            (true, crate::sample::Guidance::Denoiser),
            (false, crate::sample::Guidance::OutputSpace),
        ] {
            let mut v = fresh.clone();
            let o = v.as_object_mut().unwrap();
            o.remove("guidance");
            o.insert("through_denoiser".into(), old.into());
            let read: SessionConfig = serde_json::from_value(v).unwrap();
            assert_eq!(read.guidance, want);
            assert_eq!(read.sample_config().guidance, want);
        }
        let mut v = fresh;
        v["guidance"] = "denoiser".into();
        let read: SessionConfig = serde_json::from_value(v.clone()).unwrap();
        assert_eq!(read.guidance, crate::sample::Guidance::Denoiser);
        // Named, with what it holds (issue 32: "data did not match any variant of untagged
        // enum Written").
        v["guidance"] = "back\u{1b}wards".into();
        let e = serde_json::from_value::<SessionConfig>(v)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("`guidance` is \"back\\u001bwards\": it is \"denoiser\" or \"output\"")
                && !e.contains("untagged"),
            "{e}"
        );
    }

    fn record(meets: bool, passed: bool, fully_checked: bool) -> RoundRecord {
        RoundRecord {
            exchange: 0,
            meets,
            achieved: passed,
            passed,
            reasons: Vec::new(),
            success: Some(round_succeeded(meets, passed, fully_checked)),
        }
    }

    #[test]
    fn a_round_succeeds_by_its_checkers_where_they_judge_the_whole_request() {
        // Every checker passes, a script term is over its tolerance: met, by the checkers.
        let r = record(false, true, true);
        assert!(r.succeeded());
        assert_eq!(
            r.verdict_words(),
            "met by the checkers (script terms over tolerance)"
        );
        // A clause without a checker: its terms judge it, and they fail.
        let r = record(false, true, false);
        assert!(!r.succeeded());
        assert_eq!(
            r.verdict_words(),
            "checkers pass, unchecked clauses not met"
        );
        // No checker at all: the terms and the named agents' motion.
        assert!(record(true, false, false).succeeded());
        assert!(!record(false, false, false).succeeded());
        // The run's verdict is its last round's.
        let v = run_verdict(&[record(false, false, true), record(false, true, true)]);
        assert!(v.succeeded && v.round == Some(0), "{v:?}");
        assert!(!run_verdict(&[]).succeeded);
        // Records from before the judgement was kept.
        let old = RoundRecord {
            success: None,
            ..record(false, true, true)
        };
        assert!(old.succeeded());
    }
}
