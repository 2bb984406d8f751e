//! Baselines every model is compared with: log replay, constant velocity, and constant speed
//! along the current lane. Each returns a simulated copy of the scene: history kept, the future
//! of every agent observed at the current step replaced (others left unobserved).

use crate::geom::Point;
use crate::scene::{AgentState, Scene, Turn};

/// Which baseline.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Baseline {
    /// The recorded future.
    Log,
    /// Constant velocity from the current state, heading held.
    ConstantVelocity,
    /// Constant speed along the current lane path at the current lateral offset.
    Lane,
}

impl Baseline {
    /// Display name, as in tables.
    pub fn name(self) -> &'static str {
        match self {
            Baseline::Log => "log replay",
            Baseline::ConstantVelocity => "constant velocity",
            Baseline::Lane => "constant speed along lane",
        }
    }

    /// The simulated scene; cars leave it where they reach a map exit
    /// ([`Scene::retire_exited`]).
    pub fn simulate(self, scene: &Scene) -> Scene {
        match self {
            Baseline::Log => scene.clone(),
            Baseline::ConstantVelocity => constant_velocity(scene),
            Baseline::Lane => lane_following(scene),
        }
        .retire_exited()
    }
}

fn with_future(scene: &Scene, mut f: impl FnMut(usize, &AgentState, f64) -> AgentState) -> Scene {
    let c = scene.meta.current_step;
    let dt = scene.meta.dt;
    let mut out = scene.clone();
    for (i, a) in out.agents.iter_mut().enumerate() {
        let cur = scene.agents[i].states[c];
        for t in c + 1..a.states.len() {
            a.states[t] = if cur.valid {
                f(i, &cur, (t - c) as f64 * dt)
            } else {
                AgentState::INVALID
            };
        }
    }
    out
}

/// Every agent keeps its current velocity and heading.
pub fn constant_velocity(scene: &Scene) -> Scene {
    with_future(scene, |_, s, tau| AgentState {
        x: s.x + s.vx * tau,
        y: s.y + s.vy * tau,
        ..*s
    })
}

/// Every agent keeps its current speed along its current lane (straight on at forks) at its
/// current lateral offset, facing along the lane; agents on no lane keep their velocity.
pub fn lane_following(scene: &Scene) -> Scene {
    let c = scene.meta.current_step;
    let plans: Vec<Option<(crate::scene::LanePath, f64, f64)>> = scene
        .agents
        .iter()
        .map(|a| {
            let s = a.states[c];
            if !s.valid {
                return None;
            }
            let p = Point::new(s.x, s.y);
            let lane = scene.map.lane_at(p, s.heading)?;
            let along = scene.map.lane(lane)?.centerline.nearest(&p).s;
            let path = scene
                .map
                .lane_path(lane, along + 400.0, 50.0, Turn::Straight)
                .ok()?;
            let f = path.frenet.project(p);
            Some((path, f.s, f.d))
        })
        .collect();
    with_future(scene, |i, s, tau| match &plans[i] {
        Some((path, s0, d0)) => {
            let sp = s.speed();
            let st = s0 + sp * tau;
            let q = path.frenet.to_cartesian(st, *d0);
            let h = path.frenet.heading_at(st);
            AgentState {
                x: q.x,
                y: q.y,
                heading: h,
                vx: sp * h.cos(),
                vy: sp * h.sin(),
                valid: true,
            }
        }
        None => AgentState {
            x: s.x + s.vx * tau,
            y: s.y + s.vy * tau,
            ..*s
        },
    })
}
