//! The native functions scripts call, registered into the Rhai engine with their documentation.
//!
//! Every function is registered next to a [`DocEntry`] (signature and one line), so that the
//! reference `drivescript stdlib-doc` prints, and that the LLM prompts include, is generated
//! from what the engine actually has.

mod agents;
mod frenet;
mod interact;
mod lanes;
mod math;

use std::cell::RefCell;
use std::collections::HashMap;
use std::rc::Rc;

use rhai::{Dynamic, Engine, EvalAltResult, Position};

use super::dual::Dual;
use super::series::Series;
use super::trajectory::Trajectories;
use crate::scene::{LanePath, Scene, Turn};

pub(crate) use agents::AgentRef;
pub(crate) use frenet::{FrenetRef, PathRef};

/// One documented function, property or operator of the script API.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct DocEntry {
    /// Section of the reference.
    pub section: &'static str,
    /// Signature as scripts write it.
    pub signature: &'static str,
    /// One line of documentation.
    pub doc: &'static str,
}

/// A term declared by a script.
#[derive(Debug, Clone)]
pub(crate) struct Term {
    pub name: String,
    pub weight: f64,
    pub value: Dual,
    pub line: Option<usize>,
    pub tolerance: Option<f64>,
}

/// What native functions see: the scene, the candidate trajectories and what the script has
/// declared so far.
pub(crate) struct Ctx {
    pub scene: Rc<Scene>,
    pub traj: Trajectories,
    pub terms: Vec<Term>,
    pub prints: Vec<String>,
    /// `print`/`debug` lines past [`super::Limits::max_print_lines`], counted, not kept.
    pub prints_dropped: usize,
    pub paths: HashMap<(i64, u64, u64, Turn), Rc<LanePath>>,
    pub widths: HashMap<usize, Rc<Vec<(f64, f64)>>>,
    pub params: std::collections::BTreeMap<String, Dynamic>,
    /// Agent coordinate series of the current evaluation, built once per agent and coordinate.
    pub coords: HashMap<(usize, u8), Series>,
    /// Agents (scene indices) the script allows to reverse (`allow(a, "reverse")`).
    pub may_reverse: Vec<usize>,
    /// Pairs of agents (scene indices, smaller first) the script allows to touch
    /// (`allow(a, "collide", b)`).
    pub may_collide: Vec<(usize, usize)>,
    /// Agent ids the script looked up by `agent(id)`, in first-lookup order: the agents it
    /// names (the loop judges their motion).
    pub named: Vec<i64>,
    /// When the current evaluation started (shared with the engine's progress callback), and
    /// its wall-time limit: long native calls check it themselves, since the engine's
    /// callback runs only between script operations.
    pub clock: (Rc<std::cell::Cell<std::time::Instant>>, std::time::Duration),
}

/// The error that ends an evaluation past its wall time, inside a native call (the engine's
/// progress callback reports the same between operations).
pub(crate) fn over_time(ctx: &Ctx) -> RResult<()> {
    if ctx.clock.0.get().elapsed() > ctx.clock.1 {
        return Err(Box::new(EvalAltResult::ErrorTerminated(
            Dynamic::from(crate::cost::engine::WALL_TIME_MARK.to_string()),
            Position::NONE,
        )));
    }
    Ok(())
}

pub(crate) type Shared = Rc<RefCell<Ctx>>;

pub(crate) type RResult<T> = Result<T, Box<EvalAltResult>>;

/// A script-level error from a message.
pub(crate) fn err<T>(msg: impl Into<String>) -> RResult<T> {
    Err(Box::new(EvalAltResult::ErrorRuntime(
        Dynamic::from(msg.into()),
        Position::NONE,
    )))
}

/// `--param NAME=VALUE` for each given parameter whose value is `v`: a function handed a value
/// it cannot take names where it came from.
pub(crate) fn given_as(shared: &Shared, v: &Dynamic) -> Vec<String> {
    let ctx = shared.borrow();
    ctx.params
        .iter()
        .filter(|(_, p)| p.type_name() == v.type_name() && p.to_string() == v.to_string())
        .map(|(k, p)| format!("--param {k}={}", crate::io::name::shown(&p.to_string())))
        .collect()
}

/// A numeric script value: a series, a scalar dual or a plain number.
pub(crate) enum Val {
    S(Series),
    D(Dual),
    F(f64),
}

impl Val {
    pub(crate) fn from_dynamic(d: &Dynamic, what: &str) -> RResult<Val> {
        if let Some(s) = d.clone().try_cast::<Series>() {
            Ok(Val::S(s))
        } else if let Some(x) = d.clone().try_cast::<Dual>() {
            Ok(Val::D(x))
        } else if let Ok(f) = d.as_float() {
            Ok(Val::F(f))
        } else if let Ok(i) = d.as_int() {
            Ok(Val::F(i as f64))
        } else {
            err(format!(
                "{what} expects a Series, Dual or number, got {}",
                a_type(d)
            ))
        }
    }

    pub(crate) fn into_dynamic(self) -> Dynamic {
        match self {
            Val::S(s) => Dynamic::from(s),
            Val::D(d) => Dynamic::from(d),
            Val::F(f) => Dynamic::from(f),
        }
    }
}

/// What a script value is, with an article, as the script's author knows it: Rhai's
/// `type_name` gives the Rust path of the types registered here ("the value is a
/// drivescript::cost::stdlib::agents::AgentRef") and "a ()" for nothing.
pub(crate) fn a_type(d: &Dynamic) -> String {
    let name = d.type_name();
    let word = match name.rsplit("::").next().unwrap_or(name) {
        "AgentRef" => "an Agent",
        "PathRef" => "a Path",
        "FrenetRef" => "a Frenet",
        "Series" => "a Series",
        "Dual" => "a Dual",
        "()" => "nothing (the unit value ())",
        "array" => "an array",
        "map" => "a map",
        "Fn" => "a function",
        "bool" => "true or false",
        "string" => "a string",
        "char" => "a character",
        "i64" => "a whole number",
        "f64" => "a decimal number",
        other => return format!("a {other}"),
    };
    word.to_string()
}

/// A plain number from an int or float argument.
pub(crate) fn number(d: &Dynamic, what: &str) -> RResult<f64> {
    if let Ok(f) = d.as_float() {
        Ok(f)
    } else if let Ok(i) = d.as_int() {
        Ok(i as f64)
    } else {
        err(format!("{what} expects a number, got {}", a_type(d)))
    }
}

/// [`number`] for a bound, threshold or shape parameter, refused when NaN: no comparison with
/// NaN holds, so `clamp(x, NaN, 5)` clamped every value to 5 and `hinge(x, NaN)` was 0,
/// both without a word. Infinities stay (`clamp(x, -1.0 / 0.0, 5)` has no lower bound).
pub(crate) fn real(d: &Dynamic, what: &str) -> RResult<f64> {
    let v = number(d, what)?;
    if v.is_nan() {
        return err(format!("{what} is NaN, not a number"));
    }
    Ok(v)
}

/// Registers every native function and returns their documentation.
pub(crate) fn register(engine: &mut Engine, shared: &Shared) -> Vec<DocEntry> {
    let mut docs = Vec::new();
    engine
        .register_type_with_name::<Series>("Series")
        .register_type_with_name::<Dual>("Dual")
        .register_type_with_name::<AgentRef>("Agent")
        .register_type_with_name::<PathRef>("Path")
        .register_type_with_name::<FrenetRef>("Frenet");
    math::register(engine, &mut docs);
    agents::register(engine, shared, &mut docs);
    frenet::register(engine, shared, &mut docs);
    lanes::register(engine, shared, &mut docs);
    interact::register(engine, shared, &mut docs);
    docs
}

/// Records a documentation entry.
pub(crate) fn doc(
    docs: &mut Vec<DocEntry>,
    section: &'static str,
    signature: &'static str,
    doc: &'static str,
) {
    docs.push(DocEntry {
        section,
        signature,
        doc,
    });
}

/// Parses a turn name.
pub(crate) fn turn(s: &str) -> RResult<Turn> {
    match Turn::from_word(s) {
        Some(t) => Ok(t),
        None => err(format!(
            "turn must be \"straight\", \"left\" or \"right\", got {s:?}"
        )),
    }
}
