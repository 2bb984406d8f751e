//! Windows → tensors: the denoiser's [`Context`] and the normalised PCA targets.

use candle_core::{Device, Result, Tensor};

use super::dataset::{Window, WindowConfig, AGENT_ATTRS};
use crate::model::route::RouteInputs;
use crate::model::{Context, Pca, GOAL_FEATURES, ROUTE_FEATURES};
use crate::scene::routes::route_ahead;

/// Metres per unit of the relative-pose features (keeps them near 1).
pub const REL_SCALE: f32 = 50.0;
/// Metres per unit of lane points and history positions.
pub const POS_SCALE: f32 = 10.0;

/// Where route inputs put the points of absent lanes (metres): never the nearest.
const FAR: f32 = 1e5;

/// `(Δx, Δy, cos Δθ, sin Δθ)` of pose `j` in pose `i`'s frame, positions scaled.
pub fn rel(i: [f32; 3], j: [f32; 3]) -> [f32; 4] {
    let (s, c) = i[2].sin_cos();
    let (dx, dy) = (j[0] - i[0], j[1] - i[1]);
    let dh = j[2] - i[2];
    [
        (c * dx + s * dy) / REL_SCALE,
        (-s * dx + c * dy) / REL_SCALE,
        dh.cos(),
        dh.sin(),
    ]
}

/// Which agents' end points a batch gives the denoiser, for a model that reads them
/// ([`WindowConfig::goals`]; ignored otherwise). An agent's end point is its last observed
/// state after the current step in the window.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Goals {
    /// None: unconditional sampling, where the future is not known.
    Hidden,
    /// Every agent's that the window observes: conditional sampling, where the recorded end
    /// point is known.
    Recorded,
    /// Each agent's with probability `keep`, drawn from `seed`, the window's index and the
    /// agent's: training, so that one model learns both with and without them.
    Drawn {
        /// Probability that an agent's end point is given.
        keep: f64,
        /// Seed of the draw.
        seed: u64,
    },
}

impl Goals {
    fn given(&self, window: usize, agent: usize) -> bool {
        match *self {
            Goals::Hidden => false,
            Goals::Recorded => true,
            Goals::Drawn { keep, seed } => {
                // splitmix64 of the seed and the slot: independent of batch order elsewhere.
                let mut z = seed
                    ^ ((window as u64) << 32 | agent as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
                z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
                z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
                z ^= z >> 31;
                ((z >> 11) as f64 / (1u64 << 53) as f64) < keep
            }
        }
    }
}

/// Pose of lane `k` of a window: its first point and the direction to its second.
fn lane_pose(w: &Window, cfg: &WindowConfig, k: usize) -> [f32; 3] {
    let p = &w.lanes[k * cfg.lane_points..(k + 1) * cfg.lane_points];
    [
        p[0][0],
        p[0][1],
        (p[1][1] - p[0][1]).atan2(p[1][0] - p[0][0]),
    ]
}

/// The pose of the point of polyline `line` nearest to `at`, with the direction of the
/// segment it lies on.
fn nearest_pose(line: &[[f32; 2]], at: [f32; 3]) -> [f32; 3] {
    let mut best = (f32::INFINITY, [line[0][0], line[0][1], 0.0]);
    for s in line.windows(2) {
        let (ax, ay) = (s[0][0], s[0][1]);
        let (dx, dy) = (s[1][0] - ax, s[1][1] - ay);
        let len2 = dx * dx + dy * dy;
        if len2 <= 0.0 {
            continue;
        }
        let t = (((at[0] - ax) * dx + (at[1] - ay) * dy) / len2).clamp(0.0, 1.0);
        let (qx, qy) = (ax + t * dx, ay + t * dy);
        let d2 = (at[0] - qx).powi(2) + (at[1] - qy).powi(2);
        if d2 < best.0 {
            best = (d2, [qx, qy, dy.atan2(dx)]);
        }
    }
    best.1
}

/// A batch: the context, the normalised target coefficients `[B, N, K]`, the loss mask
/// `[B, N]` (agents with a future to learn from) and which future coordinates are observed
/// `[B, N, 3·future]`.
pub struct Batch {
    /// Model inputs.
    pub ctx: Context,
    /// Targets (zeros where unknown; fitted to the observed steps where the future is partly
    /// unobserved, [`Normaliser::encode_seen`]).
    pub target: Tensor,
    /// 1 where the agent has a target.
    pub loss_mask: Tensor,
    /// 1 for each observed `(x, y, heading)` coordinate of each agent's future: the loss is
    /// taken over these only.
    pub seen: Tensor,
    /// The loss basis, `[K, 3·future]` ([`Normaliser::loss_basis`]): normalised coefficients
    /// times these are the future in the normaliser's loss scale.
    pub basis: Tensor,
    /// Per observed future step of each target, the unit normal of the recorded path in the
    /// agent's frame, `(-sin h, cos h, 0)` (zeros elsewhere), `[B, N, 3·future]`: a position
    /// error times it is the part across the path, which the loss can weigh apart
    /// (`TrainConfig::across_weight`).
    pub normals: Tensor,
}

/// Observed future steps an agent needs to have a target: fewer say too little about where
/// it goes.
pub const MIN_SEEN_STEPS: usize = 5;

/// Standard deviation (metres, radians) with which observed future steps pin the fitted
/// coefficients of a partly observed future: about the PCA basis' own reconstruction error.
const SEEN_NOISE: f64 = 0.05;

/// How a new run's normaliser scales the PCA components ([`Normaliser::with_scale`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ComponentScale {
    /// One scale for all, the root mean variance ([`Normaliser::new`]).
    #[default]
    Common,
    /// Each its own spread, at most the common scale ([`Normaliser::capped`]).
    Capped,
}

/// PCA plus per-component scaling to the EDM data standard deviation.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Normaliser {
    /// The basis.
    pub pca: Pca,
    /// Scale of each coefficient ([`Normaliser::new`]; older checkpoints hold one common value).
    pub std: Vec<f64>,
    /// Target standard deviation (EDM's σ_data).
    pub sigma_data: f64,
}

impl Normaliser {
    /// From a fitted basis. Every component gets the same scale, the root mean variance over
    /// components. Scaling each by its own spread was tried for the 8 s cities model (each by
    /// the geometric mean of its own spread and the common one, 4,500 steps on the same split):
    /// the validation loss fell faster, but unguided samples of held-out towns moved cars that
    /// stand in the log at 2.88 m/s against 0.96 m/s with one scale, since the largest
    /// components, the distance driven, then carry more metres per unit of denoising error
    /// (and the sampler's guidance steps and polish weights are tuned in units of one common
    /// scale). [`Normaliser::loss_basis`] keeps the loss in metres whatever scales a checkpoint
    /// holds.
    pub fn new(pca: Pca, sigma_data: f64) -> Self {
        let mean_var = pca.variances.iter().sum::<f64>() / pca.variances.len().max(1) as f64;
        let std = vec![mean_var.sqrt().max(1e-6); pca.variances.len()];
        Self {
            pca,
            std,
            sigma_data,
        }
    }

    /// From a fitted basis, each component scaled by its own spread but never by more than
    /// the common scale of [`Normaliser::new`] ([`ComponentScale::Capped`]). With one common
    /// scale a denoising error of one normalised unit moves every component by the same
    /// metres: the 8 s cities model's was 24 m, against spreads of 89 m for the largest
    /// component and 0.26 m for the smallest, and its unguided samples of cars that stand for
    /// 8 s in held-out towns missed standing still by 2-9 m in each of the components whose
    /// spread is 0.3-1.5 m: the wobble of cars that should stand. Capped, an error in a small
    /// component is bounded by that component's own spread, while the large components, which
    /// carry the distance driven, keep the common scale (the geometric mean of own and common
    /// scales, tried before, raised those to 46 m and made stopped cars drift 3x as much).
    pub fn capped(pca: Pca, sigma_data: f64) -> Self {
        Self::capped_at(pca, sigma_data, 1.0)
    }

    /// [`Normaliser::capped`] with the cap at `fraction` (in (0, 1]) of the common scale. A
    /// lower cap gives the largest components, which carry the distance driven, fewer metres
    /// per unit of denoising error, which is what cars that stand or drive straight in the
    /// log need; it also puts their spread at several σ_data.
    pub fn capped_at(pca: Pca, sigma_data: f64, fraction: f64) -> Self {
        let common = Self::new(pca, sigma_data);
        let r = common.std.first().copied().unwrap_or(1e-6) * fraction.clamp(1e-3, 1.0);
        let floor = (r * 1e-3).max(1e-6);
        let std = common
            .pca
            .variances
            .iter()
            .map(|v| v.max(0.0).sqrt().clamp(floor, r))
            .collect();
        Self { std, ..common }
    }

    /// From a fitted basis with the scales `rule` gives.
    /// `cap` is the fraction of the common scale that [`ComponentScale::Capped`] caps at.
    pub fn with_scale(pca: Pca, sigma_data: f64, rule: ComponentScale, cap: f64) -> Self {
        match rule {
            ComponentScale::Common => Self::new(pca, sigma_data),
            ComponentScale::Capped => Self::capped_at(pca, sigma_data, cap),
        }
    }

    /// The reference scale of the training loss: the root mean variance of the components,
    /// the one scale every component had before they were scaled apart, so that losses of
    /// either kind of checkpoint read the same.
    pub fn loss_scale(&self) -> f64 {
        let v = &self.pca.variances;
        (v.iter().sum::<f64>() / v.len().max(1) as f64)
            .sqrt()
            .max(1e-6)
    }

    /// The basis the training loss maps coefficient errors through, `K × 3·future`: each PCA
    /// component times its scale over [`Normaliser::loss_scale`], so that an error of one
    /// normalised unit in component `c` costs what it moves the trajectory, in the loss scale.
    pub fn loss_basis(&self) -> Vec<f64> {
        let dim = self.pca.components.len() / self.std.len().max(1);
        let r = self.loss_scale();
        self.pca
            .components
            .chunks(dim.max(1))
            .zip(&self.std)
            .flat_map(|(row, s)| row.iter().map(move |v| v * s / r))
            .collect()
    }

    /// Normalised coefficients of a future residual (`future × 3`, agent frame, anchor removed:
    /// see [`Window::agent_residual`]).
    pub fn encode(&self, v: &[f64]) -> Vec<f32> {
        self.pca
            .encode(v)
            .iter()
            .zip(&self.std)
            .map(|(c, s)| (c / s * self.sigma_data) as f32)
            .collect()
    }

    /// [`Normaliser::encode`] of a future observed only at the steps marked in `seen`
    /// ([`crate::model::Pca::encode_seen`]).
    pub fn encode_seen(&self, v: &[f64], seen: &[bool]) -> Vec<f32> {
        if seen.iter().all(|s| *s) {
            return self.encode(v);
        }
        self.pca
            .encode_seen(v, seen, SEEN_NOISE)
            .iter()
            .zip(&self.std)
            .map(|(c, s)| (c / s * self.sigma_data) as f32)
            .collect()
    }

    /// The future residual (`future × 3`, agent frame, anchor not yet added back) of
    /// normalised coefficients.
    pub fn decode(&self, c: &[f32]) -> Vec<f64> {
        let raw: Vec<f64> = c
            .iter()
            .zip(&self.std)
            .map(|(c, s)| *c as f64 * s / self.sigma_data)
            .collect();
        self.pca.decode(&raw)
    }
}

/// Builds the tensors of `windows`.
pub fn build(
    windows: &[&Window],
    cfg: &WindowConfig,
    norm: &Normaliser,
    goals: Goals,
    dev: &Device,
) -> Result<Batch> {
    // Lanes are padded to the batch's largest map, not to `max_lanes`: NGSIM windows hold 26
    // lanes on average against 64 slots, and the lane-lane and agent-lane tensors grow with
    // the square and the product of that count. Windows store connectivity with stride
    // `max_lanes`.
    let m = if cfg.pad_lanes {
        cfg.max_lanes
    } else {
        windows
            .iter()
            .map(|w| w.lane_ids.len())
            .max()
            .unwrap_or(0)
            .max(1)
    };
    let mw = cfg.max_lanes;
    let (b, n, p, h, k) = (
        windows.len(),
        cfg.max_agents,
        cfg.lane_points,
        cfg.history,
        norm.pca.k(),
    );
    let steps = cfg.steps();
    let mut lane_points = vec![0f32; b * m * p * 2];
    let mut lane_mask = vec![0f32; b * m];
    let mut lane_rel = vec![0f32; b * m * m * 4];
    let mut lane_conn = vec![0u32; b * m * m];
    let mut agent_hist = vec![0f32; b * n * h * 4];
    let mut agent_mask = vec![0f32; b * n];
    let fl = cfg.agent_lane_features();
    let mut agent_lane_rel = vec![0f32; b * n * m * fl];
    let mut agent_rel = vec![0f32; b * n * n * 4];
    let mut target = vec![0f32; b * n * k];
    let mut loss_mask = vec![0f32; b * n];
    let dim = 3 * cfg.future;
    let mut seen_mask = vec![0f32; b * n * dim];
    let mut normals = vec![0f32; b * n * dim];
    let mut agent_attr = vec![0f32; b * n * AGENT_ATTRS];
    let rt = cfg.route_times;
    let route_steps = crate::model::route::route_steps(cfg.future, rt);
    let mut route_points = vec![FAR; if rt > 0 { b * n * m * p * 4 } else { 0 }];
    let mut route_offset = vec![0f32; b * n * rt * 3];
    let mut agent_goal = vec![0f32; if cfg.goals { b * n * GOAL_FEATURES } else { 0 }];
    let mut agent_route = vec![
        0f32;
        if cfg.route_frame {
            b * n * ROUTE_FEATURES
        } else {
            0
        }
    ];
    for (wi, w) in windows.iter().enumerate() {
        let nl = w.lane_ids.len();
        let poses: Vec<[f32; 3]> = (0..nl).map(|l| lane_pose(w, cfg, l)).collect();
        for (l, pose) in poses.iter().enumerate() {
            lane_mask[wi * m + l] = 1.0;
            let (s, c) = pose[2].sin_cos();
            for j in 0..p {
                let q = w.lanes[l * p + j];
                let (dx, dy) = (q[0] - pose[0], q[1] - pose[1]);
                let o = ((wi * m + l) * p + j) * 2;
                lane_points[o] = (c * dx + s * dy) / POS_SCALE;
                lane_points[o + 1] = (-s * dx + c * dy) / POS_SCALE;
            }
            for (l2, pose2) in poses.iter().enumerate() {
                let o = ((wi * m + l) * m + l2) * 4;
                lane_rel[o..o + 4].copy_from_slice(&rel(*pose, *pose2));
                lane_conn[(wi * m + l) * m + l2] = w.lane_conn[l * mw + l2] as u32;
            }
        }
        let na = w.agents.len();
        let cur: Vec<[f32; 3]> = (0..na).map(|a| w.states[a * steps + h - 1]).collect();
        for a in 0..na {
            if !w.valid[a * steps + h - 1] {
                continue;
            }
            agent_mask[wi * n + a] = 1.0;
            agent_attr[(wi * n + a) * AGENT_ATTRS..(wi * n + a + 1) * AGENT_ATTRS]
                .copy_from_slice(&w.attrs[a]);
            let (s, c) = cur[a][2].sin_cos();
            for t in 0..h {
                if w.valid[a * steps + t] {
                    let st = w.states[a * steps + t];
                    let (dx, dy) = (st[0] - cur[a][0], st[1] - cur[a][1]);
                    let o = ((wi * n + a) * h + t) * 4;
                    agent_hist[o] = (c * dx + s * dy) / POS_SCALE;
                    agent_hist[o + 1] = (-s * dx + c * dy) / POS_SCALE;
                    agent_hist[o + 2] = st[2] - cur[a][2];
                    agent_hist[o + 3] = 1.0;
                }
            }
            for (l, pose) in poses.iter().enumerate() {
                let o = ((wi * n + a) * m + l) * fl;
                agent_lane_rel[o..o + 4].copy_from_slice(&rel(cur[a], *pose));
                if cfg.nearest_lane_pose {
                    let line = &w.lanes[l * p..(l + 1) * p];
                    agent_lane_rel[o + 4..o + 8]
                        .copy_from_slice(&rel(cur[a], nearest_pose(line, cur[a])));
                }
            }
            if rt > 0 {
                let row = &mut route_points[(wi * n + a) * m * p * 4..][..nl * p * 4];
                for l in 0..nl {
                    let line = &w.lanes[l * p..(l + 1) * p];
                    for j in 0..p {
                        let (q, r) = if j + 1 < p {
                            (line[j], line[j + 1])
                        } else {
                            (line[j - 1], line[j])
                        };
                        let (dx, dy) = (line[j][0] - cur[a][0], line[j][1] - cur[a][1]);
                        let (tx, ty) = (r[0] - q[0], r[1] - q[1]);
                        let len = (tx * tx + ty * ty).sqrt();
                        let (hc, hs) = if len > 0.0 {
                            (tx / len, ty / len)
                        } else {
                            (1.0, 0.0)
                        };
                        let o = (l * p + j) * 4;
                        row[o] = c * dx + s * dy;
                        row[o + 1] = -s * dx + c * dy;
                        row[o + 2] = c * hc + s * hs;
                        row[o + 3] = -s * hc + c * hs;
                    }
                }
                let advance = w.advance(cfg, a);
                let off = &mut route_offset[(wi * n + a) * rt * 3..][..rt * 3];
                for (i, st) in route_steps.iter().enumerate() {
                    for d in 0..3 {
                        off[i * 3 + d] = norm.pca.mean[st * 3 + d] as f32;
                    }
                    off[i * 3] += (advance * (st + 1) as f64) as f32;
                }
            }
            if cfg.goals && goals.given(wi, a) {
                if let Some(t) = (h..steps).rev().find(|t| w.valid[a * steps + t]) {
                    let r = rel(cur[a], w.states[a * steps + t]);
                    let o = (wi * n + a) * GOAL_FEATURES;
                    agent_goal[o..o + GOAL_FEATURES].copy_from_slice(&[
                        r[0],
                        r[1],
                        r[3],
                        r[2],
                        (t + 1 - h) as f32 / cfg.future as f32,
                        1.0,
                    ]);
                }
            }
            if let Some(path) = w.route_path(a).filter(|_| cfg.route_frame) {
                let here = crate::geom::Point::new(cur[a][0] as f64, cur[a][1] as f64);
                let o = (wi * n + a) * ROUTE_FEATURES;
                for (j, q) in route_ahead(&path, here).iter().enumerate() {
                    let r = rel(cur[a], [q.x as f32, q.y as f32, 0.0]);
                    agent_route[o + 2 * j..o + 2 * j + 2].copy_from_slice(&r[..2]);
                }
            }
            for a2 in 0..na {
                let o = ((wi * n + a) * n + a2) * 4;
                agent_rel[o..o + 4].copy_from_slice(&rel(cur[a], cur[a2]));
            }
            if !w.is_mover_slot(a) {
                continue;
            }
            if let Some((f, seen)) = w
                .agent_residual_seen(cfg, a)
                .filter(|(_, seen)| seen.iter().filter(|s| **s).count() >= MIN_SEEN_STEPS)
            {
                let coeffs = norm.encode_seen(&f, &seen);
                target[(wi * n + a) * k..(wi * n + a + 1) * k].copy_from_slice(&coeffs);
                loss_mask[wi * n + a] = 1.0;
                let row = &mut seen_mask[(wi * n + a) * dim..(wi * n + a + 1) * dim];
                for (r, s) in row.chunks_mut(3).zip(&seen) {
                    if *s {
                        r.fill(1.0);
                    }
                }
                if let Some((future, _)) = w.agent_future_seen(cfg, a) {
                    let row = &mut normals[(wi * n + a) * dim..(wi * n + a + 1) * dim];
                    for ((r, p), s) in row.chunks_mut(3).zip(future.chunks(3)).zip(&seen) {
                        if *s {
                            let (sin, cos) = p[2].sin_cos();
                            r[0] = -sin as f32;
                            r[1] = cos as f32;
                        }
                    }
                }
            }
        }
    }
    let t = |v: Vec<f32>, shape: &[usize]| Tensor::from_vec(v, shape, dev);
    let route = if rt > 0 {
        let dim = norm.pca.components.len() / k.max(1);
        let mut basis = vec![0f32; k * rt * 3];
        for (c, row) in norm.pca.components.chunks(dim.max(1)).enumerate() {
            let scale = norm.std[c] / norm.sigma_data;
            for (i, st) in route_steps.iter().enumerate() {
                for d in 0..3 {
                    basis[(c * rt + i) * 3 + d] = (row[st * 3 + d] * scale) as f32;
                }
            }
        }
        Some(RouteInputs {
            points: t(route_points, &[b, n, m * p, 4])?,
            basis: t(basis, &[k, rt * 3])?,
            offset: t(route_offset, &[b, n, rt * 3])?,
        })
    } else {
        None
    };
    Ok(Batch {
        ctx: Context {
            lane_points: t(lane_points, &[b, m, p, 2])?,
            lane_mask: t(lane_mask, &[b, m])?,
            lane_rel: t(lane_rel, &[b, m, m, 4])?,
            lane_conn: Tensor::from_vec(lane_conn, (b, m, m), dev)?,
            agent_hist: t(agent_hist, &[b, n, h * 4])?,
            agent_mask: t(agent_mask, &[b, n])?,
            agent_lane_rel: t(agent_lane_rel, &[b, n, m, fl])?,
            agent_rel: t(agent_rel, &[b, n, n, 4])?,
            agent_attr: t(agent_attr, &[b, n, AGENT_ATTRS])?,
            route,
            agent_goal: if cfg.goals {
                Some(t(agent_goal, &[b, n, GOAL_FEATURES])?)
            } else {
                None
            },
            agent_route: if cfg.route_frame {
                Some(t(agent_route, &[b, n, ROUTE_FEATURES])?)
            } else {
                None
            },
        },
        target: t(target, &[b, n, k])?,
        loss_mask: t(loss_mask, &[b, n])?,
        seen: t(seen_mask, &[b, n, dim])?,
        normals: t(normals, &[b, n, dim])?,
        basis: t(
            norm.loss_basis().iter().map(|v| *v as f32).collect(),
            &[k, dim],
        )?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pca(variances: Vec<f64>) -> Pca {
        // Two orthonormal components over a future of two steps (six coordinates).
        let s = 0.5f64.sqrt();
        Pca {
            mean: vec![0.0; 6],
            components: vec![s, 0.0, 0.0, s, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
            variances,
            dim: 6,
        }
    }

    /// The sample highway of scripts/scenes.
    fn highway() -> crate::scene::Scene {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes");
        crate::io::load_scene(
            &dir.join("highway.yaml"),
            0,
            &crate::io::LoadOptions::default(),
        )
        .unwrap()
    }

    #[test]
    fn the_nearest_point_of_a_lane_gives_the_agents_offset_from_it() {
        // A lane along x from -30 to +30 m, an agent 1.5 m to its left at x = 12 heading
        // along it, and an agent beyond its end: the first point's pose says 42 m behind,
        // the nearest point's says 1.5 m to the right, for the first; the second's nearest
        // point is the lane's end.
        let line: Vec<[f32; 2]> = (0..20)
            .map(|i| [-30.0 + 60.0 * i as f32 / 19.0, 0.0])
            .collect();
        let q = nearest_pose(&line, [12.0, 1.5, 0.0]);
        assert!(
            (q[0] - 12.0).abs() < 1e-4 && q[1].abs() < 1e-6 && q[2].abs() < 1e-6,
            "{q:?}"
        );
        let r = rel([12.0, 1.5, 0.0], q);
        assert!(r[0].abs() < 1e-5 && (r[1] * REL_SCALE + 1.5).abs() < 1e-4 && r[2] > 0.9999);
        let start = rel([12.0, 1.5, 0.0], [-30.0, 0.0, 0.0]);
        assert!((start[0] * REL_SCALE + 42.0).abs() < 1e-4);
        let end = nearest_pose(&line, [40.0, -2.0, 0.0]);
        assert!(
            (end[0] - 30.0).abs() < 1e-4 && end[1].abs() < 1e-6,
            "{end:?}"
        );
    }

    #[test]
    fn the_route_ahead_is_given_in_the_agents_own_frame_whichever_way_the_window_faces() {
        // Vehicle 1 takes the left turn 10 m ahead of it, at 8 m/s.
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes");
        let opts = crate::io::LoadOptions::default();
        let scene = crate::io::load_scene(&dir.join("crossroads_left.yaml"), 0, &opts).unwrap();
        let cfg = crate::train::WindowConfig {
            route_frame: true,
            ..crate::train::WindowConfig::ngsim()
        };
        let w = crate::train::window_at(&scene, &cfg, 10, 0);
        let futures = crate::train::dataset::residual_futures(&[w.clone()], &cfg);
        let norm = Normaliser::new(crate::model::Pca::fit(&futures, 1).unwrap(), 0.5);
        let route = |w: &Window| -> Vec<f32> {
            let b = build(&[w], &cfg, &norm, Goals::Hidden, &Device::Cpu).unwrap();
            let r = b.ctx.agent_route.unwrap();
            assert_eq!(r.dims(), [1, cfg.max_agents, ROUTE_FEATURES]);
            r.flatten_all().unwrap().to_vec1().unwrap()
        };
        let r = route(&w);
        let point = |j: usize| (r[2 * j] * REL_SCALE, r[2 * j + 1] * REL_SCALE);
        // From where it stands, straight on to the junction, 5 m apart...
        for j in 0..3 {
            let (x, y) = point(j);
            assert!(
                (x - 5.0 * j as f32).abs() < 1e-3 && y.abs() < 1e-3,
                "{j}: {x} {y}"
            );
        }
        // ...then round the corner to the north, on lane 3's last leg (x = 62 - 40).
        let (x, y) = point(crate::scene::routes::AHEAD_POINTS - 1);
        assert!((x - 22.0).abs() < 0.1 && y > 40.0, "{x} {y}");
        // The same in a rotated window (training's augmentation).
        for (a, b) in r.iter().zip(&route(&w.rotated(0.7))) {
            assert!((a - b).abs() < 1e-4, "{a} {b}");
        }
        // Slots beyond the window's agents have none; a window without routes gives no tensor.
        assert!(r[2 * ROUTE_FEATURES..].iter().all(|v| *v == 0.0));
        let plain = crate::train::WindowConfig::ngsim();
        let w = crate::train::window_at(&scene, &plain, 10, 0);
        let b = build(&[&w], &plain, &norm, Goals::Hidden, &Device::Cpu).unwrap();
        assert!(b.ctx.agent_route.is_none());
    }

    #[test]
    fn a_window_with_nearest_lane_poses_has_eight_features_per_agent_lane_pair() {
        let scene = highway();
        let mut cfg = crate::train::WindowConfig::ngsim();
        let plain = crate::train::windows(&scene, &cfg);
        cfg.nearest_lane_pose = true;
        let near = crate::train::windows(&scene, &cfg);
        let futures = crate::train::dataset::residual_futures(&plain, &cfg);
        let norm = Normaliser::new(crate::model::Pca::fit(&futures, 4).unwrap(), 0.5);
        let dev = Device::Cpu;
        let a = build(
            &[&plain[0]],
            &crate::train::WindowConfig::ngsim(),
            &norm,
            Goals::Hidden,
            &dev,
        )
        .unwrap();
        let b = build(&[&near[0]], &cfg, &norm, Goals::Hidden, &dev).unwrap();
        let (x, y) = (a.ctx.agent_lane_rel, b.ctx.agent_lane_rel);
        assert_eq!(x.dims()[3], 4);
        assert_eq!(y.dims()[3], 8);
        // The first four are the lane starts' poses, as without the option.
        let first: Vec<f32> = y
            .narrow(3, 0, 4)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        assert_eq!(first, x.flatten_all().unwrap().to_vec1::<f32>().unwrap());
        // The centre agent drives on a lane: some lane's nearest point is within 2 m of it.
        let near: Vec<f32> = y
            .narrow(3, 4, 2)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let lanes = x.dims()[2];
        let closest = (0..lanes)
            .map(|l| (near[2 * l].hypot(near[2 * l + 1])) * REL_SCALE)
            .fold(f32::INFINITY, f32::min);
        assert!(closest < 2.0, "{closest}");
    }

    #[test]
    fn end_points_are_given_where_asked_at_the_last_observed_future_state() {
        let scene = highway();
        let mut cfg = crate::train::WindowConfig::ngsim();
        cfg.goals = true;
        let ws = crate::train::windows(&scene, &cfg);
        let futures = crate::train::dataset::residual_futures(&ws, &cfg);
        let norm = Normaliser::new(crate::model::Pca::fit(&futures, 4).unwrap(), 0.5);
        let refs: Vec<&Window> = ws.iter().take(4).collect();
        let feats = |goals: Goals| -> Vec<f32> {
            let b = build(&refs, &cfg, &norm, goals, &Device::Cpu).unwrap();
            b.ctx
                .agent_goal
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap()
        };
        let (n, h, steps) = (cfg.max_agents, cfg.history, cfg.steps());
        let recorded = feats(Goals::Recorded);
        let mut given = 0;
        for (wi, w) in refs.iter().enumerate() {
            for a in 0..n {
                let f = &recorded[(wi * n + a) * GOAL_FEATURES..][..GOAL_FEATURES];
                let present = a < w.agents.len() && w.valid[a * steps + h - 1];
                let last = (h..steps).rev().find(|t| present && w.valid[a * steps + t]);
                let Some(t) = last else {
                    assert!(f.iter().all(|v| *v == 0.0), "{f:?}");
                    continue;
                };
                given += 1;
                // The end point in the agent's current frame, worked out here by hand.
                let (now, end) = (w.states[a * steps + h - 1], w.states[a * steps + t]);
                let (dx, dy) = (end[0] - now[0], end[1] - now[1]);
                let (sin, cos) = now[2].sin_cos();
                let want = [
                    (dx * cos + dy * sin) / 50.0,
                    (dy * cos - dx * sin) / 50.0,
                    (end[2] - now[2]).sin(),
                    (end[2] - now[2]).cos(),
                    (t + 1 - h) as f32 / cfg.future as f32,
                    1.0,
                ];
                // Highway cars drive ahead: their end points lie ahead of them.
                assert!(want[0] > 0.0 && want[3] > 0.9, "{want:?}");
                for (x, y) in f.iter().zip(want) {
                    assert!((x - y).abs() < 1e-6, "{f:?} {want:?}");
                }
            }
        }
        assert!(given > 4);
        assert!(feats(Goals::Hidden).iter().all(|v| *v == 0.0));
        // Drawn: about half given, the same for the same seed, another set for another.
        let flags = |seed| -> Vec<f32> {
            feats(Goals::Drawn { keep: 0.5, seed })
                .chunks(GOAL_FEATURES)
                .map(|f| f[5])
                .collect()
        };
        let (a, b) = (flags(1), flags(2));
        let count = |v: &[f32]| v.iter().filter(|x| **x == 1.0).count();
        assert_eq!(a, flags(1));
        assert_ne!(a, b);
        assert!(
            count(&a) > 0 && count(&a) < given,
            "{} of {given}",
            count(&a)
        );
        // A configuration without end points builds none, whatever is asked.
        cfg.goals = false;
        let b = build(&refs, &cfg, &norm, Goals::Recorded, &Device::Cpu).unwrap();
        assert!(b.ctx.agent_goal.is_none());
    }

    #[test]
    fn route_inputs_decode_the_target_to_the_recorded_future_beside_its_lane() {
        let scene = highway();
        let mut cfg = crate::train::WindowConfig::ngsim();
        cfg.route_times = 4;
        let ws = crate::train::windows(&scene, &cfg);
        let futures = crate::train::dataset::residual_futures(&ws, &cfg);
        // Enough components to reproduce the futures to centimetres, and capped scales, so
        // that the scales differ per component.
        let norm = Normaliser::capped(crate::model::Pca::fit(&futures, 12).unwrap(), 0.5);
        let b = build(&[&ws[0]], &cfg, &norm, Goals::Hidden, &Device::Cpu).unwrap();
        let r = b.ctx.route.as_ref().unwrap();
        let n = cfg.max_agents;
        let steps = crate::model::route::route_steps(cfg.future, 4);
        let pose: Vec<f32> = b
            .target
            .reshape((n, ()))
            .unwrap()
            .matmul(&r.basis)
            .unwrap()
            .reshape((1, n, 12))
            .unwrap()
            .add(&r.offset)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let mask: Vec<f32> = b.loss_mask.flatten_all().unwrap().to_vec1().unwrap();
        let feats: Vec<f32> = crate::model::route::route_features(&b.target, r)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let mut checked = 0;
        for a in (0..n).filter(|a| mask[*a] > 0.0) {
            let Some(future) = ws[0].agent_future(&cfg, a) else {
                continue;
            };
            for (i, st) in steps.iter().enumerate() {
                for d in 0..3 {
                    let (got, want) = (pose[(a * 4 + i) * 3 + d], future[st * 3 + d] as f32);
                    assert!(
                        (got - want).abs() < 0.05,
                        "agent {a}, step {st}, coordinate {d}: {got} against {want}"
                    );
                }
                // The highway's cars keep to their lanes: well within half a lane of the
                // nearest lane point, heading along it.
                let f = &feats[(a * 4 + i) * 4..][..4];
                assert!(
                    f[0].abs() < (1.75f32 / 2.0).tanh() && f[2] > 0.95,
                    "agent {a}: {f:?}"
                );
            }
            checked += 1;
        }
        assert!(checked >= 3, "{checked}");
    }

    #[test]
    fn the_loss_basis_weighs_each_component_by_its_scale() {
        let mut n = Normaliser::new(pca(vec![400.0, 4.0]), 0.5);
        // One common scale, the root mean variance, which is also the loss scale.
        let r = (202.0f64).sqrt();
        assert!((n.loss_scale() - r).abs() < 1e-12);
        assert_eq!(n.std, vec![r, r]);
        // A checkpoint with scales of its own: an error of one normalised unit in a component
        // costs, through the loss basis, what it moves the trajectory.
        n.std = vec![20.0, 2.0];
        let b = n.loss_basis();
        let s = 0.5f64.sqrt();
        assert!((b[0] - s * 20.0 / r).abs() < 1e-12 && (b[7] - 2.0 / r).abs() < 1e-12);
        let one = n.decode(&[1.0, 0.0]);
        let moved = one.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!((moved - 20.0 / 0.5).abs() < 1e-9, "{moved}");
        let through: f64 = b[..6].iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!((through * r - 20.0).abs() < 1e-9);
        let c = n.encode(&n.decode(&[0.3, -1.2]));
        assert!(
            (c[0] - 0.3).abs() < 1e-6 && (c[1] + 1.2).abs() < 1e-6,
            "{c:?}"
        );
    }

    #[test]
    fn a_checkpoint_with_one_common_scale_keeps_its_loss_basis() {
        let mut n = Normaliser::new(pca(vec![400.0, 4.0]), 0.5);
        n.std = vec![n.loss_scale(); 2];
        let b = n.loss_basis();
        for (a, c) in b.iter().zip(&n.pca.components) {
            assert!((a - c).abs() < 1e-12);
        }
    }

    #[test]
    fn capped_scales_bound_an_error_in_a_small_component_by_its_own_spread() {
        let n = Normaliser::capped(pca(vec![400.0, 4.0]), 0.5);
        let r = (202.0f64).sqrt();
        // The large component keeps the common scale; the small one its own spread, 2.
        assert!(
            (n.std[0] - r).abs() < 1e-12 && (n.std[1] - 2.0).abs() < 1e-12,
            "{:?}",
            n.std
        );
        let moved =
            |n: &Normaliser, c: [f32; 2]| n.decode(&c).iter().map(|v| v * v).sum::<f64>().sqrt();
        // A denoising error of 0.1 normalised units in the small component: 0.4 m capped,
        // 2.8 m with the common scale.
        let common = Normaliser::new(pca(vec![400.0, 4.0]), 0.5);
        assert!((moved(&n, [0.0, 0.1]) - 0.4).abs() < 1e-6);
        assert!((moved(&common, [0.0, 0.1]) - 0.1 * r / 0.5).abs() < 1e-5);
        assert_eq!(moved(&n, [0.1, 0.0]), moved(&common, [0.1, 0.0]));
        // The loss stays in the common scale's units, and a component without variance keeps
        // a finite scale.
        assert!((n.loss_scale() - r).abs() < 1e-12);
        let z = Normaliser::capped(pca(vec![400.0, 0.0]), 0.5);
        assert!(z.std[1] > 0.0 && z.std[1] < 1e-1, "{:?}", z.std);
        let c = n.encode(&n.decode(&[0.3, -1.2]));
        assert!(
            (c[0] - 0.3).abs() < 1e-6 && (c[1] + 1.2).abs() < 1e-6,
            "{c:?}"
        );
        assert_eq!(
            Normaliser::with_scale(pca(vec![400.0, 4.0]), 0.5, ComponentScale::Capped, 1.0),
            n
        );
        // A quarter cap gives the large component a quarter of the common scale's metres per
        // unit, and leaves the small one, below that cap, alone.
        let q = Normaliser::capped_at(pca(vec![400.0, 4.0]), 0.5, 0.25);
        assert!(
            (q.std[0] - r / 4.0).abs() < 1e-12 && (q.std[1] - 2.0).abs() < 1e-12,
            "{:?}",
            q.std
        );
        assert!((moved(&q, [0.1, 0.0]) * 4.0 - moved(&n, [0.1, 0.0])).abs() < 1e-5);
        assert!((q.loss_scale() - r).abs() < 1e-12);
    }
}
