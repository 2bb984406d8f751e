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
            Behavior::Stop => "the speed (from positions) is at most 0.5 m/s at every step from `within` seconds (default 4) on",
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

fn lane_of(s: &Scene, a: &Agent, t: usize) -> Option<i64> {
    let st = a.states.get(t).filter(|x| x.valid)?;
    s.map.lane_at(st.position(), st.heading)
}

fn path_of(s: &Scene, a: &Agent) -> Option<LanePath> {
    route_of(s, a, Turn::Straight)
}

/// The path from `a`'s lane at the current step, taking `turn` at forks.
fn route_of(s: &Scene, a: &Agent, turn: Turn) -> Option<LanePath> {
    let c = s.meta.current_step;
    let lane = lane_of(s, a, c)?;
    let along = s
        .map
        .lane(lane)?
        .centerline
        .nearest(&a.states[c].position())
        .s;
    s.map.lane_path(lane, along + 400.0, 50.0, turn).ok()
}

/// Whether the yielder's path ends in a lane of the other's: the paths merge rather than cross
/// (the yield script then stops the yielder further back, as they run side by side first).
fn merges(yielder: &LanePath, other: &LanePath) -> bool {
    yielder
        .lanes
        .last()
        .is_some_and(|l| other.lanes.contains(l))
}

/// The route `a` drives in `s`: of the paths straight on, left and right at forks, the one its
/// last observed state lies nearest (the first of equals), with the turn that makes it.
fn driven_route(s: &Scene, a: &Agent) -> Option<(Turn, LanePath)> {
    let last = (s.meta.current_step + 1..a.states.len())
        .rev()
        .find(|&t| a.is_valid(t))?;
    let end = a.states[last].position();
    let mut best: Option<(f64, Turn, LanePath)> = None;
    for turn in [Turn::Straight, Turn::Left, Turn::Right] {
        let Some(p) = route_of(s, a, turn) else {
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
        let from = c + (x.or("from", 0.0)? / s.meta.dt).round() as usize;
        let vmax = speeds(s, a)
            .iter()
            .filter(|(t, _)| *t > from)
            .map(|v| v.1)
            .fold(0.0, f64::max);
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
        let (tx, ty, tol) = (x.get("x")?, x.get("y")?, x.or("tol", 1.0)?);
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
        let want = x.or("gap", 10.0)?;
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

/// [`check`] for `Stop`.
fn stop(mut x: Ctx<'_>) -> Result<Verdict, CheckError> {
    let (s, c) = (x.s, x.s.meta.current_step);
    Ok({
        let a = x.agent("vehicle")?;
        let within = x.or("within", 4.0)?;
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

/// Speed (m/s) above which `suggest` counts a car as moving.
const MOVING: f64 = 2.0;
/// The bumper-to-bumper gap (metres) `suggest` asks a follower to keep.
const FOLLOW_GAP: f64 = 10.0;
/// How far (metres, from the lane path's centre line) a yielder or the car it yields to may
/// be from the route the request names: within its lane, with room to cut a junction's corner.
const ROUTE_TOLERANCE: f64 = 2.0;

/// Farthest a neighbouring lane's centre may lie from the recorded end (m) for `target_point`:
/// a lane beside it, not one that stops short of it.
const TARGET_BESIDE: f64 = 5.0;

/// How far inside the road edge (m, centre to edge) `suggest` looks for a car to drive off
/// it: the outer lane.
const OFF_ROAD_REACH: f64 = 4.0;

/// Braking and backing up as [`suggest`] times a `reverse` request: to a stop at
/// [`REVERSE_BRAKE`], then backwards at [`REVERSE_ACCEL`] up to [`REVERSE_SPEED`] (the script's
/// default speed), until [`REVERSE_MARGIN`] beyond the checker's metre behind the start.
const REVERSE_BRAKE: f64 = 4.0;
/// See [`REVERSE_BRAKE`].
const REVERSE_ACCEL: f64 = 2.0;
/// See [`REVERSE_BRAKE`].
const REVERSE_SPEED: f64 = 2.0;
/// See [`REVERSE_BRAKE`].
const REVERSE_MARGIN: f64 = 0.5;

/// Whether `a` can stop and back up 1 m behind where it is now (plus [`REVERSE_MARGIN`])
/// within `horizon` seconds less 0.5 s, and the nearest vehicle behind it in its lane (a box
/// overlapping its corridor) can stop at [`REVERSE_BRAKE`] short of where it backs to, 1 m
/// clear.
fn can_back_up(scene: &Scene, a: &Agent, horizon: f64) -> bool {
    let c = scene.meta.current_step;
    let s = a.states[c];
    let v = s.speed();
    // Forward while braking, then back past the start.
    let ahead = v * v / (2.0 * REVERSE_BRAKE);
    let back = ahead + 1.0 + REVERSE_MARGIN;
    let ramp = REVERSE_SPEED * REVERSE_SPEED / (2.0 * REVERSE_ACCEL);
    let backing = if back <= ramp {
        (2.0 * back / REVERSE_ACCEL).sqrt()
    } else {
        REVERSE_SPEED / REVERSE_ACCEL + (back - ramp) / REVERSE_SPEED
    };
    if v / REVERSE_BRAKE + backing > horizon - 0.5 {
        return false;
    }
    let dir = Point::new(s.heading.cos(), s.heading.sin());
    let room = 1.0 + REVERSE_MARGIN + 1.0;
    scene
        .agents
        .iter()
        .filter(|o| o.id != a.id && o.agent_type == AgentType::Vehicle && o.is_valid(c))
        .all(|o| {
            let r = o.states[c].position() - s.position();
            let (lon, lat) = (r.dot(&dir), dir.x * r.y - dir.y * r.x);
            let behind = lon < 0.0 && lat.abs() < 0.5 * (a.width + o.width);
            let gap = -lon - 0.5 * (a.length + o.length);
            let vo = o.states[c].speed();
            !behind || gap >= room + vo * vo / (2.0 * REVERSE_BRAKE)
        })
}

/// Agents for which a behaviour is a meaningful request in `scene`, chosen by geometry alone,
/// so that success rates over many scenes need no hand-picked ids (`None` when the scene has
/// no suitable agent). Candidates are vehicles observed at the current step and through the
/// recorded future, on a lane; ties go to the one nearest the scene's ego (or first vehicle).
/// `horizon` is the number of future steps the methods simulate, which may exceed the
/// recording's (`eval --horizon`, a model's horizon): requests are timed by it.
///
/// - one-vehicle behaviours: the nearest candidate; lane changes and `rightmost_lane` need a
///   lane on that side (for `rightmost_lane`, not already the rightmost); `speed_limit` asks for
///   80 % of its current speed from the time braking to it at 2.5 m/s² takes; `target_point`
///   for the point level with its recorded end on the centre line of the lane beside it (left
///   where there is one, else right; within 5 m of the end); `stop` within 60 % of the horizon or the
///   time braking at 4 m/s² takes, if longer, for the nearest vehicle that can then stand
///   still for the last 0.5 s; `reverse` for the nearest one that can brake to a stop at 4 m/s²
///   and back up 1.5 m behind its start (at 2 m/s² up to 2 m/s) within the horizon less 0.5 s,
///   with room for the vehicle behind it in its lane to stop at 4 m/s² 1 m short of that;
/// - `cut_in`: a victim and a cutter moving at 2 m/s or more in an adjacent lane within 15 m
///   along the victim's path that can end 5 m (bumper to bumper) ahead of the victim holding its speed, accelerating at
///   2.5 m/s² and no faster than 0.75 of the sprint bound allows (the kinematic checker's and
///   realism's bounds): a slower car far behind cannot cut in plausibly;
/// - `follow`: a leader ahead in the follower's lane within 60 m, asking for a 10 m gap that
///   the follower can bring within the checker's 5–20 m by half the horizon with the leader
///   holding its speed, braking at up to 3 m/s² (never backing up) or speeding up at 2 m/s²;
/// - `off_road`: the nearest car moving at 2 m/s or more with its centre within 4 m of the
///   road edge (a car queued at a light, or boxed in mid-road, has no way off it);
/// - `yield`: two vehicles whose routes (the lane paths, straight on, left or right at forks,
///   that their recorded ends lie nearest) meet ahead of both, within 1.2 times the distance
///   the yielder covers over the horizon at its current speed plus 20 m, and that the other,
///   moving at 2 m/s or more, passes by 2 m within the horizon at its current speed, while the
///   yielder, moving too, would get there first at its own but can hold back 2 m before the
///   point until then braking at 3 m/s² at most (yielding to a car that waits at a light, is
///   too far away to arrive or passes first anyway asks for nothing; yielding from the
///   junction's edge asks for an emergency stop);
/// - `accident`: the nearest pair; `no_collisions`: no agents;
/// - `turn_left` / `turn_right`: the nearest car whose route (that way at forks) has such a
///   turn ahead, whose middle it can reach within the horizon less a second.
pub fn suggest(b: Behavior, scene: &Scene, horizon: usize) -> Option<Params> {
    let c = scene.meta.current_step;
    let n = scene.num_steps();
    let horizon = horizon as f64 * scene.meta.dt;
    // Recorded over the whole horizon without reaching a map exit: a car that leaves the
    // scene within it (every method's car leaves there too) cannot show a behaviour.
    let kept = scene.retire_exited();
    let mut cands: Vec<(&Agent, i64, LanePath)> = scene
        .agents
        .iter()
        .zip(&kept.agents)
        .filter(|(a, k)| a.agent_type == AgentType::Vehicle && (c..n).all(|t| k.is_valid(t)))
        .map(|(a, _)| a)
        // The recording must end on a mapped lane: where the map stops short of the agent's
        // future (NGSIM maps cover a few hundred metres), no lane-based behaviour can be
        // judged at the end of the horizon, whatever the simulator does.
        .filter(|a| lane_of(scene, a, n - 1).is_some())
        .filter_map(|a| Some((a, lane_of(scene, a, c)?, path_of(scene, a)?)))
        .collect();
    let centre = scene
        .meta
        .ego
        .and_then(|e| scene.agent(e))
        .or_else(|| cands.first().map(|x| x.0))?
        .states[c]
        .position();
    cands.sort_by(|x, y| {
        let d = |a: &Agent| (a.states[c].position() - centre).norm();
        d(x.0).total_cmp(&d(y.0)).then(x.0.id.cmp(&y.0.id))
    });
    let g = scene.map.graph();
    let p = |kv: &[(&str, f64)]| Some(Params::numbers(kv));
    match b {
        Behavior::NoCollisions => p(&[]),
        // The limit is below the current speed; braking to it at a moderate 2.5 m/s² takes
        // time (a 14 m/s car needs 1.2 s), which the request allows.
        Behavior::SpeedLimit => {
            let (a, _, _) = cands.first()?;
            let v = a.states[c].speed();
            p(&[
                ("vehicle", a.id as f64),
                ("limit", 0.8 * v),
                ("from", (0.2 * v / 2.5 * 10.0).ceil() / 10.0),
            ])
        }
        // The point level with the recorded end in the lane beside it (the left one where
        // there is one): a lane change, ended where the recorded car ended. The request 20 m
        // to the left it replaces crossed five lanes, or the road's edge, within 4 s.
        Behavior::TargetPoint => cands.iter().find_map(|(a, _, _)| {
            let end = a.states[n - 1].position();
            let lane = lane_of(scene, a, n - 1)?;
            let centre = &scene
                .map
                .lane(g.left(lane).or_else(|| g.right(lane))?)?
                .centerline;
            let hit = centre.nearest(&end);
            // Beside the end, not where a neighbour that stops short of it ends.
            (hit.distance <= TARGET_BESIDE).then_some(())?;
            let at = centre.point_at(hit.s);
            p(&[("vehicle", a.id as f64), ("x", at.x), ("y", at.y)])
        }),
        Behavior::LaneChangeLeft => cands
            .iter()
            .find(|x| g.left(x.1).is_some())
            .and_then(|x| p(&[("vehicle", x.0.id as f64)])),
        Behavior::LaneChangeRight => cands
            .iter()
            .find(|x| g.right(x.1).is_some())
            .and_then(|x| p(&[("vehicle", x.0.id as f64)])),
        // A lane change takes about 2 s, so the nearest vehicle with at most one lane per 2 s
        // of horizon to go (at least one): five lanes across a US-101 in 4 s is no behaviour
        // a driver shows.
        Behavior::RightmostLane => {
            let reach = ((horizon / 2.0).floor() as usize).max(1);
            let lanes_to_right = |mut l: i64| {
                let mut k = 0;
                while let Some(r) = g.right(l).filter(|_| k <= reach) {
                    (l, k) = (r, k + 1);
                }
                k
            };
            cands
                .iter()
                .find(|x| (1..=reach).contains(&lanes_to_right(x.1)))
                .and_then(|x| p(&[("vehicle", x.0.id as f64)]))
        }
        Behavior::Weave => cands.first().and_then(|x| p(&[("vehicle", x.0.id as f64)])),
        // A car that can stop, then back up past the checker's metre within the horizon, with
        // room behind it for the car that follows to stop: a 15 m/s car cannot do it in
        // 4 s, and one with a car on its bumper can only back into it.
        Behavior::Reverse => cands
            .iter()
            .find(|x| can_back_up(scene, x.0, horizon))
            .and_then(|x| p(&[("vehicle", x.0.id as f64)])),
        // A moving car within a lane of the road's edge. A car at rest in a queue, or one in
        // a middle lane with traffic on both sides, has no way off the road a driver could
        // take in a few seconds (held-out NGSIM: most failed requests were such cars).
        Behavior::OffRoad => cands
            .iter()
            .find(|x| {
                let s = x.0.states[c];
                s.speed() >= MOVING
                    && scene
                        .map
                        .signed_distance_to_road_edge(s.position())
                        .is_some_and(|d| d >= -OFF_ROAD_REACH)
            })
            .and_then(|x| p(&[("vehicle", x.0.id as f64)])),
        // The 4 s default assumes WOMD's 8 s future; a car at 18 m/s cannot stop within
        // 2.4 s, nor without braking harder than the script allows.
        Behavior::Stop => cands.iter().find_map(|x| {
            let braking = x.0.states[c].speed() / 4.0;
            let within = ((0.6 * horizon).max(braking) * 10.0).ceil() / 10.0;
            (within <= horizon - 0.5)
                .then(|| p(&[("vehicle", x.0.id as f64), ("within", within)]))?
        }),
        Behavior::CutIn => {
            for (victim, lv, path) in &cands {
                let sv = path.frenet.project(victim.states[c].position()).s;
                for (cutter, lc, _) in &cands {
                    let adjacent =
                        g.left_neighbors(*lv).contains(lc) || g.right_neighbors(*lv).contains(lc);
                    let sc = path.frenet.project(cutter.states[c].position()).s;
                    let speed = |a: &Agent| a.states[c].vx.hypot(a.states[c].vy);
                    let (vc, vv) = (speed(cutter), speed(victim));
                    // Speed gain at 2.5 m/s² up to the cap, as a ramp over the horizon.
                    let lim = KinematicLimits::default();
                    let cap = vc
                        + 0.75
                            * (lim
                                .max_speed
                                .min(lim.sprint_factor * vc + lim.sprint_margin)
                                - vc)
                                .max(0.0);
                    let gain = (2.5 * horizon).min(cap - vc);
                    let reach = sc - sv - 0.5 * (cutter.length + victim.length)
                        + (vc - vv) * horizon
                        + 0.5 * gain * horizon;
                    // A cutter at rest (a queue at a light) does not cut in.
                    if cutter.id != victim.id
                        && adjacent
                        && vc >= MOVING
                        && (sc - sv).abs() <= 15.0
                        && reach >= 5.0
                    {
                        return p(&[("cutter", cutter.id as f64), ("victim", victim.id as f64)]);
                    }
                }
            }
            None
        }
        Behavior::Follow => {
            let want = FOLLOW_GAP;
            // The checker wants the bumper gap within gap/2 .. 2·gap over the last half of
            // the horizon. With the leader holding its speed, the follower can open the gap
            // at most by braking to a standstill at 3 m/s² and close it at most by speeding
            // up at 2 m/s², never backing up: a car queued 3 m behind a standing one cannot
            // drop back to 5 m.
            let reachable = |f: &Agent, l: &Agent, ahead: f64| {
                let half = horizon / 2.0;
                let gap0 = ahead - 0.5 * (f.length + l.length);
                let (vf, vl) = (f.states[c].speed(), l.states[c].speed());
                let stop = (vf / 3.0).min(half);
                let widest = gap0 + vl * half - (vf * stop - 1.5 * stop * stop);
                let closest = gap0 + vl * half - (vf * half + half * half);
                widest >= want / 2.0 && closest <= 2.0 * want
            };
            for (f, lf, path) in &cands {
                let sf = path.frenet.project(f.states[c].position()).s;
                for (l, ll, _) in &cands {
                    let ahead = path.frenet.project(l.states[c].position()).s - sf;
                    if l.id != f.id
                        && ll == lf
                        && ahead > 0.0
                        && ahead <= 60.0
                        && reachable(f, l, ahead)
                    {
                        return p(&[
                            ("follower", f.id as f64),
                            ("leader", l.id as f64),
                            ("gap", want),
                        ]);
                    }
                }
            }
            None
        }
        Behavior::Yield => {
            // How far the yielder could get over the horizon: its current speed with some
            // slack (2.5 m/s² of acceleration).
            let reach = |a: &Agent| 1.2 * a.states[c].speed() * horizon + 20.0;
            // The other must be coming: moving, and past the meeting point (by the checker's
            // 2 m) within the horizon at its current speed. Yielding to a car that is waiting
            // at a light, or that is too far to arrive, asks for nothing a driver can show.
            let coming = |o: &Agent, to_go: f64| {
                let v = o.states[c].speed();
                v >= MOVING && to_go + 2.0 <= v * horizon
            };
            // And the yielder, holding its speed, would get there first (otherwise the other
            // passes first by itself and "yield" asks for nothing either), yet can hold back,
            // braking at most 3 m/s², where the yield script stops it (front bumper 2 m short
            // of the meeting point, 10 m more where the lanes merge) until the other's rear
            // bumper is 2 m past: a car already at the junction cannot yield without an
            // emergency stop, and a request the script can only meet that way is not offered.
            let first = |a: &Agent, a_to_go: f64, o: &Agent, o_to_go: f64, merge: bool| {
                let (va, vo) = (a.states[c].speed(), o.states[c].speed());
                let stop_short = a.length / 2.0 + 2.0 + if merge { 10.0 } else { 0.0 };
                let (room, other_past) =
                    (a_to_go - stop_short, (o_to_go + o.length / 2.0 + 2.0) / vo);
                let brake = 3.0;
                let holds = room > 0.0
                    && (va * va / (2.0 * brake) <= room
                        || (va - (va * va - 2.0 * brake * room).sqrt()) / brake >= other_past);
                va >= MOVING && a_to_go / va <= o_to_go / vo && holds
            };
            // Each car's route as recorded: a car that turned left at the junction meets the
            // oncoming traffic there, which its path straight on never does.
            let routes: Vec<(&Agent, Turn, LanePath)> = cands
                .iter()
                .filter_map(|(a, _, _)| driven_route(scene, a).map(|(t, p)| (*a, t, p)))
                .collect();
            for (a, ta, pa) in &routes {
                let sa0 = pa.frenet.project(a.states[c].position()).s;
                for (o, to, po) in &routes {
                    if o.id == a.id {
                        continue;
                    }
                    let so0 = po.frenet.project(o.states[c].position()).s;
                    if let Some((sa, so, _)) = pa.first_meeting(po) {
                        if sa > sa0
                            && so > so0
                            && sa - sa0 <= reach(a)
                            && coming(o, so - so0)
                            && first(a, sa - sa0, o, so - so0, merges(pa, po))
                        {
                            let mut p = Params::numbers(&[
                                ("yielder", a.id as f64),
                                ("other", o.id as f64),
                            ]);
                            p.set("yielder_turn", ParamValue::Str(ta.word().into()));
                            p.set("other_turn", ParamValue::Str(to.word().into()));
                            return Some(p);
                        }
                    }
                }
            }
            None
        }
        // The nearest car whose route has the turn ahead, with the middle of the corner within
        // what it covers over the horizon less a second, speeding up at 1.5 m/s² at most, and
        // not yet reached: a car already round the corner has nothing left to do.
        Behavior::TurnLeft | Behavior::TurnRight => {
            let way = b.turn().expect("a turning behaviour");
            cands.iter().find_map(|(a, _, _)| {
                let route = route_of(scene, a, way)?;
                let span = route.next_turn(&scene.map, way)?;
                let to_go = span.middle - route.frenet.project(a.states[c].position()).s;
                let t = (horizon - 1.0).max(0.0);
                let reach = a.states[c].speed() * t + 0.75 * t * t;
                (to_go > 0.0 && to_go + 1.0 <= reach).then(|| p(&[("vehicle", a.id as f64)]))?
            })
        }
        Behavior::Accident => {
            let (a, _, _) = cands.first()?;
            let (b, _, _) = cands.get(1)?;
            p(&[("attacker", a.id as f64), ("target", b.id as f64)])
        }
    }
}
/// Where a lane query ended, in words: "in lane 695", or "on no lane".
fn lane_words(lane: Option<i64>) -> String {
    lane.map_or_else(|| "on no lane".into(), |l| format!("in lane {l}"))
}
