//! `drivescript ask`: words → cost script → guided samples → repaired script, with an
//! OpenAI-compatible server, a person (manual) or the rules planner answering. The loop is
//! [`drivescript::llm::Session`]; this file parses flags and prints progress.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use drivescript::geom::num;
use drivescript::io::name::terminal_safe;
use drivescript::io::{load_scene, LoadOptions};
use drivescript::llm::client::ClientEvent;
use drivescript::llm::{
    Backend, Cot, HttpClient, HttpConfig, LlmError, Outcome, PromptOptions, Prompts, Session,
    SessionConfig,
};
use drivescript::train::{load, Trained};

/// Which backend answers.
#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Llm {
    /// An OpenAI-compatible server when one is configured (URL and model), else the rules
    /// planner (announced).
    Auto,
    /// An OpenAI-compatible chat-completions server.
    Http,
    /// Write each prompt to a file and stop until its reply is saved; `--resume` continues.
    Manual,
    /// The deterministic rules planner over scripts/ (not a language model).
    Rules,
}

#[derive(clap::Args)]
pub struct Args {
    /// SCENE "REQUEST" for a new run; only "REQUEST" with --continue; nothing with --resume.
    words: Vec<String>,
    /// Run directory (prompts, replies, scripts, rollouts, transcript, final.rhai, final.gif).
    #[arg(short, long)]
    output: Option<PathBuf>,
    /// Continue the run in this directory where it stopped (a manual round's reply saved, or
    /// a run that was killed).
    #[arg(long, value_name = "DIR", conflicts_with = "follow_up")]
    resume: Option<PathBuf>,
    /// Revise the run in this directory with a follow-up request instead of starting over.
    #[arg(long = "continue", value_name = "DIR", conflicts_with = "batch")]
    follow_up: Option<PathBuf>,
    /// Run again a run recorded in this transcript.json, its replies read from the file (no
    /// server is asked), into the new run directory -o DIR; then compare its scripts, verdicts
    /// and outcome with the recorded run's (exit 2 where they differ).
    #[arg(long, value_name = "TRANSCRIPT", conflicts_with_all = ["resume", "follow_up", "batch"])]
    replay: Option<PathBuf>,
    /// Run every (scene, request) pair of this YAML file into -o DIR and write a summary table
    /// per behaviour (before refinement and after each round) and rollouts for `eval`.
    #[arg(long, value_name = "FILE", conflicts_with = "resume")]
    batch: Option<PathBuf>,
    /// With --batch: scenes (files or directories) replacing the file's top-level `scenes:`.
    #[arg(long, value_name = "PATH", requires = "batch")]
    scenes: Vec<PathBuf>,
    /// With --batch: only the pairs whose scene falls in shard I of N (a stable partition by
    /// scenario id, as `simulate --shard`). Run the shards into one -o, then the same command
    /// without --shard: it reads every finished pair back and writes the whole summary.
    #[arg(long, value_name = "I/N", requires = "batch")]
    shard: Option<drivescript::io::shard::Shard>,
    /// Print every round's progress in --batch runs (default: one line per pair; a single run
    /// prints every round).
    #[arg(short, long)]
    verbose: bool,
    /// Who answers.
    #[arg(long, value_enum, default_value = "auto")]
    llm: Llm,
    /// Server base URL (overrides DRIVESCRIPT_LLM_URL), e.g. http://127.0.0.1:11434/v1.
    #[arg(long)]
    llm_url: Option<String>,
    /// Model name (overrides DRIVESCRIPT_LLM_MODEL). The key is read only from
    /// DRIVESCRIPT_LLM_KEY, never from a flag, so it stays out of shell history.
    #[arg(long)]
    model: Option<String>,
    /// Sampling temperature sent with every request, 0 to 2.
    #[arg(long, value_parser = float, default_value_t = 0.2)]
    temperature: f64,
    /// Most tokens per reply, 1 to 1,000,000.
    #[arg(long, default_value_t = 4096, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    max_tokens: u32,
    /// The request field for --max-tokens: max_tokens (most servers) or max_completion_tokens
    /// (OpenAI's newer models); ASCII letters, digits and `_`, at most 64, and none of the
    /// fields the request already sends.
    #[arg(long, default_value = "max_tokens")]
    max_tokens_field: String,
    /// Ask for the reply in one piece instead of as a stream of events (streamed replies show
    /// tokens so far, tokens per second and elapsed time on a terminal).
    #[arg(long)]
    no_stream: bool,
    /// Seconds of silence allowed: before the reply's head, and between the parts of a reply;
    /// also the longest a streamed reply may go without a token, whatever else it sends
    /// (more than 0, at most 3600).
    #[arg(long, value_parser = float, default_value_t = 300.0)]
    llm_timeout: f64,
    /// Seconds a reply may take in all, from the first request (retries and the waits between
    /// them included): past it a reply still coming is abandoned (more than 0, at most 86400).
    #[arg(long, value_parser = float, default_value_t = 1800.0)]
    reply_deadline: f64,
    /// Attempts per request on 429 and 5xx answers, 1 to 20.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=20))]
    attempts: u32,
    /// First wait between attempts, seconds (doubles each time unless the server sends
    /// Retry-After), 0 to 600.
    #[arg(long, value_parser = float, default_value_t = 2.0)]
    backoff: f64,
    /// The longest wait between attempts, seconds: the doubling stops there, and a server's
    /// Retry-After asking for more is cut to it (said on the terminal), 0 to 3600.
    #[arg(long, value_parser = float, default_value_t = 600.0)]
    backoff_max: f64,
    /// Refinement rounds after the first sampling (0: the first script is final), at most 20.
    #[arg(long, default_value_t = 3, value_parser = usize_in(0, drivescript::llm::session::MAX_ROUNDS))]
    rounds: usize,
    /// Unusable replies, failed validations and rejected ACCEPTs allowed in a row, at most 20.
    #[arg(long, default_value_t = 3, value_parser = usize_in(0, drivescript::llm::session::MAX_FIXES))]
    fixes: usize,
    /// Samples per round, 1 to 1024.
    #[arg(long, default_value_t = 4, value_parser = usize_in(1, drivescript::sample::MAX_SAMPLES))]
    samples: usize,
    /// Seed of the initial noise (also sent to the server, which treats it as best effort).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Largest unweighted script term a sample may keep and still meet the request (finite,
    /// 0 to 1000).
    #[arg(long, value_parser = float, default_value_t = 0.05)]
    tolerance: f64,
    /// Checkpoint directory (default: the one shipped in data/checkpoint).
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    #[command(flatten)]
    prompt: PromptFlags,
    /// Where the guidance gradient is taken: at the denoised output, or pulled back through
    /// the denoiser (the paper's rule, slower); the same flag and default as `simulate`'s.
    #[arg(long, value_enum, default_value = "output")]
    guidance: super::GuidanceArg,
    /// The old name of `--guidance denoiser`, still read (hidden): one setting had two names.
    #[arg(long, hide = true, conflicts_with = "guidance")]
    through_denoiser: bool,
    /// Descent steps on the guidance cost after the last denoising step, 0 to 1000, then as
    /// many with realism's collision term (0: none).
    #[arg(long, default_value_t = drivescript::sample::POLISH_STEPS, value_parser = usize_in(0, 1000))]
    polish: usize,
    /// Seconds the cost script may take over one round's sampling, every evaluation together
    /// (more than 0, at most 86400); the same flag and default as `simulate`'s. A script past
    /// it goes back to the model as that round's feedback, and the run goes on.
    #[arg(long, value_parser = float, value_name = "SECONDS", default_value_t = drivescript::sample::DEFAULT_SCRIPT_BUDGET.as_secs_f64())]
    script_budget: f64,
}

/// What the first prompt holds: shared by `ask` and `prompt show`, so that the prompt shown is
/// the prompt sent.
#[derive(clap::Args)]
pub(crate) struct PromptFlags {
    /// Most agents in the scene summary (the request's are always listed), 1 to 1000.
    #[arg(long, default_value_t = 30, value_parser = usize_in(1, drivescript::llm::session::MAX_AGENTS))]
    pub max_agents: usize,
    /// Prompt templates (default: prompts/).
    #[arg(long)]
    pub prompts: Option<PathBuf>,
    /// Ablation: request → script with no reasoning.
    #[arg(long, conflicts_with = "zero_shot_cot")]
    pub no_cot: bool,
    /// Ablation: "think step by step" instead of the designed chain of thought.
    #[arg(long)]
    pub zero_shot_cot: bool,
    /// Ablation: the reference without the Frenet-frame functions.
    #[arg(long)]
    pub no_frenet: bool,
    /// The model's context window, tokens (512 to 10,000,000): every request is fitted to it,
    /// a quarter of it (at most --max-tokens) kept for the reply; the first prompt gets a
    /// compact reference, fewer agents and examples as it must, later rounds a summary of the
    /// older ones; what was left out is said. Without it the whole conversation is sent.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(drivescript::llm::fit::MIN_CONTEXT..=drivescript::llm::fit::MAX_CONTEXT))]
    pub context: Option<u64>,
}

impl PromptFlags {
    /// The prompt options these flags choose.
    pub(crate) fn options(&self) -> PromptOptions {
        PromptOptions {
            cot: if self.no_cot {
                Cot::None
            } else if self.zero_shot_cot {
                Cot::ZeroShot
            } else {
                Cot::Designed
            },
            frenet: !self.no_frenet,
        }
    }

    /// The window --context states, with the reply's part of it for replies of at most
    /// `max_tokens`.
    pub(crate) fn window(&self, max_tokens: u32) -> Option<drivescript::llm::fit::Window> {
        self.context.map(|tokens| drivescript::llm::fit::Window {
            tokens,
            reply: drivescript::llm::fit::reply_budget(tokens, u64::from(max_tokens)),
        })
    }

    /// The templates, from --prompts or prompts/.
    pub(crate) fn load(&self) -> Result<Prompts, LlmError> {
        Prompts::load(&self.prompts.clone().unwrap_or_else(Prompts::default_dir))
    }
}

fn env(name: &str) -> Result<Option<String>, LlmError> {
    match std::env::var(name) {
        Ok(v) => Ok(Some(v).filter(|v| !v.trim().is_empty())),
        Err(std::env::VarError::NotPresent) => Ok(None),
        // Taken for unset, it made a set URL "no server URL" and a set key no key at all. The
        // value is not quoted: it may be the key.
        Err(std::env::VarError::NotUnicode(_)) => Err(LlmError::Setup(format!(
            "{name} is set but is not UTF-8 text (a value read from a file in another encoding?): \
             set it again as plain text"
        ))),
    }
}

/// The backend the flags and environment choose, with a line saying which.
pub(crate) fn backend(
    llm: Llm,
    url: Option<&str>,
    model: Option<&str>,
    args_http: impl FnOnce(String, String) -> HttpConfig,
) -> Result<(Backend, String), LlmError> {
    // Read only where a server may be asked: --llm rules or manual reads none of them.
    let server = matches!(llm, Llm::Http | Llm::Auto);
    let url = match url {
        Some(u) => Some(u.to_string()),
        None if server => env("DRIVESCRIPT_LLM_URL")?,
        None => None,
    };
    let model = match model {
        Some(m) => Some(m.to_string()),
        None if server => env("DRIVESCRIPT_LLM_MODEL")?,
        None => None,
    };
    let http = |url: String, model: String| -> Result<(Backend, String), LlmError> {
        let mut cfg = args_http(url, model);
        // A key pasted or read from a file may end in a line break, which no header can carry.
        cfg.key = env("DRIVESCRIPT_LLM_KEY")?.map(|k| k.trim().to_string());
        let line = format!(
            "LLM: {} at {}",
            cfg.model,
            drivescript::llm::client::redact_url(&cfg.endpoint())
        );
        let client = HttpClient::new(cfg)?.with_observer(observer());
        Ok((Backend::Http(client), line))
    };
    match llm {
        Llm::Rules => Ok((
            Backend::Rules,
            "LLM: none; the rules planner (a fixed vocabulary, not a language model) writes the scripts".into(),
        )),
        Llm::Manual => Ok((
            Backend::Manual,
            "LLM: manual; each prompt is written to a file for you to paste into any chat".into(),
        )),
        Llm::Http => match (url, model) {
            (Some(u), Some(m)) => http(u, m),
            (u, m) => Err(LlmError::Setup(format!(
                "--llm http needs {}: set DRIVESCRIPT_LLM_URL and DRIVESCRIPT_LLM_MODEL or pass --llm-url and --model",
                match (u, m) {
                    (None, None) => "a server URL and a model",
                    (None, _) => "a server URL",
                    _ => "a model name",
                }
            ))),
        },
        Llm::Auto => match (url, model) {
            (Some(u), Some(m)) => http(u, m),
            (Some(_), None) => Err(LlmError::Setup(
                "an LLM URL is set but no model: set DRIVESCRIPT_LLM_MODEL or pass --model".into(),
            )),
            // The rules planner, announced as "none configured", was not what a model asked.
            (None, Some(_)) => Err(LlmError::Setup(
                "an LLM model is set but no server URL: set DRIVESCRIPT_LLM_URL or pass \
                 --llm-url (or --llm rules for the rules planner)"
                    .into(),
            )),
            _ => Ok((
                Backend::Rules,
                "LLM: none configured (DRIVESCRIPT_LLM_URL and DRIVESCRIPT_LLM_MODEL are unset), so the rules planner writes the scripts: a fixed vocabulary of behaviours, not a language model".into(),
            )),
        },
    }
}

/// Prints what the client reports while a reply is under way: notices always, and on a
/// terminal a progress line of a streamed reply, rewritten in place a few times a second.
fn observer() -> drivescript::llm::client::Observer {
    use std::io::{IsTerminal, Write};
    let terminal = std::io::stderr().is_terminal();
    let last = std::sync::Mutex::new(None::<std::time::Instant>);
    std::sync::Arc::new(move |e: ClientEvent<'_>| match e {
        ClientEvent::Notice(line) => eprintln!("{}", terminal_safe(line)),
        ClientEvent::Streaming {
            tokens,
            since_first,
            elapsed,
        } if terminal => {
            let mut last = last.lock().unwrap_or_else(|p| p.into_inner());
            if last.is_some_and(|t| t.elapsed() < Duration::from_millis(250)) {
                return;
            }
            *last = Some(std::time::Instant::now());
            let line = drivescript::llm::stream::progress_line(tokens, since_first, elapsed);
            let _ = write!(std::io::stderr(), "\r\x1b[K  {line}");
        }
        ClientEvent::StreamEnd if terminal => {
            *last.lock().unwrap_or_else(|p| p.into_inner()) = None;
            let _ = write!(std::io::stderr(), "\r\x1b[K");
        }
        _ => {}
    })
}

impl Args {
    fn http_config(&self, url: String, model: String) -> HttpConfig {
        let mut c = HttpConfig::new(url, model);
        c.temperature = self.temperature;
        c.max_tokens = self.max_tokens;
        c.max_tokens_field = self.max_tokens_field.clone();
        c.seed = Some(self.seed);
        c.stream = !self.no_stream;
        if let Some(w) = self.prompt.window(self.max_tokens) {
            // The reply's share of the window, which the prompt was fitted to leave.
            c.max_tokens = u32::try_from(w.reply).unwrap_or(u32::MAX);
        }
        c.read_timeout = Duration::from_secs_f64(self.llm_timeout.max(0.001));
        c.reply_deadline = Duration::from_secs_f64(self.reply_deadline.max(0.001));
        c.attempts = self.attempts;
        c.backoff = Duration::from_secs_f64(self.backoff.max(0.0));
        c.backoff_max = Duration::from_secs_f64(self.backoff_max.max(0.0));
        c
    }

    fn session_config(&self) -> SessionConfig {
        SessionConfig {
            rounds: self.rounds,
            fixes: self.fixes,
            prompt: self.prompt.options(),
            tolerance: self.tolerance,
            max_agents: self.prompt.max_agents,
            samples: self.samples,
            seed: self.seed,
            guidance: self.guidance(),
            polish: self.polish,
            script_budget: self.script_budget,
            context: self.prompt.window(self.max_tokens),
            ..SessionConfig::default()
        }
    }

    /// `--guidance`, or denoiser where the old `--through-denoiser` asks for it.
    fn guidance(&self) -> drivescript::sample::Guidance {
        if self.through_denoiser {
            drivescript::sample::Guidance::Denoiser
        } else {
            self.guidance.into()
        }
    }

    /// The backend the flags and environment choose, with the line that says which; a flag
    /// that backend does not read is refused ([`unread`]).
    fn backend(&self, given: &[String]) -> Result<(Backend, String), LlmError> {
        let (b, line) = backend(
            self.llm,
            self.llm_url.as_deref(),
            self.model.as_deref(),
            |u, m| self.http_config(u, m),
        )?;
        let by = if self.llm == Llm::Auto {
            ChosenBy::Auto
        } else {
            ChosenBy::Flag
        };
        unread(given, &Reading::of(&b, by), None)?;
        Ok((b, line))
    }
}

/// Flags (clap id, as typed) that only a server reads: sent with each request or governing
/// how it is sent and retried.
const SERVER_FLAGS: [(&str, &str); 11] = [
    ("llm_url", "--llm-url"),
    ("model", "--model"),
    ("temperature", "--temperature"),
    ("max_tokens", "--max-tokens"),
    ("max_tokens_field", "--max-tokens-field"),
    ("no_stream", "--no-stream"),
    ("llm_timeout", "--llm-timeout"),
    ("reply_deadline", "--reply-deadline"),
    ("attempts", "--attempts"),
    ("backoff", "--backoff"),
    ("backoff_max", "--backoff-max"),
];

/// Flags that shape only the prompt a model reads.
const PROMPT_FLAGS: [(&str, &str); 6] = [
    ("context", "--context"),
    ("max_agents", "--max-agents"),
    ("prompts", "--prompts"),
    ("no_cot", "--no-cot"),
    ("zero_shot_cot", "--zero-shot-cot"),
    ("no_frenet", "--no-frenet"),
];

/// The settings a run records when it starts (`state.json`), which `--resume`, `--continue`
/// and `--replay` take from there.
const RUN_SETTINGS: [(&str, &str); 9] = [
    ("rounds", "--rounds"),
    ("fixes", "--fixes"),
    ("samples", "--samples"),
    ("seed", "--seed"),
    ("tolerance", "--tolerance"),
    ("guidance", "--guidance"),
    ("through_denoiser", "--through-denoiser"),
    ("polish", "--polish"),
    ("script_budget", "--script-budget"),
];

/// How the backend came to be chosen, for the message that refuses a flag it does not read.
#[derive(Clone, Copy, PartialEq, Eq)]
enum ChosenBy {
    /// `--llm manual` or `--llm rules`.
    Flag,
    /// `--llm auto`, where no server is configured.
    Auto,
    /// The backend the run recorded (`--resume`, `--continue`).
    Recorded,
}

/// Who answers, as far as which flags it reads.
enum Reading {
    /// A server: every flag.
    Server,
    /// A person pasting prompts.
    Manual(ChosenBy),
    /// The rules planner.
    Rules(ChosenBy),
}

impl Reading {
    fn of(b: &Backend, by: ChosenBy) -> Self {
        match b {
            Backend::Manual => Reading::Manual(by),
            Backend::Rules => Reading::Rules(by),
            _ => Reading::Server,
        }
    }
}

/// Refuses a flag in `given` (clap ids given on the command line) that the backend does not
/// read: dropped without a word, it would leave the user believing the run used it
/// (`--llm rules --temperature 1.5`). `again` is `--resume` or `--continue` where the run is
/// taken up again: the advice then names no flag that mode refuses.
fn unread(given: &[String], reading: &Reading, again: Option<&str>) -> Result<(), LlmError> {
    let is_given = |id: &str| given.iter().any(|g| g == id);
    let first = |flags: &[(&'static str, &'static str)]| {
        flags.iter().find(|(id, _)| is_given(id)).map(|(_, f)| *f)
    };
    let refuse = |flag: &str, why: &str| Err(LlmError::Setup(format!("{flag}: {why}")));
    match reading {
        Reading::Server => Ok(()),
        Reading::Manual(by) => {
            let who = if *by == ChosenBy::Recorded {
                "the run's backend, manual,"
            } else {
                "--llm manual"
            };
            // With --context, --max-tokens sets the reply's share of the window the first
            // prompt is fitted to.
            let server: Vec<(&str, &str)> = SERVER_FLAGS
                .into_iter()
                .filter(|(id, _)| !(*id == "max_tokens" && is_given("context")))
                .collect();
            match first(&server) {
                Some("--max-tokens") => refuse(
                    "--max-tokens",
                    &match again {
                        None => format!(
                            "{who} asks no server; --max-tokens sets only the reply's share of \
                             the --context window, and --context is not given"
                        ),
                        // --context is refused there: the window is the run's.
                        Some(mode) => format!(
                            "{who} asks no server; --max-tokens would set only the reply's share \
                             of a --context window, which a run states when it starts, and \
                             {mode} goes on with the run's (its state.json)"
                        ),
                    },
                ),
                Some(flag) => refuse(
                    flag,
                    &format!(
                        "{who} asks no server (you paste each prompt into a chat of your choice, \
                         with its own settings)"
                    ),
                ),
                None => Ok(()),
            }
        }
        Reading::Rules(by) => {
            let who = match by {
                ChosenBy::Flag => "--llm rules",
                ChosenBy::Auto => {
                    "the rules planner (--llm auto's choice: no server is configured with \
                     DRIVESCRIPT_LLM_URL and DRIVESCRIPT_LLM_MODEL, or --llm-url and --model)"
                }
                ChosenBy::Recorded => "the run's backend, the rules planner,",
            };
            if let Some(flag) = first(&SERVER_FLAGS) {
                return refuse(flag, &format!("{who} asks no server"));
            }
            if let Some(flag) = first(&PROMPT_FLAGS) {
                return refuse(
                    flag,
                    &format!(
                        "{who} sends no prompt to a model (the rules planner reads only the \
                         request; round_N/prompt.md is written for the record)"
                    ),
                );
            }
            Ok(())
        }
    }
}

/// Refuses a flag in `given` that a run taken up again would not read: the settings it
/// recorded when it started, and for `--replay` the backend and its settings too (the
/// transcript's replies answer), or that a single run does not read (`-v`).
fn unread_by_mode(args: &Args, given: &[String]) -> Result<()> {
    let is_given = |id: &str| given.iter().any(|g| g == id);
    if is_given("verbose") && args.batch.is_none() {
        bail!(
            "-v/--verbose: only --batch prints less than every round; a single run prints every \
             round already"
        );
    }
    let again = if args.resume.is_some() {
        Some("--resume")
    } else if args.follow_up.is_some() {
        Some("--continue")
    } else {
        None
    };
    if let Some(mode) = again {
        let mut recorded = RUN_SETTINGS.iter().chain(&PROMPT_FLAGS);
        if let Some((_, flag)) = recorded.find(|(id, _)| is_given(id)) {
            bail!(
                "{flag}: {mode} goes on with the settings the run started with (its state.json); \
                 start a new run (-o NEWDIR) to change them"
            );
        }
        if is_given("output") {
            bail!("-o: {mode} DIR goes on in DIR, the run's own directory");
        }
    }
    if args.replay.is_some() {
        let mut recorded = RUN_SETTINGS
            .iter()
            .chain(PROMPT_FLAGS.iter().filter(|(id, _)| *id != "prompts"))
            .chain(&SERVER_FLAGS)
            .chain(&[("llm", "--llm")]);
        if let Some((_, flag)) = recorded.find(|(id, _)| is_given(id)) {
            bail!(
                "{flag}: --replay asks no backend (the transcript's replies answer) and runs with \
                 the recorded run's settings"
            );
        }
    }
    Ok(())
}

pub(crate) fn checkpoint(path: Option<&Path>) -> Result<Trained> {
    let ckpt = path
        .map(Path::to_path_buf)
        .unwrap_or_else(|| super::samples_dir().join("../checkpoint"));
    load(&ckpt).with_context(|| format!("loading the diffusion checkpoint {}", ckpt.display()))
}

/// Reopens the run in `dir` with its own backend, unless the flags choose another.
fn reopen<'a>(
    args: &Args,
    given: &[String],
    dir: &Path,
    trained: &'a Trained,
) -> Result<Session<'a>, LlmError> {
    let s = Session::resume(
        dir,
        trained,
        |recorded, rec_model, _| {
            let chosen = match (args.llm, recorded) {
                (Llm::Auto, "http") => Llm::Http,
                (Llm::Auto, "manual") => Llm::Manual,
                (Llm::Auto, _) => Llm::Rules,
                (l, _) => l,
            };
            let model = args.model.clone().or_else(|| rec_model.map(str::to_string));
            let (b, line) = backend(chosen, args.llm_url.as_deref(), model.as_deref(), |u, m| {
                args.http_config(u, m)
            })?;
            let by = if args.llm == Llm::Auto {
                ChosenBy::Recorded
            } else {
                ChosenBy::Flag
            };
            let mode = if args.resume.is_some() {
                "--resume"
            } else {
                "--continue"
            };
            unread(given, &Reading::of(&b, by), Some(mode))?;
            println!("{line}");
            Ok(b)
        },
        load_one,
    )?;
    // With a window, --max-tokens chose the reply's share of it when the run started, and
    // every prompt since was fitted to leave that share; the run's requests ask for it.
    if let Some(w) = s.config().context {
        if given.iter().any(|g| g == "max_tokens") {
            let mode = if args.resume.is_some() {
                "--resume"
            } else {
                "--continue"
            };
            return Err(LlmError::Setup(format!(
                "--max-tokens: the run fits its prompts to --context {} with {} tokens for the \
                 reply (its state.json), and {mode} goes on with them; start a new run \
                 (-o NEWDIR) to change them",
                w.tokens, w.reply
            )));
        }
    }
    Ok(s)
}

/// A clap parser for a `usize` in `lo..=hi` (clap's ranged parsers are for the fixed-width
/// integer types).
pub(crate) fn usize_in(
    lo: usize,
    hi: usize,
) -> impl clap::builder::TypedValueParser<Value = usize> {
    clap::builder::TypedValueParser::map(
        clap::value_parser!(u64).range(lo as u64..=hi as u64),
        |v| v as usize,
    )
}

/// A clap parser for a float flag: a number written beyond the largest float (`1e400`) is
/// refused as written, where Rust's parser reads it as infinity and the flag's range check
/// then spoke of `inf`, a value nobody typed. `inf` and `nan` typed as such pass through to
/// that check.
pub(crate) fn float(text: &str) -> Result<f64, String> {
    let v: f64 = text
        .parse()
        .map_err(|_| format!("{} is not a number", drivescript::io::name::shown(text)))?;
    if drivescript::geom::written_beyond_f64(text, v) {
        return Err(format!(
            "{} {}",
            drivescript::io::name::shown(text),
            drivescript::geom::BEYOND_F64
        ));
    }
    Ok(v)
}

fn load_one(path: &Path) -> Result<drivescript::scene::Scene, LlmError> {
    load_scene(path, 0, &LoadOptions::default()).map_err(|e| LlmError::Input {
        path: path.to_path_buf(),
        message: format!("cannot load the scene: {}", e.reason()),
    })
}

/// Runs `ask`; `given` are the flags given on the command line (clap ids).
pub fn run(args: Args, given: &[String]) -> Result<ExitCode> {
    let max_tolerance = drivescript::llm::session::MAX_TOLERANCE;
    if !(args.tolerance.is_finite() && (0.0..=max_tolerance).contains(&args.tolerance)) {
        bail!(
            "--tolerance {}: must be finite and not negative, at most {max_tolerance}",
            num(args.tolerance)
        );
    }
    if !(0.0..=2.0).contains(&args.temperature) {
        bail!("--temperature {}: must be 0 to 2", num(args.temperature));
    }
    if !(args.llm_timeout > 0.0 && args.llm_timeout <= 3600.0) {
        bail!(
            "--llm-timeout {}: must be more than 0 and at most 3600 seconds",
            num(args.llm_timeout)
        );
    }
    if !(args.reply_deadline > 0.0 && args.reply_deadline <= 86400.0) {
        bail!(
            "--reply-deadline {}: must be more than 0 and at most 86400 seconds",
            num(args.reply_deadline)
        );
    }
    if !(0.0..=600.0).contains(&args.backoff) {
        bail!("--backoff {}: must be 0 to 600 seconds", num(args.backoff));
    }
    if !(0.0..=3600.0).contains(&args.backoff_max) {
        bail!(
            "--backoff-max {}: must be 0 to 3600 seconds",
            num(args.backoff_max)
        );
    }
    super::script_budget(args.script_budget)?;
    drivescript::llm::client::check_max_tokens_field(&args.max_tokens_field)?;
    unread_by_mode(&args, given)?;
    if args.through_denoiser {
        eprintln!("note: --through-denoiser is the old name of --guidance denoiser");
    }
    let trained = checkpoint(args.checkpoint.as_deref())?;
    if let Some(file) = &args.batch {
        return batch(&args, given, file, &trained);
    }
    // Plans, scripts and verdicts quote the model's reply, escape sequences included.
    let mut progress = |line: &str| println!("{}", terminal_safe(line));
    let mut session = if let Some(dir) = &args.resume {
        if !args.words.is_empty() {
            bail!("--resume DIR takes no scene or request (the run recorded them)");
        }
        let s = reopen(&args, given, dir, &trained)?;
        println!("resuming {}", super::shown(&dir));
        s
    } else if let Some(file) = &args.replay {
        if !args.words.is_empty() {
            bail!("--replay TRANSCRIPT takes no scene or request (the transcript has them)");
        }
        let Some(dir) = &args.output else {
            bail!("--replay needs -o DIR, a new run directory");
        };
        let rec = drivescript::llm::replay::read_transcript(file)?;
        // The model's name and the request are the transcript's, a file that may come from
        // anyone: an escape sequence in them reached the terminal, a line break faked a line.
        println!(
            "LLM: none; replaying the {} recorded replies of {} ({}) from {}",
            rec.exchanges.len(),
            drivescript::io::name::shown(rec.model.as_deref().unwrap_or("a model")),
            terminal_safe(&rec.request),
            super::shown(&file)
        );
        let raw = load_one(&rec.scene)?;
        let checks = rec
            .checks
            .as_deref()
            .map(drivescript::llm::session::stored_checks);
        Session::start(
            dir,
            &rec.scene.clone(),
            raw,
            &rec.request.clone(),
            &trained,
            Backend::Replay(std::sync::Arc::new(rec.clone())),
            args.prompt.load()?,
            rec.config.clone(),
            checks,
        )?
    } else if let Some(dir) = &args.follow_up {
        let [request] = args.words.as_slice() else {
            bail!("--continue DIR takes one argument, the follow-up request in quotes");
        };
        let mut s = reopen(&args, given, dir, &trained)?;
        s.follow_up(request)?;
        println!("follow-up on {}: {request}", super::shown(&dir));
        s
    } else {
        let [scene, request] = args.words.as_slice() else {
            bail!(
                "ask needs a scene and a request in quotes: drivescript ask SCENE \"vehicle 3 cuts in front of vehicle 5\" -o runs/ask1 (or --resume DIR, or --continue DIR \"follow-up\")"
            );
        };
        let Some(dir) = &args.output else {
            bail!("ask needs -o DIR, the run directory");
        };
        let (b, line) = args.backend(given)?;
        println!("{line}");
        let path = PathBuf::from(scene);
        let raw = load_one(&path)?;
        let prompts = args.prompt.load()?;
        let s = Session::start(
            dir,
            &path,
            raw,
            request,
            &trained,
            b,
            prompts,
            args.session_config(),
            None,
        )?;
        if let Some(w) = args.prompt.window(args.max_tokens) {
            println!(
                "context: fitted to --context {} ({} tokens for the prompt, {} for the reply){}",
                w.tokens,
                w.prompt(),
                w.reply,
                if s.left_out().is_empty() {
                    String::from("; nothing left out")
                } else {
                    format!("; left out: {}", s.left_out().join("; "))
                }
            );
        }
        let checks = s.checks();
        if checks.is_empty() {
            println!("checkers: none (the request is not in the rules planner's vocabulary; acceptance is judged on the terms and the named agents' motion)");
        } else {
            for (b, p) in &checks {
                println!("checker: {} ({p}): {}", b.name(), b.definition());
            }
            for clause in s.unchecked() {
                println!("no checker for {clause:?} (not in the rules planner's vocabulary): it is judged on the terms and the named agents' motion only");
            }
        }
        s
    };
    let outcome = session.run(&mut progress)?;
    let dir = session.dir().to_path_buf();
    let mut reproduced = true;
    if let Some(file) = &args.replay {
        let original = file.parent().unwrap_or(Path::new("."));
        let c = drivescript::llm::replay::compare_replay(file, &dir)?;
        reproduced = c.differences.is_empty();
        match &c.not_compared {
            None if reproduced => println!(
                "replay: the same scripts, verdicts and outcome as the recorded run in {}",
                super::shown(original)
            ),
            None => {}
            Some(why) => println!("replay: {why}"),
        }
        for d in &c.differences {
            println!("replay differs: {d}");
        }
    }
    match outcome {
        Outcome::Waiting { prompt, reply } => {
            println!(
                "waiting for a reply: paste {} into a chat, save the answer as {}, then run: drivescript ask --resume {}",
                super::shown(&prompt),
                super::shown(&reply),
                super::shown(&dir)
            );
            Ok(ExitCode::SUCCESS)
        }
        Outcome::Infeasible { .. } => {
            eprintln!(
                "error: no plausible motion meets the request within the horizon; nothing was \
                 asked or sampled (see {})",
                super::shown(&dir.join("report.md"))
            );
            Ok(ExitCode::from(2))
        }
        Outcome::Accepted { .. } | Outcome::RoundsUsed { .. } | Outcome::GaveUp { .. } => {
            // The exit status is the run's verdict, the judgement `ask --batch` counts too.
            let verdict = session.verdict();
            if let Outcome::GaveUp { reason } = &outcome {
                eprintln!(
                    "{}: {reason} (see {})",
                    if verdict.succeeded { "note" } else { "error" },
                    super::shown(&dir.join("report.md"))
                );
            }
            if verdict.round.is_some() {
                println!(
                    "wrote {}, {} and {}{}",
                    super::shown(&dir.join("final.rhai")),
                    super::shown(&dir.join("final.gif")),
                    super::shown(&dir.join("report.md")),
                    if matches!(outcome, Outcome::Accepted { .. }) {
                        ""
                    } else {
                        " (not accepted)"
                    }
                );
            }
            Ok(if verdict.succeeded && reproduced {
                ExitCode::SUCCESS
            } else {
                ExitCode::from(2)
            })
        }
    }
}

fn batch(args: &Args, given: &[String], file: &Path, trained: &Trained) -> Result<ExitCode> {
    use drivescript::llm::batch::{expand, markdown, read_batch, summarise, Batch, Progress};
    if !args.words.is_empty() {
        bail!("--batch FILE takes no scene or request (the file lists them)");
    }
    let Some(out) = &args.output else {
        bail!("--batch needs -o DIR for the runs, rollouts and summary");
    };
    if args.llm == Llm::Manual {
        bail!("--batch runs without a person: use --llm http or --llm rules");
    }
    let mut entries = read_batch(file)?;
    // A --scenes path that is not there was reported as the batch file's ("FILE: entry on
    // line 3: sub: No such file or directory"), though the file never named it.
    for p in &args.scenes {
        if std::fs::metadata(p).is_err() {
            bail!(
                "--scenes {}: no such file or directory (a --scenes path is taken from the \
                 current directory, not the batch file's)",
                super::shown(p)
            );
        }
    }
    if !args.scenes.is_empty() {
        for e in entries.iter_mut().filter(|e| e.default_scenes) {
            e.scenes = args.scenes.clone();
        }
    }
    let horizon = trained.meta.config.window.future;
    let (instances, skipped) = expand(&entries, horizon)?;
    for s in &skipped {
        println!("skipped: {s}");
    }
    if instances.is_empty() {
        bail!("{}: no (scene, request) pair to run", file.display());
    }
    let (backend, line) = args.backend(given)?;
    println!("{line}");
    let prompts = args.prompt.load()?;
    let n = instances.len();
    let batch = Batch {
        file: file.to_path_buf(),
        instances,
        skipped,
        out: out.clone(),
        trained,
        backend,
        prompts,
        config: args.session_config(),
        shard: args.shard,
    };
    let verbose = args.verbose;
    let results = batch.run(&mut |p| match p {
        Progress::Ready { runs } => println!("{n} pairs; runs in {}", super::shown(runs)),
        Progress::Line(l) if verbose => println!("  {}", terminal_safe(l)),
        Progress::Line(_) => {}
        Progress::Done { k, result, resumed } => println!(
            "{}",
            terminal_safe(&format!(
                "[{}/{n}] {}: {}: {}{}; {}; {}",
                k + 1,
                result.scenario,
                result.label,
                result.outcome,
                if resumed { " (continued run)" } else { "" },
                result.verdict.text,
                result
                    .rounds
                    .iter()
                    .enumerate()
                    .map(|(r, h)| format!("round {r} {}", h.verdict_words()))
                    .collect::<Vec<_>>()
                    .join(", ")
            ))
        ),
    })?;
    println!();
    print!(
        "{}",
        markdown(&summarise(&results, args.rounds), args.rounds)
    );
    println!(
        "wrote {}, {} and rollouts per behaviour in {}",
        super::shown(&out.join("summary.md")),
        super::shown(&out.join("summary.json")),
        super::shown(&out.join("rollouts"))
    );
    Ok(ExitCode::SUCCESS)
}
