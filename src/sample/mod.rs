//! Sampling from the diffusion model, guided by cost scripts, open or closed loop.

pub mod attempt;
pub mod closed_loop;
pub mod config;
pub mod guided;
mod heun;
mod plan;
pub mod provenance;

pub use crate::cost::ScriptSpec;
pub use attempt::{
    attempt, attempt_until, AgentShare, Attempt, AttemptError, AttemptReport, AttemptSpec, Carried,
    RealismEvent, SampleOutcome, Settings, TermOutcome, CARRIERS_SHOWN,
};
pub use closed_loop::{closed_loop, closed_loop_until};
pub use config::{
    Clamp, Guidance, LambdaSchedule, SampleConfig, SampleError, Task, BEHAVIOUR_LAMBDA,
    DEFAULT_GUIDANCE, DEFAULT_SCRIPT_BUDGET, MAX_HEUN_STEPS, MAX_SAMPLES, MAX_SCRIPT_BUDGET,
    MAX_WEIGHT, MIN_HEUN_STEPS, POLISH_STEPS, REALISM_WEIGHT,
};
pub use guided::{
    check_samples_fit, horizon_note, modelled, prepare, prepare_for, recorded_future,
    reference_run, sample, sample_until, sampled_horizon, too_few_steps, Sample,
};
