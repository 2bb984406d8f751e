//! The sampling plan: which windows cover a scene (tiling), which slot of which window owns
//! each agent and which slots hold its copies (kept equal to the owner's: consensus), the
//! agents the conditional task holds standing, and the decoding of coefficients into world
//! trajectories with headings aligned to the path.

use crate::cost::Trajectories;
use crate::geom::{wrap_angle, FrenetPath, Point, Polyline};
use crate::scene::routes::route_residual;
use crate::scene::{AgentId, AgentType, KinematicLimits, Scene};
use crate::train::dataset::{add_anchor, agent_route_lines, from_frame, line_point, remove_anchor};
use crate::train::{window_among, RouteHint, Trained, Window};

use super::config::Clamp;

pub(super) struct Plan<'a> {
    pub(super) trained: &'a Trained,
    /// Windows covering every agent observed at the current step (see [`tile`]).
    pub(super) windows: Vec<Window>,
    /// Modelled agents, each once, in the first window that holds it.
    pub(super) slots: Vec<Slot>,
    /// Per modelled agent (as in `slots`), every `(window, slot)` that holds it: its own slot
    /// first, then the windows where it is context (see [`Plan::consensus`]).
    pub(super) copies: Vec<Vec<(usize, usize)>>,
    /// Trajectories before the model fills them in: agents not observed at the current step
    /// (they appear later in the recording) have no future, rather than their recorded one,
    /// which the simulator must not know.
    pub(super) base: Trajectories,
    /// Agents of types the model does not move ([`super::Sample::fixed`]).
    pub(super) fixed: Vec<(AgentId, AgentType)>,
    /// Per slot, the agent that the conditional task shows standing ([`Plan::standing`]).
    pub(super) held: Vec<Option<Held>>,
    /// Per slot, the route its future is told against, for a checkpoint that tells futures
    /// against routes (`route_frame`); `None` everywhere otherwise.
    pub(super) routes: Vec<Option<Route>>,
    /// Where each sample has routes of its own ([`Plan::draw_routes`]): per sample, the
    /// windows with its routes and its route per slot. Empty: every sample has `windows` and
    /// `routes`.
    pub(super) drawn: Vec<(Vec<Window>, Vec<Option<Route>>)>,
}

/// How often an unguided unconditional sample takes the first route open to an agent
/// (straight on from the nearest lane) where it has several; the others share the rest
/// evenly. The first is the one a recorded future strays from least for 1,090 of the 1,385
/// moving vehicles of the 100 DEU_Flensburg scenes of `commonroad-sumo` at 8 s (0.787;
/// SUMO-simulated), and for 350 of 454 offered three routes, the second and third for 56 and
/// 48 (`cargo run --release --example route_coverage -- 80 DIR`).
pub const FIRST_ROUTE_SHARE: f64 = 0.79;

/// Relative difference below which [`Plan::cheapest_routes`] counts an agent's routes as
/// costing the same: summed script costs of identical futures of the others differ only in
/// rounding.
const SAME_COST: f64 = 1e-9;

/// A modelled agent's route in the world ([`crate::train::WindowConfig::route_frame`]), with
/// where the agent stands on it: its coefficients decode to `(along, across, heading)` beyond
/// `(s0, d0)` and the route's heading ([`crate::scene::routes::from_route_residual`]).
#[derive(Debug, Clone)]
pub(super) struct Route {
    path: FrenetPath,
    s0: f64,
    d0: f64,
}

/// Writes `line` (a route in the world) as the route of one agent in every window that holds
/// it (`copies`, its own first) and gives the route its owner decodes along.
fn route_into(
    windows: &mut [Window],
    copies: &[(usize, usize)],
    slot: &Slot,
    line: &[Point],
) -> Option<Route> {
    for &(wi, k) in copies {
        let w = &mut windows[wi];
        let origin = w.origin;
        w.routes[k] = line.iter().map(|p| line_point(origin, *p)).collect();
    }
    let (wi, k) = copies[0];
    Route::of(&windows[wi], k, slot.pose)
}

impl Route {
    /// The route of `slot` in window `w` (whose frame it is stored in), taken to the world;
    /// `None` where the slot has none.
    fn of(w: &Window, slot: usize, pose: [f64; 3]) -> Option<Self> {
        let line = w
            .routes
            .get(slot)?
            .iter()
            .map(|q| from_frame(w.origin, q[0] as f64, q[1] as f64));
        let path = FrenetPath::new(Polyline::new(line).ok()?);
        let f = path.project(Point::new(pose[0], pose[1]));
        Some(Self {
            path,
            s0: f.s,
            d0: f.d,
        })
    }

    /// The world pose of one decoded step `(along, across, heading)` (the anchor added), with
    /// the frame's derivatives there.
    fn frame(&self, r: &[f64]) -> crate::geom::FramePoint {
        self.path.frame_at(self.s0 + r[0], self.d0 + r[1])
    }
}

/// A modelled agent held standing: it rolls at an even pace from where it stands to its
/// recorded end, which lies within [`STANDING_END`] of it, and keeps its heading.
#[derive(Debug, Clone)]
pub(super) struct Held {
    /// Its normalised coefficients, written to every copy so that the denoiser sees it where
    /// it is.
    pub(super) coeffs: Vec<f32>,
    /// Future step of its recorded end.
    pub(super) end_step: usize,
    /// World position of its recorded end.
    pub(super) end: [f64; 2],
}

/// Below this speed (m/s) at the current step, with its recorded end at most
/// [`STANDING_END`] away, an agent is held standing in conditional simulation.
pub const STANDING_SPEED: f64 = 0.3;

/// See [`STANDING_SPEED`] (metres).
pub const STANDING_END: f64 = 0.5;

/// A heading that [`Plan::align_headings`] set from the motion between two states: a
/// function of their positions, `atan2(dy, dx)` (or that plus π for a reversing car).
pub(super) struct Aligned {
    /// The state whose heading was set (index into [`Trajectories::xyh`]).
    pub(super) at: usize,
    /// The state behind it (`None`: the current state, which is fixed).
    pub(super) behind: Option<usize>,
    /// The state ahead of it (itself at the last step).
    pub(super) ahead: usize,
    pub(super) dx: f64,
    pub(super) dy: f64,
}

impl Aligned {
    /// Moves the cost gradient w.r.t. aligned headings onto the positions that decide them,
    /// so that guidance acts on the trajectories that are output: the heading channel there is
    /// overwritten, and a gradient on it would steer nothing.
    pub(super) fn chain(set: &[Aligned], world: &mut [f64]) {
        for a in set {
            let gh = std::mem::take(&mut world[a.at * 3 + 2]);
            if gh == 0.0 {
                continue;
            }
            let r2 = a.dx * a.dx + a.dy * a.dy;
            let (gx, gy) = (-gh * a.dy / r2, gh * a.dx / r2);
            world[a.ahead * 3] += gx;
            world[a.ahead * 3 + 1] += gy;
            if let Some(b) = a.behind {
                world[b * 3] -= gx;
                world[b * 3 + 1] -= gy;
            }
        }
    }
}

/// Where a modelled agent sits in the batch, and what decoding its coefficients needs.
#[derive(Debug, Clone, Copy)]
pub(super) struct Slot {
    /// Window (batch row within a sample).
    pub(super) window: usize,
    /// Agent slot within the window.
    pub(super) slot: usize,
    /// Scene agent index.
    pub(super) agent: usize,
    /// Current world pose `(x, y, heading)`.
    pub(super) pose: [f64; 3],
    /// Constant-velocity anchor ([`Window::advance`]), fixed for the whole run.
    pub(super) advance: f64,
    /// Tightest path curvature its type steers, 1/m ([`KinematicLimits::max_curvature`];
    /// infinite for a pedestrian, who turns on the spot).
    pub(super) curvature: f64,
}

/// Cuts windows until every agent observed at step `c` sits in one (with routes chosen as
/// `hint` says, for a checkpoint that tells futures against them): the first centred on
/// `centre`, each next one on the uncovered agent nearest to it. A window holds at most
/// `max_agents` agents, and NGSIM scenes have up to a hundred; agents left outside would
/// drift at constant velocity, ignored by the model and by guidance. Windows overlap, and
/// each agent is modelled by (owned by) the window whose centre is nearest to it, where its
/// lanes and neighbours are most completely in view; its other copies are context, kept equal
/// to the owner's ([`Plan::consensus`]). (Counting an agent as covered only in the nearest
/// two thirds of a window, for more overlap, cost 2-3x the windows and measured the same.)
pub(super) fn tile(
    scene: &Scene,
    wcfg: &crate::train::WindowConfig,
    c: usize,
    centre: usize,
    meta: &crate::train::CheckpointMeta,
    hint: RouteHint,
) -> Tiling {
    let moves = |i: usize| meta.models(&scene.agents[i]);
    let observed = |i: usize| scene.agents[i].is_valid(c) && moves(i);
    // A model that reads what each agent is was trained with every road user and obstacle in
    // its windows; one that does not (NGSIM's) saw only the vehicles it moves.
    let context = |i: usize| meta.config.model.attrs > 0 || moves(i);
    let pose = |i: usize| {
        let s = scene.agents[i].states[c];
        [s.x, s.y, s.heading]
    };
    let dist = |i: usize, j: usize| {
        let (p, q) = (pose(i), pose(j));
        (p[0] - q[0]).hypot(p[1] - q[1])
    };
    let mut covered = vec![false; scene.agents.len()];
    let mut windows = Vec::new();
    // Per agent, in order of first appearance: (window, slot, distance to the window centre).
    let mut seen: Vec<Vec<(usize, usize, f64)>> = vec![Vec::new(); scene.agents.len()];
    let mut order = Vec::new();
    let mut next = Some(centre);
    while let Some(ci) = next {
        let w = window_among(scene, wcfg, c, ci, &context, hint);
        let wi = windows.len();
        for (slot, &ai) in w.agents.iter().enumerate() {
            if !observed(ai) {
                continue;
            }
            if seen[ai].is_empty() {
                order.push(ai);
            }
            seen[ai].push((wi, slot, dist(ai, ci)));
            covered[ai] = true;
        }
        windows.push(w);
        next = (0..scene.agents.len())
            .filter(|&i| observed(i) && !covered[i])
            .min_by(|&a, &b| dist(a, centre).total_cmp(&dist(b, centre)));
    }
    let (mut slots, mut copies) = (Vec::new(), Vec::new());
    for ai in order {
        let mut list = std::mem::take(&mut seen[ai]);
        // Stable: of equally near centres the earlier window owns the agent.
        list.sort_by(|a, b| a.2.total_cmp(&b.2));
        let (wi, slot, _) = list[0];
        slots.push(Slot {
            window: wi,
            slot,
            agent: ai,
            pose: pose(ai),
            advance: windows[wi].advance(wcfg, slot),
            curvature: KinematicLimits::default()
                .for_type(scene.agents[ai].agent_type)
                .map_or(f64::INFINITY, |l| l.max_curvature),
        });
        copies.push(list.iter().map(|&(w, s, _)| (w, s)).collect());
    }
    let routes = slots
        .iter()
        .map(|sl| Route::of(&windows[sl.window], sl.slot, sl.pose))
        .collect();
    Tiling {
        windows,
        slots,
        copies,
        routes,
    }
}

/// What [`tile`] cuts: [`Plan`]'s fields of the same names.
pub(super) struct Tiling {
    pub(super) windows: Vec<Window>,
    pub(super) slots: Vec<Slot>,
    pub(super) copies: Vec<Vec<(usize, usize)>>,
    pub(super) routes: Vec<Option<Route>>,
}

impl Plan<'_> {
    /// `(agents per window, components, future steps, windows)`.
    pub(super) fn dims(&self) -> (usize, usize, usize, usize) {
        let c = &self.trained.meta.config;
        (
            c.window.max_agents,
            c.model.k,
            c.window.future,
            self.windows.len(),
        )
    }

    /// World trajectories of every scene agent for each sample of `coeffs` `[K, N, k]`:
    /// modelled agents from the coefficients, the others at constant velocity.
    pub(super) fn trajectories(&self, coeffs: &[f32]) -> Vec<Trajectories> {
        let (n, k, f, nw) = self.dims();
        let samples = coeffs.len() / (nw * n * k);
        let base = &self.base;
        let norm = &self.trained.meta.normaliser;
        (0..samples)
            .map(|s| {
                let mut t = base.clone();
                for (si, sl) in self.slots.iter().enumerate() {
                    let (ai, p0) = (sl.agent, sl.pose);
                    let held = self.held.get(si).and_then(Option::as_ref);
                    let row = (s * nw + sl.window) * n + sl.slot;
                    let mut local = norm.decode(&coeffs[row * k..(row + 1) * k]);
                    add_anchor(&mut local, sl.advance);
                    if let Some(h) = held {
                        for j in 0..f.min(t.layout.steps) {
                            let u = ((j + 1) as f64 / (h.end_step + 1) as f64).min(1.0);
                            let i = ai * t.layout.steps + j;
                            t.xyh[i] = [
                                p0[0] + u * (h.end[0] - p0[0]),
                                p0[1] + u * (h.end[1] - p0[1]),
                                p0[2],
                            ];
                            t.valid[i] = true;
                        }
                        continue;
                    }
                    if let Some(route) = self.route(s, si) {
                        for j in 0..f.min(t.layout.steps) {
                            let r = &local[j * 3..j * 3 + 3];
                            let fp = route.frame(r);
                            let i = ai * t.layout.steps + j;
                            t.xyh[i] = [fp.point.x, fp.point.y, wrap_angle(fp.heading + r[2])];
                            t.valid[i] = true;
                        }
                        continue;
                    }
                    let (sn, cs) = p0[2].sin_cos();
                    for j in 0..f.min(t.layout.steps) {
                        let (x, y, h) = (local[j * 3], local[j * 3 + 1], local[j * 3 + 2]);
                        let i = ai * t.layout.steps + j;
                        t.xyh[i] = [p0[0] + cs * x - sn * y, p0[1] + sn * x + cs * y, p0[2] + h];
                        t.valid[i] = true;
                    }
                }
                t
            })
            .collect()
    }

    /// Points each modelled agent's heading along its direction of motion wherever it moves
    /// (central differences over more than 0.2 m per step), backwards where it reverses.
    /// Where it is slower, or the motion runs more than 45° across it, a vehicle or cyclist
    /// keeps the heading it had: over a few centimetres the direction of motion is noise, and
    /// the model's heading channel there wobbled by 0.01-0.1 rad/s where the SUMO log holds its
    /// heading exactly (held-out preview: 25 % of steps under 0.025 rad/s against the log's
    /// 82 %; holding instead brought the angular-speed JSD from 0.37 to 0.19 on the same
    /// positions). A pedestrian, who walks below that threshold and turns on the spot, keeps
    /// the model's heading there.
    /// Positions and headings are separate PCA channels, and guidance that pushes positions
    /// sideways drags the heading channel along arbitrarily; a car drives where it points, so
    /// the output keeps its headings consistent with its path. Then, from the current pose on,
    /// each heading turns from the one before by at most the type's curvature bound times the
    /// distance moved: a car turns only as it rolls. Without that, a car that stands or creeps
    /// turned with the model's heading channel (a wobble of 0.05-0.1 rad/s where the log holds
    /// its heading exactly), and one near 2 m/s jumped by up to 1.4 rad/s wherever its steps
    /// crossed the 0.2 m threshold between the model's heading and the path's. Returns the
    /// headings it set from the path (not those the bound then held back), for
    /// [`Aligned::chain`].
    pub(super) fn align_headings(&self, t: &mut Trajectories) -> Vec<Aligned> {
        let n = t.layout.steps;
        let mut set = Vec::new();
        for &Slot {
            agent: ai,
            pose: p0,
            curvature,
            ..
        } in &self.slots
        {
            let idx = |j: isize| (j >= 0).then(|| ai * n + (j as usize).min(n - 1));
            let at = |t: &Trajectories, j: isize| idx(j).map_or(p0, |i| t.xyh[i]);
            let mut heading: Vec<f64> = (0..n).map(|j| t.xyh[ai * n + j][2]).collect();
            let mut from_path: Vec<Option<Aligned>> = (0..n).map(|_| None).collect();
            let mut held = vec![curvature.is_finite(); n];
            for j in 0..n as isize {
                let (a, b) = (at(t, j - 1), at(t, j + 1));
                let span = if j as usize + 1 >= n { 1.0 } else { 2.0 };
                let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
                let h = at(t, j)[2];
                if dx.hypot(dy) <= 0.2 * span {
                    continue;
                }
                // A car moving against its heading reverses; one moving across it is
                // jitter of a near-standstill, not a reason to turn it sideways.
                let mut diff = crate::geom::wrap_angle(dy.atan2(dx) - h);
                if diff.abs() > std::f64::consts::FRAC_PI_2 {
                    diff = crate::geom::wrap_angle(diff + std::f64::consts::PI);
                }
                if diff.abs() <= std::f64::consts::FRAC_PI_4 && t.valid[ai * n + j as usize] {
                    heading[j as usize] = h + diff;
                    held[j as usize] = false;
                    from_path[j as usize] = Some(Aligned {
                        at: ai * n + j as usize,
                        behind: idx(j - 1),
                        ahead: idx(j + 1).expect("j + 1 >= 0"),
                        dx,
                        dy,
                    });
                }
            }
            let (mut last, mut last_h) = ([p0[0], p0[1]], p0[2]);
            for j in 0..n {
                let i = ai * n + j;
                if !t.valid[i] {
                    continue;
                }
                let p = t.xyh[i];
                if held[j] {
                    heading[j] = last_h;
                }
                let most = curvature * (p[0] - last[0]).hypot(p[1] - last[1]);
                let turn = crate::geom::wrap_angle(heading[j] - last_h);
                if turn.abs() > most {
                    heading[j] = last_h + turn.clamp(-most, most);
                    from_path[j] = None;
                }
                t.xyh[i][2] = heading[j];
                (last, last_h) = ([p[0], p[1]], heading[j]);
            }
            set.extend(from_path.into_iter().flatten());
        }
        set
    }

    /// Makes every window agree on each agent: the denoised estimate `d` becomes the owner's,
    /// minus `lambda`·clamp(Σ copies of `grad`), written to every copy. Coefficients live in
    /// each agent's own frame, so copies are comparable as they are. The copies share one
    /// noisy input, so the gradient w.r.t. it is the sum over copies (through the denoiser,
    /// context copies feed the owners in their windows). Without this an agent is context
    /// in other windows with an independently sampled future, and its neighbours there plan
    /// around a car that is not where its owner puts it.
    pub(super) fn consensus(&self, d: &mut [f32], grad: Option<&[f32]>, lambda: f64, clamp: Clamp) {
        let (n, k, _, nw) = self.dims();
        let samples = d.len() / (nw * n * k);
        let mut owned = vec![0f32; k];
        let mut gsum = vec![0f32; k];
        for s in 0..samples {
            let at = |(w, slot): (usize, usize)| ((s * nw + w) * n + slot) * k;
            for copies in &self.copies {
                gsum.fill(0.0);
                if let Some(g) = grad {
                    for &c in copies {
                        let o = at(c);
                        for j in 0..k {
                            gsum[j] += g[o + j];
                        }
                    }
                }
                let scale = match clamp {
                    Clamp::Coordinate => 1.0,
                    Clamp::Agent => 1.0 / gsum.iter().fold(1f32, |m, v| m.max(v.abs())),
                };
                let o = at(copies[0]);
                for j in 0..k {
                    owned[j] = d[o + j] - (lambda as f32) * (gsum[j] * scale).clamp(-1.0, 1.0);
                }
                for &c in copies {
                    let o = at(c);
                    d[o..o + k].copy_from_slice(&owned);
                }
            }
        }
    }

    /// Per slot, the agent that the conditional task shows standing: a vehicle or cyclist
    /// under [`STANDING_SPEED`] at the current step whose recorded end, at the last sampled
    /// step (`steps`), lies within [`STANDING_END`] of where it stands. The task says where
    /// each agent is at the end; one that stands now and then is taken to stand between.
    /// The model has no traffic-light state, and left free it started queued cars and slid
    /// them sideways into oncoming traffic and back (the cities checkpoint at 8 s, training
    /// town DEU_Flensburg: standing cars' largest move median 1.25 m, p90 2.38 m).
    pub(super) fn standing(
        &self,
        scene: &Scene,
        ends: &[Option<(usize, f64, f64)>],
        steps: usize,
    ) -> Vec<Option<Held>> {
        let (_, _, f, _) = self.dims();
        let norm = &self.trained.meta.normaliser;
        let c = scene.meta.current_step;
        self.slots
            .iter()
            .enumerate()
            .map(|(si, sl)| {
                let (j, ex, ey) = ends[sl.agent]?;
                let a = &scene.agents[sl.agent];
                let (dx, dy) = (ex - sl.pose[0], ey - sl.pose[1]);
                let stands = a.agent_type != AgentType::Pedestrian
                    && j + 1 >= steps.min(f)
                    && a.states[c].speed() < STANDING_SPEED
                    && dx.hypot(dy) <= STANDING_END;
                if !stands {
                    return None;
                }
                let mut local = vec![0.0; 3 * f];
                if let Some(route) = self.routes.get(si).and_then(Option::as_ref) {
                    // The same roll in the plane, told against the route.
                    let future: Vec<Option<[f64; 3]>> = (0..f)
                        .map(|i| {
                            let u = ((i + 1) as f64 / (j + 1) as f64).min(1.0);
                            Some([sl.pose[0] + u * dx, sl.pose[1] + u * dy, sl.pose[2]])
                        })
                        .collect();
                    let r = route_residual(&route.path, sl.pose, &future, sl.advance);
                    for (i, v) in r.into_iter().enumerate() {
                        local[i * 3..i * 3 + 3].copy_from_slice(&v.expect("every step given"));
                    }
                } else {
                    let (sn, cs) = sl.pose[2].sin_cos();
                    let (tx, ty) = (cs * dx + sn * dy, -sn * dx + cs * dy);
                    for i in 0..f {
                        let u = ((i + 1) as f64 / (j + 1) as f64).min(1.0);
                        local[i * 3] = u * tx;
                        local[i * 3 + 1] = u * ty;
                    }
                    remove_anchor(&mut local, sl.advance);
                }
                Some(Held {
                    coeffs: norm.encode(&local),
                    end_step: j,
                    end: [ex, ey],
                })
            })
            .collect()
    }

    /// The route slot `si` of sample `s` is decoded along.
    fn route(&self, s: usize, si: usize) -> Option<&Route> {
        match self.drawn.get(s) {
            Some((_, routes)) => routes.get(si),
            None => self.routes.get(si),
        }
        .and_then(Option::as_ref)
    }

    /// The windows of sample `s`: its own where its routes were drawn.
    pub(super) fn windows_of(&self, s: usize) -> &[Window] {
        self.drawn.get(s).map_or(&self.windows, |(w, _)| w)
    }

    /// Tells slot `si`'s future against `line` (a route in the world) from now on: in every
    /// window that holds the agent, so that each copy reads the route its owner decodes along.
    fn set_route(&mut self, si: usize, line: &[Point]) {
        self.routes[si] = route_into(&mut self.windows, &self.copies[si], &self.slots[si], line);
    }

    /// Gives every sample of `samples` routes of its own: each modelled agent with a choice
    /// takes the first route with probability [`FIRST_ROUTE_SHARE`], each other with an even
    /// share of the rest. An unguided unconditional sample then turns where recorded traffic
    /// turns about as often, where straight on for all would never turn. A slot `decided`
    /// names ([`Plan::cheapest_routes`]) takes that route in every sample; the draw for it is
    /// made all the same, so that every other agent draws what it draws in the unguided twin
    /// of the same seed.
    pub(super) fn draw_routes(
        &mut self,
        scene: &Scene,
        samples: usize,
        seed: u64,
        decided: &[Option<usize>],
    ) {
        if self.routes.iter().all(Option::is_none) {
            return;
        }
        let wcfg = self.trained.meta.config.window;
        let c = scene.meta.current_step;
        let offered: Vec<Vec<Vec<Point>>> = self
            .slots
            .iter()
            .enumerate()
            .map(|(si, sl)| match self.routes[si] {
                Some(_) => agent_route_lines(scene, &wcfg, c, sl.agent),
                None => Vec::new(),
            })
            .collect();
        let mut rng = crate::train::rng::Rng::new(seed);
        self.drawn = (0..samples)
            .map(|_| {
                let (mut windows, mut routes) = (self.windows.clone(), self.routes.clone());
                for (si, lines) in offered.iter().enumerate() {
                    if lines.len() < 2 {
                        continue;
                    }
                    let u = rng.uniform();
                    let drawn = if u < FIRST_ROUTE_SHARE {
                        0
                    } else {
                        let rest = (u - FIRST_ROUTE_SHARE) / (1.0 - FIRST_ROUTE_SHARE);
                        1 + ((rest * (lines.len() - 1) as f64) as usize).min(lines.len() - 2)
                    };
                    let pick = decided.get(si).copied().flatten().unwrap_or(drawn);
                    routes[si] = route_into(
                        &mut windows,
                        &self.copies[si],
                        &self.slots[si],
                        &lines[pick],
                    );
                }
                (windows, routes)
            })
            .collect();
    }

    /// Per slot, the route (an index into [`agent_route_lines`]) whose constant-speed future
    /// along it costs least by `cost` (the others on the routes they have), one agent at a
    /// time in slot order, each set as it is chosen: a script that asks a car to turn left at
    /// the junction ahead then samples it on the left turn's route, where a future with no
    /// offset across it already turns. `None` for an agent whose routes all cost the same
    /// (one the scripts do not steer, or steer along any route alike: a speed limit): it is
    /// left on its first route, for [`Plan::draw_routes`] to draw as an unguided sample
    /// would. Otherwise it would go straight on in every guided sample, wherever recorded
    /// traffic turns.
    pub(super) fn cheapest_routes<E>(
        &mut self,
        scene: &Scene,
        cost: &dyn Fn(&Trajectories) -> Result<f64, E>,
    ) -> Result<Vec<Option<usize>>, E> {
        let mut decided = vec![None; self.slots.len()];
        if self.routes.iter().all(Option::is_none) {
            return Ok(decided);
        }
        let (n, k, f, nw) = self.dims();
        let norm = &self.trained.meta.normaliser;
        let zero = norm.encode(&vec![0.0; 3 * f]);
        let mut coeffs = vec![0f32; nw * n * k];
        for copies in &self.copies {
            for &(wi, slot) in copies {
                let o = (wi * n + slot) * k;
                coeffs[o..o + k].copy_from_slice(&zero);
            }
        }
        let wcfg = self.trained.meta.config.window;
        let c = scene.meta.current_step;
        let evaluate = |plan: &Plan| -> Result<f64, E> {
            let mut t = plan.trajectories(&coeffs).swap_remove(0);
            plan.align_headings(&mut t);
            cost(&t)
        };
        for si in 0..self.slots.len() {
            if self.routes[si].is_none() {
                continue;
            }
            let lines = agent_route_lines(scene, &wcfg, c, self.slots[si].agent);
            if lines.len() < 2 {
                continue;
            }
            let mut costs = Vec::with_capacity(lines.len());
            for line in &lines {
                self.set_route(si, line);
                costs.push(evaluate(self)?);
            }
            // The first of the least (a NaN cost never wins).
            let (i, least) = costs
                .iter()
                .enumerate()
                .fold((0, costs[0]), |(bi, b), (i, &v)| {
                    if v < b || b.is_nan() && !v.is_nan() {
                        (i, v)
                    } else {
                        (bi, b)
                    }
                });
            let same = costs
                .iter()
                .all(|v| (v - least).abs() <= SAME_COST * least.abs().max(1.0));
            let pick = if same { 0 } else { i };
            self.set_route(si, &lines[pick]);
            decided[si] = (!same).then_some(pick);
        }
        Ok(decided)
    }

    /// Writes each held agent's coefficients ([`Plan::standing`]) to every copy of it.
    pub(super) fn hold(&self, d: &mut [f32]) {
        let (n, k, _, nw) = self.dims();
        let samples = d.len() / (nw * n * k);
        for s in 0..samples {
            for (h, copies) in self.held.iter().zip(&self.copies) {
                let Some(h) = h else { continue };
                for &(wi, slot) in copies {
                    let o = ((s * nw + wi) * n + slot) * k;
                    d[o..o + k].copy_from_slice(&h.coeffs);
                }
            }
        }
    }

    /// Gradient of a dense world-coordinate gradient w.r.t. the normalised coefficients, for
    /// the trajectories [`Plan::trajectories`] decoded from `coeffs` (a route's frame turns
    /// along it, so the chain rule depends on where each step lies).
    pub(super) fn to_coeffs(
        &self,
        world: &[f64],
        steps: usize,
        out: &mut [f32],
        sample: usize,
        coeffs: &[f32],
    ) {
        let (n, k, f, nw) = self.dims();
        let norm = &self.trained.meta.normaliser;
        let dim = norm.pca.dim;
        for (si, (sl, copies)) in self.slots.iter().zip(&self.copies).enumerate() {
            let (ai, p0) = (sl.agent, sl.pose);
            let (sn, cs) = p0[2].sin_cos();
            let mut local = vec![0.0; dim];
            let route = self.route(sample, si);
            let decoded = route.map(|_| {
                let (wi, slot) = copies[0];
                let row = (sample * nw + wi) * n + slot;
                let mut v = norm.decode(&coeffs[row * k..(row + 1) * k]);
                add_anchor(&mut v, sl.advance);
                v
            });
            for j in 0..f.min(steps) {
                let g = &world[(ai * steps + j) * 3..(ai * steps + j) * 3 + 3];
                if let (Some(route), Some(v)) = (route, &decoded) {
                    // x = frame(s0 + along, d0 + across), heading = route's there + heading.
                    let fp = route.frame(&v[j * 3..j * 3 + 3]);
                    local[j * 3] = g[0] * fp.along.x + g[1] * fp.along.y + g[2] * fp.curvature;
                    local[j * 3 + 1] = g[0] * fp.across.x + g[1] * fp.across.y;
                    local[j * 3 + 2] = g[2];
                    continue;
                }
                local[j * 3] = cs * g[0] + sn * g[1];
                local[j * 3 + 1] = -sn * g[0] + cs * g[1];
                local[j * 3 + 2] = g[2];
            }
            for c in 0..k {
                let comp = &norm.pca.components[c * dim..(c + 1) * dim];
                let g: f64 = comp.iter().zip(&local).map(|(a, b)| a * b).sum::<f64>() * norm.std[c]
                    / norm.sigma_data;
                // The trajectory decodes the owner's copy ([`Plan::consensus`]).
                let (wi, slot) = copies[0];
                out[((sample * nw + wi) * n + slot) * k + c] += g as f32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{load_scene, LoadOptions};
    use crate::train::rng::Rng;
    use crate::train::trainer::tiny_config;
    use std::path::Path;

    /// A tiny model that tells futures against routes, and the crossroads where vehicle 1 turns
    /// left (vehicle 2 waits across the junction), prepared for it.
    fn crossroads() -> (Trained, Scene) {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes");
        let scenes: Vec<Scene> = ["crossroads_left.yaml", "highway.yaml"]
            .iter()
            .map(|f| load_scene(&dir.join(f), 0, &LoadOptions::default()).unwrap())
            .collect();
        let mut cfg = tiny_config(2, 3, 2);
        cfg.window.route_frame = true;
        cfg.model.route_frame = true;
        let t = crate::train::train(&scenes, cfg, None, None, |_, _, _| {}).unwrap();
        let s = crate::sample::prepare(&scenes[0], &t).unwrap();
        (t, s)
    }

    fn plan<'a>(t: &'a Trained, s: &Scene, hint: RouteHint) -> Plan<'a> {
        let c = s.meta.current_step;
        let tiling = tile(s, &t.meta.config.window, c, 0, &t.meta, hint);
        Plan {
            trained: t,
            windows: tiling.windows,
            slots: tiling.slots,
            copies: tiling.copies,
            base: Trajectories::filled(s),
            fixed: Vec::new(),
            held: Vec::new(),
            routes: tiling.routes,
            drawn: Vec::new(),
        }
    }

    #[test]
    fn the_route_is_the_one_to_the_given_end_or_straight_on_when_nothing_is_known() {
        let (t, s) = crossroads();
        let end_of = |p: &Plan, agent: usize| {
            let si = p.slots.iter().position(|sl| sl.agent == agent).unwrap();
            let r = p.routes[si].as_ref().expect("a route");
            r.path.to_cartesian(r.path.length(), 0.0)
        };
        // Given its end (conditional), vehicle 1 takes the left turn north.
        let given = plan(&t, &s, RouteHint::EndPoint);
        let e = end_of(&given, 0);
        assert!(e.y > 30.0 && (e.x - 62.0).abs() < 0.5, "{e:?}");
        // Knowing nothing, it goes straight on east.
        let e = end_of(&plan(&t, &s, RouteHint::Unknown), 0);
        assert!(e.y.abs() < 1e-6 && e.x > 100.0, "{e:?}");
        // The waiting vehicle 2 faces west on lane 10 either way.
        let e = end_of(&given, 1);
        assert!(e.x < 60.0 && (e.y - 3.5).abs() < 1e-6, "{e:?}");
    }

    #[test]
    fn a_script_that_asks_for_a_turn_gets_the_route_that_turns_that_way() {
        use crate::cost::{CostScript, Limits, Params};
        let (t, s) = crossroads();
        let script = |name: &str| {
            let path = Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("scripts")
                .join(name);
            CostScript::compile(
                &std::fs::read_to_string(path).unwrap(),
                name,
                std::rc::Rc::new(s.clone()),
                &Params::parse(&["vehicle=1"]).unwrap(),
                &Limits::default(),
            )
            .unwrap()
        };
        for (name, north) in [("turn_left.rhai", true), ("turn_right.rhai", false)] {
            let script = script(name);
            let mut p = plan(&t, &s, RouteHint::Unknown);
            let cost = |tr: &Trajectories| -> Result<f64, crate::cost::CostError> {
                script.evaluate(tr).map(|r| r.total)
            };
            let decided = p.cheapest_routes(&s, &cost).unwrap();
            let si = p.slots.iter().position(|sl| sl.agent == 0).unwrap();
            assert_eq!(decided[si], Some(if north { 1 } else { 2 }), "{name}");
            let r = p.routes[si].as_ref().unwrap();
            let e = r.path.to_cartesian(r.path.length(), 0.0);
            assert_eq!(e.y > 30.0, north, "{name}: {e:?}");
            assert_eq!(e.y < -30.0, !north, "{name}: {e:?}");
            // Every window that holds vehicle 1 reads the route it decodes along.
            for &(wi, slot) in &p.copies[si] {
                let w = &p.windows[wi];
                let last = *w.routes[slot].last().unwrap();
                let world = from_frame(w.origin, last[0] as f64, last[1] as f64);
                assert!((world.x - e.x).abs() < 1e-3 && (world.y - e.y).abs() < 1e-3);
            }
            // Vehicle 2, whom the script does not name, keeps the first of its routes.
            let sj = p.slots.iter().position(|sl| sl.agent == 1).unwrap();
            let r = p.routes[sj].as_ref().unwrap();
            let e = r.path.to_cartesian(r.path.length(), 0.0);
            assert!((e.y - 3.5).abs() < 1e-6, "{e:?}");
        }
    }

    #[test]
    fn unguided_samples_draw_their_routes_straight_on_most_often() {
        let (t, s) = crossroads();
        let mut p = plan(&t, &s, RouteHint::Unknown);
        let samples = 400;
        p.draw_routes(&s, samples, 3, &[]);
        assert_eq!(p.drawn.len(), samples);
        let (n, k, f, nw) = p.dims();
        // Every sample's vehicle 1 at constant speed along its route: where it ends says which
        // route it drew, and each sample's own windows carry that route.
        let si = p.slots.iter().position(|sl| sl.agent == 0).unwrap();
        let zero = t.meta.normaliser.encode(&vec![0.0; 3 * f]);
        let mut coeffs = vec![0f32; samples * nw * n * k];
        for smp in 0..samples {
            for copies in &p.copies {
                for &(wi, slot) in copies {
                    let o = ((smp * nw + wi) * n + slot) * k;
                    coeffs[o..o + k].copy_from_slice(&zero);
                }
            }
        }
        let trajs = p.trajectories(&coeffs);
        let ai = p.slots[si].agent;
        let (mut east, mut north, mut south) = (0, 0, 0);
        for (smp, tr) in trajs.iter().enumerate() {
            let last = tr.xyh[ai * tr.layout.steps + f - 1];
            match (last[0] > 64.0, last[1] > 8.0, last[1] < -8.0) {
                (true, false, false) => east += 1,
                (false, true, false) => north += 1,
                (false, false, true) => south += 1,
                _ => panic!("sample {smp} ends at {last:?}"),
            }
            let (wi, slot) = p.copies[si][0];
            let stored = *p.windows_of(smp)[wi].routes[slot].last().unwrap();
            let route = p.route(smp, si).unwrap();
            let end = route.path.to_cartesian(route.path.length(), 0.0);
            let w = &p.windows_of(smp)[wi];
            assert_eq!(stored, line_point(w.origin, end));
        }
        // 0.79 straight on, the turns 0.105 each: 316, 42 and 42 expected of 400.
        assert!((290..=340).contains(&east), "{east} {north} {south}");
        assert!((25..=60).contains(&north) && (25..=60).contains(&south));
        // The plan's own routes stay as they were: straight on.
        let r = p.routes[si].as_ref().unwrap();
        assert!(r.path.to_cartesian(r.path.length(), 0.0).x > 100.0);
    }

    #[test]
    fn a_guided_sample_draws_the_routes_of_the_agents_its_scripts_do_not_steer() {
        let (t, s) = crossroads();
        let ends = |p: &Plan, si: usize| -> Vec<(i64, i64)> {
            (0..p.drawn.len())
                .map(|smp| {
                    let r = p.route(smp, si).unwrap();
                    let e = r.path.to_cartesian(r.path.length(), 0.0);
                    (e.x.round() as i64, e.y.round() as i64)
                })
                .collect()
        };
        let samples = 60;
        let mut unguided = plan(&t, &s, RouteHint::Unknown);
        unguided.draw_routes(&s, samples, 5, &[]);
        let si = unguided.slots.iter().position(|sl| sl.agent == 0).unwrap();
        let twin = ends(&unguided, si);
        // A cost of vehicle 2's future alone (index 1) cannot tell vehicle 1's routes apart:
        // it is left to the draw, sample by sample as in the unguided twin, and turns in some
        // (before, straight on in every guided sample).
        let mut p = plan(&t, &s, RouteHint::Unknown);
        let of_two = |tr: &Trajectories| -> Result<f64, ()> {
            let st = tr.layout.steps;
            Ok(tr.xyh[st..2 * st].iter().map(|q| q[0] + q[1]).sum())
        };
        let decided = p.cheapest_routes(&s, &of_two).unwrap();
        assert!(decided.iter().all(Option::is_none), "{decided:?}");
        p.draw_routes(&s, samples, 5, &decided);
        let drawn = ends(&p, si);
        assert_eq!(drawn, twin);
        assert!(drawn.iter().any(|e| e.1 > 30) && drawn.iter().any(|e| e.1 < -30));
        // One that rewards vehicle 1 for ending north takes the left turn in every sample.
        let mut p = plan(&t, &s, RouteHint::Unknown);
        let north = |tr: &Trajectories| -> Result<f64, ()> { Ok(-tr.xyh[tr.layout.steps - 1][1]) };
        let decided = p.cheapest_routes(&s, &north).unwrap();
        assert_eq!(decided[si], Some(1));
        p.draw_routes(&s, samples, 5, &decided);
        assert!(ends(&p, si).iter().all(|e| e.1 > 30), "{:?}", ends(&p, si));
    }

    #[test]
    fn coefficients_decode_along_the_route_and_the_chain_rule_matches_finite_differences() {
        let (t, s) = crossroads();
        let plan = plan(&t, &s, RouteHint::EndPoint);
        let (n, k, f, nw) = plan.dims();
        let norm = &t.meta.normaliser;
        // The coefficients of "constant speed along the route": the car rounds the corner.
        let si = plan.slots.iter().position(|sl| sl.agent == 0).unwrap();
        let sl = plan.slots[si];
        let zero = vec![0.0; 3 * f];
        let mut coeffs = vec![0f32; nw * n * k];
        let row = sl.window * n + sl.slot;
        coeffs[row * k..(row + 1) * k].copy_from_slice(&norm.encode(&zero));
        let tr = &plan.trajectories(&coeffs)[0];
        let steps = tr.layout.steps;
        let last = tr.xyh[sl.agent * steps + f - 1];
        // 8 m/s for 4 s from 10 m before the junction: on lane 3's northward leg (x = 62),
        // to the PCA's reconstruction error, heading north as the route's frame does there
        // (its normals turn smoothly from corner to end, so 5 m into a 50 m leg it still
        // leans 0.15 rad into the corner).
        assert!((last[0] - 62.0).abs() < 0.5 && last[1] > 8.0, "{last:?}");
        assert!(
            (last[2] - std::f64::consts::FRAC_PI_2).abs() < 0.2,
            "{last:?}"
        );
        // The chain rule of to_coeffs against central differences of a linear objective of
        // the decoded trajectories, at random coefficients.
        let mut rng = Rng::new(9);
        let coeffs: Vec<f32> = (0..nw * n * k).map(|_| 0.5 * rng.normal() as f32).collect();
        let world: Vec<f64> = (0..tr.xyh.len() * 3).map(|_| rng.normal()).collect();
        let objective = |c: &[f32]| -> f64 {
            let tr = &plan.trajectories(c)[0];
            tr.xyh
                .iter()
                .zip(&tr.valid)
                .flat_map(|(p, v)| p.map(|x| if *v { x } else { 0.0 }))
                .zip(&world)
                .map(|(a, b)| a * b)
                .sum()
        };
        let mut g = vec![0f32; coeffs.len()];
        plan.to_coeffs(&world, steps, &mut g, 0, &coeffs);
        let h = 1e-3f32;
        let mut checked = 0;
        for (si, sl) in plan.slots.iter().enumerate() {
            assert!(plan.routes[si].is_some());
            let row = sl.window * n + sl.slot;
            for c in row * k..(row + 1) * k {
                let (mut up, mut down) = (coeffs.clone(), coeffs.clone());
                up[c] += h;
                down[c] -= h;
                let fd = (objective(&up) - objective(&down)) / (2.0 * h as f64);
                let an = g[c] as f64;
                assert!(
                    (fd - an).abs() <= 2e-3 * fd.abs().max(1.0),
                    "coefficient {c}: finite differences {fd}, chain rule {an}"
                );
                checked += 1;
            }
        }
        assert_eq!(checked, plan.slots.len() * k);
    }
}
