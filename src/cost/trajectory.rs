//! Candidate trajectories: what a cost script is evaluated on and differentiated against.

use crate::io::rollout::Rollout;
use crate::scene::{velocities_from_positions, AgentState, AgentType, Scene};

/// Numbering of the trajectory coordinates that gradients refer to: agent (in scene order),
/// future step, then x | y | heading.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VarLayout {
    /// Number of agents.
    pub agents: usize,
    /// Number of future steps.
    pub steps: usize,
}

/// Which coordinate of a state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coord {
    /// x position.
    X = 0,
    /// y position.
    Y = 1,
    /// heading.
    Heading = 2,
}

impl VarLayout {
    /// The layout of trajectories over `scene`: its agents by its future steps.
    pub fn of(scene: &Scene) -> Self {
        Self {
            agents: scene.agents.len(),
            steps: scene.num_future_steps(),
        }
    }

    /// Index of a coordinate.
    #[inline]
    pub fn var(&self, agent: usize, step: usize, c: Coord) -> u32 {
        (((agent * self.steps) + step) * 3 + c as usize) as u32
    }

    /// Total number of coordinates.
    pub fn len(&self) -> usize {
        self.agents * self.steps * 3
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// `(agent, step, coord)` of a coordinate index.
    pub fn decode(&self, var: u32) -> (usize, usize, Coord) {
        let v = var as usize;
        let c = match v % 3 {
            0 => Coord::X,
            1 => Coord::Y,
            _ => Coord::Heading,
        };
        let s = v / 3;
        (s / self.steps, s % self.steps, c)
    }
}

/// Future states `(x, y, heading)` of every agent of a scene, with validity.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectories {
    /// The coordinate layout.
    pub layout: VarLayout,
    /// States, indexed `agent * steps + step`.
    pub xyh: Vec<[f64; 3]>,
    /// Validity, same indexing.
    pub valid: Vec<bool>,
}

impl Trajectories {
    /// All-invalid trajectories for a scene.
    pub fn empty(scene: &Scene) -> Self {
        let layout = VarLayout::of(scene);
        Self {
            layout,
            xyh: vec![[0.0; 3]; layout.agents * layout.steps],
            valid: vec![false; layout.agents * layout.steps],
        }
    }

    /// The recorded future (invalid where an agent was not observed).
    pub fn recorded(scene: &Scene) -> Self {
        let mut t = Self::empty(scene);
        let c = scene.meta.current_step;
        for (a, agent) in scene.agents.iter().enumerate() {
            for k in 0..t.layout.steps {
                let s = agent.states[c + 1 + k];
                let i = a * t.layout.steps + k;
                t.xyh[i] = [s.x, s.y, s.heading];
                t.valid[i] = s.valid;
            }
        }
        t
    }

    /// The recorded future with gaps filled so that every agent is valid at every future step:
    /// after its last observation an agent continues at its last velocity, before its first
    /// it is held at its first. Used for dry runs, where every function must see a full series.
    pub fn filled(scene: &Scene) -> Self {
        let mut t = Self::recorded(scene);
        let c = scene.meta.current_step;
        let n = t.layout.steps;
        for (a, agent) in scene.agents.iter().enumerate() {
            // The latest observed state at or before each future step, with its velocity.
            let mut last = agent.states[..=c]
                .iter()
                .rposition(|s| s.valid)
                .map(|k| (k, agent.states[k]));
            for k in 0..n {
                let i = a * n + k;
                let step = c + 1 + k;
                if t.valid[i] {
                    last = Some((step, agent.states[step]));
                    continue;
                }
                let fill = match last {
                    Some((ls, s)) => {
                        let dtt = (step - ls) as f64 * scene.meta.dt;
                        [s.x + s.vx * dtt, s.y + s.vy * dtt, s.heading]
                    }
                    None => {
                        let first = agent.states.iter().find(|s| s.valid);
                        first.map_or([0.0; 3], |s| [s.x, s.y, s.heading])
                    }
                };
                t.xyh[i] = fill;
                t.valid[i] = true;
            }
        }
        t
    }

    /// The future part of a rollout of this scene (agents matched by id).
    pub fn from_rollout(scene: &Scene, r: &Rollout) -> Result<Self, String> {
        r.check_against(scene, std::path::Path::new("rollout"))
            .map_err(|e| e.to_string())?;
        let mut t = Self::empty(scene);
        let n = t.layout.steps;
        for (a, agent) in scene.agents.iter().enumerate() {
            let ra = r
                .agents
                .iter()
                .find(|x| x.id == agent.id)
                .ok_or_else(|| format!("the rollout has no agent {}", agent.id))?;
            // `cost` cuts the scene to a rollout's own horizon, but not to none: a rollout
            // that stops at the current step was told to have the recording's length, though
            // one step more passes.
            if ra.states.len() == scene.meta.current_step + 1 && scene.num_steps() > ra.states.len()
            {
                return Err(format!(
                    "agent {}: the rollout stops at the current step (step {}, {} states): it \
                     holds no future step for the script to judge",
                    agent.id,
                    scene.meta.current_step,
                    ra.states.len()
                ));
            }
            if ra.states.len() != scene.num_steps() {
                return Err(format!(
                    "agent {} has {} states in the rollout, the scene has {} steps",
                    agent.id,
                    ra.states.len(),
                    scene.num_steps()
                ));
            }
            for k in 0..n {
                let s = ra.states[scene.meta.current_step + 1 + k];
                t.xyh[a * n + k] = [s.0, s.1, s.2];
                t.valid[a * n + k] = s.3;
            }
        }
        Ok(t)
    }

    /// Trajectories from a flat row-major array `[agent][step][x, y, heading]` in `layout`
    /// (what [`Trajectories::to_array`] writes, and what the Python package passes): a state
    /// of three NaN is unobserved; one with only some coordinates NaN, or any infinite, is an
    /// error naming the agent (index in scene order), step and coordinate.
    pub fn from_array(layout: VarLayout, values: &[f64]) -> Result<Self, String> {
        if values.len() != layout.len() {
            return Err(format!(
                "{} values given, {} agents x {} steps x 3 wanted",
                values.len(),
                layout.agents,
                layout.steps
            ));
        }
        let n = layout.agents * layout.steps;
        // Every call from Python passes through here; a complete array (what optimisers
        // pass) is checked and copied in one pass each.
        // (A fold, not `all`: without the early exit it runs on vector registers.)
        // Positions beyond any map are refused as the scene readers refuse them: 1e300 is
        // finite, but its squares are not, and a checker's road-edge distance panicked on it.
        let (far, turned) = (crate::geom::MAX_COORD, crate::scene::MAX_HEADING);
        if values.chunks_exact(3).fold(true, |ok, v| {
            ok & (v[0].abs() <= far) & (v[1].abs() <= far) & (v[2].abs() <= turned)
        }) {
            let mut xyh = vec![[0.0; 3]; n];
            xyh.as_flattened_mut().copy_from_slice(values);
            return Ok(Self {
                layout,
                xyh,
                valid: vec![true; n],
            });
        }
        let mut t = Self {
            layout,
            xyh: Vec::with_capacity(n),
            valid: Vec::with_capacity(n),
        };
        for (i, v) in values.chunks_exact(3).enumerate() {
            let s = [v[0], v[1], v[2]];
            match s.iter().position(|x| !x.is_finite()) {
                None => {
                    let limits = [far, far, turned];
                    if let Some(c) = (0..3).find(|&c| s[c].abs() > limits[c]) {
                        return Err(format!(
                            "agent index {}, step {}: {} is {}, beyond {} {} ({})",
                            i / layout.steps,
                            i % layout.steps,
                            ["x", "y", "heading"][c],
                            crate::geom::num(s[c]),
                            crate::geom::num(limits[c]),
                            ["m", "m", "rad"][c],
                            "positions lie within 1e7 m of the origin and headings within \
                             1e4 rad, as in every scene"
                        ));
                    }
                    t.xyh.push(s);
                    t.valid.push(true);
                }
                Some(_) if s.iter().all(|x| x.is_nan()) => {
                    t.xyh.push([0.0; 3]);
                    t.valid.push(false);
                }
                Some(c) => {
                    return Err(format!(
                        "agent index {}, step {}: {} is {} ({})",
                        i / layout.steps,
                        i % layout.steps,
                        ["x", "y", "heading"][c],
                        v[c],
                        "a state is three finite numbers, or three NaN where unobserved"
                    ))
                }
            }
        }
        Ok(t)
    }

    /// The states as a flat row-major array `[agent][step][x, y, heading]`, NaN where
    /// unobserved.
    pub fn to_array(&self) -> Vec<f64> {
        self.xyh
            .iter()
            .zip(&self.valid)
            .flat_map(|(s, &v)| if v { *s } else { [f64::NAN; 3] })
            .collect()
    }

    /// `scene` over these trajectories' horizon ([`Scene::over_horizon`]) with its future
    /// replaced by them: unobserved where they are invalid, velocities from the positions as
    /// the sampler sets them. What a checker judges a trajectory from elsewhere on.
    pub fn applied_to(&self, scene: &Scene) -> Result<Scene, String> {
        if scene.agents.len() != self.layout.agents {
            return Err(format!(
                "{} agents given, the scene has {}",
                self.layout.agents,
                scene.agents.len()
            ));
        }
        let mut out = scene.over_horizon(self.layout.steps);
        let c = out.meta.current_step;
        for (a, agent) in out.agents.iter_mut().enumerate() {
            for k in 0..self.layout.steps {
                let ([x, y, heading], valid) = self.state(a, k);
                agent.states[c + 1 + k] = if valid {
                    AgentState {
                        x,
                        y,
                        heading,
                        vx: 0.0,
                        vy: 0.0,
                        valid,
                    }
                } else {
                    AgentState::INVALID
                };
            }
            velocities_from_positions(&mut agent.states, c + 1, out.meta.dt);
        }
        Ok(out)
    }

    /// Marks every vehicle invalid from the first step at which it reaches a map exit, as
    /// [`Scene::retire_exited`] does to a simulated scene: a sampler guides what it will
    /// output, not a car driving on beyond the end of the map.
    pub fn retire_exited(&mut self, scene: &Scene) {
        if scene.map.exits().is_empty() {
            return;
        }
        let n = self.layout.steps;
        for (a, agent) in scene.agents.iter().enumerate() {
            if agent.agent_type != AgentType::Vehicle {
                continue;
            }
            let at = |k: usize| {
                let [x, y, h] = self.xyh[a * n + k];
                self.valid[a * n + k] && scene.map.bumper_at_exit(x, y, h, agent.length)
            };
            if let Some(k) = (0..n).find(|&k| at(k)) {
                self.valid[a * n + k..(a + 1) * n].fill(false);
            }
        }
    }

    /// State of `agent` at future step `k`.
    #[inline]
    pub fn state(&self, agent: usize, k: usize) -> ([f64; 3], bool) {
        let i = agent * self.layout.steps + k;
        (self.xyh[i], self.valid[i])
    }

    /// These trajectories with their steps from `done` on replaced by the first steps of
    /// `rest`: a closed loop's executed part (`self`, steps before `done`) followed by the
    /// round's sample, so that a script compiled at the original current step judges the
    /// whole original horizon. `rest` must have as many agents; its steps past the original
    /// horizon are not used.
    pub fn spliced(&self, done: usize, rest: &Trajectories) -> Self {
        let (n, m) = (self.layout.steps, rest.layout.steps);
        debug_assert_eq!(self.layout.agents, rest.layout.agents);
        let mut out = self.clone();
        for a in 0..self.layout.agents {
            for j in done.min(n)..n.min(done + m) {
                out.xyh[a * n + j] = rest.xyh[a * m + j - done];
                out.valid[a * n + j] = rest.valid[a * m + j - done];
            }
        }
        out
    }

    /// Adds `step * gradient` to the coordinates (for tests and simple descent).
    pub fn apply(&mut self, gradient: &[f64], step: f64) {
        for (i, g) in gradient.iter().enumerate() {
            self.xyh[i / 3][i % 3] += step * g;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene() -> Scene {
        crate::cost::gradient_tests::sample(crate::cost::gradient_tests::US101).over_horizon(40)
    }

    #[test]
    fn an_array_round_trips_with_nan_where_unobserved() {
        let s = scene();
        let t = Trajectories::recorded(&s);
        assert!(t.valid.iter().any(|v| !v), "the scene has unobserved steps");
        let a = t.to_array();
        assert_eq!(a.len(), t.layout.len());
        let back = Trajectories::from_array(t.layout, &a).unwrap();
        assert_eq!(back.valid, t.valid);
        for (i, (p, q)) in back.xyh.iter().zip(&t.xyh).enumerate() {
            if t.valid[i] {
                assert_eq!(p, q);
            } else {
                assert!(a[3 * i..3 * i + 3].iter().all(|x| x.is_nan()));
            }
        }
        // A complete array (read on the fast path) as well.
        let full = Trajectories::filled(&s);
        assert!(full.valid.iter().all(|&v| v));
        assert_eq!(
            Trajectories::from_array(full.layout, &full.to_array()),
            Ok(full)
        );
    }

    #[test]
    fn a_half_observed_or_infinite_state_is_named() {
        let s = scene();
        let t = Trajectories::recorded(&s);
        let mut a = t.to_array();
        let i = t.valid.iter().position(|&v| v).unwrap();
        a[3 * i + 1] = f64::NAN;
        let e = Trajectories::from_array(t.layout, &a).unwrap_err();
        let (agent, step) = (i / t.layout.steps, i % t.layout.steps);
        assert!(
            e.starts_with(&format!("agent index {agent}, step {step}: y is NaN")),
            "{e}"
        );
        a[3 * i + 1] = 0.0;
        a[3 * i + 2] = f64::INFINITY;
        let e = Trajectories::from_array(t.layout, &a).unwrap_err();
        assert!(e.contains("heading is inf"), "{e}");
        let e = Trajectories::from_array(t.layout, &a[3..]).unwrap_err();
        assert!(e.contains("x 40 steps x 3 wanted"), "{e}");
        // Finite, but beyond any map: a checker's road-edge distance panicked on 1e300.
        a[3 * i + 2] = 0.0;
        a[3 * i] = 1e300;
        let e = Trajectories::from_array(t.layout, &a).unwrap_err();
        assert!(
            e.starts_with(&format!(
                "agent index {agent}, step {step}: x is 1e300, beyond 1e7 m"
            )),
            "{e}"
        );
        a[3 * i] = 0.0;
        a[3 * i + 2] = -2e4;
        let e = Trajectories::from_array(t.layout, &a).unwrap_err();
        assert!(e.contains("heading is -20000, beyond 10000 rad"), "{e}");
        a[3 * i + 2] = 0.0;
        Trajectories::from_array(t.layout, &a).unwrap();
    }

    #[test]
    fn applied_trajectories_become_the_scene_s_future_with_their_velocities() {
        let s = scene();
        let mut t = Trajectories::recorded(&s);
        let a = t.valid.iter().position(|&v| v).unwrap() / t.layout.steps;
        let n = t.layout.steps;
        for k in 0..n {
            t.xyh[a * n + k] = [2.0 * k as f64, 1.0, 0.0];
            t.valid[a * n + k] = true;
        }
        let out = t.applied_to(&s).unwrap();
        assert_eq!(out.num_future_steps(), n);
        let c = out.meta.current_step;
        let st = out.agents[a].states[c + 5];
        assert_eq!((st.x, st.y), (8.0, 1.0));
        assert!((st.vx - 2.0 / s.meta.dt).abs() < 1e-9, "{}", st.vx);
        let back = Trajectories::recorded(&out);
        assert_eq!(back.valid, t.valid);
        assert_eq!(back.xyh[a * n..(a + 1) * n], t.xyh[a * n..(a + 1) * n]);
        assert!(t.applied_to(&s.over_horizon(40)).is_ok());
        let mut fewer = s.clone();
        fewer.agents.pop();
        assert!(t.applied_to(&fewer).unwrap_err().contains("agents given"));
    }
}
