//! The cost engine: sandboxed Rhai cost scripts evaluated with sparse dual-number gradients.
//!
//! A script sees the scene (agents, lanes, lane graph) and one set of candidate trajectories,
//! and declares named terms with `term(name, value)`. Values are [`Dual`] numbers or
//! [`Series`] of them over the future steps; the gradient of each term w.r.t. every
//! trajectory coordinate ([`VarLayout`]) comes out of the evaluation with its value.

pub mod attribution;
mod bound;
mod dual;
mod engine;
mod fwd;
mod params;
pub mod probe;
mod realism;
mod report;
mod resident;
mod series;
mod spec;
pub mod stdlib;
mod trajectory;

pub use bound::{on_script_stack, BoundScript, SCRIPT_STACK_BYTES};
pub use dual::{Dual, Grad};
pub use engine::{
    check_params, module_functions, read_script, reference, reference_markdown,
    reference_markdown_without, script_params, uses_param, CostError, CostScript, DeadTerm, Limits,
    Usage, MAX_SOURCE_BYTES, STDLIB_MODULES,
};
pub use fwd::{box_clearance, Fwd};
pub use params::{ParamValue, Params};
pub use realism::{Allowed, Realism, TERMS as REALISM_TERMS};
pub use report::{CostReport, TermReport};
pub use series::Series;
pub use spec::ScriptSpec;
pub use stdlib::DocEntry;
pub use trajectory::{Coord, Trajectories, VarLayout};

#[cfg(test)]
mod gradient_tests;
pub mod handwritten;
pub mod script_test;
