//! The scene model: a road map with its lane graph, agents with states at a fixed time step,
//! and where it all came from. World frame, SI units.

mod agents;
pub mod description;
mod kinematic_limits;
mod lane_graph;
mod lane_path;
mod map;
pub mod routes;

use std::collections::{BTreeMap, HashSet};

use serde::Serialize;

pub use agents::{velocities_from_positions, Agent, AgentId, AgentState, AgentType};
pub use description::{describe, DescribeOptions, SceneDescription};
pub use kinematic_limits::KinematicLimits;
pub use lane_graph::{far_links, EdgeCounts, FarLink, LaneGraph, LINK_GAP};
pub use lane_path::{LanePath, Turn, TurnSpan, TURN_THRESHOLD};
pub use map::{
    lanes_turning_back, signed_width, Lane, LaneId, LaneType, Map, MapExit, MapParts, RoadEdge,
    RoadEdgeKind, RoadLine, RoadLineKind, StopLine, MAX_LANE_TURN, MIN_JUDGED_LENGTH, ZERO_WIDTH,
};

use crate::geom::{num, GeomError, MAX_COORD};

/// The largest speed a state's velocity may have, m/s. A bound on numbers, not on driving:
/// rollouts of a bad model must still be read and scored (`eval`'s kinematic check judges
/// whether a car could drive them), but velocities of 1e300 from a corrupt file are refused
/// where they are read.
pub const MAX_SPEED: f64 = 1.0e5;
/// The time steps recorded data may have, seconds: from 1 ms (1 kHz) to 10 s. A file with
/// `timeStepSize` 1e-9 or 1e9 is damaged or not traffic.
pub const RECORDED_DT: std::ops::RangeInclusive<f64> = 1.0e-3..=10.0;
/// The largest speed between two recorded positions of one agent, m/s (720 km/h): real
/// tracks stay far below it, and a damaged value (a y of 1330 m read as 7e-204) jumps far
/// above it. Rollouts are not held to it (see [`MAX_SPEED`]).
pub const MAX_RECORDED_SPEED: f64 = 200.0;
/// The speed limits a lane may have, m/s (above 0, at most 360 km/h): real limits stay far
/// inside it. A NaN, negative or 1e300 limit from a damaged file reached the LLM's prompt and
/// the speed checkers as it was (a NaN limit scored every car as within it).
pub const LANE_SPEED_LIMIT: std::ops::RangeInclusive<f64> = f64::MIN_POSITIVE..=100.0;
/// The largest agent length, metres (road trains reach about 55 m).
pub const MAX_LENGTH: f64 = 100.0;
/// The largest agent width, metres.
pub const MAX_WIDTH: f64 = 20.0;
/// The largest |heading|, radians: formats give headings in (−π, π] or unwrapped over a
/// recording; beyond this, sin and cos lose their digits.
pub const MAX_HEADING: f64 = 1.0e4;

/// Errors that make a scene inconsistent.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// A scenario id with a control or invisible character ([`crate::io::name`]).
    #[error("scenario id \"{id}\" contains {bad}: an id is shown on terminals, in file names and in the LLM's prompt")]
    ScenarioId {
        /// The id, its bad characters written as escapes.
        id: String,
        /// The first bad character.
        bad: crate::io::name::BadChar,
    },
    /// A scenario id too long to name the files written for it.
    #[error("scenario id \"{id}\" is {bytes} bytes long, more than the {max} an id may have: ids name output files (ID_K.json); give it a shorter one (`convert --id`)", max = crate::io::name::MAX_SCENARIO_ID_BYTES)]
    ScenarioIdTooLong {
        /// The start of the id.
        id: String,
        /// Its length in bytes.
        bytes: usize,
    },
    /// Two lanes share an id.
    #[error("lane id {0} appears twice")]
    DuplicateLane(LaneId),
    /// A lane's speed limit outside [`LANE_SPEED_LIMIT`] (or not a number).
    #[error("lane {lane}: speed limit {} m/s is implausible (more than 0, at most 100 m/s)", num(*.limit))]
    SpeedLimit {
        /// The lane.
        lane: LaneId,
        /// Its limit, m/s.
        limit: f64,
    },
    /// Two agents share an id.
    #[error("agent id {0} appears twice")]
    DuplicateAgent(AgentId),
    /// A lane id that is not in the map.
    #[error("no lane with id {0} in the map")]
    UnknownLane(LaneId),
    /// An agent id that is not in the scene.
    #[error("no agent with id {0} in the scene")]
    UnknownAgent(AgentId),
    /// Agents must all have one state per scene step.
    #[error("agent {agent} has {got} states, the scene has {expected} steps")]
    StepCount {
        /// The agent.
        agent: AgentId,
        /// Its number of states.
        got: usize,
        /// The scene's number of steps.
        expected: usize,
    },
    /// A valid state with a NaN or infinite value.
    #[error("agent {agent} step {step}: state is not finite")]
    NonFiniteState {
        /// The agent.
        agent: AgentId,
        /// The step.
        step: usize,
    },
    /// A footprint that is not positive and finite.
    #[error("agent {agent}: size {length} x {width} is not positive and finite")]
    BadSize {
        /// The agent.
        agent: AgentId,
        /// Its length.
        length: f64,
        /// Its width.
        width: f64,
    },
    /// The time step must be positive and finite.
    #[error("time step dt = {} must be positive and finite", num(*.0))]
    BadDt(f64),
    /// Recorded data's time step is outside [`RECORDED_DT`].
    #[error("time step dt = {} s is implausible for recorded traffic (0.001 to 10 s)", num(*.0))]
    RecordedDt(f64),
    /// The current step must be one of the scene's steps.
    #[error("current step {current} is outside the scene's {steps} steps")]
    CurrentStep {
        /// The current step.
        current: usize,
        /// Number of steps.
        steps: usize,
    },
    /// A value no real agent has (see [`MAX_SPEED`], [`MAX_LENGTH`], [`MAX_WIDTH`],
    /// [`MAX_HEADING`], [`crate::geom::MAX_COORD`]).
    #[error("agent {agent}{}: implausible {what}", step.map_or(String::new(), |s| format!(" step {s}")))]
    Implausible {
        /// The agent.
        agent: AgentId,
        /// The step, for a state.
        step: Option<usize>,
        /// What is wrong.
        what: String,
    },
    /// A crop that would keep nothing to evaluate: no agent or no future step.
    #[error("a crop keeps at least one agent and one future step (asked for {agents} agents and {future} future steps)")]
    EmptyCrop {
        /// The agents asked for.
        agents: usize,
        /// The future steps asked for.
        future: usize,
    },
    /// A current step with no step after it.
    #[error("current step {step} leaves no future (the scene has {steps} steps)")]
    NoFutureAfter {
        /// The current step asked for.
        step: usize,
        /// The scene's steps.
        steps: usize,
    },
    /// A current step at which no agent is observed: nothing to start from.
    #[error("no agent is observed at step {0}")]
    NoneObserved(usize),
    /// A recording without agents: they set its time grid (its steps and current step), so
    /// one without them has none, and nothing to simulate or score.
    #[error("no agents: a scene needs at least one (its agents' states set its steps)")]
    NoAgents,
    /// A crop asks for more steps than the scene has.
    #[error("the scene has {steps} steps, {needed} are needed")]
    TooShort {
        /// The scene's steps.
        steps: usize,
        /// The steps asked for: the current one and the future.
        needed: usize,
    },
    /// A crop needs a vehicle on a lane to centre on.
    #[error("no vehicle observed at step {step} is on a lane")]
    NoVehicleOnLane {
        /// The step looked at.
        step: usize,
    },
    /// Geometry that could not be built.
    #[error("{what}: {source}")]
    Geometry {
        /// What was being built.
        what: String,
        /// Why it failed.
        #[source]
        source: GeomError,
    },
}

/// Scene file formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SourceFormat {
    /// Waymo Open Motion Dataset `Scenario` protos in TFRecord files.
    Womd,
    /// CommonRoad XML (2018b or 2020a).
    CommonRoad,
    /// Argoverse 2 motion forecasting (scenario parquet + log map JSON).
    Av2,
    /// drivescript's hand-written YAML scenes.
    Yaml,
    /// GPUDrive / Nocturne scenario JSON (WOMD scenarios converted by those simulators).
    Gpudrive,
}

impl SourceFormat {
    /// Display name.
    pub fn name(self) -> &'static str {
        match self {
            SourceFormat::Womd => "womd",
            SourceFormat::CommonRoad => "commonroad",
            SourceFormat::Av2 => "av2",
            SourceFormat::Yaml => "yaml",
            SourceFormat::Gpudrive => "gpudrive",
        }
    }
}

/// Where a scene came from and its time grid.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SceneMeta {
    /// Source format.
    pub source_format: SourceFormat,
    /// Source file (or directory).
    pub source_file: String,
    /// Scenario id from the source, or the file stem.
    pub scenario_id: String,
    /// Seconds between steps.
    pub dt: f64,
    /// Index of the current step: steps up to it are history, after it future.
    pub current_step: usize,
    /// The focal or ego agent, when the format names one.
    pub ego: Option<AgentId>,
    /// Source records that were read but could not be represented (with why), so that nothing
    /// is dropped without a word.
    pub warnings: Vec<String>,
}

/// A map, the agents on it and metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    /// Source and time grid.
    pub meta: SceneMeta,
    /// The road map.
    pub map: Map,
    /// Agents, each with one state per step.
    pub agents: Vec<Agent>,
}

impl Scene {
    /// Assembles a scene and checks that it is consistent.
    pub fn new(meta: SceneMeta, map: Map, agents: Vec<Agent>) -> Result<Self, SceneError> {
        // Every reader builds its scene here, so every format's id is checked once.
        if let Err(bad) = crate::io::name::check_name(&meta.scenario_id) {
            return Err(SceneError::ScenarioId {
                id: crate::io::name::shown(&meta.scenario_id),
                bad,
            });
        }
        if meta.scenario_id.len() > crate::io::name::MAX_SCENARIO_ID_BYTES {
            return Err(SceneError::ScenarioIdTooLong {
                id: crate::io::name::shown(&meta.scenario_id),
                bytes: meta.scenario_id.len(),
            });
        }
        if !(meta.dt.is_finite() && meta.dt > 0.0) {
            return Err(SceneError::BadDt(meta.dt));
        }
        let steps = agents.first().map_or(0, |a| a.states.len());
        let mut ids = HashSet::new();
        for a in &agents {
            if !ids.insert(a.id) {
                return Err(SceneError::DuplicateAgent(a.id));
            }
            if a.states.len() != steps {
                return Err(SceneError::StepCount {
                    agent: a.id,
                    got: a.states.len(),
                    expected: steps,
                });
            }
            let size_ok =
                a.length.is_finite() && a.length > 0.0 && a.width.is_finite() && a.width > 0.0;
            // A track that is never observed has no size to speak of.
            if !size_ok && a.valid_count() > 0 {
                return Err(SceneError::BadSize {
                    agent: a.id,
                    length: a.length,
                    width: a.width,
                });
            }
            if size_ok && (a.length > MAX_LENGTH || a.width > MAX_WIDTH) {
                return Err(SceneError::Implausible {
                    agent: a.id,
                    step: None,
                    what: format!(
                        "size {} x {} m (at most {MAX_LENGTH} x {MAX_WIDTH} m)",
                        num(a.length),
                        num(a.width)
                    ),
                });
            }
            for (step, s) in a.states.iter().enumerate() {
                let finite = [s.x, s.y, s.heading, s.vx, s.vy]
                    .iter()
                    .all(|v| v.is_finite());
                if s.valid && !finite {
                    return Err(SceneError::NonFiniteState { agent: a.id, step });
                }
                if !s.valid {
                    continue;
                }
                let what = if s.x.abs() > MAX_COORD || s.y.abs() > MAX_COORD {
                    format!(
                        "position ({}, {}) is more than {MAX_COORD:e} m from the origin",
                        num(s.x),
                        num(s.y)
                    )
                } else if s.vx.hypot(s.vy) > MAX_SPEED {
                    // A speed is computed (from a rollout's positions, or a velocity's two
                    // components): `num` printed it to 17 digits (2.4999603999999996e7).
                    format!(
                        "speed {} m/s (at most {MAX_SPEED})",
                        crate::geom::approx(s.vx.hypot(s.vy))
                    )
                } else if s.heading.abs() > MAX_HEADING {
                    format!(
                        "heading {} rad (at most {MAX_HEADING} in magnitude)",
                        num(s.heading)
                    )
                } else {
                    continue;
                };
                return Err(SceneError::Implausible {
                    agent: a.id,
                    step: Some(step),
                    what,
                });
            }
        }
        if steps > 0 && meta.current_step >= steps {
            return Err(SceneError::CurrentStep {
                current: meta.current_step,
                steps,
            });
        }
        if let Some(ego) = meta.ego {
            if !ids.contains(&ego) {
                return Err(SceneError::UnknownAgent(ego));
            }
        }
        Ok(Self { meta, map, agents })
    }

    /// A scene read from a recording: [`Scene::new`]'s checks, a time step in
    /// [`RECORDED_DT`], and no agent moving faster than [`MAX_RECORDED_SPEED`] between two
    /// of its recorded positions. What a format cannot verify itself (a flipped byte in a
    /// Parquet page without checksums) shows up here as a jump.
    pub fn recorded(meta: SceneMeta, map: Map, agents: Vec<Agent>) -> Result<Self, SceneError> {
        if !RECORDED_DT.contains(&meta.dt) {
            return Err(SceneError::RecordedDt(meta.dt));
        }
        // Checked here, not in `new`: an empty scene serves to compile scripts against, but a
        // file without agents had its steps and current step dropped (`steps: 91` with
        // `agents: []` read as 0 steps), and `convert` wrote files its own readers refuse.
        if agents.is_empty() {
            return Err(SceneError::NoAgents);
        }
        let scene = Self::new(meta, map, agents)?;
        let dt = scene.meta.dt;
        for a in &scene.agents {
            let mut last: Option<(usize, &AgentState)> = None;
            for (t, s) in a.states.iter().enumerate().filter(|(_, s)| s.valid) {
                if let Some((t0, s0)) = last {
                    let d = (s.x - s0.x).hypot(s.y - s0.y);
                    let seconds = (t - t0) as f64 * dt;
                    if d > MAX_RECORDED_SPEED * seconds {
                        return Err(SceneError::Implausible {
                            agent: a.id,
                            step: Some(t),
                            what: format!(
                                "jump: {} m from step {t0} in {} s ({} m/s; recorded motion is at most {MAX_RECORDED_SPEED} m/s)",
                                crate::geom::approx(d),
                                crate::geom::approx(seconds),
                                crate::geom::approx(d / seconds)
                            ),
                        });
                    }
                }
                last = Some((t, s));
            }
        }
        Ok(scene)
    }

    /// Number of time steps.
    pub fn num_steps(&self) -> usize {
        self.agents.first().map_or(0, |a| a.states.len())
    }

    /// Number of future steps (after the current one).
    pub fn num_future_steps(&self) -> usize {
        self.num_steps().saturating_sub(self.meta.current_step + 1)
    }

    /// The scene with at most `future` steps after the current one (shorter recordings are
    /// kept as they are): what a model with that horizon is scored on.
    pub fn with_horizon(&self, future: usize) -> Scene {
        let n = (self.meta.current_step + 1 + future).min(self.num_steps());
        let mut s = self.clone();
        for a in &mut s.agents {
            a.states.truncate(n);
        }
        s
    }

    /// The scene with exactly `future` steps after the current one: a longer recording cut, a
    /// shorter one extended with unobserved steps. What a model with that horizon simulates,
    /// and what every method is scored over.
    pub fn over_horizon(&self, future: usize) -> Scene {
        let n = self.meta.current_step + 1 + future;
        let mut s = self.clone();
        for a in &mut s.agents {
            a.states.resize(n, AgentState::INVALID);
        }
        s
    }

    /// The path a script's `a.lane_path(ahead, turn)` gives for agent index `agent`: its
    /// lane at the current step (the nearest going its way), from `behind` metres before that
    /// lane's start to `ahead` metres ahead of the agent. `None` where the agent is not
    /// observed at the current step or near no lane going its way.
    pub fn agent_lane_path(
        &self,
        agent: usize,
        ahead: f64,
        behind: f64,
        turn: Turn,
    ) -> Option<LanePath> {
        let s = self.agents.get(agent)?.states[self.meta.current_step];
        if !s.valid {
            return None;
        }
        let p = crate::geom::Point::new(s.x, s.y);
        let lane = self.map.lane_at(p, s.heading)?;
        let along = self.map.lane(lane)?.centerline.nearest(&p).s;
        self.map.lane_path(lane, along + ahead, behind, turn).ok()
    }

    /// The scene with its current step moved to `step` (history before it, future after):
    /// one of several evaluation instances cut from a long recording. `step` must leave a
    /// step after it and have an agent observed.
    pub fn at_step(&self, step: usize) -> Result<Scene, SceneError> {
        let steps = self.num_steps();
        // `step + 1` overflows for the largest step a flag can hold.
        if step >= steps.saturating_sub(1) {
            return Err(SceneError::NoFutureAfter { step, steps });
        }
        if !self.agents.iter().any(|a| a.is_valid(step)) {
            return Err(SceneError::NoneObserved(step));
        }
        let mut s = self.clone();
        s.meta.current_step = step;
        Ok(s)
    }

    /// At most `n` agents observed at the current step, with exactly `future` steps after it:
    /// vehicles on a lane first, nearest first to the first such vehicle in the scene's order,
    /// then the other agents by the same distance. A recording too short after its current
    /// step has its current step moved earlier. Fewer agents where fewer are observed. The
    /// fixed-size scene that `drivescript bench cost` and the Python benchmark time.
    pub fn crop(&self, n: usize, future: usize) -> Result<Scene, SceneError> {
        // A crop of no agent (or no future) is a scene nothing can be evaluated on, whose
        // empty trajectory arrays the Python binding could not even shape.
        if n == 0 || future == 0 {
            return Err(SceneError::EmptyCrop { agents: n, future });
        }
        let total = self.num_steps();
        if total <= future {
            return Err(SceneError::TooShort {
                steps: total,
                // `future` is any usize a caller gives (Python's `crop(1, 2**64 - 1)`): +1
                // overflowed, a panic in a debug build and "0 are needed" in a release one.
                needed: future.saturating_add(1),
            });
        }
        let current = self.meta.current_step.min(total - future - 1);
        let at = |a: &Agent| a.states[current];
        let lane_vehicle = |a: &Agent| {
            a.agent_type == AgentType::Vehicle
                && self.map.lane_at(at(a).position(), at(a).heading).is_some()
        };
        let mut picked: Vec<(bool, f64, &Agent)> = Vec::new();
        let observed = self.agents.iter().filter(|a| at(a).valid);
        let first = observed
            .clone()
            .find(|a| lane_vehicle(a))
            .ok_or(SceneError::NoVehicleOnLane { step: current })?;
        let centre = at(first).position();
        for a in observed {
            picked.push((!lane_vehicle(a), (at(a).position() - centre).norm(), a));
        }
        picked.sort_by(|x, y| x.0.cmp(&y.0).then(x.1.total_cmp(&y.1)));
        let agents = picked
            .into_iter()
            .take(n)
            .map(|(_, _, a)| Agent {
                states: a.states[..current + future + 1].to_vec(),
                ..a.clone()
            })
            .collect();
        let meta = SceneMeta {
            current_step: current,
            ego: None,
            ..self.meta.clone()
        };
        Scene::new(meta, self.map.clone(), agents)
    }

    /// The scene with every vehicle removed (its states invalid) from the first future step at
    /// which its front bumper reaches a map exit ([`Map::at_exit`]), as recorded traffic
    /// leaves a recording where its map ends. Simulators and baselines keep driving there, onto
    /// unmapped ground that every metric would count as off the road.
    pub fn retire_exited(&self) -> Scene {
        let mut s = self.clone();
        if self.map.exits().is_empty() {
            return s;
        }
        let c = self.meta.current_step;
        for a in &mut s.agents {
            if a.agent_type != AgentType::Vehicle {
                continue;
            }
            let first = (c + 1..a.states.len()).find(|&t| {
                let st = &a.states[t];
                st.valid && self.map.bumper_at_exit(st.x, st.y, st.heading, a.length)
            });
            if let Some(t) = first {
                a.states[t..].fill(AgentState::INVALID);
            }
        }
        s
    }

    /// The scene with each agent's future states kept only at steps where the same agent
    /// (by id) is valid in `reference`: a simulation scored over the recorded agents'
    /// lifetimes. NGSIM tracks stop where the cameras' view ends, and so does the map; a car
    /// that leaves by a side street or a driveway drives on over ground the map does not have.
    /// Agents that `reference` lacks are kept as they are.
    pub fn with_lifetimes_of(&self, reference: &Scene) -> Scene {
        let mut s = self.clone();
        let c = self.meta.current_step;
        for a in &mut s.agents {
            let Some(r) = reference.agent(a.id) else {
                continue;
            };
            for t in c + 1..a.states.len() {
                if !r.is_valid(t) {
                    a.states[t] = AgentState::INVALID;
                }
            }
        }
        s
    }

    /// The agent with this id.
    pub fn agent(&self, id: AgentId) -> Option<&Agent> {
        self.agents.iter().find(|a| a.id == id)
    }

    /// A summary for `inspect`.
    pub fn summary(&self) -> SceneSummary {
        let mut agents_by_type = BTreeMap::new();
        for a in &self.agents {
            *agents_by_type.entry(a.agent_type.name()).or_insert(0) += 1;
        }
        let steps = self.num_steps();
        SceneSummary {
            format: self.meta.source_format.name(),
            file: self.meta.source_file.clone(),
            scenario_id: self.meta.scenario_id.clone(),
            dt: self.meta.dt,
            steps,
            current_step: self.meta.current_step,
            duration_s: steps.saturating_sub(1) as f64 * self.meta.dt,
            ego: self.meta.ego,
            agents: self.agents.len(),
            agents_by_type,
            lanes: self.map.lanes().len(),
            road_edges: self.map.road_edges().len(),
            road_lines: self.map.road_lines().len(),
            crosswalks: self.map.crosswalks().len(),
            stop_lines: self.map.stop_lines().len(),
            speed_bumps: self.map.speed_bumps().len(),
            drivable_areas: self.map.drivable_areas().len(),
            lane_graph: self.map.graph().edge_counts(),
            dangling_lane_refs: self.map.graph().dangling(),
            warnings: self.meta.warnings.clone(),
        }
    }
}

/// What `drivescript inspect` reports about a scene.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SceneSummary {
    /// Source format.
    pub format: &'static str,
    /// Source file.
    pub file: String,
    /// Scenario id.
    pub scenario_id: String,
    /// Seconds per step.
    pub dt: f64,
    /// Number of steps.
    pub steps: usize,
    /// Current step index.
    pub current_step: usize,
    /// Seconds from the first to the last step.
    pub duration_s: f64,
    /// Ego or focal agent.
    pub ego: Option<AgentId>,
    /// Number of agents.
    pub agents: usize,
    /// Agents per type.
    pub agents_by_type: BTreeMap<&'static str, usize>,
    /// Number of lanes.
    pub lanes: usize,
    /// Number of road edges.
    pub road_edges: usize,
    /// Number of painted lines.
    pub road_lines: usize,
    /// Number of crosswalks.
    pub crosswalks: usize,
    /// Number of stop lines and signs.
    pub stop_lines: usize,
    /// Number of speed bumps.
    pub speed_bumps: usize,
    /// Number of drivable-area polygons.
    pub drivable_areas: usize,
    /// Lane-graph edge counts.
    pub lane_graph: EdgeCounts,
    /// Lane references to lanes outside the map.
    pub dangling_lane_refs: usize,
    /// What the reader could not represent.
    pub warnings: Vec<String>,
}

impl std::fmt::Display for SceneSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let types: Vec<String> = self
            .agents_by_type
            .iter()
            .map(|(k, v)| format!("{v} {k}"))
            .collect();
        writeln!(f, "scene       {} ({})", self.scenario_id, self.format)?;
        // Found by a directory walk, the name is not one the user typed.
        writeln!(f, "file        {}", crate::io::name::one_line(&self.file))?;
        writeln!(
            f,
            "time        {} steps x {} s = {:.1} s, current step {}",
            self.steps, self.dt, self.duration_s, self.current_step
        )?;
        writeln!(
            f,
            "agents      {} ({}){}",
            self.agents,
            types.join(", "),
            self.ego.map(|e| format!(", ego {e}")).unwrap_or_default()
        )?;
        writeln!(
            f,
            "map         {} lanes, {} road edges, {} road lines, {} crosswalks, {} stop lines, {} speed bumps, {} drivable areas",
            self.lanes,
            self.road_edges,
            self.road_lines,
            self.crosswalks,
            self.stop_lines,
            self.speed_bumps,
            self.drivable_areas
        )?;
        write!(
            f,
            "lane graph  {} successor, {} predecessor, {} left, {} right edges; {} references to lanes outside the map",
            self.lane_graph.successor,
            self.lane_graph.predecessor,
            self.lane_graph.left,
            self.lane_graph.right,
            self.dangling_lane_refs
        )?;
        for w in &self.warnings {
            write!(f, "\nwarning     {w}")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use crate::io::yaml;
    use std::path::Path;

    #[test]
    fn a_summary_shows_a_file_name_with_a_line_break_or_escape_on_its_one_line() {
        // `inspect DIR` printed a file named `n\n\e[31mred.yaml` as it is: the terminal
        // turned red and the name broke the layout.
        let text = "scenario_id: weird\nsteps: 31\ncurrent_step: 10\n\
                    road: {lanes: 1, lane_width: 3.5, length: 300}\n\
                    agents:\n  - {id: 1, lane: 0, s: 100, speed: 10}\n";
        let s = yaml::parse(Path::new("dir/n\n\u{1b}[31mred\u{202E}.yaml"), text).unwrap();
        let shown = s.summary().to_string();
        assert!(
            shown.contains("file        dir/n\\u{000A}\\u{001B}[31mred\\u{202E}.yaml\n"),
            "{shown}"
        );
        assert!(
            !shown.contains('\u{1b}') && !shown.contains('\u{202E}'),
            "{shown}"
        );
    }

    #[test]
    fn a_crop_keeps_the_nearest_observed_agents_over_the_future_asked_for() {
        // Three cars on a two-lane road and a pedestrian beside it; car 4 is not yet observed
        // at the current step.
        let text = r#"
steps: 31
current_step: 10
road: {lanes: 2, lane_width: 3.5, length: 300}
agents:
  - {id: 1, lane: 0, s: 100, speed: 10}
  - {id: 2, lane: 1, s: 160, speed: 10}
  - {id: 3, lane: 0, s: 120, speed: 10}
  - {id: 5, type: pedestrian, lane: 1, s: 101, speed: 1}
  - {id: 4, lane: 1, s: 90, speed: 10, valid_from: 12}
"#;
        let s = yaml::parse(Path::new("crop.yaml"), text).unwrap();
        let c = s.crop(3, 15).unwrap();
        let ids: Vec<i64> = c.agents.iter().map(|a| a.id).collect();
        // Vehicles by distance from car 1, then the pedestrian (nearer, but not a vehicle).
        assert_eq!(ids, [1, 3, 2]);
        assert_eq!((c.meta.current_step, c.num_future_steps()), (10, 15));
        assert_eq!(c.agents[1].states[..], s.agents[2].states[..26]);
        let all = s.crop(10, 15).unwrap();
        assert_eq!(
            all.agents.iter().map(|a| a.id).collect::<Vec<_>>(),
            [1, 3, 2, 5]
        );
        // A future longer than the recording after the current step moves the current step.
        let late = s.crop(2, 25).unwrap();
        assert_eq!((late.meta.current_step, late.num_steps()), (5, 31));
        let e = s.crop(2, 31).unwrap_err();
        assert_eq!(e.to_string(), "the scene has 31 steps, 32 are needed");
        let e = s.crop(2, usize::MAX).unwrap_err();
        assert_eq!(
            e.to_string(),
            format!("the scene has 31 steps, {} are needed", usize::MAX)
        );
        // Nothing to keep is an error, not an empty scene.
        for (n, future) in [(0, 15), (3, 0)] {
            let e = s.crop(n, future).unwrap_err().to_string();
            assert!(e.contains("at least one agent and one future step"), "{e}");
        }
    }

    #[test]
    fn the_current_step_moves_only_where_a_future_and_an_agent_are() {
        let text = "steps: 31\ncurrent_step: 10\nroad: {lanes: 2, lane_width: 3.5, length: 300}\nagents:\n  - {id: 1, lane: 0, s: 100, speed: 10, valid_from: 5}\n";
        let s = yaml::parse(Path::new("m.yaml"), text).unwrap();
        assert_eq!(s.at_step(29).unwrap().meta.current_step, 29);
        for step in [30, 31, usize::MAX] {
            let e = s.at_step(step).unwrap_err().to_string();
            assert_eq!(
                e,
                format!("current step {step} leaves no future (the scene has 31 steps)")
            );
        }
        let e = s.at_step(2).unwrap_err().to_string();
        assert_eq!(e, "no agent is observed at step 2");
    }

    #[test]
    fn a_recording_without_agents_is_refused_not_read_as_zero_steps() {
        let text = "steps: 91\ncurrent_step: 10\nroad: {lanes: 2, lane_width: 3.5, length: 300}\nagents: []\n";
        let e = yaml::parse(Path::new("empty.yaml"), text)
            .unwrap_err()
            .to_string();
        assert!(e.contains("empty.yaml") && e.contains("no agents"), "{e}");
    }

    #[test]
    fn cars_leave_the_scene_where_the_map_ends() {
        // A 100 m road: car 1 reaches its end within the recording, car 2 never does.
        let text = r#"
steps: 41
current_step: 10
road: {lanes: 2, lane_width: 3.5, length: 100}
agents:
  - {id: 1, lane: 0, s: 40, speed: 20}
  - {id: 2, lane: 1, s: 10, speed: 10}
"#;
        let s = yaml::parse(Path::new("end.yaml"), text).unwrap();
        let r = s.retire_exited();
        let a = &s.agents[0];
        let front = |t: usize| a.states[t].x + 0.5 * a.length;
        let gone = (11..41)
            .find(|&t| front(t) > 99.5)
            .expect("car 1 reaches the end");
        for t in 0..41 {
            assert_eq!(r.agents[0].is_valid(t), t < gone, "car 1 at step {t}");
        }
        assert_eq!(r.agents[1].states, s.agents[1].states, "car 2 stays");
        assert_eq!(r.retire_exited().agents[0].states, r.agents[0].states);
        // What the sampler guides is what it outputs: trajectories retire the same steps.
        let mut t = crate::cost::Trajectories::recorded(&s);
        t.retire_exited(&s);
        assert_eq!(t.valid, crate::cost::Trajectories::recorded(&r).valid);
        // Scored over the recorded lifetimes, car 1 of any simulation leaves where it did.
        let mut sim = s.clone();
        sim.agents[0].states[40].x += 1.0;
        let life = sim.with_lifetimes_of(&r);
        for t in 0..41 {
            assert_eq!(life.agents[0].is_valid(t), t < gone, "car 1 at step {t}");
        }
        assert_eq!(life.agents[1].states, s.agents[1].states);
        // A horizon cuts a longer recording and extends a shorter one, unobserved.
        let short = s.over_horizon(5);
        assert_eq!(short.num_steps(), 16);
        assert_eq!(short.agents[1].states[..], s.agents[1].states[..16]);
        let long = s.over_horizon(40);
        assert_eq!(long.num_steps(), 51);
        assert!((41..51).all(|t| !long.agents[1].is_valid(t)));
        assert_eq!(long.agents[1].states[..41], s.agents[1].states[..]);
    }
}
