//! Agents: the road users of a scene and their states over time.

use serde::{Deserialize, Serialize};

use crate::geom::{OrientedBox, Point};

/// Identifier of an agent, as the source format numbers it.
pub type AgentId = i64;

/// What kind of road user an agent is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AgentType {
    /// Cars, trucks, buses, motorcycles.
    Vehicle,
    /// People on foot.
    Pedestrian,
    /// Bicycles with a rider.
    Cyclist,
    /// Anything else (static objects, unknown tracks).
    Other,
}

impl AgentType {
    /// Lower-case name used in files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            AgentType::Vehicle => "vehicle",
            AgentType::Pedestrian => "pedestrian",
            AgentType::Cyclist => "cyclist",
            AgentType::Other => "other",
        }
    }

    /// Parses a name written by [`AgentType::name`].
    pub fn from_name(s: &str) -> Option<Self> {
        Some(match s {
            "vehicle" => AgentType::Vehicle,
            "pedestrian" => AgentType::Pedestrian,
            "cyclist" => AgentType::Cyclist,
            "other" => AgentType::Other,
            _ => return None,
        })
    }
}

/// One agent's state at one time step. Invalid states (not observed) carry zeros.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct AgentState {
    /// Centre x, metres.
    pub x: f64,
    /// Centre y, metres.
    pub y: f64,
    /// Heading of the body, radians.
    pub heading: f64,
    /// Velocity x, m/s.
    pub vx: f64,
    /// Velocity y, m/s.
    pub vy: f64,
    /// Whether the state was observed.
    pub valid: bool,
}

impl AgentState {
    /// The invalid state used for steps where an agent is absent.
    pub const INVALID: AgentState = AgentState {
        x: 0.0,
        y: 0.0,
        heading: 0.0,
        vx: 0.0,
        vy: 0.0,
        valid: false,
    };

    /// Position as a point.
    pub fn position(&self) -> Point {
        Point::new(self.x, self.y)
    }

    /// Speed, m/s.
    pub fn speed(&self) -> f64 {
        self.vx.hypot(self.vy)
    }
}

/// A road user with a fixed footprint and one state per scene time step.
#[derive(Debug, Clone, PartialEq)]
pub struct Agent {
    /// Identifier from the source.
    pub id: AgentId,
    /// Kind of road user.
    pub agent_type: AgentType,
    /// Footprint length, metres.
    pub length: f64,
    /// Footprint width, metres.
    pub width: f64,
    /// One state per scene step (same length for every agent of a scene).
    pub states: Vec<AgentState>,
    /// A static obstacle (a parked car, a barrier): it holds its pose, and no sampler moves
    /// it, whatever its type.
    pub is_static: bool,
}

impl Agent {
    /// The footprint at step `t`, if the state there is valid.
    pub fn footprint(&self, t: usize) -> Option<OrientedBox> {
        let s = self.states.get(t).filter(|s| s.valid)?;
        Some(OrientedBox::new(
            s.x,
            s.y,
            s.heading,
            self.length,
            self.width,
        ))
    }

    /// Whether the agent is observed at step `t`.
    pub fn is_valid(&self, t: usize) -> bool {
        self.states.get(t).is_some_and(|s| s.valid)
    }

    /// Number of valid states.
    pub fn valid_count(&self) -> usize {
        self.states.iter().filter(|s| s.valid).count()
    }

    /// First and last valid steps, if any.
    pub fn valid_span(&self) -> Option<(usize, usize)> {
        let first = self.states.iter().position(|s| s.valid)?;
        let last = self.states.iter().rposition(|s| s.valid)?;
        Some((first, last))
    }
}

/// Sets the velocity of every valid state from step `from` on from the positions around it:
/// the centred difference where both neighbours are valid, else the one-sided one, else zero.
/// The sampler and the rollout reader both use it, so that a rollout read back from its file
/// moves as the sample did in memory.
pub fn velocities_from_positions(states: &mut [AgentState], from: usize, dt: f64) {
    let valid = |t: Option<usize>| t.and_then(|t| states.get(t)).is_some_and(|s| s.valid);
    let v: Vec<Option<(f64, f64)>> = (from..states.len())
        .map(|t| {
            if !valid(Some(t)) {
                return None;
            }
            let before = if valid(t.checked_sub(1)) { t - 1 } else { t };
            let after = if valid(Some(t + 1)) { t + 1 } else { t };
            if before == after {
                return Some((0.0, 0.0));
            }
            let span = (after - before) as f64 * dt;
            let (p, q) = (&states[before], &states[after]);
            Some(((q.x - p.x) / span, (q.y - p.y) / span))
        })
        .collect();
    let start = from.min(states.len());
    for (s, v) in states[start..].iter_mut().zip(v) {
        if let Some((vx, vy)) = v {
            s.vx = vx;
            s.vy = vy;
        }
    }
}
