//! Evaluation: the paper's metrics, independent behaviour checkers and baselines. Everything
//! here is a pure function of scenes, so any rollout (any simulator's) can be scored.

pub mod asked;
pub mod baselines;
pub mod behaviors;
pub mod collateral;
pub mod feasibility;
pub mod kinematic;
pub mod merge;
pub mod metrics;
pub mod suggest;
pub mod tally;

pub use baselines::Baseline;
pub use behaviors::{check, check_against_unguided, check_allowing, Behavior, CheckError, Verdict};
pub use collateral::{collateral, Collateral, CollateralError};
pub use feasibility::{infeasible, Infeasible};
pub use kinematic::{judge, Judgement, KinematicLimits, Violation};
pub use tally::{map_kind, Group, MapKind, Tally, Task};

#[cfg(test)]
mod tests;
