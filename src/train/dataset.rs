//! Training windows cut from scenes: up to `max_agents` agents (the centre agent first, then
//! the nearest agents observed at the current step), up to `max_lanes` lane polylines (the
//! nearest, resampled to `lane_points` points), everything in the centre agent's current frame,
//! with masks for missing states and padding.

use serde::{Deserialize, Serialize};

use crate::geom::{wrap_angle, FrenetPath, Point, Polyline};
use crate::scene::routes::{route_line, route_lines, route_residual};
use crate::scene::{AgentType, Scene};

/// Window sizes and how windows are cut.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WindowConfig {
    /// History steps including the current one.
    pub history: usize,
    /// Future steps.
    pub future: usize,
    /// Agents per window (padded).
    pub max_agents: usize,
    /// Lanes per window (padded).
    pub max_lanes: usize,
    /// Points per lane polyline.
    pub lane_points: usize,
    /// Steps between consecutive windows of a scene.
    pub stride: usize,
    /// Centre agents per window position (vehicles observed over the whole window).
    pub centres_per_step: usize,
    /// Pad every batch to `max_lanes` lanes instead of to its largest map (fixed tensor
    /// shapes, as benchmarks at the paper's sizes need).
    #[serde(default)]
    pub pad_lanes: bool,
    /// Future steps a centre agent must be observed for (from the current step on) for a
    /// window to be cut; the rest of its future, and of every other agent's, is masked out of
    /// the loss. 0 (configurations written before the field) means the whole future, so
    /// recordings shorter than the window trained nothing.
    #[serde(default)]
    pub min_future: usize,
    /// Besides the pose of each lane's first point, give every agent-lane pair the pose of the
    /// lane's point nearest to the agent ([`crate::train::batch::build`]): the agent's offset
    /// from a lane it is half-way along, which the first point's pose tells only through the
    /// lane's pooled shape. Off in configurations written before the field.
    #[serde(default)]
    pub nearest_lane_pose: bool,
    /// Future times at which the denoiser measures each agent's noisy future against the
    /// lanes ([`crate::model::route`]): 0 (configurations written before the field) for none.
    #[serde(default)]
    pub route_times: usize,
    /// Give the denoiser each agent's recorded end point as an input where it is known
    /// ([`crate::train::batch::Goals`]): conditional simulation then samples from a model of
    /// the futures that end there, not from one of every future with a pull to the end.
    /// Off in configurations written before the field.
    #[serde(default)]
    pub goals: bool,
    /// Tell each agent's future against its route of the lane graph
    /// ([`crate::scene::routes`]): the distance along it beyond constant speed, the offset
    /// across it and the heading beyond its own, so that a future is on its lane by
    /// construction. Off (the line of the agent's heading) in configurations written before
    /// the field.
    #[serde(default)]
    pub route_frame: bool,
}

/// `Ok` when `lo ≤ v ≤ hi`, else a message naming the setting and its range.
pub(crate) fn within(name: &str, v: usize, lo: usize, hi: usize) -> Result<(), String> {
    if (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(format!("{name} = {v}: must be {lo} to {hi}"))
    }
}

impl WindowConfig {
    /// Checks the sizes before any window is cut: history 1–100, future 1–1000, stride at
    /// least 1, 1–1024 agents, 1–2048 lanes of 2–1000 points, at least one centre per step.
    /// The message names the field.
    pub fn validate(&self) -> Result<(), String> {
        within("history", self.history, 1, 100)?;
        within("future", self.future, 1, 1000)?;
        within("stride", self.stride, 1, 100_000)?;
        within("max_agents", self.max_agents, 1, 1024)?;
        within("max_lanes", self.max_lanes, 1, 2048)?;
        within("lane_points", self.lane_points, 2, 1000)?;
        within("centres_per_step", self.centres_per_step, 1, 1024)?;
        within("min_future", self.min_future, 0, self.future)?;
        within("route_times", self.route_times, 0, self.future)?;
        if self.route_frame && self.route_times > 0 {
            return Err(
                "route_frame with route_times: the route features measure a future told \
                 along the agent's heading, not along its route"
                    .into(),
            );
        }
        Ok(())
    }

    /// Future steps a centre must be observed for ([`WindowConfig::min_future`], 0 meaning all).
    pub fn centre_future(&self) -> usize {
        if self.min_future == 0 {
            self.future
        } else {
            self.min_future
        }
    }

    /// The NGSIM setting: 1.1 s of history (11 steps, current included) and 4 s of future
    /// (40 steps) at 10 Hz. Half of the 108 NGSIM scenes are 8 s or longer but only a quarter
    /// reach 9 s, so WOMD's 8 s future would drop most of the corpus; 51 steps keep 89 of the
    /// 108 scenes, and a stride of 10 steps cuts several windows from the long ones. 24 agents
    /// (the median scene has 37) and 64 lanes (the median map has 12, the largest 116).
    pub fn ngsim() -> Self {
        Self {
            history: 11,
            future: 40,
            max_agents: 24,
            max_lanes: 64,
            lane_points: 20,
            stride: 10,
            centres_per_step: 2,
            pad_lanes: false,
            min_future: 0,
            nearest_lane_pose: false,
            route_times: 0,
            goals: false,
            route_frame: false,
        }
    }

    /// Highways and cities at the paper's horizon: 1.1 s of history and 8 s of future (80
    /// steps) at 10 Hz, 24 agents and 64 lanes as for NGSIM. A window needs its centre
    /// observed for 2 s of future: the urban scenes of 3.5 s and the NGSIM recordings shorter
    /// than 9.1 s still train, with what they do not record masked out of the loss.
    pub fn cities() -> Self {
        Self {
            future: 80,
            min_future: 20,
            ..Self::ngsim()
        }
    }

    /// The paper's WOMD setting: 11 history + 80 future steps, 24 agents, 200 lanes.
    pub fn womd() -> Self {
        Self {
            history: 11,
            future: 80,
            max_agents: 24,
            max_lanes: 200,
            lane_points: 20,
            stride: 91,
            centres_per_step: 1,
            pad_lanes: false,
            min_future: 0,
            nearest_lane_pose: false,
            route_times: 0,
            goals: false,
            route_frame: false,
        }
    }

    /// Features of an agent-lane pair: the lane's first point's pose in the agent's frame, and
    /// with [`WindowConfig::nearest_lane_pose`] its nearest point's.
    pub fn agent_lane_features(&self) -> usize {
        if self.nearest_lane_pose {
            8
        } else {
            4
        }
    }

    /// Steps per window.
    pub fn steps(&self) -> usize {
        self.history + self.future
    }
}

/// One training example.
#[derive(Debug, Clone, PartialEq)]
pub struct Window {
    /// Scenario id of the source scene.
    pub scene_id: String,
    /// Scene step of the window's current step.
    pub current: usize,
    /// The centre agent's world pose `(x, y, heading)` at the current step.
    pub origin: [f64; 3],
    /// Scene agent indices, centre agent first (length ≤ `max_agents`).
    pub agents: Vec<usize>,
    /// `[agent][step] -> (x, y, heading)` in the centre frame, `max_agents × steps`.
    pub states: Vec<[f32; 3]>,
    /// Validity per `[agent][step]` (false for padding and unobserved states).
    pub valid: Vec<bool>,
    /// `[lane][point] -> (x, y)` in the centre frame, `max_lanes × lane_points`.
    pub lanes: Vec<[f32; 2]>,
    /// Lane ids (length ≤ `max_lanes`); lanes beyond are padding.
    pub lane_ids: Vec<i64>,
    /// `[lane i][lane j]` connectivity, `max_lanes × max_lanes`: 0 none, 1 j precedes i,
    /// 2 j succeeds i, 3 j is i's left neighbour, 4 its right neighbour.
    pub lane_conn: Vec<u8>,
    /// What each agent slot is ([`agent_attributes`]), `max_agents` rows (zeros for padding).
    pub attrs: Vec<[f32; AGENT_ATTRS]>,
    /// With [`WindowConfig::route_frame`], each agent slot's route ([`route_line`]) in the
    /// centre frame (empty for slots not observed at the current step); otherwise empty.
    pub routes: Vec<Vec<[f32; 2]>>,
}

/// Features that say what a road user is: vehicle, cyclist, pedestrian (one-hot; other types
/// all zero), static, and its length and width (so that a bus is not a car).
pub const AGENT_ATTRS: usize = 6;

/// Seconds between the steps of every window, and so of every model trained on them: the
/// settings' history and future are counted in steps of 10 Hz recordings, and a checkpoint
/// records no step of its own.
pub const WINDOW_DT: f64 = 0.1;

/// Why `scene` can be neither cut into windows nor sampled by a model: its steps are not
/// [`WINDOW_DT`] apart. A scene of 0.5-s (or 0.04-s) steps was taught, and sampled, as if each
/// step were 0.1 s: futures five times too slow (or 2.5 times too fast), with exit 0. The
/// message names the scene's file and id.
pub fn step_mismatch(scene: &Scene) -> Option<String> {
    let dt = scene.meta.dt;
    // Within 1 %: recorded timestamps jitter (a WOMD scene's step is their median).
    ((dt / WINDOW_DT - 1.0).abs() > 0.01).then(|| {
        format!(
            "{}: scene {}: its steps are {} s apart, but the model's are {WINDOW_DT} s (10 Hz): \
             its motion would be read as if each of its steps took {WINDOW_DT} s; resample the \
             scene to 10 Hz",
            crate::io::name::one_line(&scene.meta.source_file),
            crate::io::name::shown_counted(&scene.meta.scenario_id),
            crate::geom::num(dt)
        )
    })
}

/// [`AGENT_ATTRS`] features of `a`: the model's input that tells a truck from a car from a
/// cyclist, and a parked car from one that drives.
pub fn agent_attributes(a: &crate::scene::Agent) -> [f32; AGENT_ATTRS] {
    let one = |t: AgentType| if a.agent_type == t { 1.0 } else { 0.0 };
    [
        one(AgentType::Vehicle),
        one(AgentType::Cyclist),
        one(AgentType::Pedestrian),
        if a.is_static { 1.0 } else { 0.0 },
        (a.length / 5.0) as f32,
        (a.width / 2.0) as f32,
    ]
}

/// Whether a model learns (and samples) how agents like `a` move: any road user that is not a
/// static obstacle and not of an unknown type.
pub fn is_mover(a: &crate::scene::Agent) -> bool {
    !a.is_static && a.agent_type != AgentType::Other
}

/// Pose of `p` (world) in the frame at `origin`.
pub fn to_frame(origin: [f64; 3], p: Point, heading: f64) -> [f64; 3] {
    let (s, c) = origin[2].sin_cos();
    let d = p - Point::new(origin[0], origin[1]);
    [
        c * d.x + s * d.y,
        -s * d.x + c * d.y,
        wrap_angle(heading - origin[2]),
    ]
}

/// The world point at `(x, y)` of the frame at `origin`: the inverse of [`to_frame`]'s
/// position.
pub fn from_frame(origin: [f64; 3], x: f64, y: f64) -> Point {
    let (s, c) = origin[2].sin_cos();
    Point::new(origin[0] + c * x - s * y, origin[1] + s * x + c * y)
}

/// Cuts the windows of one scene.
pub fn windows(scene: &Scene, cfg: &WindowConfig) -> Vec<Window> {
    let n = scene.num_steps();
    let mut out = Vec::new();
    let need = cfg.centre_future();
    if n < cfg.history + need || scene.agents.is_empty() {
        return out;
    }
    let mut c = cfg.history - 1;
    while c + need < n {
        let span = c + 1 - cfg.history..=c + need;
        let full: Vec<usize> = (0..scene.agents.len())
            .filter(|&i| {
                let a = &scene.agents[i];
                is_mover(a) && span.clone().all(|t| a.is_valid(t))
            })
            .collect();
        let k = cfg.centres_per_step.min(full.len());
        for j in 0..k {
            // Evenly spaced over the candidates, so that windows do not all centre on one car.
            let centre = full[j * full.len() / k];
            out.push(window(scene, cfg, c, centre));
        }
        c += cfg.stride.max(1);
    }
    out
}

/// The window at scene step `c` centred on agent index `centre` (which must be observed at
/// `c`). Steps outside the scene (before its start or after its end) are unobserved, so this
/// also serves inference, where the future is what the model generates.
pub fn window_at(scene: &Scene, cfg: &WindowConfig, c: usize, centre: usize) -> Window {
    window(scene, cfg, c, centre)
}

fn window(scene: &Scene, cfg: &WindowConfig, c: usize, centre: usize) -> Window {
    window_among(scene, cfg, c, centre, &|_| true, RouteHint::Recorded)
}

/// What chooses the route each agent's future is told against ([`WindowConfig::route_frame`];
/// [`route_line`] picks among the lane paths open to it).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RouteHint {
    /// The route its recorded future strays from least: training, where the future is the
    /// target.
    Recorded,
    /// The route nearest its last recorded point within the window's future: conditional
    /// simulation, which is given where each agent ends.
    EndPoint,
    /// Straight on from the nearest lane going its way: nothing of its future is known.
    Unknown,
}

/// [`window_at`] holding only the agents for which `keep` is true (and `centre`).
pub fn window_among(
    scene: &Scene,
    cfg: &WindowConfig,
    c: usize,
    centre: usize,
    keep: &dyn Fn(usize) -> bool,
    hint: RouteHint,
) -> Window {
    let s0 = scene.agents[centre].states[c];
    let origin = [s0.x, s0.y, s0.heading];
    let here = s0.position();
    let mut others: Vec<(f64, usize)> = (0..scene.agents.len())
        .filter(|&i| i != centre && scene.agents[i].is_valid(c) && keep(i))
        .map(|i| ((scene.agents[i].states[c].position() - here).norm(), i))
        .collect();
    others.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let mut agents = vec![centre];
    agents.extend(others.iter().take(cfg.max_agents - 1).map(|x| x.1));
    let steps = cfg.steps();
    let mut states = vec![[0f32; 3]; cfg.max_agents * steps];
    let mut valid = vec![false; cfg.max_agents * steps];
    let mut attrs = vec![[0f32; AGENT_ATTRS]; cfg.max_agents];
    for (k, &i) in agents.iter().enumerate() {
        attrs[k] = agent_attributes(&scene.agents[i]);
        for j in 0..steps {
            let Some(s) = (c + 1 + j)
                .checked_sub(cfg.history)
                .and_then(|t| scene.agents[i].states.get(t))
            else {
                continue;
            };
            if s.valid {
                let f = to_frame(origin, s.position(), s.heading);
                states[k * steps + j] = [f[0] as f32, f[1] as f32, f[2] as f32];
                valid[k * steps + j] = true;
            }
        }
    }
    let mut near: Vec<(f64, usize)> = scene
        .map
        .lanes()
        .iter()
        .enumerate()
        .map(|(i, l)| (l.centerline.distance_to(&here), i))
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let mut lanes = vec![[0f32; 2]; cfg.max_lanes * cfg.lane_points];
    let mut lane_ids = Vec::new();
    for (k, &(_, i)) in near.iter().take(cfg.max_lanes).enumerate() {
        let lane = &scene.map.lanes()[i];
        lane_ids.push(lane.id);
        let line = lane.centerline.resample_count(cfg.lane_points);
        for (j, p) in line.points().iter().enumerate() {
            let f = to_frame(origin, *p, 0.0);
            lanes[k * cfg.lane_points + j] = [f[0] as f32, f[1] as f32];
        }
    }
    let routes = if cfg.route_frame {
        agents
            .iter()
            .map(|&i| agent_route(scene, cfg, c, i, origin, hint))
            .collect()
    } else {
        Vec::new()
    };
    let m = cfg.max_lanes;
    let mut lane_conn = vec![0u8; m * m];
    let g = scene.map.graph();
    for (i, &a) in lane_ids.iter().enumerate() {
        for (j, &b) in lane_ids.iter().enumerate() {
            lane_conn[i * m + j] = if g.predecessors(a).contains(&b) {
                1
            } else if g.successors(a).contains(&b) {
                2
            } else if g.left_neighbors(a).contains(&b) {
                3
            } else if g.right_neighbors(a).contains(&b) {
                4
            } else {
                0
            };
        }
    }
    Window {
        scene_id: scene.meta.scenario_id.clone(),
        current: c,
        origin,
        agents,
        states,
        valid,
        lanes,
        lane_ids,
        lane_conn,
        attrs,
        routes,
    }
}

/// Agent `i`'s route at scene step `c` ([`route_line`], chosen as `hint` says, reaching
/// [`route_reach`]) in the frame at `origin`; empty unless it is observed at `c`.
fn agent_route(
    scene: &Scene,
    cfg: &WindowConfig,
    c: usize,
    i: usize,
    origin: [f64; 3],
    hint: RouteHint,
) -> Vec<[f32; 2]> {
    let a = &scene.agents[i];
    let Some(now) = a.states.get(c).filter(|s| s.valid) else {
        return Vec::new();
    };
    let mut observed: Vec<Point> = match hint {
        RouteHint::Unknown => Vec::new(),
        RouteHint::Recorded | RouteHint::EndPoint => (c + 1..=c + cfg.future)
            .filter_map(|t| a.states.get(t).filter(|s| s.valid))
            .map(|s| s.position())
            .collect(),
    };
    if hint == RouteHint::EndPoint && observed.len() > 1 {
        observed.drain(..observed.len() - 1);
    }
    let reach = route_reach(scene, cfg, now.speed());
    route_line(&scene.map, now.position(), now.heading, &observed, reach)
        .iter()
        .map(|p| line_point(origin, *p))
        .collect()
}

/// Metres a route reaches ahead of an agent at `speed` ([`agent_route`]): as far as it could go
/// in the window's future at one and a half times its speed (at least 8 m/s), and 20 m more.
fn route_reach(scene: &Scene, cfg: &WindowConfig, speed: f64) -> f64 {
    let horizon = cfg.future as f64 * scene.meta.dt;
    20.0 + (1.5 * speed).max(8.0) * horizon
}

/// A world point of a route as [`Window::routes`] stores it, in the frame at `origin`.
pub fn line_point(origin: [f64; 3], p: Point) -> [f32; 2] {
    let f = to_frame(origin, p, 0.0);
    [f[0] as f32, f[1] as f32]
}

/// Every route open to agent `i` at scene step `c`, in the world, cut as [`window_among`]
/// cuts the one it chooses ([`crate::scene::routes::route_lines`]); none unless it is
/// observed at `c`.
pub fn agent_route_lines(scene: &Scene, cfg: &WindowConfig, c: usize, i: usize) -> Vec<Vec<Point>> {
    let Some(now) = scene.agents[i].states.get(c).filter(|s| s.valid) else {
        return Vec::new();
    };
    let reach = route_reach(scene, cfg, now.speed());
    route_lines(&scene.map, now.position(), now.heading, reach)
}

/// Subtracts the constant-velocity anchor (`advance` metres per step along +x of the agent's
/// frame) from a flattened `future × 3` trajectory.
pub fn remove_anchor(v: &mut [f64], advance: f64) {
    for (j, p) in v.chunks_mut(3).enumerate() {
        p[0] -= advance * (j + 1) as f64;
    }
}

/// Adds the anchor back: the inverse of [`remove_anchor`].
pub fn add_anchor(v: &mut [f64], advance: f64) {
    remove_anchor(v, -advance);
}

impl Window {
    /// Whether slot `k` holds a road user the model learns to move ([`is_mover`]).
    pub fn is_mover_slot(&self, k: usize) -> bool {
        self.attrs
            .get(k)
            .is_some_and(|a| a[3] == 0.0 && a[..3].iter().any(|v| *v > 0.0))
    }

    /// The complete futures of this window's moving agents, as residuals
    /// ([`residual_futures`]).
    pub fn residual_futures(&self, cfg: &WindowConfig) -> Vec<Vec<f64>> {
        (0..self.agents.len())
            .filter(|&k| self.is_mover_slot(k))
            .filter_map(|k| self.agent_residual(cfg, k))
            .collect()
    }

    /// The window rotated by `angle` about the centre agent (augmentation: the model should not
    /// learn a preferred direction).
    pub fn rotated(&self, angle: f64) -> Window {
        let (s, c) = (angle.sin() as f32, angle.cos() as f32);
        let mut w = self.clone();
        for st in &mut w.states {
            let (x, y) = (st[0], st[1]);
            *st = [
                c * x - s * y,
                s * x + c * y,
                wrap_angle(st[2] as f64 + angle) as f32,
            ];
        }
        for p in w.lanes.iter_mut().chain(w.routes.iter_mut().flatten()) {
            let (x, y) = (p[0], p[1]);
            *p = [c * x - s * y, s * x + c * y];
        }
        w
    }

    /// Metres agent slot `k` moved per step along its current heading, averaged over its last
    /// (up to 4) consecutively observed history steps; 0 without any. The constant-velocity
    /// anchor of [`Window::agent_residual`].
    pub fn advance(&self, cfg: &WindowConfig, k: usize) -> f64 {
        let steps = cfg.steps();
        let c = k * steps + cfg.history - 1;
        if !self.valid[c] {
            return 0.0;
        }
        let mut m = 0;
        while m < 4 && m + 1 < cfg.history && self.valid[c - m - 1] {
            m += 1;
        }
        if m == 0 {
            return 0.0;
        }
        let (cur, past) = (self.states[c], self.states[c - m]);
        let (s, co) = (cur[2] as f64).sin_cos();
        ((cur[0] - past[0]) as f64 * co + (cur[1] - past[1]) as f64 * s) / m as f64
    }

    /// [`Window::agent_future`] minus the constant-velocity anchor (`advance` metres per step
    /// straight ahead): what the model generates. Most of a future is its speed; against the
    /// anchor the network only has to model how the agent deviates from holding it, and an
    /// untrained or uncertain model falls back to constant velocity instead of standing still.
    ///
    /// With [`WindowConfig::route_frame`], the future told against the agent's route instead
    /// ([`route_residual`]): the anchor is the same speed held along the route.
    pub fn agent_residual(&self, cfg: &WindowConfig, k: usize) -> Option<Vec<f64>> {
        let (v, seen) = self.agent_residual_seen(cfg, k)?;
        seen.iter().all(|s| *s).then_some(v)
    }

    /// Future `(x, y, heading)` of agent slot `k` in its own current frame, flattened
    /// (`future × 3`), or `None` unless the agent is valid at the current step and every future
    /// step: the vectors PCA is fitted on.
    pub fn agent_future(&self, cfg: &WindowConfig, k: usize) -> Option<Vec<f64>> {
        let (v, seen) = self.agent_future_seen(cfg, k)?;
        seen.iter().all(|s| *s).then_some(v)
    }

    /// [`Window::agent_future`] of an agent whose future is partly unobserved: the future
    /// (zeros where unobserved) and which steps are observed, or `None` unless the agent is
    /// valid at the current step.
    pub fn agent_future_seen(&self, cfg: &WindowConfig, k: usize) -> Option<(Vec<f64>, Vec<bool>)> {
        let steps = cfg.steps();
        let cur = self.states[k * steps + cfg.history - 1];
        if !self.valid[k * steps + cfg.history - 1] {
            return None;
        }
        let origin = [cur[0] as f64, cur[1] as f64, cur[2] as f64];
        let mut v = Vec::with_capacity(cfg.future * 3);
        let mut seen = Vec::with_capacity(cfg.future);
        let mut prev = 0.0;
        for j in 0..cfg.future {
            let i = k * steps + cfg.history + j;
            if !self.valid[i] {
                v.extend_from_slice(&[0.0; 3]);
                seen.push(false);
                continue;
            }
            let s = self.states[i];
            let f = to_frame(origin, Point::new(s[0] as f64, s[1] as f64), s[2] as f64);
            // Unwrapped heading: continuous through ±π.
            let h = prev + wrap_angle(f[2] - prev);
            prev = h;
            v.extend_from_slice(&[f[0], f[1], h]);
            seen.push(true);
        }
        Some((v, seen))
    }

    /// [`Window::agent_future_seen`] minus the constant-velocity anchor (see
    /// [`Window::agent_residual`]); unobserved steps stay zero.
    pub fn agent_residual_seen(
        &self,
        cfg: &WindowConfig,
        k: usize,
    ) -> Option<(Vec<f64>, Vec<bool>)> {
        if cfg.route_frame {
            return self.route_residual_seen(cfg, k);
        }
        let (mut v, seen) = self.agent_future_seen(cfg, k)?;
        remove_anchor(&mut v, self.advance(cfg, k));
        for (p, s) in v.chunks_mut(3).zip(&seen) {
            if !s {
                p.fill(0.0);
            }
        }
        Some((v, seen))
    }

    /// Slot `k`'s route ([`Window::routes`]) as a path in the centre frame; `None` where it
    /// has none.
    pub fn route_path(&self, k: usize) -> Option<FrenetPath> {
        let line = self.routes.get(k)?;
        let points = line.iter().map(|p| Point::new(p[0] as f64, p[1] as f64));
        // Windows come from `window_among` or a store that checked its routes.
        Some(FrenetPath::new(Polyline::new(points).ok()?))
    }

    /// [`Window::agent_residual_seen`] told against the agent's route (`routes[k]`): `None`
    /// where the slot has no route or is not observed at the current step.
    fn route_residual_seen(&self, cfg: &WindowConfig, k: usize) -> Option<(Vec<f64>, Vec<bool>)> {
        let steps = cfg.steps();
        let c = k * steps + cfg.history - 1;
        if !self.valid[c] {
            return None;
        }
        let path = self.route_path(k)?;
        let pose = |i: usize| {
            let s = self.states[i];
            [s[0] as f64, s[1] as f64, s[2] as f64]
        };
        let future: Vec<Option<[f64; 3]>> = (1..=cfg.future)
            .map(|j| self.valid[c + j].then(|| pose(c + j)))
            .collect();
        let r = route_residual(&path, pose(c), &future, self.advance(cfg, k));
        let seen = r.iter().map(Option::is_some).collect();
        Some((
            r.into_iter().flat_map(|v| v.unwrap_or([0.0; 3])).collect(),
            seen,
        ))
    }
}

/// Every complete future of a moving agent ([`Window::is_mover_slot`]) of `windows` as a
/// residual to its constant-velocity anchor ([`Window::agent_residual`]): what the PCA basis
/// is fitted on.
pub fn residual_futures(windows: &[Window], cfg: &WindowConfig) -> Vec<Vec<f64>> {
    windows
        .iter()
        .flat_map(|w| w.residual_futures(cfg))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{load_scene, LoadOptions};
    use std::path::Path;

    fn highway() -> Scene {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway_cut_in.yaml");
        load_scene(&p, 0, &LoadOptions::default()).unwrap()
    }

    #[test]
    fn windows_are_in_the_centre_frame() {
        let s = highway();
        let cfg = WindowConfig {
            stride: 20,
            ..WindowConfig::ngsim()
        };
        let w = windows(&s, &cfg);
        // 81 steps: current steps 10, 30 (50 needs 90 steps); two centres each.
        assert_eq!(w.len(), 4);
        let first = &w[0];
        assert_eq!(first.current, 10);
        let steps = cfg.steps();
        // The centre agent sits at the origin facing +x at the current step.
        let cur = first.states[cfg.history - 1];
        assert!(cur[0].abs() < 1e-4 && cur[1].abs() < 1e-4 && cur[2].abs() < 1e-5);
        assert_eq!(first.agents.len(), 4);
        assert!(first.valid[..steps].iter().all(|v| *v));
        assert!(!first.valid[4 * steps], "slot 4 is padding");
        assert_eq!(first.lane_ids.len(), 6);
        // Rotation keeps distances and turns headings.
        let r = first.rotated(0.7);
        let d = |w: &Window, k: usize| (w.states[k][0].hypot(w.states[k][1])) as f64;
        assert!((d(first, steps + 12) - d(&r, steps + 12)).abs() < 1e-3);
        assert!((r.states[cfg.history - 1][2] - 0.7).abs() < 1e-5);
    }

    #[test]
    fn residuals_remove_the_constant_velocity_anchor() {
        // highway.yaml: agents following their lanes at constant speed, so their futures are
        // almost exactly the anchor.
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        let s = load_scene(&p, 0, &LoadOptions::default()).unwrap();
        let cfg = WindowConfig::ngsim();
        let w = &windows(&s, &cfg)[0];
        for k in 0..w.agents.len() {
            let f = w.agent_future(&cfg, k).unwrap();
            let r = w.agent_residual(&cfg, k).unwrap();
            let adv = w.advance(&cfg, k);
            assert!(adv > 0.5, "agent {k} advances {adv} m per step");
            let far = f.chunks(3).map(|p| p[0].abs()).fold(0.0, f64::max);
            let left = r.chunks(3).map(|p| p[0].abs()).fold(0.0, f64::max);
            assert!(
                far > 20.0 && left < 0.05 * far,
                "{far} m ahead, {left} m off the anchor"
            );
            let mut back = r.clone();
            add_anchor(&mut back, adv);
            for (a, b) in back.iter().zip(&f) {
                assert!((a - b).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn agent_futures_are_in_their_own_frame() {
        let s = highway();
        let cfg = WindowConfig::ngsim();
        let w = &windows(&s, &cfg)[0];
        for k in 0..w.agents.len() {
            let v = w.agent_future(&cfg, k).unwrap();
            assert_eq!(v.len(), 120);
            // Everyone drives forwards along +x of their own frame at 18-26 m/s.
            assert!(v[0] > 1.5 && v[0] < 3.0, "{}", v[0]);
        }
        assert!(w.agent_future(&cfg, 10).is_none(), "padding has no future");
    }

    #[test]
    fn a_turning_future_told_against_its_route_stays_on_it_whichever_way_the_window_faces() {
        // Vehicle 1 turns left at the crossroads: 14.6 m north of its lane's line after 4 s.
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/crossroads_left.yaml");
        let s = load_scene(&p, 0, &LoadOptions::default()).unwrap();
        let cfg = WindowConfig {
            route_frame: true,
            ..WindowConfig::ngsim()
        };
        let w = window_at(&s, &cfg, 10, 0);
        assert_eq!(w.routes.len(), 2);
        let plain = WindowConfig::ngsim();
        let heading_frame = w.agent_residual(&plain, 0).unwrap();
        let across = |v: &[f64]| v.chunks(3).map(|p| p[1].abs()).fold(0.0, f64::max);
        assert!(across(&heading_frame) > 14.0, "{}", across(&heading_frame));
        let route_frame = w.agent_residual(&cfg, 0).unwrap();
        assert!(across(&route_frame) < 0.05, "{}", across(&route_frame));
        // At constant speed along the route, only the corner's cut lengthens the path a little.
        let along = route_frame
            .chunks(3)
            .map(|p| p[0].abs())
            .fold(0.0, f64::max);
        assert!(along < 0.5, "{along}");
        // Rotating the window (training's augmentation) leaves the residual as it was.
        let turned = w.rotated(1.1).agent_residual(&cfg, 0).unwrap();
        for (a, b) in route_frame.iter().zip(&turned) {
            assert!((a - b).abs() < 1e-3, "{a} {b}");
        }
        // And the residual goes back to the window's own future.
        let line: Vec<Point> = w.routes[0]
            .iter()
            .map(|p| Point::new(p[0] as f64, p[1] as f64))
            .collect();
        let path = FrenetPath::new(Polyline::new(line).unwrap());
        let steps = cfg.steps();
        let cur = w.states[cfg.history - 1];
        let current = [cur[0] as f64, cur[1] as f64, cur[2] as f64];
        let res: Vec<[f64; 3]> = route_frame.chunks(3).map(|p| [p[0], p[1], p[2]]).collect();
        let back =
            crate::scene::routes::from_route_residual(&path, current, &res, w.advance(&cfg, 0));
        for (j, b) in back.iter().enumerate() {
            let st = w.states[cfg.history + j];
            assert!((b[0] - st[0] as f64).abs() < 1e-3 && (b[1] - st[1] as f64).abs() < 1e-3);
        }
        let _ = steps;
        // The standing vehicle 2 has a route too; a window without routes has none.
        assert!(w.routes[1].len() >= 2);
        assert!(window_at(&s, &plain, 10, 0).routes.is_empty());
    }
}
