//! Sampling from the diffusion model, guided by cost scripts, open or closed loop.

pub mod attempt;
pub mod closed_loop;
pub mod guided;
pub mod provenance;

pub use crate::cost::ScriptSpec;
pub use attempt::{
    attempt, Attempt, AttemptError, AttemptReport, AttemptSpec, RealismEvent, SampleOutcome,
    Settings, TermOutcome,
};
pub use closed_loop::closed_loop;
pub use guided::{
    horizon_note, modelled, prepare, prepare_for, recorded_future, reference_run, sample,
    sampled_horizon, Clamp, Guidance, LambdaSchedule, Sample, SampleConfig, SampleError, Task,
    BEHAVIOUR_LAMBDA, DEFAULT_GUIDANCE, DEFAULT_SCRIPT_BUDGET, MAX_SCRIPT_BUDGET, POLISH_STEPS,
    REALISM_WEIGHT,
};
