//! The denoiser `D_θ(x; m, σ)`: MiniPointNet lanes refined by lane-lane attention (encoded once
//! per scene), agents encoded from their history, noisy PCA coefficients and the noise level,
//! then alternating agent-lane and agent-agent attention, and a head back to PCA coefficients,
//! all under EDM preconditioning.

use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};

use super::attention::{Pairs, RelAttention, Scores};
use super::edm::Edm;
use super::encoder::{noise_features, AgentEncoder, MiniPointNet};
use super::ops::{linear, Linear};
use super::route::{route_features, RouteInputs, FEATURES_PER_TIME};

/// Sizes of the network.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DenoiserConfig {
    /// Feature width.
    pub d: usize,
    /// Attention layers per module (lane-lane, agent-lane, agent-agent).
    pub layers: usize,
    /// PCA components per agent.
    pub k: usize,
    /// History steps fed to the agent encoder.
    pub history: usize,
    /// Fourier frequencies of the noise embedding.
    pub noise_freqs: usize,
    /// How attention scores are formed; configs written before this field existed mean
    /// [`Scores::Raw`].
    #[serde(default)]
    pub scores: Scores,
    /// Features per agent that say what it is (`train::dataset::AGENT_ATTRS`: type, static,
    /// size). 0, as in configs written before the field, feeds none: such a model has seen
    /// one kind of road user only.
    #[serde(default)]
    pub attrs: usize,
    /// Features of an agent-lane pair (`train::WindowConfig::agent_lane_features`): 4, as in
    /// configs written before the field, or 8 with the lane's nearest point's pose.
    #[serde(default = "four")]
    pub agent_lane_features: usize,
    /// Future times at which each agent's noisy future is measured against the lanes
    /// ([`super::route`], `train::WindowConfig::route_times`); 0, as in configs written before
    /// the field, for none.
    #[serde(default)]
    pub route_times: usize,
    /// Whether each agent's end point, where given, is an input ([`Context::agent_goal`];
    /// `train::WindowConfig::goals`); false in configs written before the field.
    #[serde(default)]
    pub goals: bool,
    /// Whether futures are told against each agent's lane route and the route is an input
    /// ([`Context::agent_route`]; `train::WindowConfig::route_frame`); false in configs written
    /// before the field.
    #[serde(default)]
    pub route_frame: bool,
}

/// Features of an agent's route ([`Context::agent_route`]): `(x, y)` of each of
/// [`crate::scene::routes::AHEAD_POINTS`] points.
pub const ROUTE_FEATURES: usize = 2 * crate::scene::routes::AHEAD_POINTS;

/// Features of an agent's end point ([`Context::agent_goal`]): its position in the agent's
/// frame (÷ 50 m), the heading change to it (sin, cos), when it is reached (as a fraction of
/// the future) and 1 where it is given (all 0 where it is not).
pub const GOAL_FEATURES: usize = 6;

fn four() -> usize {
    4
}

/// Tensors describing the map and the agents of a batch of windows (see `train::batch`).
#[derive(Debug, Clone)]
pub struct Context {
    /// Lane points in each lane's own frame, `[B, M, P, 2]`.
    pub lane_points: Tensor,
    /// 1 for lanes present, `[B, M]`.
    pub lane_mask: Tensor,
    /// Lane j's pose in lane i's frame, `[B, M, M, 4]`.
    pub lane_rel: Tensor,
    /// Lane connectivity kinds, `[B, M, M]` (u32).
    pub lane_conn: Tensor,
    /// History features per agent, `[B, N, history·4]`.
    pub agent_hist: Tensor,
    /// 1 for agents present, `[B, N]`.
    pub agent_mask: Tensor,
    /// Lane j's pose in agent i's frame, `[B, N, M, 4]`, and with
    /// `WindowConfig::nearest_lane_pose` the pose of its point nearest to agent i, `[B, N, M, 8]`.
    pub agent_lane_rel: Tensor,
    /// Agent j's pose in agent i's frame, `[B, N, N, 4]`.
    pub agent_rel: Tensor,
    /// What each agent is, `[B, N, A]` (`train::dataset::agent_attributes`); a model reads the
    /// first [`DenoiserConfig::attrs`] of them.
    pub agent_attr: Tensor,
    /// What route features are measured with; present when the window configuration asks
    /// for them (`train::WindowConfig::route_times`).
    pub route: Option<RouteInputs>,
    /// Each agent's end point where it is given, `[B, N, GOAL_FEATURES]`; present when the
    /// window configuration asks for it (`train::WindowConfig::goals`).
    pub agent_goal: Option<Tensor>,
    /// Each agent's route ahead ([`crate::scene::routes::route_ahead`]) in its own frame,
    /// ÷ 50 m, `[B, N, ROUTE_FEATURES]` (zeros for an agent without one); present when the
    /// window configuration tells futures against routes (`train::WindowConfig::route_frame`).
    pub agent_route: Option<Tensor>,
}

impl Context {
    /// The same context with its float tensors in `dtype` (f64 for gradient checks).
    pub fn to_dtype(&self, dtype: candle_core::DType) -> Result<Self> {
        Ok(Self {
            lane_points: self.lane_points.to_dtype(dtype)?,
            lane_mask: self.lane_mask.to_dtype(dtype)?,
            lane_rel: self.lane_rel.to_dtype(dtype)?,
            lane_conn: self.lane_conn.clone(),
            agent_hist: self.agent_hist.to_dtype(dtype)?,
            agent_mask: self.agent_mask.to_dtype(dtype)?,
            agent_lane_rel: self.agent_lane_rel.to_dtype(dtype)?,
            agent_rel: self.agent_rel.to_dtype(dtype)?,
            agent_attr: self.agent_attr.to_dtype(dtype)?,
            route: self.route.as_ref().map(|r| r.to_dtype(dtype)).transpose()?,
            agent_goal: self
                .agent_goal
                .as_ref()
                .map(|g| g.to_dtype(dtype))
                .transpose()?,
            agent_route: self
                .agent_route
                .as_ref()
                .map(|g| g.to_dtype(dtype))
                .transpose()?,
        })
    }
}

/// A scene's encoding ([`Denoiser::encode_scene`]).
#[derive(Debug, Clone)]
pub struct SceneEncoding {
    lanes: Tensor,
    agent_lane: Vec<Pairs>,
    agent_agent: Vec<Pairs>,
}

impl SceneEncoding {
    /// Every tensor of the encoding.
    pub fn tensors(&self) -> Vec<&Tensor> {
        let pairs = self.agent_lane.iter().chain(&self.agent_agent);
        std::iter::once(&self.lanes)
            .chain(pairs.flat_map(|p| p.tensors()))
            .collect()
    }
}

/// The denoiser network.
#[derive(Debug, Clone)]
pub struct Denoiser {
    cfg: DenoiserConfig,
    lanes: MiniPointNet,
    lane_lane: Vec<RelAttention>,
    agents: AgentEncoder,
    agent_lane: Vec<RelAttention>,
    agent_agent: Vec<RelAttention>,
    head1: Linear,
    head2: Linear,
    edm: Edm,
}

impl Denoiser {
    /// Builds the network's variables under `vb`.
    pub fn new(cfg: DenoiserConfig, edm: Edm, vb: VarBuilder) -> Result<Self> {
        let d = cfg.d;
        let stack = |name: &str, rel: usize, conn: bool| -> Result<Vec<RelAttention>> {
            (0..cfg.layers)
                .map(|i| RelAttention::new(d, rel, cfg.scores, conn, vb.pp(format!("{name}{i}"))))
                .collect()
        };
        Ok(Self {
            lanes: MiniPointNet::new(d, vb.pp("lanes"))?,
            lane_lane: stack("lane_lane", 4, true)?,
            agents: AgentEncoder::new(
                cfg.history * 4
                    + cfg.attrs
                    + cfg.k
                    + 2 * cfg.noise_freqs
                    + FEATURES_PER_TIME * cfg.route_times
                    + if cfg.goals { GOAL_FEATURES } else { 0 }
                    + if cfg.route_frame { ROUTE_FEATURES } else { 0 },
                d,
                vb.pp("agents"),
            )?,
            agent_lane: stack("agent_lane", cfg.agent_lane_features, false)?,
            agent_agent: stack("agent_agent", 4, false)?,
            head1: linear(d, d, vb.pp("head1"))?,
            head2: linear(d, cfg.k, vb.pp("head2"))?,
            cfg,
            edm,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &DenoiserConfig {
        &self.cfg
    }

    /// What depends on the scene alone, so that a sampler computes it once: the lane features
    /// after lane-lane attention and the agent-lane and agent-agent pair features of every
    /// layer (agents' current poses do not change while their futures are sampled).
    pub fn encode_scene(&self, ctx: &Context) -> Result<SceneEncoding> {
        let mut x = self.lanes.forward(&ctx.lane_points)?;
        for l in &self.lane_lane {
            let pairs = l.pairs(&ctx.lane_rel, Some(&ctx.lane_conn))?;
            x = l.forward(&x, &x, &pairs, &ctx.lane_mask)?;
        }
        Ok(SceneEncoding {
            lanes: x,
            agent_lane: self
                .agent_lane
                .iter()
                .map(|l| l.pairs(&ctx.agent_lane_rel, None))
                .collect::<Result<_>>()?,
            agent_agent: self
                .agent_agent
                .iter()
                .map(|l| l.pairs(&ctx.agent_rel, None))
                .collect::<Result<_>>()?,
        })
    }

    /// `D(x; σ)` for noisy coefficients `x` `[B, N, K]` and noise levels `sigma` (one per
    /// window), given the scene's encoding.
    pub fn denoise(
        &self,
        ctx: &Context,
        enc: &SceneEncoding,
        x: &Tensor,
        sigma: &[f64],
    ) -> Result<Tensor> {
        let (dev, dt) = (x.device(), x.dtype());
        let b = sigma.len();
        let pre: Vec<(f64, f64, f64, f64)> =
            sigma.iter().map(|s| self.edm.precondition(*s)).collect();
        let col = |f: fn(&(f64, f64, f64, f64)) -> f64| -> Result<Tensor> {
            Tensor::from_vec(
                pre.iter().map(|p| f(p) as f32).collect::<Vec<_>>(),
                (b, 1, 1),
                dev,
            )?
            .to_dtype(dt)
        };
        let (c_skip, c_out, c_in) = (col(|p| p.0)?, col(|p| p.1)?, col(|p| p.2)?);
        let c_noise = Tensor::from_vec(pre.iter().map(|p| p.3 as f32).collect::<Vec<_>>(), b, dev)?
            .to_dtype(dt)?;
        let n = x.dim(1)?;
        let noise = noise_features(&c_noise, self.cfg.noise_freqs)?
            .unsqueeze(1)?
            .repeat((1, n, 1))?;
        let mut parts = vec![ctx.agent_hist.clone()];
        if self.cfg.attrs > 0 {
            parts.push(ctx.agent_attr.narrow(2, 0, self.cfg.attrs)?);
        }
        parts.extend([x.broadcast_mul(&c_in)?, noise]);
        if self.cfg.route_times > 0 {
            let route = ctx.route.as_ref().ok_or_else(|| {
                candle_core::Error::Msg(format!(
                    "the model measures futures against the lanes at {} times, but the batch \
                     has no route inputs (window.route_times = 0)",
                    self.cfg.route_times
                ))
            })?;
            if route.basis.dim(1)? != 3 * self.cfg.route_times {
                candle_core::bail!(
                    "the model measures futures against the lanes at {} times, the batch at {}",
                    self.cfg.route_times,
                    route.basis.dim(1)? / 3
                );
            }
            parts.push(route_features(x, route)?);
        }
        if self.cfg.goals {
            let goal = ctx.agent_goal.as_ref().ok_or_else(|| {
                candle_core::Error::Msg(
                    "the model reads agents' end points, but the batch has none \
                     (window.goals = false)"
                        .into(),
                )
            })?;
            parts.push(goal.clone());
        }
        if self.cfg.route_frame {
            let route = ctx.agent_route.as_ref().ok_or_else(|| {
                candle_core::Error::Msg(
                    "the model tells futures against lane routes, but the batch has no routes \
                     (window.route_frame = false)"
                        .into(),
                )
            })?;
            parts.push(route.clone());
        }
        let feats = Tensor::cat(&parts, 2)?;
        let mut a = self.agents.forward(&feats)?;
        let layers = self.agent_lane.iter().zip(&self.agent_agent);
        for ((al, aa), (pl, pa)) in layers.zip(enc.agent_lane.iter().zip(&enc.agent_agent)) {
            a = al.forward(&a, &enc.lanes, pl, &ctx.lane_mask)?;
            a = aa.forward(&a, &a, pa, &ctx.agent_mask)?;
        }
        let f = self.head2.forward(&self.head1.forward(&a)?.relu()?)?;
        x.broadcast_mul(&c_skip)? + f.broadcast_mul(&c_out)?
    }
}
