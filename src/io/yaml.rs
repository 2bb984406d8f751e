//! drivescript's YAML scenes: a straight or curved multi-lane road and a few agents, written by
//! hand in a few lines. The format is documented in README.md ("YAML scenes").
//!
//! The road is built along a reference line, its right edge: it starts at `origin`, heads
//! `heading` degrees and is straight (`radius: 0`) or an arc (`radius > 0` bends left, `< 0`
//! right). Lane `k` (0 = rightmost) of road segment `j` has id `100 * (j + 1) + k`. Agents
//! either move along a lane (`lane`, `s`, `d`, `speed`, `accel`, optional `lane_change`) or
//! give explicit `states`.

use std::path::Path;

use serde::Deserialize;

use super::IoError;
use crate::geom::{FrenetPath, Point, Polyline};
use crate::scene::{
    Agent, AgentState, AgentType, Lane, LaneType, Map, MapParts, RoadEdge, RoadEdgeKind,
    RoadLine, RoadLineKind, Scene, SceneMeta, SourceFormat,
};

/// A YAML scene file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct YamlScene {
    /// Scenario id (default: the file name).
    #[serde(default)]
    pub scenario_id: Option<String>,
    /// Seconds per step.
    #[serde(default = "default_dt")]
    pub dt: f64,
    /// Number of steps.
    #[serde(default = "default_steps")]
    pub steps: usize,
    /// Index of the current step.
    #[serde(default = "default_current")]
    pub current_step: usize,
    /// The road.
    pub road: YamlRoad,
    /// The agents.
    #[serde(default)]
    pub agents: Vec<YamlAgent>,
    /// The ego agent's id.
    #[serde(default)]
    pub ego: Option<i64>,
}

fn default_dt() -> f64 {
    0.1
}
fn default_steps() -> usize {
    91
}
fn default_current() -> usize {
    10
}

/// The road of a YAML scene.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct YamlRoad {
    /// Number of lanes, all driving the same way.
    pub lanes: usize,
    /// Lane width, metres.
    #[serde(default = "default_lane_width")]
    pub lane_width: f64,
    /// Length of the road, metres.
    pub length: f64,
    /// Lanes are cut into this many consecutive pieces (to give the lane graph successors).
    #[serde(default = "default_segments")]
    pub segments: usize,
    /// Radius of the reference line: 0 straight, > 0 bends left, < 0 bends right.
    #[serde(default)]
    pub radius: f64,
    /// Start of the reference line (the road's right edge).
    #[serde(default)]
    pub origin: [f64; 2],
    /// Initial heading, degrees.
    #[serde(default)]
    pub heading: f64,
    /// Speed limit, m/s.
    #[serde(default)]
    pub speed_limit: Option<f64>,
    /// `freeway` or `surface_street`.
    #[serde(default = "default_lane_type")]
    pub lane_type: LaneType,
}

fn default_lane_width() -> f64 {
    3.6
}
fn default_segments() -> usize {
    1
}
fn default_lane_type() -> LaneType {
    LaneType::Freeway
}

/// A scripted lane change.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct YamlLaneChange {
    /// Target lane index.
    pub to: usize,
    /// Start, seconds after the current step (negative: in the history).
    pub start: f64,
    /// Duration, seconds.
    #[serde(default = "default_lc_duration")]
    pub duration: f64,
}

fn default_lc_duration() -> f64 {
    3.0
}

/// An agent of a YAML scene.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct YamlAgent {
    /// Identifier.
    pub id: i64,
    /// `vehicle`, `pedestrian`, `cyclist` or `other`.
    #[serde(default = "default_agent_type", rename = "type")]
    pub agent_type: AgentType,
    /// Footprint length (default by type).
    #[serde(default)]
    pub length: Option<f64>,
    /// Footprint width (default by type).
    #[serde(default)]
    pub width: Option<f64>,
    /// Lane index at the current step (0 = rightmost).
    #[serde(default)]
    pub lane: usize,
    /// Distance along the road at the current step, metres.
    #[serde(default)]
    pub s: f64,
    /// Lateral offset from the lane centre, metres (left positive).
    #[serde(default)]
    pub d: f64,
    /// Speed at the current step, m/s (negative drives backwards).
    #[serde(default)]
    pub speed: f64,
    /// Constant acceleration, m/s² (the agent stops rather than reverse).
    #[serde(default)]
    pub accel: f64,
    /// Optional scripted lane change.
    #[serde(default)]
    pub lane_change: Option<YamlLaneChange>,
    /// First valid step (default 0): agents that appear late.
    #[serde(default)]
    pub valid_from: usize,
    /// Explicit `[x, y, heading]` per step, replacing the motion fields.
    #[serde(default)]
    pub states: Option<Vec<[f64; 3]>>,
}

fn default_agent_type() -> AgentType {
    AgentType::Vehicle
}

/// Default footprint (length, width) for an agent type.
pub fn default_size(t: AgentType) -> (f64, f64) {
    match t {
        AgentType::Vehicle => (4.6, 1.9),
        AgentType::Pedestrian => (0.6, 0.6),
        AgentType::Cyclist => (1.8, 0.7),
        AgentType::Other => (1.0, 1.0),
    }
}

/// Reads a YAML scene file.
pub fn read(path: &Path) -> Result<Scene, IoError> {
    let text = std::fs::read_to_string(path).map_err(|e| IoError::read(path, e))?;
    parse(path, &text)
}

/// Parses YAML scene text (`path` is used for messages and metadata).
pub fn parse(path: &Path, text: &str) -> Result<Scene, IoError> {
    let y: YamlScene = serde_yaml::from_str(text).map_err(|e| {
        let loc = e
            .location()
            .map(|l| format!("line {}, column {}", l.line(), l.column()))
            .unwrap_or_else(|| "document".into());
        IoError::invalid(path, loc, e.to_string())
    })?;
    build(path, &y)
}

fn reference_line(r: &YamlRoad) -> Polyline {
    let n = (r.length / 1.0).ceil().max(1.0) as usize + 1;
    let h0 = r.heading.to_radians();
    let o = Point::new(r.origin[0], r.origin[1]);
    let pts = (0..n).map(|k| {
        let s = r.length * k as f64 / (n - 1) as f64;
        if r.radius == 0.0 {
            o + Point::new(h0.cos(), h0.sin()) * s
        } else {
            let a = s / r.radius;
            // Arc from the origin with curvature 1/radius, in the road's local frame.
            let local = Point::new(r.radius * a.sin(), r.radius * (1.0 - a.cos()));
            o + Point::new(
                local.x * h0.cos() - local.y * h0.sin(),
                local.x * h0.sin() + local.y * h0.cos(),
            )
        }
    });
    Polyline::new(pts).expect("a road of positive length")
}

fn build(path: &Path, y: &YamlScene) -> Result<Scene, IoError> {
    let bad = |loc: String, msg: String| IoError::invalid(path, loc, msg);
    let r = &y.road;
    if r.lanes == 0 || r.segments == 0 {
        return Err(bad("road".into(), "lanes and segments must be at least 1".into()));
    }
    if !(r.length.is_finite() && r.length > 0.0 && r.lane_width.is_finite() && r.lane_width > 0.0)
    {
        return Err(bad("road".into(), "length and lane_width must be positive".into()));
    }
    let max_offset = r.lanes as f64 * r.lane_width;
    if r.radius != 0.0 && (r.radius.abs() <= max_offset + 1.0 || !r.radius.is_finite()) {
        return Err(bad(
            "road.radius".into(),
            format!("|radius| must exceed the road width ({max_offset} m)"),
        ));
    }
    if y.steps == 0 || y.current_step >= y.steps {
        return Err(bad(
            "current_step".into(),
            format!("current_step {} must be below steps {}", y.current_step, y.steps),
        ));
    }
    let reference = FrenetPath::new(reference_line(r));
    let w = r.lane_width;
    let offset_line = |d: f64, s0: f64, s1: f64| {
        let n = ((s1 - s0) / 1.0).ceil().max(1.0) as usize + 1;
        Polyline::new((0..n).map(|k| reference.to_cartesian(s0 + (s1 - s0) * k as f64 / (n - 1) as f64, d)))
            .expect("positive length")
    };
    let mut parts = MapParts::default();
    let seg_len = r.length / r.segments as f64;
    let lane_id = |j: usize, k: usize| 100 * (j as i64 + 1) + k as i64;
    for j in 0..r.segments {
        let (s0, s1) = (j as f64 * seg_len, (j + 1) as f64 * seg_len);
        for k in 0..r.lanes {
            let mut lane = Lane::new(lane_id(j, k), offset_line((k as f64 + 0.5) * w, s0, s1));
            lane.left_boundary = Some(offset_line((k + 1) as f64 * w, s0, s1));
            lane.right_boundary = Some(offset_line(k as f64 * w, s0, s1));
            lane.lane_type = r.lane_type;
            lane.speed_limit = r.speed_limit;
            if j > 0 {
                lane.predecessors.push(lane_id(j - 1, k));
            }
            if j + 1 < r.segments {
                lane.successors.push(lane_id(j + 1, k));
            }
            if k + 1 < r.lanes {
                lane.left_neighbors.push(lane_id(j, k + 1));
            }
            if k > 0 {
                lane.right_neighbors.push(lane_id(j, k - 1));
            }
            if let Some(s) = lane.surface() {
                parts.drivable_areas.push(s);
            }
            parts.lanes.push(lane);
        }
    }
    parts.road_edges.push(RoadEdge::new(
        RoadEdgeKind::Boundary,
        offset_line(0.0, 0.0, r.length),
    ));
    parts.road_edges.push(RoadEdge::new(
        RoadEdgeKind::Boundary,
        offset_line(max_offset, 0.0, r.length).reversed(),
    ));
    for k in 1..r.lanes {
        parts.road_lines.push(RoadLine {
            kind: RoadLineKind::Broken,
            yellow: false,
            line: offset_line(k as f64 * w, 0.0, r.length),
        });
    }
    let map = Map::new(parts).map_err(|e| IoError::Scene {
        path: path.display().to_string(),
        location: "road".into(),
        source: e,
    })?;

    let mut agents = Vec::new();
    for (i, a) in y.agents.iter().enumerate() {
        let loc = format!("agents[{i}] (id {})", a.id);
        let (dl, dw) = default_size(a.agent_type);
        let (length, width) = (a.length.unwrap_or(dl), a.width.unwrap_or(dw));
        let states = if let Some(explicit) = &a.states {
            if explicit.len() != y.steps {
                return Err(bad(loc, format!("{} states for {} steps", explicit.len(), y.steps)));
            }
            explicit_states(explicit, y.dt)
        } else {
            if a.lane >= r.lanes || a.lane_change.as_ref().is_some_and(|c| c.to >= r.lanes) {
                return Err(bad(loc, format!("lane index out of range: the road has {} lanes", r.lanes)));
            }
            lane_motion(a, y, &reference, w)
        };
        let mut states = states;
        if a.valid_from >= y.steps {
            return Err(bad(loc, format!("valid_from {} must be below steps {}", a.valid_from, y.steps)));
        }
        for s in states.iter_mut().take(a.valid_from) {
            *s = AgentState::INVALID;
        }
        agents.push(Agent {
            id: a.id,
            agent_type: a.agent_type,
            length,
            width,
            states,
        });
    }
    let meta = SceneMeta {
        source_format: SourceFormat::Yaml,
        source_file: path.display().to_string(),
        scenario_id: y.scenario_id.clone().unwrap_or_else(|| super::file_stem(path)),
        dt: y.dt,
        current_step: y.current_step,
        ego: y.ego,
        warnings: Vec::new(),
    };
    Scene::new(meta, map, agents).map_err(|e| IoError::Scene {
        path: path.display().to_string(),
        location: "agents".into(),
        source: e,
    })
}

fn explicit_states(xyh: &[[f64; 3]], dt: f64) -> Vec<AgentState> {
    let n = xyh.len();
    (0..n)
        .map(|k| {
            let (a, b) = (k.saturating_sub(1), (k + 1).min(n - 1));
            let span = (b - a).max(1) as f64 * dt;
            AgentState {
                x: xyh[k][0],
                y: xyh[k][1],
                heading: xyh[k][2],
                vx: (xyh[b][0] - xyh[a][0]) / span,
                vy: (xyh[b][1] - xyh[a][1]) / span,
                valid: true,
            }
        })
        .collect()
}

fn lane_motion(a: &YamlAgent, y: &YamlScene, reference: &FrenetPath, w: f64) -> Vec<AgentState> {
    let centre = |k: usize| (k as f64 + 0.5) * w;
    let pos = |k: usize| -> (f64, f64) {
        let tau = (k as f64 - y.current_step as f64) * y.dt;
        // Constant acceleration until the speed reaches zero, then standing still.
        let s = if a.accel != 0.0 && (a.speed / a.accel) < 0.0 && tau > -a.speed / a.accel {
            let t_stop = -a.speed / a.accel;
            a.s + a.speed * t_stop + 0.5 * a.accel * t_stop * t_stop
        } else {
            a.s + a.speed * tau + 0.5 * a.accel * tau * tau
        };
        let mut d = centre(a.lane) + a.d;
        if let Some(lc) = &a.lane_change {
            let u = ((tau - lc.start) / lc.duration.max(1e-6)).clamp(0.0, 1.0);
            d += (centre(lc.to) - centre(a.lane)) * 0.5 * (1.0 - (std::f64::consts::PI * u).cos());
        }
        (s, d)
    };
    let xy: Vec<Point> = (0..y.steps)
        .map(|k| {
            let (s, d) = pos(k);
            reference.to_cartesian(s, d)
        })
        .collect();
    let n = xy.len();
    (0..n)
        .map(|k| {
            let (lo, hi) = (k.saturating_sub(1), (k + 1).min(n - 1));
            let v = (xy[hi] - xy[lo]) / ((hi - lo).max(1) as f64 * y.dt);
            let heading = if v.norm() > 0.05 {
                let h = v.y.atan2(v.x);
                // Reversing keeps the body facing the road's direction.
                if a.speed < 0.0 {
                    crate::geom::wrap_angle(h + std::f64::consts::PI)
                } else {
                    h
                }
            } else {
                reference.heading_at(pos(k).0)
            };
            AgentState {
                x: xy[k].x,
                y: xy[k].y,
                heading,
                vx: v.x,
                vy: v.y,
                valid: true,
            }
        })
        .collect()
}
