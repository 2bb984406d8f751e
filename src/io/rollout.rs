//! Rollout JSON: the trajectories of every agent of a scene, recorded or simulated.
//!
//! ```json
//! { "format": "drivescript-rollout", "version": 1, "scene_id": "USA_US101-3_3_T-1",
//!   "dt": 0.1, "current_step": 10,
//!   "agents": [ { "id": 7, "type": "vehicle", "length": 4.6, "width": 1.9,
//!                 "states": [[x, y, heading, valid], ...] } ],
//!   "costs": { "ends_in_lane": 0.0 },
//!   "allowed": [ { "agent": 7, "motion": "reverse" } ] }
//! ```
//! Every agent has one state per step; invalid states are written as zeros with `false`.
//! `costs` (optional) holds per-term cost values. `allowed` (optional) is the motion the cost
//! scripts that guided the rollout allowed (`allow(a, "reverse")`): what the request asked of
//! those agents, which judging the rollout (`eval`) does not hold against them, as `ask` and
//! `simulate` did not. A file without it (one written before it existed, or by another
//! simulator) allowed nothing.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::IoError;
use crate::scene::{velocities_from_positions, Agent, AgentState, AgentType, Scene, SceneMeta};

/// The `format` tag of rollout files.
pub const FORMAT_TAG: &str = "drivescript-rollout";
/// The schema version written.
pub const VERSION: u32 = 1;

/// One state: `[x, y, heading, valid]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RolloutState(pub f64, pub f64, pub f64, pub bool);

/// The most steps a rollout may hold after the current step (`eval --horizon`'s bound).
pub const MAX_ROLLOUT_FUTURE: usize = 10_000;

/// Motion a script can allow an agent that realism and the plausibility checks would
/// otherwise hold against it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AllowedMotion {
    /// Backing up (`allow(a, "reverse")`).
    Reverse,
}

/// Motion the scripts that guided a rollout allowed one agent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Allowance {
    /// The agent's id.
    pub agent: i64,
    /// What it may do.
    pub motion: AllowedMotion,
}

/// One agent's trajectory.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RolloutAgent {
    /// Agent id.
    pub id: i64,
    /// Agent type.
    #[serde(rename = "type")]
    pub agent_type: AgentType,
    /// Footprint length.
    pub length: f64,
    /// Footprint width.
    pub width: f64,
    /// One state per step.
    pub states: Vec<RolloutState>,
}

/// Trajectories of all agents of a scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rollout {
    /// Always [`FORMAT_TAG`].
    pub format: String,
    /// Schema version.
    pub version: u32,
    /// Scenario id of the scene it belongs to.
    pub scene_id: String,
    /// Seconds per step.
    pub dt: f64,
    /// Index of the current step.
    pub current_step: usize,
    /// The agents.
    pub agents: Vec<RolloutAgent>,
    /// Per-term cost values, when a cost script was evaluated.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub costs: BTreeMap<String, f64>,
    /// What made it (`simulate`'s run record: command, version, checkpoint, task, seed,
    /// scripts, params), when a run wrote it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub run: Option<serde_json::Value>,
    /// The motion the scripts that guided it allowed ([`Allowance`]); empty when nothing was
    /// allowed, or the file predates the field.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub allowed: Vec<Allowance>,
}

impl Rollout {
    /// The recorded trajectories of a scene.
    pub fn from_scene(scene: &Scene) -> Self {
        Self {
            format: FORMAT_TAG.into(),
            version: VERSION,
            scene_id: scene.meta.scenario_id.clone(),
            dt: scene.meta.dt,
            current_step: scene.meta.current_step,
            agents: scene
                .agents
                .iter()
                .map(|a| RolloutAgent {
                    id: a.id,
                    agent_type: a.agent_type,
                    length: a.length,
                    width: a.width,
                    states: a
                        .states
                        .iter()
                        .map(|s| {
                            if s.valid {
                                RolloutState(s.x, s.y, s.heading, true)
                            } else {
                                RolloutState(0.0, 0.0, 0.0, false)
                            }
                        })
                        .collect(),
                })
                .collect(),
            costs: BTreeMap::new(),
            run: None,
            allowed: Vec::new(),
        }
    }

    /// Checks the schema's rules; `what` names the source in messages.
    fn validate(&self, what: &Path) -> Result<(), IoError> {
        let bad = |loc: String, msg: String| IoError::invalid(what, loc, msg);
        if self.format != FORMAT_TAG {
            return Err(bad(
                "format".into(),
                format!("expected {FORMAT_TAG:?}, found {:?}", self.format),
            ));
        }
        if self.version != VERSION {
            return Err(bad(
                "version".into(),
                format!(
                    "unsupported version {} (this build reads {VERSION})",
                    self.version
                ),
            ));
        }
        if !(self.dt.is_finite() && self.dt > 0.0) {
            return Err(bad(
                "dt".into(),
                format!("{} must be positive", crate::geom::num(self.dt)),
            ));
        }
        let steps = self.agents.first().map_or(0, |a| a.states.len());
        for (i, a) in self.agents.iter().enumerate() {
            let loc = format!("agents[{i}] (id {})", a.id);
            if a.states.len() != steps {
                return Err(bad(
                    loc,
                    format!("{} states, agents[0] has {steps}", a.states.len()),
                ));
            }
            if let Some(k) = a
                .states
                .iter()
                .position(|s| s.3 && !(s.0.is_finite() && s.1.is_finite() && s.2.is_finite()))
            {
                return Err(bad(loc, format!("state {k} is valid but not finite")));
            }
        }
        if steps > 0 && self.current_step >= steps {
            return Err(bad(
                "current_step".into(),
                format!("{} is outside the {steps} steps", self.current_step),
            ));
        }
        Ok(())
    }

    /// Checks that this is a rollout of `scene`, as every consumer (`eval`, `cost`, `render`,
    /// script tests) needs it: the same scenario id, dt and current step; exactly the scene's
    /// agents, with the scene's types and sizes; a history equal to the scene's; at least the
    /// current step and at most [`MAX_ROLLOUT_FUTURE`] steps after it. `what` names the file.
    pub fn check_against(&self, scene: &Scene, what: &Path) -> Result<(), IoError> {
        let bad = |loc: String, msg: String| IoError::invalid(what, loc, msg);
        let m = &scene.meta;
        if self.scene_id != m.scenario_id {
            return Err(bad(
                "scene_id".into(),
                format!(
                    "the rollout is of scene \"{}\", not of \"{}\"",
                    super::name::shown(&self.scene_id),
                    super::name::shown(&m.scenario_id)
                ),
            ));
        }
        if (self.dt - m.dt).abs() > 1e-9 * m.dt {
            return Err(bad(
                "dt".into(),
                format!(
                    "{} s, the scene's is {} s",
                    crate::geom::num(self.dt),
                    crate::geom::num(m.dt)
                ),
            ));
        }
        if self.current_step != m.current_step {
            return Err(bad(
                "current_step".into(),
                format!("{}, the scene's is {}", self.current_step, m.current_step),
            ));
        }
        let steps = self.agents.first().map_or(0, |a| a.states.len());
        if steps > m.current_step + 1 + MAX_ROLLOUT_FUTURE {
            return Err(bad(
                "agents".into(),
                format!(
                    "{steps} steps: at most {MAX_ROLLOUT_FUTURE} after the current step {}",
                    m.current_step
                ),
            ));
        }
        for (i, ra) in self.agents.iter().enumerate() {
            let loc = || format!("agents[{i}] (id {})", ra.id);
            if self.agents[..i].iter().any(|o| o.id == ra.id) {
                return Err(bad(loc(), "a second agent with this id".into()));
            }
            let Some(a) = scene.agent(ra.id) else {
                return Err(bad(loc(), "the scene has no agent with this id".into()));
            };
            if ra.agent_type != a.agent_type {
                return Err(bad(
                    loc(),
                    // The files' words (`Pedestrian` was Rust's).
                    format!(
                        "type {} in the rollout, {} in the scene",
                        ra.agent_type.name(),
                        a.agent_type.name()
                    ),
                ));
            }
            if (ra.length - a.length).abs() > 1e-6 || (ra.width - a.width).abs() > 1e-6 {
                return Err(bad(
                    loc(),
                    format!(
                        "{} x {} m in the rollout, {} x {} m in the scene",
                        crate::geom::num(ra.length),
                        crate::geom::num(ra.width),
                        crate::geom::num(a.length),
                        crate::geom::num(a.width)
                    ),
                ));
            }
            for k in 0..=m.current_step.min(a.states.len() - 1) {
                let (r, s) = (ra.states[k], a.states[k]);
                let same = r.3 == s.valid
                    && (!s.valid
                        || ((r.0 - s.x).abs() <= 1e-6
                            && (r.1 - s.y).abs() <= 1e-6
                            && crate::geom::wrap_angle(r.2 - s.heading).abs() <= 1e-6));
                if !same {
                    return Err(bad(
                        loc(),
                        format!(
                            "step {k} of the history differs from the scene's (a rollout keeps \
                             the recorded history up to the current step)"
                        ),
                    ));
                }
            }
        }
        if let Some(a) = scene
            .agents
            .iter()
            .find(|a| !self.agents.iter().any(|r| r.id == a.id))
        {
            return Err(bad(
                "agents".into(),
                format!("the rollout has no agent {} (the scene's)", a.id),
            ));
        }
        // An allowance for an agent the scene lacks would exempt nobody, silently.
        if let Some((i, x)) = self
            .allowed
            .iter()
            .enumerate()
            .find(|(_, x)| scene.agent(x.agent).is_none())
        {
            return Err(bad(
                format!("allowed[{i}]"),
                format!("the scene has no agent {}", x.agent),
            ));
        }
        Ok(())
    }

    /// Reads and checks a rollout file.
    pub fn read(path: &Path) -> Result<Self, IoError> {
        let text = super::read_text(path)?;
        // Named by the path to the value (`agents[0].states[20][0]`), and a NaN that Python's
        // json.dump wrote said to be one: "expected value" at a column alone said neither.
        let r: Rollout = serde_json::from_str(&text).map_err(|e| {
            // A scene given where a rollout goes (`--rollout scene.yaml`) was "line 1, column
            // 1: expected value", which named neither what the file is nor what was wanted.
            let head = &text.as_bytes()[..text.len().min(16)];
            match super::classify(head) {
                super::Content::Json => super::gpudrive::json_error(path, &text, &e),
                other => IoError::invalid(
                    path,
                    "file",
                    format!(
                        "not a rollout: its content is {}, and a rollout is the JSON that \
                         `simulate` or `convert SCENE -o FILE.json` writes",
                        other.describe()
                    ),
                ),
            }
        })?;
        r.validate(path)?;
        Ok(r)
    }

    /// Writes the rollout atomically (fails on non-finite valid states, which JSON cannot hold).
    pub fn write(&self, path: &Path) -> Result<(), IoError> {
        self.validate(path)?;
        let text = serde_json::to_string(self).expect("rollouts serialise");
        super::write_atomic(path, text.as_bytes())
    }

    /// The scene's map and metadata with this rollout's agents, velocities from the positions
    /// as the sampler sets them ([`velocities_from_positions`]).
    pub fn apply_to(&self, scene: &Scene, what: &Path) -> Result<Scene, IoError> {
        self.validate(what)?;
        self.check_against(scene, what)?;
        let agents = self
            .agents
            .iter()
            .map(|a| {
                let mut states: Vec<AgentState> = a
                    .states
                    .iter()
                    .map(|s| {
                        if s.3 {
                            AgentState {
                                x: s.0,
                                y: s.1,
                                heading: s.2,
                                vx: 0.0,
                                vy: 0.0,
                                valid: true,
                            }
                        } else {
                            AgentState::INVALID
                        }
                    })
                    .collect();
                velocities_from_positions(&mut states, 0, self.dt);
                Agent {
                    id: a.id,
                    agent_type: a.agent_type,
                    length: a.length,
                    width: a.width,
                    states,
                    is_static: false,
                }
            })
            .collect();
        let meta = SceneMeta {
            dt: self.dt,
            current_step: self.current_step,
            ..scene.meta.clone()
        };
        Scene::new(meta, scene.map.clone(), agents).map_err(|e| IoError::Scene {
            path: what.display().to_string(),
            location: "rollout".into(),
            error: e,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn read_back_a_rollout_moves_as_the_sampler_set_it_even_beside_gaps() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        let scene = crate::io::load_scene(&path, 0, &crate::io::LoadOptions::default()).unwrap();
        let mut r = Rollout::from_scene(&scene);
        // Agent 0 leaves the view for one step at 15: the steps beside the gap keep the
        // one-sided difference of their positions, not zero.
        r.agents[0].states[15].3 = false;
        let read = r.apply_to(&scene, Path::new("r.json")).unwrap();
        let mut want = scene.agents[0].states.clone();
        want[15] = AgentState::INVALID;
        velocities_from_positions(&mut want, 0, scene.meta.dt);
        let got = &read.agents[0].states;
        for t in [0, 14, 16, want.len() - 1] {
            assert!(
                (got[t].vx - want[t].vx).abs() < 1e-9 && (got[t].vy - want[t].vy).abs() < 1e-9,
                "step {t}: {:?} vs {:?}",
                got[t],
                want[t]
            );
        }
        let (p, q) = (&scene.agents[0].states[13], &scene.agents[0].states[14]);
        assert!((got[14].vx - (q.x - p.x) / scene.meta.dt).abs() < 1e-9);
        assert!(got[14].vx.abs() > 1.0, "a car driving at 20 m/s");
    }

    #[test]
    fn a_nan_in_a_rollout_file_is_named_by_where_it_is_and_what_it_is() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        let scene = crate::io::load_scene(&path, 0, &crate::io::LoadOptions::default()).unwrap();
        let r = Rollout::from_scene(&scene);
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("r.json");
        r.write(&f).unwrap();
        let text = std::fs::read_to_string(&f).unwrap();
        // Python's json.dump writes NaN for a value that is not a number: the second agent's
        // third state's x becomes one.
        let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
        v["agents"][1]["states"][2][0] = serde_json::json!(123456.75);
        let bad = serde_json::to_string(&v)
            .unwrap()
            .replace("123456.75", "NaN");
        std::fs::write(&f, bad).unwrap();
        let e = Rollout::read(&f).unwrap_err().to_string();
        assert!(
            e.contains("agents[1].states[2][0]") && e.contains("NaN and Infinity are not JSON"),
            "{e}"
        );
    }
}
