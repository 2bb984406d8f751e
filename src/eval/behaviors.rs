//! Behaviour checkers: for every behaviour in scripts/, an independent geometric definition of
//! success that never looks at the cost script. Each returns the verdict with the measured
//! quantities behind it, so that a person or an LLM can see why it failed.

use std::collections::BTreeMap;

use serde::Serialize;

use super::collateral::{collateral, Collateral};
use super::kinematic::{self, KinematicLimits, Violation};
use crate::cost::{ParamValue, Params};
use crate::geom::{wrap_angle, Point};
use crate::scene::{Agent, AgentType, LanePath, Scene, Turn};

/// The behaviours, named like the scripts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Behavior {
    /// speed_limit(vehicle, limit, from)
    SpeedLimit,
    /// target_point(vehicle, x, y, tol)
    TargetPoint,
    /// no_collisions()
    NoCollisions,
    /// lane_change_left(vehicle)
    LaneChangeLeft,
    /// lane_change_right(vehicle)
    LaneChangeRight,
    /// rightmost_lane(vehicle)
    RightmostLane,
    /// cut_in(cutter, victim)
    CutIn,
    /// yield(yielder, other)
    Yield,
    /// follow(follower, leader, gap)
    Follow,
    /// reverse(vehicle)
    Reverse,
    /// off_road(vehicle)
    OffRoad,
    /// weave(vehicle)
    Weave,
    /// stop(vehicle, within)
    Stop,
    /// accident(attacker, target)
    Accident,
    /// turn_left(vehicle)
    TurnLeft,
    /// turn_right(vehicle)
    TurnRight,
}

/// Every behaviour, in table order.
pub const ALL: [Behavior; 16] = [
    Behavior::SpeedLimit,
    Behavior::TargetPoint,
    Behavior::NoCollisions,
    Behavior::LaneChangeLeft,
    Behavior::LaneChangeRight,
    Behavior::RightmostLane,
    Behavior::CutIn,
    Behavior::Yield,
    Behavior::Follow,
    Behavior::Reverse,
    Behavior::OffRoad,
    Behavior::Weave,
    Behavior::Stop,
    Behavior::Accident,
    Behavior::TurnLeft,
    Behavior::TurnRight,
];

impl Behavior {
    /// The name (also the script's file stem).
    pub fn name(self) -> &'static str {
        match self {
            Behavior::SpeedLimit => "speed_limit",
            Behavior::TargetPoint => "target_point",
            Behavior::NoCollisions => "no_collisions",
            Behavior::LaneChangeLeft => "lane_change_left",
            Behavior::LaneChangeRight => "lane_change_right",
            Behavior::RightmostLane => "rightmost_lane",
            Behavior::CutIn => "cut_in",
            Behavior::Yield => "yield",
            Behavior::Follow => "follow",
            Behavior::Reverse => "reverse",
            Behavior::OffRoad => "off_road",
            Behavior::Weave => "weave",
            Behavior::Stop => "stop",
            Behavior::Accident => "accident",
            Behavior::TurnLeft => "turn_left",
            Behavior::TurnRight => "turn_right",
        }
    }

    /// The way a turning behaviour turns.
    pub fn turn(self) -> Option<Turn> {
        match self {
            Behavior::TurnLeft => Some(Turn::Left),
            Behavior::TurnRight => Some(Turn::Right),
            _ => None,
        }
    }

    /// The behaviour with this name.
    pub fn from_name(s: &str) -> Option<Self> {
        ALL.iter().copied().find(|b| b.name() == s)
    }

    /// The behaviour with this name, or the error that quotes the name (cut where it is long)
    /// and lists the known ones: for a name a user typed (`--behaviour`, `--auto`, a batch
    /// file's `behaviour:`).
    pub fn parse(s: &str) -> Result<Self, UnknownBehaviour> {
        Self::from_name(s).ok_or_else(|| UnknownBehaviour {
            name: crate::io::name::shown_counted(s),
        })
    }

    /// The checker's definition of success, in one line.
    pub fn definition(self) -> &'static str {
        match self {
            Behavior::SpeedLimit => "the speed (from positions) never exceeds `limit` + 0.5 m/s from `from` seconds (default 0) on",
            Behavior::TargetPoint => "the final position is within `tol` (default 1 m) of (`x`, `y`)",
            Behavior::NoCollisions => "no two vehicles' boxes overlap at any future step",
            Behavior::LaneChangeLeft => "the vehicle ends in the left neighbour of a lane on its starting lane's path (or a lane straight on from one), within 1 m of that lane's centre line",
            Behavior::LaneChangeRight => "the vehicle ends in the right neighbour of a lane on its starting lane's path (or a lane straight on from one), within 1 m of that lane's centre line",
            Behavior::RightmostLane => "the vehicle ends within 1 m of the centre line of a lane with no same-direction lane to its right",
            Behavior::CutIn => "A starts in a lane adjacent to B's, ends within 1 m of the centre of B's lane path ahead of B (bumper to bumper), and they never collide",
            Behavior::Yield => "B passes the point where their lane paths (taking `yielder_turn` / `other_turn` at forks, default straight) meet before A reaches it, both stay within 2 m of those paths, and they never collide",
            Behavior::Follow => "over the last half of the horizon A stays within 1.5 m of B's lane path, behind B at a bumper-to-bumper gap between gap/2 and 2·gap",
            Behavior::Reverse => "the vehicle ends at least 1 m behind its start along its starting heading, its heading never more than 30 degrees off",
            Behavior::OffRoad => "the vehicle's centre ends beyond the road edge",
            Behavior::Weave => "the lateral offset on the starting lane path crosses the centre line at least twice, reaching 0.3 m on both sides",
            Behavior::Stop => "the speed (from positions) is at most 0.5 m/s at every step from `within` seconds (default 4, or 0.5 s before the end of a shorter horizon) on",
            Behavior::Accident => "the two boxes overlap at some future step",
            Behavior::TurnLeft => "the vehicle takes the first left-turning lane on its route (left at forks, from its current lane), passing the middle of that turn, and stays within 2 m of the route",
            Behavior::TurnRight => "the vehicle takes the first right-turning lane on its route (right at forks, from its current lane), passing the middle of that turn, and stays within 2 m of the route",
        }
    }

    /// Parameters the checker needs (defaults are documented in [`Behavior::definition`]).
    pub fn required(self) -> &'static [&'static str] {
        match self {
            Behavior::SpeedLimit => &["vehicle", "limit"],
            Behavior::TargetPoint => &["vehicle", "x", "y"],
            Behavior::NoCollisions => &[],
            Behavior::LaneChangeLeft | Behavior::LaneChangeRight | Behavior::RightmostLane => {
                &["vehicle"]
            }
            Behavior::Reverse
            | Behavior::OffRoad
            | Behavior::Weave
            | Behavior::Stop
            | Behavior::TurnLeft
            | Behavior::TurnRight => &["vehicle"],
            Behavior::CutIn => &["cutter", "victim"],
            Behavior::Yield => &["yielder", "other"],
            Behavior::Follow => &["follower", "leader"],
            Behavior::Accident => &["attacker", "target"],
        }
    }

    /// Parameters the checker reads when given and otherwise defaults (the defaults are in
    /// [`Behavior::definition`]).
    pub fn optional(self) -> &'static [&'static str] {
        match self {
            Behavior::SpeedLimit => &["from"],
            Behavior::TargetPoint => &["tol"],
            Behavior::Yield => &["yielder_turn", "other_turn"],
            Behavior::Follow => &["gap"],
            Behavior::Stop => &["within"],
            _ => &[],
        }
    }

    /// Every parameter the checker reads: [`Behavior::required`], then
    /// [`Behavior::optional`].
    pub fn params(self) -> impl Iterator<Item = &'static str> {
        self.required().iter().chain(self.optional()).copied()
    }

    /// Every name in `params` is one the checker reads: one it does not (`gapp=30`) would be
    /// dropped without a word and the verdict taken for one with that value.
    pub fn check_param_names(self, params: &Params) -> Result<(), CheckError> {
        match params.names().find(|n| !self.params().any(|p| p == *n)) {
            None => Ok(()),
            Some(name) => Err(CheckError::UnknownParam {
                behavior: self.name(),
                name: name.to_string(),
                known: self.params().collect::<Vec<_>>().join(", "),
            }),
        }
    }

    /// The pairs of `named` agents (ids, in a verdict's order) the behaviour asks to touch:
    /// an accident's attacker and target; no pair for any other behaviour.
    pub fn contacts(self, named: &[i64]) -> Vec<(i64, i64)> {
        match (self, named) {
            (Behavior::Accident, [a, b]) => vec![(*a, *b)],
            _ => Vec::new(),
        }
    }

    /// The motion the behaviour asks of the agents it names that is otherwise implausible:
    /// reversing, for `reverse`. Neither its verdict nor eval's implausible count holds it
    /// against them.
    pub fn allowed_motion(self) -> &'static [Violation] {
        match self {
            Behavior::Reverse => &[Violation::Reverse],
            _ => &[],
        }
    }

    /// The parameters that name agents (their roles), a subset of [`Behavior::required`].
    pub fn roles(self) -> &'static [&'static str] {
        match self {
            Behavior::SpeedLimit | Behavior::TargetPoint => &["vehicle"],
            b => b.required(),
        }
    }
}

/// A checker's verdict.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Verdict {
    /// Whether the behaviour happened plausibly: its geometric condition holds
    /// (`achieved`), every agent the behaviour names drives as a car can
    /// ([`super::kinematic`]; reversing allowed where the behaviour asks for it, or the
    /// request's script allows it: [`check_allowing`]), and named
    /// agents do not collide with each other (except in `accident`). The headline.
    pub passed: bool,
    /// Whether the geometric condition alone holds.
    pub achieved: bool,
    /// Each named agent's implausible motion, or a collision between named agents, in words
    /// (`victim 389 reverses at -9.3 m/s at t = 3.9 s`).
    pub violations: Vec<String>,
    /// The quantities behind the verdict. One that is not finite (the offset of a car that
    /// ends on no lane is infinite) is written to JSON as `"inf"` / `"NaN"`, not `null`.
    #[serde(serialize_with = "crate::io::json::map_f64_explicit")]
    pub measured: BTreeMap<String, f64>,
    /// Why, in words.
    pub reason: String,
    /// The ids of the agents the behaviour names, in the order the checker looked them up.
    pub named: Vec<i64>,
    /// What the sample did to the vehicles the behaviour does not name, against the same
    /// sample unguided, when one was given ([`check_against_unguided`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub collateral: Option<Collateral>,
}

impl Verdict {
    /// The verdict with the rest of the scene judged too: it no longer passes when the sample
    /// wrecked more of the scene than its unguided twin, beyond [`Collateral::allowance`].
    pub fn with_collateral(mut self, c: Collateral) -> Verdict {
        let found = c.violations();
        if self.achieved && !found.is_empty() {
            let sep = if self.violations.is_empty() {
                ", but "
            } else {
                "; "
            };
            self.reason = format!("{}{sep}{}", self.reason, found.join("; "));
        }
        self.violations.extend(found);
        self.passed = self.achieved && self.violations.is_empty();
        for (k, v) in [
            ("other_vehicles", c.others),
            ("other_vehicles_collided", c.collided),
            ("other_vehicles_collided_unguided", c.collided_unguided),
            ("other_vehicles_implausible", c.implausible),
            (
                "other_vehicles_implausible_unguided",
                c.implausible_unguided,
            ),
        ] {
            self.measured.insert(k.to_string(), v as f64);
        }
        self.collateral = Some(c);
        self
    }
}

/// A behaviour name that names none ([`Behavior::parse`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "unknown behaviour \"{name}\"; known: {}",
    ALL.iter().map(|b| b.name()).collect::<Vec<_>>().join(", ")
)]
pub struct UnknownBehaviour {
    /// The name as it can be quoted ([`crate::io::name::shown_counted`]).
    pub name: String,
}

/// Why a checker cannot run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CheckError {
    /// A parameter is missing.
    #[error("{behavior}: parameter {name:?} is required")]
    MissingParam {
        /// The behaviour.
        behavior: &'static str,
        /// The parameter.
        name: &'static str,
    },
    /// A parameter the checker does not read.
    #[error(
        "{behavior}: parameter {name:?}: the checker does not read it; {}",
        if known.is_empty() {
            "it takes no parameters".to_string()
        } else {
            format!("its parameters are {known}")
        }
    )]
    UnknownParam {
        /// The behaviour.
        behavior: &'static str,
        /// The parameter.
        name: String,
        /// The parameters it reads, comma-separated.
        known: String,
    },
    /// A parameter is not a finite number.
    #[error("{behavior}: parameter {name:?} = {value:?} must be a number")]
    NotANumber {
        /// The behaviour.
        behavior: &'static str,
        /// The parameter.
        name: &'static str,
        /// Its value as given.
        value: String,
    },
    /// An agent's parameter is not an agent id.
    #[error("{behavior}: parameter {name:?} = {value:?} must be an agent id (a whole number)")]
    NotAnId {
        /// The behaviour.
        behavior: &'static str,
        /// The parameter.
        name: &'static str,
        /// Its value as given.
        value: String,
    },
    /// A parameter is not one of the words it may be.
    #[error("{behavior}: parameter {name:?} = {value:?} must be {expected}")]
    NotAWord {
        /// The behaviour.
        behavior: &'static str,
        /// The parameter.
        name: &'static str,
        /// Its value as given.
        value: String,
        /// The words it may be.
        expected: &'static str,
    },
    /// An agent is missing or unusable.
    #[error("{behavior}: {message}")]
    Agent {
        /// The behaviour.
        behavior: &'static str,
        /// What is wrong.
        message: String,
    },
    /// A number outside what the checker can judge: a `from` past the scene's end checked
    /// nothing (`speed_limit from=1e17` passed every sample), a negative tolerance nothing
    /// could meet.
    #[error("{behavior}: parameter {name:?} = {value} must be {range}")]
    OutOfRange {
        /// The behaviour.
        behavior: &'static str,
        /// The parameter.
        name: &'static str,
        /// Its value.
        value: String,
        /// What it may be, in words.
        range: String,
    },
    /// The unguided sample to judge the rest of the scene against does not fit.
    #[error("{behavior}: {message}")]
    Unguided {
        /// The behaviour.
        behavior: &'static str,
        /// What is wrong.
        message: String,
    },
}

struct Ctx<'a> {
    b: Behavior,
    s: &'a Scene,
    p: &'a Params,
    m: BTreeMap<String, f64>,
    /// The agents the behaviour names, with their roles.
    named: Vec<(&'static str, &'a Agent)>,
    /// Motion the request asks of particular agents beyond what the behaviour asks.
    allowed: &'a [(i64, Violation)],
}

impl<'a> Ctx<'a> {
    /// In tests, every parameter a checker reads is one [`Behavior::params`] lists, so that
    /// `eval` never refuses a name the checker reads ([`Behavior::check_param_names`]).
    fn declared(&self, name: &'static str) {
        if cfg!(any(test, debug_assertions)) {
            assert!(
                self.b.params().any(|p| p == name),
                "{}: reads parameter {name:?}, not in Behavior::required or optional",
                self.b.name()
            );
        }
    }

    fn get(&self, name: &'static str) -> Result<f64, CheckError> {
        self.declared(name);
        match self.p.get(name) {
            None => Err(CheckError::MissingParam {
                behavior: self.b.name(),
                name,
            }),
            Some(v) => self.numeric(name, v),
        }
    }

    /// `v`, the value of `name`, when `ok` holds of it; else an error saying it must be
    /// `range`.
    fn ranged(
        &self,
        name: &'static str,
        v: f64,
        ok: bool,
        range: impl Into<String>,
    ) -> Result<f64, CheckError> {
        if ok {
            Ok(v)
        } else {
            Err(CheckError::OutOfRange {
                behavior: self.b.name(),
                name,
                value: crate::geom::num(v),
                range: range.into(),
            })
        }
    }

    /// A time after the current step, seconds (`name`, else `default`), inside the scene's
    /// future (before its end unless `to_end`): one given beyond it left nothing to check, and
    /// `speed_limit from=1e17` passed every sample (`from=1e300` wrapped round to the start).
    /// The default is the checker's own, kept whatever the horizon.
    fn seconds_into_future(
        &self,
        name: &'static str,
        default: f64,
        to_end: bool,
    ) -> Result<f64, CheckError> {
        let v = self.or(name, default)?;
        if self.p.get(name).is_none() {
            return Ok(v);
        }
        let c = self.s.meta.current_step;
        let future = self.s.num_steps().saturating_sub(c + 1) as f64 * self.s.meta.dt;
        let inside = v >= 0.0
            && if to_end {
                v <= future + 1e-9
            } else {
                v < future
            };
        self.ranged(
            name,
            v,
            inside,
            format!(
                "0 or more seconds and {} the end of the scene's future ({} s)",
                if to_end { "at most" } else { "before" },
                crate::geom::approx(future)
            ),
        )
    }

    /// A distance in metres (`name`, else `default`), at most 1000 m and not negative (more
    /// than 0 where `positive`): 1e300 m passed every sample.
    fn metres(&self, name: &'static str, default: f64, positive: bool) -> Result<f64, CheckError> {
        let v = self.or(name, default)?;
        let low = if positive { v > 0.0 } else { v >= 0.0 };
        self.ranged(
            name,
            v,
            low && v <= 1000.0,
            if positive {
                "more than 0 and at most 1000 m"
            } else {
                "0 to 1000 m"
            },
        )
    }

    fn or(&self, name: &'static str, default: f64) -> Result<f64, CheckError> {
        self.declared(name);
        match self.p.get(name) {
            None => Ok(default),
            Some(v) => self.numeric(name, v),
        }
    }

    /// Which way a route goes at forks: `"straight"` (the default), `"left"` or `"right"`.
    fn turn(&self, name: &'static str) -> Result<Turn, CheckError> {
        self.declared(name);
        let Some(v) = self.p.get(name) else {
            return Ok(Turn::Straight);
        };
        let word = match v {
            ParamValue::Str(t) => Turn::from_word(t),
            _ => None,
        };
        word.ok_or_else(|| CheckError::NotAWord {
            behavior: self.b.name(),
            name,
            value: v.to_string(),
            expected: "\"straight\", \"left\" or \"right\"",
        })
    }

    fn numeric(&self, name: &'static str, v: &ParamValue) -> Result<f64, CheckError> {
        v.as_f64()
            .filter(|x| x.is_finite())
            .ok_or_else(|| CheckError::NotANumber {
                behavior: self.b.name(),
                name,
                value: v.to_string(),
            })
    }

    fn agent(&mut self, name: &'static str) -> Result<&'a Agent, CheckError> {
        self.declared(name);
        // `vehicle=1.5` named agent 1: an id is whole or it is no id.
        let id = match self.p.get(name) {
            None => {
                return Err(CheckError::MissingParam {
                    behavior: self.b.name(),
                    name,
                })
            }
            Some(ParamValue::Int(i)) => *i,
            Some(ParamValue::Float(f)) if f.fract() == 0.0 && f.abs() < 9.0e15 => *f as i64,
            Some(v) => {
                return Err(CheckError::NotAnId {
                    behavior: self.b.name(),
                    name,
                    value: v.to_string(),
                })
            }
        };
        let a = self.s.agent(id).ok_or_else(|| CheckError::Agent {
            behavior: self.b.name(),
            message: format!("no agent {id} ({name})"),
        })?;
        if !a.is_valid(self.s.meta.current_step) {
            return Err(CheckError::Agent {
                behavior: self.b.name(),
                message: format!("agent {id} ({name}) is not observed at the current step"),
            });
        }
        match self.named.iter().find(|(_, n)| n.id == a.id) {
            None => self.named.push((name, a)),
            Some((role, _)) if *role != name => {
                return Err(CheckError::Agent {
                    behavior: self.b.name(),
                    message: format!(
                        "{role} and {name} are both agent {id}: the roles need different agents"
                    ),
                })
            }
            Some(_) => {}
        }
        Ok(a)
    }

    fn last(&self, a: &Agent) -> Result<usize, CheckError> {
        let c = self.s.meta.current_step;
        (c + 1..a.states.len())
            .rev()
            .find(|&t| a.is_valid(t))
            .ok_or_else(|| CheckError::Agent {
                behavior: self.b.name(),
                message: format!("agent {} has no future", a.id),
            })
    }

    fn measure(&mut self, k: &str, v: f64) {
        self.m.insert(k.to_string(), v);
    }

    /// The verdict: `achieved` is the geometric condition; the named agents' motion decides
    /// whether it passes.
    fn verdict(self, achieved: bool, reason: impl Into<String>) -> Verdict {
        let mut violations = Vec::new();
        let lim = KinematicLimits::default();
        for (role, a) in &self.named {
            let allowed = motion_allowed(self.b.allowed_motion(), self.allowed, a.id);
            if let Some(j) = kinematic::judge_agent(self.s, a, &lim) {
                for e in j.without(&allowed).events {
                    violations.push(format!("{role} {} {e}", a.id));
                }
            }
        }
        if self.b != Behavior::Accident {
            for (i, (ra, a)) in self.named.iter().enumerate() {
                for (rb, b) in &self.named[i + 1..] {
                    if let Some(&t) = overlap_steps(self.s, a, b).first() {
                        let at = (t - self.s.meta.current_step) as f64 * self.s.meta.dt;
                        violations.push(format!(
                            "{ra} {} collides with {rb} {} at t = {at:.1} s",
                            a.id, b.id
                        ));
                    }
                }
            }
        }
        let mut reason = reason.into();
        if achieved && !violations.is_empty() {
            reason = format!("{reason}, but {}", violations.join("; "));
        }
        Verdict {
            passed: achieved && violations.is_empty(),
            achieved,
            violations,
            measured: self.m,
            reason,
            named: self.named.iter().map(|(_, a)| a.id).collect(),
            collateral: None,
        }
    }
}

/// The kinds of motion agent `id` may show: what the behaviour asks of the agents it names
/// (`own`), and what `allowed` allows this agent.
fn motion_allowed(own: &[Violation], allowed: &[(i64, Violation)], id: i64) -> Vec<Violation> {
    own.iter()
        .copied()
        .chain(allowed.iter().filter(|(a, _)| *a == id).map(|(_, k)| *k))
        .collect()
}

pub(super) fn lane_of(s: &Scene, a: &Agent, t: usize) -> Option<i64> {
    let st = a.states.get(t).filter(|x| x.valid)?;
    s.map.lane_at(st.position(), st.heading)
}

pub(super) fn path_of(s: &Scene, a: &Agent) -> Option<LanePath> {
    route_of(s, a, Turn::Straight)
}

/// The path from `a`'s lane at the current step, taking `turn` at forks.
pub(super) fn route_of(s: &Scene, a: &Agent, turn: Turn) -> Option<LanePath> {
    let (lane, lanes) = route_lanes(s, a, turn)?;
    s.map.path_through(lanes, lane).ok()
}

/// The lanes of [`route_of`] (its origin, then the sequence), without building the path.
fn route_lanes(s: &Scene, a: &Agent, turn: Turn) -> Option<(i64, Vec<i64>)> {
    let c = s.meta.current_step;
    let lane = lane_of(s, a, c)?;
    let along = s
        .map
        .lane(lane)?
        .centerline
        .nearest(&a.states[c].position())
        .s;
    let lanes = s.map.lane_sequence(lane, along + 400.0, 50.0, turn).ok()?;
    Some((lane, lanes))
}

/// Routes ([`route_of`]) built once per distinct lane sequence and shared: `suggest` asks for
/// a route per candidate, and each route copies its lanes' whole centre lines, so 1,500 cars on
/// one 100 km road held 8.4 GB of copies of the same three lanes.
#[derive(Default)]
pub(super) struct Routes(
    std::cell::RefCell<std::collections::HashMap<(i64, Vec<i64>), std::rc::Rc<LanePath>>>,
);

impl Routes {
    /// [`route_of`], shared with every agent whose route runs through the same lanes.
    pub(super) fn route(&self, s: &Scene, a: &Agent, turn: Turn) -> Option<std::rc::Rc<LanePath>> {
        let key = route_lanes(s, a, turn)?;
        if let Some(p) = self.0.borrow().get(&key) {
            return Some(p.clone());
        }
        let path = std::rc::Rc::new(s.map.path_through(key.1.clone(), key.0).ok()?);
        self.0.borrow_mut().insert(key, path.clone());
        Some(path)
    }
}

/// Whether the yielder's path ends in a lane of the other's: the paths merge rather than cross
/// (the yield script then stops the yielder further back, as they run side by side first).
pub(super) fn merges(yielder: &LanePath, other: &LanePath) -> bool {
    yielder
        .lanes
        .last()
        .is_some_and(|l| other.lanes.contains(l))
}

/// The route `a` drives in `s`: of the paths straight on, left and right at forks, the one its
/// last observed state lies nearest (the first of equals), with the turn that makes it.
pub(super) fn driven_route(
    s: &Scene,
    a: &Agent,
    routes: &Routes,
) -> Option<(Turn, std::rc::Rc<LanePath>)> {
    let last = (s.meta.current_step + 1..a.states.len())
        .rev()
        .find(|&t| a.is_valid(t))?;
    let end = a.states[last].position();
    let mut best: Option<(f64, Turn, std::rc::Rc<LanePath>)> = None;
    for turn in [Turn::Straight, Turn::Left, Turn::Right] {
        let Some(p) = routes.route(s, a, turn) else {
            continue;
        };
        if best.as_ref().is_some_and(|b| b.2.lanes == p.lanes) {
            continue;
        }
        let off = p.frenet.project(end).d.abs();
        if best.as_ref().is_none_or(|b| off < b.0) {
            best = Some((off, turn, p));
        }
    }
    best.map(|(_, t, p)| (t, p))
}

fn speeds(s: &Scene, a: &Agent) -> Vec<(usize, f64)> {
    let c = s.meta.current_step;
    (c + 1..a.states.len())
        .filter(|&t| a.is_valid(t) && a.is_valid(t - 1))
        .map(|t| {
            (
                t,
                (a.states[t].position() - a.states[t - 1].position()).norm() / s.meta.dt,
            )
        })
        .collect()
}

fn overlap_steps(s: &Scene, a: &Agent, b: &Agent) -> Vec<usize> {
    (s.meta.current_step + 1..s.num_steps())
        .filter(
            |&t| matches!((a.footprint(t), b.footprint(t)), (Some(x), Some(y)) if x.overlaps(&y)),
        )
        .collect()
}

/// [`check_allowing`] on a guided sample, with the rest of the scene judged against
/// `unguided`, the same scene sampled without guidance (same seed): see
/// [`super::collateral`]. The pair an `accident` names may collide, and the motion `allowed`
/// allows an agent is no fault in either sample.
pub fn check_against_unguided(
    behavior: Behavior,
    guided: &Scene,
    unguided: &Scene,
    params: &Params,
    allowed: &[(i64, Violation)],
) -> Result<Verdict, CheckError> {
    let v = check_allowing(behavior, guided, params, allowed)?;
    let c = collateral(
        guided,
        unguided,
        &v.named,
        &behavior.contacts(&v.named),
        allowed,
        &KinematicLimits::default(),
    )
    .map_err(|e| CheckError::Unguided {
        behavior: behavior.name(),
        message: e.to_string(),
    })?;
    Ok(v.with_collateral(c))
}

/// Decides whether `behavior` happened in `scene` (a simulated or logged scene).
pub fn check(behavior: Behavior, scene: &Scene, params: &Params) -> Result<Verdict, CheckError> {
    check_allowing(behavior, scene, params, &[])
}

/// [`check`], with the motion `allowed` (agent id, kind) asked of particular agents besides
/// what the behaviour asks of those it names: what the request's cost scripts allow
/// (`allow(a, "reverse")`). A car that "reverses and leaves the road" backs up because it
/// was asked to, and its `off_road` verdict must not fail it for reversing.
pub fn check_allowing(
    behavior: Behavior,
    scene: &Scene,
    params: &Params,
    allowed: &[(i64, Violation)],
) -> Result<Verdict, CheckError> {
    let x = Ctx {
        b: behavior,
        s: scene,
        p: params,
        m: BTreeMap::new(),
        named: Vec::new(),
        allowed,
    };
    match behavior {
        Behavior::SpeedLimit => speed_limit(x),
        Behavior::TargetPoint => target_point(x),
        Behavior::NoCollisions => no_collisions(x),
        Behavior::LaneChangeLeft | Behavior::LaneChangeRight => lane_change(x),
        Behavior::RightmostLane => rightmost_lane(x),
        Behavior::CutIn => cut_in(x),
        Behavior::Yield => yield_to(x),
        Behavior::Follow => follow(x),
        Behavior::Reverse => reverse(x),
        Behavior::OffRoad => off_road(x),
        Behavior::Weave => weave(x),
        Behavior::Stop => stop(x),
        Behavior::Accident => accident(x),
        Behavior::TurnLeft | Behavior::TurnRight => turn(x),
    }
}

/// [`check`] for `turn_left` and `turn_right`.
fn turn(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let (s, c, behavior) = (x.s, x.s.meta.current_step, x.b);
    let way = behavior.turn().expect("a turning behaviour");
    let a = x.agent("vehicle")?;
    let route = route_of(s, a, way).ok_or_else(|| no_lane(behavior, a.id))?;
    let Some(span) = route.next_turn(&s.map, way) else {
        x.measure("turn_ahead", 0.0);
        return Ok(x.verdict(false, format!("its route has no {} turn ahead", way.word())));
    };
    let t = x.last(a)?;
    let end = route.frenet.project(a.states[t].position());
    let off = (c + 1..=t)
        .filter(|&k| a.is_valid(k))
        .map(|k| route.frenet.project(a.states[k].position()).d.abs())
        .fold(0.0f64, f64::max);
    let short = span.middle - end.s;
    x.measure("turn_ahead", 1.0);
    x.measure("turn_lane", span.lane as f64);
    x.measure("short_of_turn_middle_m", short);
    x.measure("off_route_m", off);
    let ok = short <= 0.0 && off <= ROUTE_TOLERANCE;
    Ok(x.verdict(
        ok,
        if off > ROUTE_TOLERANCE {
            format!("leaves its {} route ({off:.1} m off it)", way.word())
        } else if short > 0.0 {
            format!(
                "ends {short:.1} m short of the middle of the {} turn (lane {})",
                way.word(),
                span.lane
            )
        } else {
            format!("turns {} into lane {}", way.word(), span.lane)
        },
    ))
}

/// A checker's error for an agent on no lane at the current step.
fn no_lane(b: Behavior, id: i64) -> CheckError {
    CheckError::Agent {
        behavior: b.name(),
        message: format!("agent {id} is on no lane at the current step"),
    }
}

/// [`check`] for `SpeedLimit`.
fn speed_limit(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let (s, c) = (x.s, x.s.meta.current_step);
    Ok({
        let a = x.agent("vehicle")?;
        let limit = x.get("limit")?;
        let limit = x.ranged(
            "limit",
            limit,
            limit > 0.0 && limit <= 100.0,
            "more than 0 and at most 100 m/s",
        )?;
        let from_s = x.seconds_into_future("from", 0.0, false)?;
        let from = c + (from_s / s.meta.dt).round() as usize;
        let judged: Vec<f64> = speeds(s, a)
            .iter()
            .filter(|(t, _)| *t > from)
            .map(|v| v.1)
            .collect();
        // A vehicle never observed there has no speed to judge: the fold's 0 passed it as
        // "stays under the limit" (a trajectory of NaN from Python's `check`, or a logged car
        // that left the recording).
        if judged.is_empty() {
            return Err(CheckError::Agent {
                behavior: x.b.name(),
                message: format!(
                    "agent {} is not observed at two steps in a row after {} s into the \
                     future, so it has no speed to judge",
                    a.id,
                    crate::geom::approx(from_s)
                ),
            });
        }
        let vmax = judged.iter().copied().fold(0.0, f64::max);
        x.measure("max_speed", vmax);
        x.measure("limit", limit);
        let ok = vmax <= limit + 0.5;
        x.verdict(
            ok,
            if ok {
                "stays under the limit"
            } else {
                "exceeds the limit"
            },
        )
    })
}

/// [`check`] for `TargetPoint`.
fn target_point(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    Ok({
        let a = x.agent("vehicle")?;
        let far = crate::geom::MAX_COORD;
        let within_map = format!("within {far:e} m of the origin, as every scene's points");
        let tx = x.get("x")?;
        let tx = x.ranged("x", tx, tx.abs() <= far, within_map.clone())?;
        let ty = x.get("y")?;
        let ty = x.ranged("y", ty, ty.abs() <= far, within_map)?;
        let tol = x.metres("tol", 1.0, true)?;
        let end = a.states[x.last(a)?].position();
        let d = (end - Point::new(tx, ty)).norm();
        x.measure("final_distance", d);
        x.verdict(
            d <= tol,
            format!("ends {d:.2} m from the target (tolerance {tol} m)"),
        )
    })
}

/// [`check`] for `NoCollisions`.
fn no_collisions(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let s = x.s;
    Ok({
        let v: Vec<&Agent> = s
            .agents
            .iter()
            .filter(|a| a.agent_type == AgentType::Vehicle)
            .collect();
        let mut pairs = 0;
        for (i, a) in v.iter().enumerate() {
            for b in &v[i + 1..] {
                if !overlap_steps(s, a, b).is_empty() {
                    pairs += 1;
                }
            }
        }
        x.measure("colliding_pairs", pairs as f64);
        x.verdict(pairs == 0, format!("{pairs} pairs of vehicles collide"))
    })
}

/// [`check`] for `LaneChangeLeft` and `LaneChangeRight`.
fn lane_change(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let (s, c, behavior) = (x.s, x.s.meta.current_step, x.b);
    Ok({
        let a = x.agent("vehicle")?;
        let start = lane_of(s, a, c).ok_or_else(|| no_lane(behavior, a.id))?;
        let path = s
            .map
            .lane_path(start, 1000.0, 200.0, Turn::Straight)
            .map_err(|e| CheckError::Agent {
                behavior: behavior.name(),
                message: e.to_string(),
            })?;
        let t = x.last(a)?;
        let end = lane_of(s, a, t);
        let g = s.map.graph();
        let side = |l: i64| {
            if behavior == Behavior::LaneChangeLeft {
                g.left(l)
            } else {
                g.right(l)
            }
        };
        // The neighbours of the path's lanes and the lanes straight on from them: maps
        // miss adjacencies (NGSIM Lankershim's lanes just past an intersection list no
        // neighbour on one side), and a car that moved over into the lane beyond one
        // has changed lanes all the same.
        let beside: Vec<i64> = path
            .lanes
            .iter()
            .filter_map(|&l| side(l))
            .flat_map(|l| {
                s.map
                    .lane_path(l, 1000.0, 0.0, Turn::Straight)
                    .map_or(vec![l], |p| p.lanes)
            })
            .collect();
        let moved = end.is_some_and(|l| beside.contains(&l) && !path.lanes.contains(&l));
        let offset = end.map_or(f64::INFINITY, |l| {
            s.map.lane(l).map_or(f64::INFINITY, |ln| {
                ln.centerline.distance_to(&a.states[t].position())
            })
        });
        x.measure("start_lane", start as f64);
        x.measure("end_lane", end.map_or(-1.0, |l| l as f64));
        x.measure("end_offset_from_centre", offset);
        let ok = moved && offset <= 1.0;
        let side = if behavior == Behavior::LaneChangeLeft {
            "left"
        } else {
            "right"
        };
        x.verdict(
            ok,
            if ok {
                format!("ends in the lane to the {side}")
            } else if moved {
                format!("reaches the {side} lane but ends {offset:.2} m off its centre")
            } else {
                format!(
                    "does not end in the lane to the {side} (ends {})",
                    lane_words(end)
                )
            },
        )
    })
}

/// [`check`] for `RightmostLane`.
fn rightmost_lane(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let s = x.s;
    Ok({
        let a = x.agent("vehicle")?;
        let t = x.last(a)?;
        let end = lane_of(s, a, t);
        let offset = end.map_or(f64::INFINITY, |l| {
            s.map.lane(l).map_or(f64::INFINITY, |ln| {
                ln.centerline.distance_to(&a.states[t].position())
            })
        });
        let rightmost = end.is_some_and(|l| s.map.graph().is_rightmost(l));
        x.measure("end_lane", end.map_or(-1.0, |l| l as f64));
        x.measure("end_offset_from_centre", offset);
        let ok = rightmost && offset <= 1.0;
        x.verdict(
            ok,
            if ok {
                "ends in the rightmost lane".into()
            } else {
                match end {
                    Some(l) => format!(
                        "ends in lane {l}, {} the rightmost, {offset:.2} m off its centre",
                        if rightmost { "which is" } else { "not" }
                    ),
                    None => "ends on no lane".into(),
                }
            },
        )
    })
}

/// [`check`] for `CutIn`.
fn cut_in(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let (s, c, behavior) = (x.s, x.s.meta.current_step, x.b);
    Ok({
        let (a, b) = (x.agent("cutter")?, x.agent("victim")?);
        let (la, lb) = (
            lane_of(s, a, c).ok_or_else(|| no_lane(behavior, a.id))?,
            lane_of(s, b, c).ok_or_else(|| no_lane(behavior, b.id))?,
        );
        let g = s.map.graph();
        let adjacent = g.left_neighbors(lb).contains(&la) || g.right_neighbors(lb).contains(&la);
        let path = path_of(s, b).ok_or_else(|| no_lane(behavior, b.id))?;
        let t = x.last(a)?.min(x.last(b)?);
        let (fa, fb) = (
            path.frenet.project(a.states[t].position()),
            path.frenet.project(b.states[t].position()),
        );
        let gap = fa.s - fb.s - 0.5 * (a.length + b.length);
        let hits = overlap_steps(s, a, b).len();
        x.measure("starts_adjacent", adjacent as u8 as f64);
        x.measure("end_offset_on_victim_path", fa.d.abs());
        x.measure("end_gap_ahead", gap);
        x.measure("collision_steps", hits as f64);
        let ok = adjacent && fa.d.abs() <= 1.0 && gap >= 0.0 && hits == 0;
        let why = if !adjacent {
            "does not start in a lane beside the victim's".to_string()
        } else if fa.d.abs() > 1.0 {
            format!("ends {:.2} m off the victim's lane centre", fa.d.abs())
        } else if gap < 0.0 {
            format!("ends {:.2} m short of being ahead", -gap)
        } else if hits > 0 {
            format!("collides at {hits} steps")
        } else {
            "cuts in".into()
        };
        x.verdict(ok, why)
    })
}

/// [`check`] for `Yield`.
fn yield_to(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let (s, c, behavior) = (x.s, x.s.meta.current_step, x.b);
    Ok({
        let (a, b) = (x.agent("yielder")?, x.agent("other")?);
        let (turn_a, turn_b) = (x.turn("yielder_turn")?, x.turn("other_turn")?);
        let (pa, pb) = (
            route_of(s, a, turn_a).ok_or_else(|| no_lane(behavior, a.id))?,
            route_of(s, b, turn_b).ok_or_else(|| no_lane(behavior, b.id))?,
        );
        let Some((sa, sb, _)) = pa.first_meeting(&pb) else {
            x.measure("paths_meet", 0.0);
            return Ok(x.verdict(false, "their lane paths never meet"));
        };
        let first = |ag: &Agent, p: &LanePath, at: f64| {
            (c + 1..ag.states.len())
                .find(|&t| ag.is_valid(t) && p.frenet.project(ag.states[t].position()).s >= at)
        };
        let (ta, tb) = (first(a, &pa, sa), first(b, &pb, sb));
        // A car that drives off its route (straight on instead of turning) yields to
        // nobody: it only avoids the meeting point.
        let off_route = |ag: &Agent, p: &LanePath| {
            (c + 1..ag.states.len())
                .filter(|&t| ag.is_valid(t))
                .map(|t| p.frenet.project(ag.states[t].position()).d.abs())
                .fold(0.0f64, f64::max)
        };
        let (da, db) = (off_route(a, &pa), off_route(b, &pb));
        let hits = overlap_steps(s, a, b).len();
        let dt = s.meta.dt;
        x.measure(
            "yielder_reaches_s",
            ta.map_or(-1.0, |t| (t - c) as f64 * dt),
        );
        x.measure("other_passes_s", tb.map_or(-1.0, |t| (t - c) as f64 * dt));
        x.measure("yielder_off_route_m", da);
        x.measure("other_off_route_m", db);
        x.measure("collision_steps", hits as f64);
        let on_route = da <= ROUTE_TOLERANCE && db <= ROUTE_TOLERANCE;
        let ok = match (ta, tb) {
            (_, None) => false,
            (None, Some(_)) => true,
            (Some(ta), Some(tb)) => tb < ta,
        } && hits == 0
            && on_route;
        x.verdict(
            ok,
            match (ta, tb) {
                _ if da > ROUTE_TOLERANCE => format!(
                    "the yielder leaves its route ({da:.1} m off its lane path, {} at forks)",
                    turn_a.word()
                ),
                _ if db > ROUTE_TOLERANCE => format!(
                    "the other agent leaves its route ({db:.1} m off its lane path, {} at forks)",
                    turn_b.word()
                ),
                (_, None) => "the other agent never reaches the meeting point".to_string(),
                (Some(ta), Some(tb)) if ta <= tb => {
                    "the yielder reaches the meeting point first".into()
                }
                _ if hits > 0 => format!("they collide at {hits} steps"),
                _ => "the other agent passes first".into(),
            },
        )
    })
}

/// [`check`] for `Follow`.
fn follow(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let (s, c, behavior) = (x.s, x.s.meta.current_step, x.b);
    Ok({
        let (a, b) = (x.agent("follower")?, x.agent("leader")?);
        let want = x.metres("gap", 10.0, false)?;
        let path = path_of(s, b).ok_or_else(|| no_lane(behavior, b.id))?;
        let n = s.num_steps();
        let from = c + 1 + (n - c - 1) / 2;
        let (mut worst_d, mut gaps) = (0.0f64, Vec::new());
        for t in from..n {
            if a.is_valid(t) && b.is_valid(t) {
                let (fa, fb) = (
                    path.frenet.project(a.states[t].position()),
                    path.frenet.project(b.states[t].position()),
                );
                worst_d = worst_d.max(fa.d.abs());
                gaps.push(fb.s - fa.s - 0.5 * (a.length + b.length));
            }
        }
        if gaps.is_empty() {
            return Ok(x.verdict(
                false,
                "the agents are not both observed in the last half of the horizon",
            ));
        }
        let (gmin, gmax) = gaps
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), g| {
                (lo.min(*g), hi.max(*g))
            });
        x.measure("max_offset_from_leader_path", worst_d);
        x.measure("min_gap", gmin);
        x.measure("max_gap", gmax);
        let ok = worst_d <= 1.5 && gmin >= 0.5 * want && gmax <= 2.0 * want;
        x.verdict(ok, format!("gap {gmin:.1}..{gmax:.1} m (wanted {:.1}..{:.1}), up to {worst_d:.2} m off the leader's lane", 0.5 * want, 2.0 * want))
    })
}

/// [`check`] for `Reverse`.
fn reverse(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let c = x.s.meta.current_step;
    Ok({
        let a = x.agent("vehicle")?;
        let s0 = a.states[c];
        let t = x.last(a)?;
        let dir = Point::new(s0.heading.cos(), s0.heading.sin());
        let along = (a.states[t].position() - s0.position()).dot(&dir);
        let turn = (c + 1..=t)
            .filter(|&k| a.is_valid(k))
            .map(|k| wrap_angle(a.states[k].heading - s0.heading).abs())
            .fold(0.0, f64::max);
        x.measure("displacement_along_heading", along);
        x.measure("max_heading_change_deg", turn.to_degrees());
        let ok = along <= -1.0 && turn <= 30f64.to_radians();
        x.verdict(
            ok,
            format!(
                "moves {along:.2} m along its heading, turning up to {:.0} degrees",
                turn.to_degrees()
            ),
        )
    })
}

/// [`check`] for `OffRoad`.
fn off_road(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let (s, behavior) = (x.s, x.b);
    Ok({
        let a = x.agent("vehicle")?;
        let t = x.last(a)?;
        let d = s
            .map
            .signed_distance_to_road_edge(a.states[t].position())
            .ok_or_else(|| CheckError::Agent {
                behavior: behavior.name(),
                message: "the map has no road edges".into(),
            })?;
        x.measure("final_edge_distance", d);
        x.verdict(
            d > 0.0,
            format!(
                "ends {:.2} m {} the road edge",
                d.abs(),
                if d > 0.0 { "beyond" } else { "inside" }
            ),
        )
    })
}

/// [`check`] for `Weave`.
fn weave(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let (s, c, behavior) = (x.s, x.s.meta.current_step, x.b);
    Ok({
        let a = x.agent("vehicle")?;
        let path = path_of(s, a).ok_or_else(|| no_lane(behavior, a.id))?;
        // About the lane's centre line, as the definition says: a car that starts off
        // centre and drifts back has not weaved.
        let ds: Vec<f64> = (c + 1..a.states.len())
            .filter(|&t| a.is_valid(t))
            .map(|t| path.frenet.project(a.states[t].position()).d)
            .collect();
        let crossings = ds
            .windows(2)
            .filter(|w| (w[0] < 0.0) != (w[1] < 0.0))
            .count();
        let (lo, hi) = ds
            .iter()
            .fold((0.0f64, 0.0f64), |(lo, hi), d| (lo.min(*d), hi.max(*d)));
        x.measure("crossings", crossings as f64);
        x.measure("max_left", hi);
        x.measure("max_right", -lo);
        let ok = crossings >= 2 && hi >= 0.3 && -lo >= 0.3;
        x.verdict(
            ok,
            format!(
                "crosses its lane's centre line {crossings} times, {hi:.2} m left and {:.2} m right",
                -lo
            ),
        )
    })
}

/// `stop`'s default `within` (seconds) for a future of `future` seconds, as
/// `scripts/stop.rhai` has it: 4 s, or half a second before the end of a shorter future (half
/// of one under a second). A fixed 4 s asked a car of a 4 s horizon to be stopped from its
/// last step, which the script refuses.
pub fn stop_within(future: f64) -> f64 {
    if future >= 4.5 {
        4.0
    } else if future >= 1.0 {
        future - 0.5
    } else {
        future / 2.0
    }
}

/// [`check`] for `Stop`.
fn stop(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let (s, c) = (x.s, x.s.meta.current_step);
    Ok({
        let a = x.agent("vehicle")?;
        let future = s.num_steps().saturating_sub(c + 1) as f64 * s.meta.dt;
        let within = x.seconds_into_future("within", stop_within(future), true)?;
        let from = c + (within / s.meta.dt).round() as usize;
        let after: Vec<f64> = speeds(s, a)
            .into_iter()
            .filter(|(t, _)| *t >= from)
            .map(|v| v.1)
            .collect();
        if after.is_empty() {
            return Ok(x.verdict(false, format!("no observed step after {within} s")));
        }
        let vmax = after.iter().copied().fold(0.0, f64::max);
        x.measure("max_speed_after", vmax);
        x.verdict(
            vmax <= 0.5,
            format!("moves at up to {vmax:.2} m/s after {within} s"),
        )
    })
}

/// [`check`] for `Accident`.
fn accident(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let (s, c) = (x.s, x.s.meta.current_step);
    Ok({
        let (a, b) = (x.agent("attacker")?, x.agent("target")?);
        let hits = overlap_steps(s, a, b);
        let min_dist = (c + 1..s.num_steps())
            .filter_map(|t| Some(a.footprint(t)?.distance(&b.footprint(t)?)))
            .fold(f64::INFINITY, f64::min);
        x.measure("collision_steps", hits.len() as f64);
        x.measure("min_box_distance", min_dist);
        x.verdict(
            !hits.is_empty(),
            if hits.is_empty() {
                format!("they come no closer than {min_dist:.2} m")
            } else {
                format!(
                    "they collide from {:.1} s",
                    (hits[0] - c) as f64 * s.meta.dt
                )
            },
        )
    })
}

/// How far (metres, from the lane path's centre line) a yielder or the car it yields to may
/// be from the route the request names: within its lane, with room to cut a junction's corner.
const ROUTE_TOLERANCE: f64 = 2.0;

/// Where a lane query ended, in words: "in lane 695", or "on no lane".
fn lane_words(lane: Option<i64>) -> String {
    lane.map_or_else(|| "on no lane".into(), |l| format!("in lane {l}"))
}
