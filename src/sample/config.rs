//! What a sampling run is asked to do: the task, where guidance acts, the guidance schedule
//! and clamp, their limits and defaults, and how a run fails.

use crate::cost::{CostError, CostScript, Realism};

/// What the sampler is conditioned on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Task {
    /// History and each agent's recorded end point (a known-state cost): its state at the
    /// end of the horizon, or its last recorded one where its recording stops earlier, after
    /// which the agent leaves the scene.
    Conditional,
    /// History only.
    Unconditional,
}

/// Where the guidance gradient is taken: `--guidance denoiser|output` on every command that
/// samples, `denoiser` / `output` in run records.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Guidance {
    /// Through the denoiser to the noisy input (candle backward; the paper's rule).
    #[serde(rename = "denoiser")]
    Denoiser,
    /// At the denoised output (no backward pass).
    #[serde(rename = "output")]
    OutputSpace,
}

impl Guidance {
    /// `denoiser` or `output`, as `--guidance` and the reports name it.
    pub fn name(self) -> &'static str {
        match self {
            Guidance::Denoiser => "denoiser",
            Guidance::OutputSpace => "output",
        }
    }
}

/// The guidance every command that samples uses unless told otherwise (`simulate`, `ask`,
/// `ask --batch`, `demo`): output space. It is what the loop and the demo were built and
/// measured with (the batch figures of docs/asking.md, the demo's run), what most behaviour tables of
/// data/checkpoint/README.md use, and it is faster (0.12 s against 0.20 s a guided sample;
/// 221 s against 268 s for the held-out windows' table) at rates within a few windows of the
/// denoiser's either way (cut-in 0.80 against 0.87, rightmost lane 0.81 against 0.75).
/// `simulate` once defaulted to the denoiser while `ask` took output space: one setting named
/// two ways with two defaults.
pub const DEFAULT_GUIDANCE: Guidance = Guidance::OutputSpace;

/// Guidance strength λ for behaviour scripts (unconditional task, [`LambdaSchedule::Fading`]),
/// chosen on the held-out NGSIM instances with the shipped checkpoint (data/checkpoint/README.md:
/// 2 suited the 10,000-step model, the 18,000-step one follows the data more closely and
/// needs 3).
pub const BEHAVIOUR_LAMBDA: f64 = 3.0;

/// The most samples one sampling run draws (`--samples`).
pub const MAX_SAMPLES: usize = 1024;

/// The fewest Heun steps a sample takes (`--steps`): one step from σ_max straight to 0 is not
/// a sample.
pub const MIN_HEUN_STEPS: usize = 2;

/// The most Heun steps a sample takes (`--steps`).
pub const MAX_HEUN_STEPS: usize = 1000;

/// The largest guidance strength and term weight the sampler takes (λ, the known-state and the
/// realism weights): the defaults are 1 to 3, and 1e308 turned the denoiser's output into
/// infinities, or printed 300-digit weights, instead of being refused.
pub const MAX_WEIGHT: f64 = 1000.0;

/// Weight of the realism terms in `simulate`, `demo` and `ask` unless told otherwise
/// ([`Realism`]; data/checkpoint/README.md has the measurements behind it).
pub const REALISM_WEIGHT: f64 = 1.0;

/// Descent steps after the last denoising step ([`SampleConfig::polish`]) in `simulate`,
/// `demo` and `ask` unless told otherwise.
pub const POLISH_STEPS: usize = 300;

/// The default [`SampleConfig::script_budget`]: five minutes of script evaluation per sampling
/// run. The hand-written scripts take a few milliseconds per evaluation, a run of four
/// samples a few hundred evaluations (Heun steps, then two stages of polish): seconds in all.
/// A script at 1.8 s per evaluation, within the per-call wall time, would take over an hour.
pub const DEFAULT_SCRIPT_BUDGET: std::time::Duration = std::time::Duration::from_secs(300);

/// The largest [`SampleConfig::script_budget`]: a day.
pub const MAX_SCRIPT_BUDGET: std::time::Duration = std::time::Duration::from_secs(86_400);

/// How the guidance step depends on the noise level σ.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LambdaSchedule {
    /// `λ` at every σ.
    Constant,
    /// `λ·σ/(σ + σ_data)`: full strength while the plan forms, fading as σ → 0, so that the
    /// last steps (where clamped gradients act like signs and a constant step overshoots) are
    /// fine corrections.
    Fading,
}

impl LambdaSchedule {
    /// The factor on λ at noise level `sigma`.
    pub fn factor(self, sigma: f64, sigma_data: f64) -> f64 {
        match self {
            LambdaSchedule::Constant => 1.0,
            LambdaSchedule::Fading => sigma / (sigma + sigma_data),
        }
    }
}

/// How the guidance gradient is kept within (-1, 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Clamp {
    /// Each coefficient clipped on its own (the paper's rule). A saturated gradient becomes
    /// its sign pattern: every component of the agent moves by the same amount, rare shapes
    /// as far as common ones, whatever the cost asked for.
    Coordinate,
    /// Each agent's coefficient gradient scaled down as a whole until its largest entry is
    /// 1: within the same bounds, but in the direction of steepest descent.
    Agent,
}

/// Sampler settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SampleConfig {
    /// Heun steps.
    pub steps: usize,
    /// Samples per scene (one batch).
    pub samples: usize,
    /// Seed of the initial noise.
    pub seed: u64,
    /// Guidance strength λ.
    pub lambda: f64,
    /// Conditioning.
    pub task: Task,
    /// Guidance gradient.
    pub guidance: Guidance,
    /// Weight of the known-state (end point) cost.
    pub known_weight: f64,
    /// How λ varies with the noise level.
    pub schedule: LambdaSchedule,
    /// How the gradient is bounded.
    pub clamp: Clamp,
    /// Realism for every agent the model moves, guided beside the scripts whenever anything
    /// guides (weight 0: off).
    pub realism: Realism,
    /// Descent steps on the guidance cost after the last denoising step (0: none), where
    /// anything guides: this many without realism's collision term, then (realism on) this
    /// many with it. Realism keeps cars clear only here, or while denoising when this is 0
    /// (the realism module says why).
    pub polish: usize,
    /// Future steps to sample, at most the model's horizon (`None`: the model's horizon). A
    /// model of 8 s samples 4 s by generating its whole future and keeping the first 40
    /// steps: guidance and the conditional end point act on those alone.
    pub horizon: Option<usize>,
    /// Wall time the cost scripts may take, all their evaluations together, over a sampling
    /// run (one scene's samples, validation, every round of a closed loop): past it the run
    /// stops with [`SampleError::ScriptBudget`] rather than go on for hours.
    pub script_budget: std::time::Duration,
}

impl SampleConfig {
    /// Checks the settings before any work: 2 to 1000 Heun steps (one step from σ_max
    /// straight to 0 is not a sample), 1 to 1024 samples, and a guidance strength and
    /// known-state weight that are finite and not negative (a negative one pushes towards the
    /// costs). The message names the setting and its range.
    pub fn validate(&self) -> Result<(), String> {
        if !(MIN_HEUN_STEPS..=MAX_HEUN_STEPS).contains(&self.steps) {
            return Err(format!(
                "steps = {}: must be {MIN_HEUN_STEPS} to {MAX_HEUN_STEPS}",
                self.steps
            ));
        }
        if !(1..=MAX_SAMPLES).contains(&self.samples) {
            return Err(format!(
                "samples = {}: must be 1 to {MAX_SAMPLES}",
                self.samples
            ));
        }
        for (name, v) in [
            ("lambda", self.lambda),
            ("known weight", self.known_weight),
            ("realism weight", self.realism.weight),
        ] {
            if !(v.is_finite() && (0.0..=MAX_WEIGHT).contains(&v)) {
                return Err(format!(
                    "{name} = {}: must be 0 to {MAX_WEIGHT}",
                    crate::geom::num(v)
                ));
            }
        }
        if self.horizon == Some(0) {
            return Err("horizon = 0: must be at least 1 step".into());
        }
        if self.polish > 1000 {
            return Err(format!("polish = {}: must be 0 to 1000", self.polish));
        }
        if self.script_budget.is_zero() || self.script_budget > MAX_SCRIPT_BUDGET {
            return Err(format!(
                "script budget = {} s: must be more than 0 and at most {} s",
                self.script_budget.as_secs_f64(),
                MAX_SCRIPT_BUDGET.as_secs()
            ));
        }
        let m = self.realism.margin;
        if !(m > 0.0 && m <= 1.0) {
            return Err(format!(
                "realism margin = {}: must be in (0, 1]",
                crate::geom::num(m)
            ));
        }
        Ok(())
    }
}

impl Default for SampleConfig {
    fn default() -> Self {
        Self {
            steps: 32,
            samples: 1,
            seed: 1,
            lambda: 0.1,
            task: Task::Conditional,
            guidance: DEFAULT_GUIDANCE,
            known_weight: 1.0,
            schedule: LambdaSchedule::Constant,
            clamp: Clamp::Coordinate,
            realism: Realism {
                weight: 0.0,
                ..Realism::default()
            },
            polish: 0,
            horizon: None,
            script_budget: DEFAULT_SCRIPT_BUDGET,
        }
    }
}

/// Errors of sampling.
#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    /// The tensor library failed (its message without candle's backtrace).
    #[error("model: {0}")]
    Candle(candle_core::Error),
    /// A cost script failed (its message names the script, line and term).
    #[error(transparent)]
    Cost(#[from] CostError),
    /// A non-finite value appeared; the run stops rather than write NaN trajectories.
    #[error("non-finite {what} at sampling step {step}")]
    NonFinite {
        /// What was not finite.
        what: &'static str,
        /// The step.
        step: usize,
    },
    /// The scene cannot be simulated.
    #[error("{0}")]
    Scene(String),
    /// Settings sampling cannot run with ([`SampleConfig::validate`]).
    #[error("sampler settings: {0}")]
    Settings(String),
    /// The cost scripts took longer than the run's budget ([`SampleConfig::script_budget`]).
    #[error(
        "the cost scripts took {:.1} s over {} evaluations ({:.3} s each), past this run's budget \
         of {} s for script evaluation (--script-budget): a sampling run evaluates its scripts \
         hundreds of times (every denoising step and polish iteration, for every sample), so a \
         script this slow would run for a long time; make it faster (fewer operations per \
         evaluation: no long loops over steps) or raise --script-budget",
        used.time.as_secs_f64(),
        used.evaluations,
        used.mean().as_secs_f64(),
        budget.as_secs_f64()
    )]
    ScriptBudget {
        /// The budget.
        budget: std::time::Duration,
        /// The scripts' evaluations and their time when it ran out.
        used: crate::cost::Usage,
    },
    /// Another thread set the run's stop flag ([`sample_until`](super::guided::sample_until)).
    #[error("sampling stopped before its end, as asked")]
    Stopped,
}

/// Ends a run whose stop flag is set.
pub(super) fn check_stop(stop: &std::sync::atomic::AtomicBool) -> Result<(), SampleError> {
    if stop.load(std::sync::atomic::Ordering::Relaxed) {
        return Err(SampleError::Stopped);
    }
    Ok(())
}

/// Stops a run whose scripts have taken more than `cfg.script_budget` together.
pub(super) fn check_script_budget(
    scripts: &[CostScript],
    cfg: &SampleConfig,
) -> Result<(), SampleError> {
    let used = scripts
        .iter()
        .fold(crate::cost::Usage::default(), |u, s| u.plus(s.usage()));
    if used.time > cfg.script_budget {
        return Err(SampleError::ScriptBudget {
            budget: cfg.script_budget,
            used,
        });
    }
    Ok(())
}

impl From<candle_core::Error> for SampleError {
    fn from(e: candle_core::Error) -> Self {
        SampleError::Candle(crate::model::error::without_backtrace(e))
    }
}
