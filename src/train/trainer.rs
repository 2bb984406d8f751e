//! The EDM training loop: windows from scenes, a held-out validation split, AdamW, and
//! checkpoints as safetensors plus a JSON config.

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor, Var, D};
use candle_nn::{VarBuilder, VarMap};
use serde::{Deserialize, Serialize};

use super::adamw::AdamW;
use super::batch::{build, ComponentScale, Goals, Normaliser};
use super::dataset::{within, Window, WindowConfig, AGENT_ATTRS};
use super::ema::Ema;
use super::rng::Rng;
use super::store::{SceneWindows, WindowSource};
use crate::model::error::{message as candle_message, message_in_file};
use crate::model::{Denoiser, DenoiserConfig, Edm, Pca, Scores};
use crate::scene::{AgentType, Scene};

/// The share of agents whose end point a training batch gives a model that reads them: half,
/// so that it learns futures with and without one (conditional and unconditional simulation).
const GOAL_KEEP: f64 = 0.5;

/// Everything a training run is configured by.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Optimiser steps.
    pub steps: usize,
    /// Windows per batch.
    pub batch: usize,
    /// Learning rate.
    pub lr: f64,
    /// Seed of initialisation, split-independent sampling, noise and augmentation.
    pub seed: u64,
    /// Window sizes.
    pub window: WindowConfig,
    /// Network sizes (its `k` and `history` follow `pca_k` and `window.history`).
    pub model: DenoiserConfig,
    /// EDM hyper-parameters.
    pub edm: Edm,
    /// Validation every this many steps.
    pub eval_every: usize,
    /// Which tenth of the scenes is held out ([`is_validation`]); models trained on different
    /// folds cross-validate each other. Checkpoints from before the option held out fold 0.
    #[serde(default)]
    pub val_fold: u64,
    /// Towns or cities held out besides those of the fold, in corpora split by town
    /// ([`crate::train::SplitBy::Town`]): a place with recordings long enough to validate
    /// the full horizon, say.
    #[serde(default)]
    pub val_towns: Vec<String>,
    /// Half-life, in steps, of the moving average of the weights that the checkpoint samples
    /// with ([`Ema`]); 0 samples with the last step's weights, as checkpoints from before the
    /// option did.
    #[serde(default)]
    pub ema_half_life: f64,
    /// How a new run scales the PCA components ([`ComponentScale`]); a resumed run keeps its
    /// checkpoint's scales. Checkpoints from before the option have one common scale.
    #[serde(default)]
    pub component_scale: ComponentScale,
    /// The cap of [`ComponentScale::Capped`] as a fraction of the common scale, in (0, 1]
    /// ([`Normaliser::capped_at`]); checkpoints from before the option capped at 1.
    #[serde(default = "one")]
    pub scale_cap: f64,
    /// Weight of the part of the training loss's position error across the recorded path,
    /// relative to the rest (1: the plain error; checkpoints from before the option). Over
    /// 8 s where a car is along its path is uncertain by metres and where it is across its
    /// lane by decimetres, so a plain error is mostly the along part, and networks trained on
    /// it left a lane by a metre from the recorded future with little noise.
    #[serde(default = "one")]
    pub across_weight: f64,
}

fn one() -> f64 {
    1.0
}

impl TrainConfig {
    /// Defaults for the NGSIM corpus on a CPU.
    pub fn ngsim() -> Self {
        let window = WindowConfig::ngsim();
        Self {
            steps: 2000,
            batch: 8,
            lr: 3e-4,
            seed: 1,
            window,
            model: DenoiserConfig {
                d: 64,
                layers: 3,
                k: 12,
                history: window.history,
                noise_freqs: 8,
                scores: Scores::Normalised,
                attrs: 0,
                agent_lane_features: 4,
                route_times: 0,
                goals: false,
                route_frame: false,
            },
            edm: Edm::default(),
            eval_every: 100,
            val_fold: 0,
            val_towns: Vec::new(),
            ema_half_life: 0.0,
            component_scale: ComponentScale::Common,
            scale_cap: 1.0,
            across_weight: 1.0,
        }
    }

    /// Defaults for highways and cities at the paper's horizon ([`WindowConfig::cities`]):
    /// the agent's type and size are inputs, and 8 s futures take 20 PCA components.
    pub fn cities() -> Self {
        let base = Self::ngsim();
        Self {
            window: WindowConfig::cities(),
            model: DenoiserConfig {
                k: 20,
                attrs: AGENT_ATTRS,
                ..base.model
            },
            ema_half_life: 500.0,
            component_scale: ComponentScale::Capped,
            ..base
        }
    }
}

/// Number of validation folds: each holds out about a tenth of the scenes.
pub const VAL_FOLDS: u64 = 10;

/// The validation fold of a scene: its id's hash mod [`VAL_FOLDS`]. The hash depends on the
/// id alone, so a scene stays in its fold whatever else the corpus holds.
pub fn val_fold(scenario_id: &str) -> u64 {
    // FNV-1a: stable across platforms and releases, unlike the std hasher.
    let h = scenario_id.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
    });
    h % VAL_FOLDS
}

/// Which scenes train and which validate: the scenes of fold `fold` ([`val_fold`]) validate.
pub fn is_validation(scenario_id: &str, fold: u64) -> bool {
    val_fold(scenario_id) == fold
}

/// Version of the checkpoint format. 2: futures are residuals to the constant-velocity
/// anchor ([`crate::train::Window::agent_residual`]); 1 (unmarked) held raw futures and would
/// decode wrongly.
pub const CHECKPOINT_VERSION: u32 = 2;

/// What a checkpoint's JSON holds besides the weights.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CheckpointMeta {
    /// [`CHECKPOINT_VERSION`] when written.
    #[serde(default)]
    pub version: u32,
    /// The training configuration.
    pub config: TrainConfig,
    /// PCA basis and normalisation.
    pub normaliser: Normaliser,
    /// Training scene ids.
    pub train_scenes: Vec<String>,
    /// Validation scene ids.
    pub val_scenes: Vec<String>,
    /// Steps taken.
    pub steps_done: usize,
    /// `(step, training loss averaged since the last validation, validation loss when there
    /// are validation scenes)`.
    pub history: Vec<(usize, f64, Option<f64>)>,
    /// Git revision of the code that trained it, when known.
    pub git_revision: Option<String>,
    /// PCA position RMSE on the training futures, metres.
    pub pca_rmse_m: f64,
    /// Agents with a future to learn from in the training windows, per type: the types the
    /// model moves ([`CheckpointMeta::models`]). Checkpoints written before the field were
    /// trained on NGSIM's vehicles alone.
    #[serde(default = "vehicles_only")]
    pub types: std::collections::BTreeMap<AgentType, usize>,
    /// Updates the moving average of the weights has had ([`TrainConfig::ema_half_life`]):
    /// a resumed run continues its warm-up.
    #[serde(default)]
    pub ema_updates: u64,
    /// The guidance strength λ of behaviour scripts chosen for these weights, on behaviour
    /// instances of towns they trained on (data/checkpoint/README.md); the default of
    /// `simulate --lambda`, `ask` and Python's `guidance` ([`CheckpointMeta::behaviour_lambda`]).
    /// How far one guidance step moves a car depends on the model's coefficient scales, so a
    /// strength that suits one checkpoint under-steers another: the route-frame model, whose
    /// scales follow urban traffic, made 0.81 of NGSIM cut-ins on its training scenes at
    /// λ = 3. Training writes none: new weights are tuned anew.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub guidance_lambda: Option<f64>,
}

fn vehicles_only() -> std::collections::BTreeMap<AgentType, usize> {
    [(AgentType::Vehicle, 1)].into_iter().collect()
}

impl CheckpointMeta {
    /// Whether the model moves `a`: a road user that is not static, of a type the model
    /// learnt from. Others keep to their log or their current velocity.
    pub fn models(&self, a: &crate::scene::Agent) -> bool {
        super::dataset::is_mover(a) && self.types.get(&a.agent_type).is_some_and(|n| *n > 0)
    }

    /// The guidance strength of behaviour scripts for these weights: [`Self::guidance_lambda`]
    /// where chosen, else [`crate::sample::BEHAVIOUR_LAMBDA`] (chosen for the shipped NGSIM
    /// checkpoint).
    pub fn behaviour_lambda(&self) -> f64 {
        self.guidance_lambda
            .unwrap_or(crate::sample::BEHAVIOUR_LAMBDA)
    }

    /// The types the model moves, in words: "vehicles", "vehicles and cyclists".
    pub fn seen_types(&self) -> String {
        let names: Vec<String> = self
            .types
            .iter()
            .filter(|(_, n)| **n > 0)
            .map(|(t, _)| format!("{}s", t.name()))
            .collect();
        match names.split_last() {
            None => "nothing".into(),
            Some((last, [])) => last.clone(),
            Some((last, rest)) => format!("{} and {last}", rest.join(", ")),
        }
    }
}

/// The range of the EDM noise levels (`sigma_data`, `sigma_min`, `sigma_max`) a checkpoint
/// may give: far around EDM's 0.002 to 80, within what the model's f32 arithmetic holds
/// after squaring.
pub const MIN_SIGMA: f64 = 1e-6;
/// See [`MIN_SIGMA`].
pub const MAX_SIGMA: f64 = 1e6;
/// The largest schedule exponent `rho`: EDM's is 7; the levels are raised to it.
pub const MAX_RHO: f64 = 1000.0;
/// The largest `edm.p_std`, the spread of ln σ training draws its noise levels from (EDM's is
/// 1.2): with `p_mean` within ln [`MIN_SIGMA`] to ln [`MAX_SIGMA`], six spreads either way stay
/// within what the loss weight 1/σ² and σ² hold in f32.
pub const MAX_P_STD: f64 = 4.0;
/// The most numbers the network may hold in one layer for the pairs of one window it attends
/// over (agent-lane, lane-lane, agent-agent) or for its lane points, `d` for each: 128 MB of
/// f32. The settings hold at most 262,144 (64 × 64 lanes × d 64), the paper's WOMD sizes
/// 2,560,000 (200 × 200 × 64).
pub const MAX_PAIR_VALUES: usize = 1 << 25;

/// The most numbers one layer of a training step holds for its whole batch: `batch` windows,
/// [`window_values`] each. A step keeps every layer's activations for the backward pass, about
/// 270 bytes for each such number (9.3 GB measured for a batch of 128 windows of the NGSIM
/// setting, 262,144 numbers each), so about 17 GB here: a batch of 256 of those windows, 26 of
/// the paper's WOMD sizes. `--batch 4096` (allowed) asked 290 GB and aborted on allocation,
/// exit 134, or took the machine's memory.
pub const MAX_TRAIN_BATCH_VALUES: usize = 1 << 26;

/// The numbers the network holds in one layer for one window of these sizes: `d` for each
/// pair it attends over (agent-lane, lane-lane, agent-agent) or lane point, the most of them.
pub fn window_values(w: &WindowConfig, m: &DenoiserConfig) -> usize {
    let (a, l) = (w.max_agents, w.max_lanes);
    [a * l, l * l, a * a, l * w.lane_points]
        .into_iter()
        .max()
        .unwrap_or(0)
        .saturating_mul(m.d)
}

/// The smallest learning rate a run takes: AdamW moves each weight by about this much a step,
/// and an f32 weight of order 0.1 keeps about 8 digits, so a smaller step is rounded away and
/// the run trains nothing.
pub const MIN_LR: f64 = 1e-8;

/// The longest half-life of the moving average of the weights, in steps: the most steps a
/// run takes (`steps` is at most 10^8).
pub const MAX_EMA_HALF_LIFE: f64 = 1e8;

/// `Ok` when `v` is positive and finite, else a message naming the setting.
fn positive(name: &str, v: f64) -> Result<(), String> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        // In a few characters: 1e308 was said in 309 digits.
        Err(format!(
            "{name} = {}: must be positive and finite",
            crate::geom::num(v)
        ))
    }
}

/// The `drivescript train` flag that sets each [`TrainConfig`] field a user can give, by the
/// field's name as [`TrainConfig::validate`] starts its message with it: the message names the
/// field ("eval_every = 0"), which the user never typed.
pub const TRAIN_FLAGS: [(&str, &str); 12] = [
    ("steps", "--steps"),
    ("edm.p_mean", "--p-mean"),
    ("edm.p_std", "--p-std"),
    ("batch", "--batch"),
    ("lr", "--lr"),
    ("eval_every", "--eval-every"),
    ("ema_half_life", "--ema-half-life"),
    ("scale_cap", "--scale-cap"),
    ("across_weight", "--across-weight"),
    ("val_towns", "--val-town"),
    // "window.route_times = 41: must be 0 to 40" named a setting the user never wrote.
    ("window.route_times", "--route-times"),
    ("window.route_frame", "--route-frame"),
];

/// The flag ([`TRAIN_FLAGS`]) that sets the setting a [`TrainConfig::validate`] message is
/// about, or `None` for a setting no flag gives (a checkpoint's sizes).
pub fn flag_of(message: &str) -> Option<&'static str> {
    let field = message.split([' ', ':']).next().unwrap_or_default();
    TRAIN_FLAGS
        .iter()
        .find(|(f, _)| *f == field)
        .map(|(_, flag)| *flag)
}

impl TrainConfig {
    /// Checks that a training step of these settings fits in memory ([`MAX_TRAIN_BATCH_VALUES`]);
    /// the message starts with `batch`, the field `--batch` sets ([`flag_of`]). Apart from
    /// [`TrainConfig::validate`]: a checkpoint another trainer wrote with a larger batch (the
    /// PyTorch port's, on a GPU) still samples.
    pub fn check_batch_memory(&self) -> Result<(), String> {
        let per = window_values(&self.window, &self.model).max(1);
        let values = self.batch.saturating_mul(per);
        if values <= MAX_TRAIN_BATCH_VALUES {
            return Ok(());
        }
        Err(format!(
            "batch = {}: {} windows × {per} numbers a layer for each (the most of agents × lanes, \
             lanes × lanes, agents × agents and lanes × points, times d) is {values}, past the \
             {MAX_TRAIN_BATCH_VALUES} a training step holds (about {} GB with what the backward \
             pass keeps); at most {} windows a batch with these sizes",
            self.batch,
            self.batch,
            (MAX_TRAIN_BATCH_VALUES as u64 * 270) >> 30,
            (MAX_TRAIN_BATCH_VALUES / per).max(1)
        ))
    }

    /// Checks that training can run with these settings, before any data is read: sizes within
    /// bounds (windows of 10^9 agents or 10^6 layers would abort on allocation), at least one
    /// step, and a learning rate and noise settings that are positive and finite (a NaN rate
    /// trained on NaN and wrote the checkpoint). The message names the field.
    pub fn validate(&self) -> Result<(), String> {
        let c = self;
        let (w, m, e) = (&c.window, &c.model, &c.edm);
        within("steps", c.steps, 1, 100_000_000)?;
        within("batch", c.batch, 1, 4096)?;
        if c.eval_every == 0 {
            return Err("eval_every = 0: must be at least 1".into());
        }
        // A checkpoint's config edited to fold 10 or more held out no scene at all (no id
        // hashes there) and trained on, validating on nothing, without a word.
        if c.val_fold >= VAL_FOLDS {
            return Err(format!(
                "val_fold = {}: must be 0 to {}",
                c.val_fold,
                VAL_FOLDS - 1
            ));
        }
        w.validate().map_err(|e| format!("window.{e}"))?;
        within("model.d", m.d, 1, 1024)?;
        within("model.layers", m.layers, 1, 32)?;
        within("model.k", m.k, 1, 3 * w.future)?;
        within("model.noise_freqs", m.noise_freqs, 1, 64)?;
        // Each within its range is not enough: the network holds d numbers for every pair of
        // a window it attends over and for every lane point, so 1024 agents, 2048 lanes and
        // d 64 (each allowed) asked 512 MB a layer to sample one window, and sampling or
        // training aborted on allocation (or took the machine's memory).
        let (a, l) = (w.max_agents, w.max_lanes);
        for (what, sizes) in [
            ("window.max_agents × window.max_lanes", [a, l]),
            ("window.max_lanes × window.max_lanes", [l, l]),
            ("window.max_agents × window.max_agents", [a, a]),
            ("window.max_lanes × window.lane_points", [l, w.lane_points]),
        ] {
            let values = sizes[0] * sizes[1] * m.d;
            if values > MAX_PAIR_VALUES {
                return Err(format!(
                    "{what} × model.d = {} × {} × {} = {values}: at most {MAX_PAIR_VALUES} (the \
                     network holds d numbers for each, {} MB a layer for one window); lower \
                     one of them",
                    sizes[0],
                    sizes[1],
                    m.d,
                    values * 4 >> 20
                ));
            }
        }
        if m.history != w.history {
            return Err(format!(
                "model.history = {} but window.history = {}: they must agree",
                m.history, w.history
            ));
        }
        if m.agent_lane_features != w.agent_lane_features() {
            return Err(format!(
                "model.agent_lane_features = {} but window.nearest_lane_pose = {} gives {}: they \
                 must agree",
                m.agent_lane_features,
                w.nearest_lane_pose,
                w.agent_lane_features()
            ));
        }
        if m.goals != w.goals {
            return Err(format!(
                "model.goals = {} but window.goals = {}: they must agree",
                m.goals, w.goals
            ));
        }
        if m.route_frame != w.route_frame {
            return Err(format!(
                "model.route_frame = {} but window.route_frame = {}: they must agree",
                m.route_frame, w.route_frame
            ));
        }
        if m.route_times != w.route_times {
            return Err(format!(
                "model.route_times = {} but window.route_times = {}: they must agree",
                m.route_times, w.route_times
            ));
        }
        positive("lr", c.lr)?;
        // Positive is not enough: `--lr 1e-300` was taken, and no step changed a weight. A
        // rate too large is let by: its first steps diverge, which training says, naming
        // --lr.
        if c.lr < MIN_LR {
            return Err(format!(
                "lr = {}: must be at least {} (AdamW's step in each weight; 3e-4 is the \
                 default): a smaller step is rounded away in the f32 weights",
                crate::geom::num(c.lr),
                crate::geom::num(MIN_LR)
            ));
        }
        // `--ema-half-life 1e308` was taken: an average that never moves from the first
        // weights, which the checkpoint then sampled with.
        if !(c.ema_half_life.is_finite()
            && c.ema_half_life >= 0.0
            && c.ema_half_life <= MAX_EMA_HALF_LIFE)
        {
            return Err(format!(
                "ema_half_life = {}: must be 0 (no average) or a positive number of steps, at \
                 most {} (the most steps a run takes)",
                crate::geom::num(c.ema_half_life),
                crate::geom::num(MAX_EMA_HALF_LIFE)
            ));
        }
        if !(c.scale_cap > 0.0 && c.scale_cap <= 1.0) {
            return Err(format!(
                "scale_cap = {}: must be in (0, 1], a fraction of the common scale",
                c.scale_cap
            ));
        }
        if !(c.across_weight.is_finite() && (1.0..=1000.0).contains(&c.across_weight)) {
            return Err(format!(
                "across_weight = {}: must be 1 (the plain error) to 1000",
                c.across_weight
            ));
        }
        positive("edm.sigma_data", e.sigma_data)?;
        positive("edm.sigma_min", e.sigma_min)?;
        positive("edm.sigma_max", e.sigma_max)?;
        positive("edm.rho", e.rho)?;
        positive("edm.p_std", e.p_std)?;
        if !e.p_mean.is_finite() {
            return Err(format!("edm.p_mean = {}: must be finite", e.p_mean));
        }
        // Finite is not enough: a P_mean of 700 or -50 (or a P_std of 50) drew noise levels
        // whose square or loss weight is past f32, and the run stopped at its first step with
        // "training loss is NaN ... (lower --lr)", blaming a flag the user had not given.
        let (lo, hi) = (MIN_SIGMA.ln(), MAX_SIGMA.ln());
        if !(lo..=hi).contains(&e.p_mean) {
            return Err(format!(
                "edm.p_mean = {}: must be {lo:.1} to {hi:.1} (ln of the median training noise \
                 level, which must lie within {MIN_SIGMA:e} to {MAX_SIGMA:e}; EDM's is -1.2)",
                crate::geom::num(e.p_mean)
            ));
        }
        if e.p_std > MAX_P_STD {
            return Err(format!(
                "edm.p_std = {}: must be at most {MAX_P_STD} (the spread of ln σ; EDM's is 1.2)",
                crate::geom::num(e.p_std)
            ));
        }
        // Positive is not enough: a σ_min of 1e-320 (below what the model's f32 holds) or a
        // σ_max of 1e308 passed, and sampling ended in "non-finite sample at sampling step
        // 32", naming no file or field. EDM's levels are 0.002 to 80 around σ_data 0.5.
        for (name, v) in [
            ("edm.sigma_data", e.sigma_data),
            ("edm.sigma_min", e.sigma_min),
            ("edm.sigma_max", e.sigma_max),
        ] {
            if !(MIN_SIGMA..=MAX_SIGMA).contains(&v) {
                return Err(format!(
                    "{name} = {}: must be {MIN_SIGMA:e} to {MAX_SIGMA:e} (a noise level in the \
                     data's units; EDM's run from 0.002 to 80)",
                    crate::geom::num(v)
                ));
            }
        }
        if e.rho > MAX_RHO {
            return Err(format!(
                "edm.rho = {}: must be at most {MAX_RHO} (EDM's is 7)",
                crate::geom::num(e.rho)
            ));
        }
        if e.sigma_min >= e.sigma_max {
            return Err(format!(
                "edm.sigma_min = {} is not below sigma_max = {}",
                e.sigma_min, e.sigma_max
            ));
        }
        // A town is the start of a scenario id (`store::town`), which names output files: no
        // longer than one, and quoted cut where it is not.
        for t in &c.val_towns {
            let bad = |why: String| {
                Err(format!(
                    "val_towns: \"{}\" {why}",
                    crate::io::name::shown_counted(t)
                ))
            };
            if t.is_empty() || t.len() > 200 {
                return bad(format!(
                    "is {} bytes long: a town (a scenario id's part before its first `-`) is 1 \
                     to 200",
                    t.len()
                ));
            }
            if let Err(ch) = crate::io::name::check_name(t) {
                return bad(format!("holds {ch}"));
            }
        }
        Ok(())
    }
}

impl CheckpointMeta {
    /// Checks that the configuration can be built and sampled from: sizes within bounds (a
    /// model of `layers` 10^6 or windows of 10^9 agents would abort on allocation), noise
    /// settings positive and finite, and a PCA basis of the right shape with finite,
    /// unit-length components and positive scales. A checkpoint is shared data: without this, a
    /// zero standard deviation or ρ = 0 sampled garbage with exit 0, and a basis one value
    /// short panicked. The message names the field.
    pub fn validate(&self) -> Result<(), String> {
        let c = &self.config;
        c.validate().map_err(|e| format!("config.{e}"))?;
        let (w, m) = (&c.window, &c.model);
        let n = &self.normaliser;
        positive("normaliser.sigma_data", n.sigma_data)?;
        let (pca, dim, k) = (&n.pca, 3 * w.future, m.k);
        let len = |name: &str, got: usize, want: usize| {
            if got == want {
                Ok(())
            } else {
                Err(format!(
                    "{name} has {got} values; config (k = {k}, {dim} future coordinates) needs {want}"
                ))
            }
        };
        if pca.dim != dim {
            return Err(format!(
                "normaliser.pca.dim = {}: config.window.future = {} needs {dim}",
                pca.dim, w.future
            ));
        }
        len("normaliser.pca.mean", pca.mean.len(), dim)?;
        len("normaliser.pca.components", pca.components.len(), k * dim)?;
        len("normaliser.pca.variances", pca.variances.len(), k)?;
        len("normaliser.std", n.std.len(), k)?;
        if let Some(i) = pca.mean.iter().position(|v| !v.is_finite()) {
            return Err(format!("normaliser.pca.mean[{i}] is not finite"));
        }
        // Finite is not enough: the basis is in metres, and a mean of 1e308 (or a scale that
        // large) overflowed in the first denoising step, reported only as a non-finite cost
        // gradient with no word of the checkpoint.
        let max = crate::geom::MAX_COORD;
        if let Some(i) = pca.mean.iter().position(|v| v.abs() > max) {
            return Err(format!(
                "normaliser.pca.mean[{i}] = {}: beyond {max:e} m, which no future offset is",
                crate::geom::num(pca.mean[i])
            ));
        }
        if let Some(i) = n.std.iter().position(|v| *v > max) {
            return Err(format!(
                "normaliser.std[{i}] = {}: beyond {max:e} m, which no coefficient's spread is",
                crate::geom::num(n.std[i])
            ));
        }
        for (i, row) in pca.components.chunks(dim).enumerate() {
            let norm = row.iter().map(|v| v * v).sum::<f64>().sqrt();
            if !(norm - 1.0).abs().lt(&1e-3) {
                return Err(format!(
                    "normaliser.pca.components row {i} has length {norm}: components must be unit vectors"
                ));
            }
        }
        for (i, v) in n.std.iter().enumerate() {
            positive(&format!("normaliser.std[{i}]"), *v)?;
        }
        if let Some(i) = pca
            .variances
            .iter()
            .position(|v| !v.is_finite() || *v < 0.0 || *v > max * max)
        {
            return Err(format!(
                "normaliser.pca.variances[{i}] = {}: must be finite, not negative and at most \
                 {:e} m²",
                crate::geom::num(pca.variances[i]),
                max * max
            ));
        }
        if let Some(l) = self.guidance_lambda {
            let max = crate::sample::MAX_WEIGHT;
            if !(l.is_finite() && l > 0.0 && l <= max) {
                return Err(format!(
                    "guidance_lambda = {}: must be above 0 and at most {max}",
                    crate::geom::num(l)
                ));
            }
        }
        // The average is updated once a step at most: more updates than steps is no count a
        // run wrote, and a resumed run took it for its warm-up without a word.
        if self.ema_updates > self.steps_done as u64 {
            return Err(format!(
                "ema_updates = {}: more than the {} steps the weights were trained (the moving \
                 average is updated once a step)",
                self.ema_updates, self.steps_done
            ));
        }
        Ok(())
    }
}

/// Errors of a training run.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// Not enough data.
    #[error("{0}")]
    Data(String),
    /// Settings training cannot run with ([`TrainConfig::validate`]).
    #[error("training settings: {0}")]
    Config(String),
    /// The tensor library failed (its message without candle's backtrace).
    #[error("model: {0}")]
    Candle(candle_core::Error),
    /// Fitting PCA failed.
    #[error("PCA: {0}")]
    Pca(#[from] crate::model::PcaError),
    /// The loss stopped being a number: training stops before the step is applied and
    /// before anything is written, so the last checkpoint stays good.
    #[error("{which} loss is {value} at step {step}: training diverged (lower --lr); {kept}")]
    Diverged {
        /// `training` or `validation`.
        which: &'static str,
        /// The step.
        step: usize,
        /// The loss.
        value: f64,
        /// What of the run is left ([`kept`]).
        kept: String,
    },
    /// A step made a weight stop being a number (a learning rate of 1e300 does it in one):
    /// found before the checkpoint is written, which every reader would refuse.
    #[error(
        "step {step}: tensor `{tensor}` holds {value}: training diverged (lower --lr); {kept}"
    )]
    DivergedWeights {
        /// What of the run is left ([`kept`]).
        kept: String,
        /// The step.
        step: usize,
        /// The first tensor (by name) holding a value that is not a number.
        tensor: String,
        /// That value.
        value: f64,
    },
    /// Reading or writing the checkpoint failed.
    #[error("{path}: {message}")]
    Io {
        /// The file.
        path: String,
        /// What went wrong.
        message: String,
    },
}

impl From<candle_core::Error> for TrainError {
    fn from(e: candle_core::Error) -> Self {
        TrainError::Candle(crate::model::error::without_backtrace(e))
    }
}

/// Overwrites every variable with seeded values: candle's own initialisers are not seedable.
/// Weights ~ N(0, 1/fan_in), embeddings ~ N(0, 1/d), layer-norm gains 1 (norms are named
/// `ln…`; a gain left at 0 would silence its block, which the every-parameter test catches),
/// biases 0, the output layer 0.
fn seeded_init(varmap: &VarMap, rng: &mut Rng) -> candle_core::Result<()> {
    let data = varmap
        .data()
        .lock()
        .expect("the var map lock is not poisoned");
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    for name in names {
        let var: &Var = &data[name];
        let dims = var.dims().to_vec();
        let n: usize = dims.iter().product();
        // The output layer starts at zero, so the first denoiser is D = c_skip·x and the loss
        // starts near 1 instead of in the hundreds (random heads throw the early steps around).
        let vals: Vec<f32> = if name.starts_with("head2.") {
            vec![0.0; n]
        } else if dims.len() == 1 {
            let one = name.contains(".ln") && name.ends_with("weight");
            vec![if one { 1.0 } else { 0.0 }; n]
        } else {
            let scale = 1.0 / (dims[dims.len() - 1] as f64).sqrt();
            (0..n).map(|_| (rng.normal() * scale) as f32).collect()
        };
        var.set(&Tensor::from_vec(vals, dims.as_slice(), var.device())?)?;
    }
    Ok(())
}

/// The weighted EDM loss of a batch for given noise levels and noise, the position error
/// across each recorded path weighted `across_weight` times the rest.
pub(crate) fn loss(
    model: &Denoiser,
    edm: &Edm,
    b: &super::Batch,
    sigma: &[f64],
    noise: &Tensor,
    across_weight: f64,
) -> candle_core::Result<Tensor> {
    let dev = noise.device();
    let bsz = sigma.len();
    let dt = noise.dtype();
    let s = Tensor::from_vec(
        sigma.iter().map(|x| *x as f32).collect::<Vec<_>>(),
        (bsz, 1, 1),
        dev,
    )?
    .to_dtype(dt)?;
    let x = (&b.target + noise.broadcast_mul(&s)?)?;
    let enc = model.encode_scene(&b.ctx)?;
    let d = model.denoise(&b.ctx, &enc, &x, sigma)?;
    let (_, n, k) = b.target.dims3()?;
    let dim = b.seen.dim(2)?;
    // The error is taken over the future's observed coordinates, through the loss basis
    // (orthonormal components times their scales): for a future observed throughout this is
    // the coefficients' error weighted by how far each moves the trajectory, and a future cut
    // short by the recording teaches only what it shows.
    let traj = (d - &b.target)?
        .reshape((bsz * n, k))?
        .matmul(&b.basis.to_dtype(dt)?)?
        .reshape((bsz, n, dim))?;
    let mut err = (traj.sqr()?.mul(&b.seen.to_dtype(dt)?)?.sum(D::Minus1)? / k as f64)?; // [B, N]
    if across_weight != 1.0 {
        // The across part is already in the plain error once: it is added (w - 1) times more.
        let steps = dim / 3;
        let across = traj
            .mul(&b.normals.to_dtype(dt)?)?
            .reshape((bsz, n, steps, 3))?
            .sum(D::Minus1)?;
        let extra = (across.sqr()?.sum(D::Minus1)? * ((across_weight - 1.0) / k as f64))?;
        err = (err + extra)?;
    }
    let w = Tensor::from_vec(
        sigma
            .iter()
            .map(|x| edm.loss_weight(*x) as f32)
            .collect::<Vec<_>>(),
        (bsz, 1),
        dev,
    )?
    .to_dtype(dt)?;
    let masked = err.broadcast_mul(&w)?.mul(&b.loss_mask)?;
    let known = b
        .loss_mask
        .to_dtype(DType::F64)?
        .sum_all()?
        .to_scalar::<f64>()?;
    masked.sum_all()? / known.max(1.0)
}

/// A trained model and its metadata.
pub struct Trained {
    /// The checkpoint it was read from ([`load`]); `None` for a network trained in memory.
    pub origin: Option<CheckpointOrigin>,
    /// Weights.
    pub varmap: VarMap,
    /// The network.
    pub model: Denoiser,
    /// Metadata.
    pub meta: CheckpointMeta,
    /// The optimiser's state when the checkpoint has one (`optimizer.safetensors`), for an
    /// exact `--resume`.
    pub optimizer: Option<AdamW>,
    /// The moving average of the weights, when training keeps one: then `varmap` holds the
    /// weights training continues from ([`ONLINE_FILE`]) and the average is what samples.
    pub ema: Option<Ema>,
}

/// Where a checkpoint was read from, and a checksum of what it samples with: `ask --resume`
/// refuses to go on with another model than the run's.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct CheckpointOrigin {
    /// The checkpoint directory, absolute where it could be made so.
    pub dir: PathBuf,
    /// CRC-32C of `config.json` followed by `model.safetensors`.
    pub crc32c: u32,
}

impl Trained {
    /// The network with its weights as constants rather than variables: what sampling uses.
    /// A backward pass through it (guidance through the denoiser) then reaches only its input,
    /// not the 400,000 weights nor the map encoding. The weights share storage with
    /// [`Trained::varmap`], so nothing is copied.
    pub fn frozen(&self) -> candle_core::Result<Denoiser> {
        let vb = VarBuilder::from_tensors(self.detached_weights(), DType::F32, &Device::Cpu);
        Denoiser::new(self.meta.config.model, self.meta.config.edm, vb)
    }

    /// The weights sampling uses, by name: the moving average when training keeps one, else
    /// every variable detached (same storage).
    pub(crate) fn detached_weights(&self) -> std::collections::HashMap<String, Tensor> {
        if let Some(e) = &self.ema {
            return e.weights().clone();
        }
        let data = self
            .varmap
            .data()
            .lock()
            .expect("the var map lock is not poisoned");
        data.iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().detach()))
            .collect()
    }
}

/// Learning rate at `step` (1-based) of `total`: linear warm-up over the first 2 % of steps
/// (at most 200), then cosine decay to a tenth of `lr`. Warm-up keeps AdamW's first, noisy
/// moment estimates from throwing the fresh network around; the decay lets the last steps
/// settle instead of bouncing at the full rate.
pub fn learning_rate(lr: f64, step: usize, total: usize) -> f64 {
    let warm = (total / 50).clamp(1, 200);
    if step <= warm {
        return lr * step as f64 / warm as f64;
    }
    let t = (step - warm) as f64 / (total.saturating_sub(warm)).max(1) as f64;
    let floor = 0.1 * lr;
    floor + (lr - floor) * 0.5 * (1.0 + (std::f64::consts::PI * t.min(1.0)).cos())
}

/// Trains on `scenes`, calling `progress(step, loss, val)` after every step (val only when
/// evaluated). Writes the checkpoint to `out` (when given) at every validation and at the end.
pub fn train(
    scenes: &[Scene],
    cfg: TrainConfig,
    out: Option<&Path>,
    git_revision: Option<String>,
    progress: impl FnMut(usize, f64, Option<f64>),
) -> Result<Trained, TrainError> {
    cfg.validate().map_err(TrainError::Config)?;
    let source = SceneWindows::new(scenes, &cfg.window, cfg.val_fold);
    train_from(&source, cfg, None, out, git_revision, progress)
}

/// [`train`], continuing from `resume` when given: its weights, PCA basis, normalisation,
/// split, history, step count and optimiser state are kept, and training runs on from its
/// `steps_done + 1` to `cfg.steps` (a total, not a number of extra steps) with `cfg`'s batch,
/// rate and validation interval. Each step draws its batch, noise and augmentation from a
/// stream seeded by the seed and the step number, so a resumed run with the same settings is
/// identical to an uninterrupted one. A checkpoint without optimiser state (the shipped one,
/// or one from before it was saved) restarts AdamW's moments.
pub fn train_from(
    source: &dyn WindowSource,
    mut cfg: TrainConfig,
    resume: Option<Trained>,
    out: Option<&Path>,
    git_revision: Option<String>,
    mut progress: impl FnMut(usize, f64, Option<f64>),
) -> Result<Trained, TrainError> {
    let dev = Device::Cpu;
    if let Some(r) = &resume {
        let c = &r.meta.config;
        cfg.window = c.window;
        cfg.model = c.model;
        cfg.edm = c.edm;
        cfg.seed = c.seed;
        cfg.component_scale = c.component_scale;
        cfg.scale_cap = c.scale_cap;
        cfg.across_weight = c.across_weight;
        cfg.val_fold = c.val_fold;
        cfg.val_towns = c.val_towns.clone();
    }
    cfg.validate().map_err(TrainError::Config)?;
    cfg.check_batch_memory().map_err(TrainError::Config)?;
    if let Some(r) = &resume {
        check_steps_left(r, cfg.steps)?;
    }
    let start = resume.as_ref().map_or(1, |r| r.meta.steps_done + 1);
    let seed = cfg.seed;
    let step_rng =
        move |step: usize| Rng::new(seed ^ (step as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    if source.train_len() == 0 {
        let steps = cfg.window.history + cfg.window.centre_future();
        // Every window held out was also told "no scene is long enough".
        return Err(TrainError::Data(match source.val_scenes().len() {
            0 => format!("no scene is long enough for {steps} steps"),
            n => format!(
                "every scene long enough for {steps} steps ({n}) is held out for validation: \
                 validate on fewer towns or add scenes"
            ),
        }));
    }
    let futures = source.futures();
    cfg.model.history = cfg.window.history;
    let (varmap, model, norm, pca_rmse_m, prior, opt, resume_ema) = match resume {
        Some(r) => {
            let rmse = r.meta.normaliser.pca.position_rmse(futures);
            (
                r.varmap,
                r.model,
                r.meta.normaliser.clone(),
                rmse,
                Some(r.meta),
                r.optimizer,
                r.ema,
            )
        }
        None => {
            let pca = Pca::fit(futures, cfg.model.k)?;
            let rmse = pca.position_rmse(futures);
            let norm =
                Normaliser::with_scale(pca, cfg.edm.sigma_data, cfg.component_scale, cfg.scale_cap);
            let varmap = VarMap::new();
            let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
            let model = Denoiser::new(cfg.model, cfg.edm, vb)?;
            seeded_init(&varmap, &mut step_rng(0))?;
            (varmap, model, norm, rmse, None, None, None)
        }
    };
    // Moments that restart on a resumed checkpoint start at its step, so that the state saved
    // with the next checkpoint names the step its weights are of (counted from 0, it named
    // fewer, and that run could never be resumed again).
    let mut opt = opt
        .unwrap_or_else(|| AdamW::starting_at(&varmap, cfg.lr, WEIGHT_DECAY, (start - 1) as u64));
    opt.weight_decay = WEIGHT_DECAY;
    // A resumed average goes on (at this run's half-life); a run that asks for none drops it.
    let mut ema = match (resume_ema, cfg.ema_half_life > 0.0) {
        (_, false) => None,
        (Some(mut e), true) => {
            e.half_life = cfg.ema_half_life;
            Some(e)
        }
        (None, true) => Some(Ema::new(&varmap, cfg.ema_half_life)?),
    };
    // A fixed validation set: the same windows, noise levels and noise at every evaluation.
    let mut vrng = Rng::new(cfg.seed ^ 0xABCD);
    let val_batches: Vec<(Vec<usize>, Vec<f64>, Vec<f32>)> = if source.val_len() == 0 {
        vec![]
    } else {
        (0..8)
            .map(|_| {
                let idx: Vec<usize> = (0..cfg.batch)
                    .map(|_| vrng.below(source.val_len()))
                    .collect();
                let sig: Vec<f64> = (0..cfg.batch)
                    .map(|_| cfg.edm.train_sigma(vrng.normal()))
                    .collect();
                let n: Vec<f32> = (0..cfg.batch * cfg.window.max_agents * cfg.model.k)
                    .map(|_| vrng.normal() as f32)
                    .collect();
                (idx, sig, n)
            })
            .collect()
    };
    let mut meta = CheckpointMeta {
        version: CHECKPOINT_VERSION,
        config: cfg.clone(),
        normaliser: norm.clone(),
        train_scenes: source.train_scenes(),
        val_scenes: source.val_scenes(),
        steps_done: start - 1,
        history: prior.map(|p| p.history).unwrap_or_default(),
        git_revision,
        pca_rmse_m,
        types: source.type_counts(),
        ema_updates: 0,
        guidance_lambda: None,
    };
    let (mut run_loss, mut run_n) = (0.0, 0usize);
    // The step of the last checkpoint this run wrote, for a divergence's message.
    let mut saved: Option<usize> = None;
    for step in start..=cfg.steps {
        let mut rng = step_rng(step);
        opt.lr = learning_rate(cfg.lr, step, cfg.steps);
        let picked: Vec<Window> = (0..cfg.batch)
            .map(|_| {
                let w = source.train_window(rng.below(source.train_len()))?;
                Ok(w.rotated(rng.uniform() * std::f64::consts::TAU))
            })
            .collect::<Result<_, TrainError>>()?;
        let refs: Vec<&Window> = picked.iter().collect();
        // Drawn only by runs that read end points: the others' random streams stay as they
        // were, so that a resumed old run goes on as it would have.
        let goals = if cfg.window.goals {
            Goals::Drawn {
                keep: GOAL_KEEP,
                seed: rng.next_u64(),
            }
        } else {
            Goals::Hidden
        };
        let b = build(&refs, &cfg.window, &norm, goals, &dev)?;
        let sigma: Vec<f64> = (0..cfg.batch)
            .map(|_| cfg.edm.train_sigma(rng.normal()))
            .collect();
        let noise: Vec<f32> = (0..cfg.batch * cfg.window.max_agents * cfg.model.k)
            .map(|_| rng.normal() as f32)
            .collect();
        let noise = Tensor::from_vec(noise, (cfg.batch, cfg.window.max_agents, cfg.model.k), &dev)?;
        let l = loss(&model, &cfg.edm, &b, &sigma, &noise, cfg.across_weight)?;
        let lv = l.to_scalar::<f32>()? as f64;
        if !lv.is_finite() {
            return Err(TrainError::Diverged {
                which: "training",
                step,
                value: lv,
                kept: kept(saved),
            });
        }
        opt.step(&l.backward()?)?;
        if let Some(e) = &mut ema {
            e.update(&varmap)?;
        }
        run_loss += lv;
        run_n += 1;
        let mut val = None;
        if step % cfg.eval_every.max(1) == 0 || step == cfg.steps {
            // Checked where a checkpoint may be written: `train --lr 1e300` (with nothing held
            // out to validate on) wrote NaN weights, which every reader refuses, and exited 0.
            if let Some((tensor, _, value)) =
                non_finite_weight(&varmap).map_err(TrainError::Data)?
            {
                return Err(TrainError::DivergedWeights {
                    kept: kept(saved),
                    step,
                    tensor,
                    value,
                });
            }
            // Validated with the weights the checkpoint samples with.
            let averaged = match &ema {
                Some(e) => Some(Denoiser::new(
                    cfg.model,
                    cfg.edm,
                    VarBuilder::from_tensors(e.weights().clone(), DType::F32, &dev),
                )?),
                None => None,
            };
            let judged = averaged.as_ref().unwrap_or(&model);
            let mut total = 0.0;
            for (vi, (idx, sig, n)) in val_batches.iter().enumerate() {
                let ws: Vec<Window> = idx
                    .iter()
                    .map(|i| source.val_window(*i))
                    .collect::<Result<_, _>>()?;
                let refs: Vec<&Window> = ws.iter().collect();
                let goals = Goals::Drawn {
                    keep: GOAL_KEEP,
                    seed: vi as u64,
                };
                let b = build(&refs, &cfg.window, &norm, goals, &dev)?;
                let noise = Tensor::from_vec(
                    n.clone(),
                    (cfg.batch, cfg.window.max_agents, cfg.model.k),
                    &dev,
                )?;
                total += loss(judged, &cfg.edm, &b, sig, &noise, cfg.across_weight)?
                    .to_scalar::<f32>()? as f64;
            }
            let v = (!val_batches.is_empty()).then(|| total / val_batches.len() as f64);
            if let Some(x) = v.filter(|x| !x.is_finite()) {
                return Err(TrainError::Diverged {
                    which: "validation",
                    step,
                    value: x,
                    kept: kept(saved),
                });
            }
            meta.history.push((step, run_loss / run_n.max(1) as f64, v));
            meta.steps_done = step;
            meta.ema_updates = ema.as_ref().map_or(0, |e| e.updates);
            (run_loss, run_n) = (0.0, 0);
            val = v;
            if let Some(dir) = out {
                save(dir, &varmap, &meta, Some(&opt), ema.as_ref())?;
                saved = Some(step);
            }
        }
        progress(step, lv, val);
    }
    meta.steps_done = cfg.steps;
    meta.ema_updates = ema.as_ref().map_or(0, |e| e.updates);
    Ok(Trained {
        origin: None,
        varmap,
        model,
        meta,
        optimizer: Some(opt),
        ema,
    })
}

/// What a diverged run leaves, said in its error: "the last checkpoint written is kept" was
/// said of a run that diverged before it wrote any.
fn kept(saved: Option<usize>) -> String {
    match saved {
        Some(step) => format!("the checkpoint written at step {step} is kept"),
        None => "this run wrote no checkpoint".into(),
    }
}

/// AdamW's decoupled weight decay.
const WEIGHT_DECAY: f64 = 1e-4;

/// File of the optimiser state beside a checkpoint's weights.
pub const OPTIMIZER_FILE: &str = "optimizer.safetensors";

/// File of the weights training continues from when `model.safetensors` holds their moving
/// average ([`Ema`]): needed to resume, not to sample.
pub const ONLINE_FILE: &str = "online.safetensors";

/// Removes the temporary files of [`save`]s that a process which has since died left in
/// `dir` (`.model.safetensors.PID.tmp`, ...): a Ctrl-C or kill in the middle of a save left
/// them, each the size of the checkpoint, and each later run under another PID added its own.
/// Those of a live process (a trainer beside this one) are its own to finish.
fn remove_dead_temps(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    let names = [
        "model.safetensors",
        ONLINE_FILE,
        OPTIMIZER_FILE,
        "config.json",
    ];
    for e in entries.flatten() {
        let name = e.file_name();
        let Some(name) = name.to_str() else {
            continue;
        };
        let pid = names.iter().find_map(|n| {
            name.strip_prefix('.')?
                .strip_prefix(n)?
                .strip_prefix('.')?
                .strip_suffix(".tmp")?
                .parse::<u32>()
                .ok()
        });
        let Some(pid) = pid else {
            continue;
        };
        if pid != std::process::id()
            && !crate::io::process_alive(pid)
            && e.file_type().is_ok_and(|t| t.is_file())
        {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

/// Writes `model.safetensors`, `config.json` and, when given, the optimiser state
/// ([`OPTIMIZER_FILE`]) into `dir` (each atomically). With a moving average, that average is
/// `model.safetensors` and `varmap`'s weights go to [`ONLINE_FILE`]; without one, a stale
/// [`ONLINE_FILE`] is removed so that a later resume does not take it for this run's.
pub fn save(
    dir: &Path,
    varmap: &VarMap,
    meta: &CheckpointMeta,
    optimizer: Option<&AdamW>,
    ema: Option<&Ema>,
) -> Result<(), TrainError> {
    let io = |path: &Path, e: String| TrainError::Io {
        path: path.display().to_string(),
        message: e,
    };
    std::fs::create_dir_all(dir).map_err(|e| io(dir, e.to_string()))?;
    remove_dead_temps(dir);
    // Every file is written under a name of this process first and renamed only when all
    // are complete, config last: a kill leaves the previous checkpoint whole (or, in the
    // instant between renames, new weights beside the old config of the same model), and two
    // trainers never write into one temporary file.
    let pid = std::process::id();
    let mut staged: Vec<(PathBuf, PathBuf)> = Vec::new();
    // Whatever lies at a temporary's name (a link planted there, a leftover of a process that
    // had this PID) is removed before the file is made: the tensor writer and `fs::write`
    // open a path through a link, and a link at `.config.json.PID.tmp` had the checkpoint
    // written over (and its mode set on) the file it named.
    let fresh = |tmp: &Path| -> Result<(), TrainError> {
        match std::fs::symlink_metadata(tmp) {
            Ok(m) if m.is_dir() => Err(io(tmp, "is a directory: remove it".into())),
            Ok(_) => std::fs::remove_file(tmp).map_err(|e| io(tmp, e.to_string())),
            Err(_) => Ok(()),
        }
    };
    let weights = dir.join("model.safetensors");
    let tmp = dir.join(format!(".model.safetensors.{pid}.tmp"));
    fresh(&tmp)?;
    match ema {
        Some(e) => {
            e.save(&tmp).map_err(|e| io(&tmp, candle_message(e)))?;
            staged.push((tmp, weights));
            let tmp = dir.join(format!(".{ONLINE_FILE}.{pid}.tmp"));
            fresh(&tmp)?;
            varmap.save(&tmp).map_err(|e| io(&tmp, candle_message(e)))?;
            staged.push((tmp, dir.join(ONLINE_FILE)));
        }
        None => {
            varmap.save(&tmp).map_err(|e| io(&tmp, candle_message(e)))?;
            staged.push((tmp, weights));
        }
    }
    if let Some(opt) = optimizer {
        let path = dir.join(OPTIMIZER_FILE);
        let tmp = dir.join(format!(".optimizer.safetensors.{pid}.tmp"));
        fresh(&tmp)?;
        opt.save(&tmp).map_err(|e| io(&tmp, candle_message(e)))?;
        staged.push((tmp, path));
    }
    let json = serde_json::to_string_pretty(meta).expect("metadata serialises");
    let tmp = dir.join(format!(".config.json.{pid}.tmp"));
    fresh(&tmp)?;
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&tmp)
        .and_then(|mut f| std::io::Write::write_all(&mut f, json.as_bytes()))
        .map_err(|e| io(&tmp, e.to_string()))?;
    staged.push((tmp, dir.join("config.json")));
    for (tmp, _) in &staged {
        // Made above: a link here now was planted while this run wrote, and is not followed.
        if std::fs::symlink_metadata(tmp).is_ok_and(|m| !m.is_file()) {
            return Err(io(
                tmp,
                "was replaced by something other than a file while the checkpoint was written"
                    .into(),
            ));
        }
    }
    for (tmp, _) in &staged {
        // One mode for every file of a checkpoint (the tensor writer creates 0600).
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(tmp, std::fs::Permissions::from_mode(0o644))
                .map_err(|e| io(tmp, e.to_string()))?;
        }
        std::fs::File::open(tmp)
            .and_then(|f| f.sync_all())
            .map_err(|e| io(tmp, e.to_string()))?;
    }
    for (tmp, dst) in staged {
        std::fs::rename(&tmp, &dst).map_err(|e| io(&dst, e.to_string()))?;
    }
    let online = dir.join(ONLINE_FILE);
    if ema.is_none() && online.symlink_metadata().is_ok() {
        std::fs::remove_file(&online).map_err(|e| io(&online, e.to_string()))?;
    }
    Ok(())
}

/// The largest checkpoint config read: the shipped one is 53 KB (its PCA basis and history).
pub(crate) const MAX_CONFIG_BYTES: u64 = 16 << 20;
/// The largest weights file read: 1024-wide, 32-layer models stay below it.
const MAX_WEIGHTS_BYTES: u64 = 4 << 30;

/// One tensor's entry in a safetensors header.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TensorEntry {
    dtype: String,
    shape: Vec<u64>,
    data_offsets: [u64; 2],
}

/// A safetensors file opened past its 8-byte header length, with its size and that length,
/// checked to fit in the file: a file cut short was "invalid header length" in candle's words
/// (the optimiser state's), naming neither lengths nor the likely cause.
fn safetensors_header(path: &Path) -> Result<(std::fs::File, u64, u64), String> {
    use std::io::Read;
    let mut f = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let size = f.metadata().map_err(|e| e.to_string())?.len();
    let mut len = [0u8; 8];
    f.read_exact(&mut len)
        .map_err(|_| format!("is {size} bytes, too short for a safetensors file"))?;
    let len = u64::from_le_bytes(len);
    // The safetensors format's own cap on its header.
    if len > (100 << 20) || len > size - 8 {
        return Err(format!(
            "the header says it is {len} bytes, but the file is {size} bytes: not a \
             safetensors file, or cut short"
        ));
    }
    Ok((f, size, len))
}

/// The tensors a safetensors file holds, from its header, each checked against itself: a
/// known layout, offsets inside the data and tiling it. candle's own checks named no tensor
/// ("invalid shape, data type, or offset for tensor") or the one after a missing one.
fn tensor_entries(path: &Path) -> Result<Vec<(String, TensorEntry)>, String> {
    use std::io::Read;
    let (f, size, len) = safetensors_header(path)?;
    let mut header = Vec::new();
    f.take(len)
        .read_to_end(&mut header)
        .map_err(|e| e.to_string())?;
    // A tensor named twice was read as its last entry without a word.
    let header = std::str::from_utf8(&header)
        .map_err(|e| format!("header: not UTF-8 text ({e})"))
        .and_then(|t| crate::io::json::parse_json(t).map_err(|e| format!("header: {e}")))?;
    let serde_json::Value::Object(header) = header else {
        return Err("header: not a JSON object".into());
    };
    let data = size - 8 - len;
    let mut entries = Vec::new();
    for (name, v) in header {
        if name == "__metadata__" {
            continue;
        }
        let shown = crate::io::name::shown(&name);
        let e: TensorEntry =
            serde_json::from_value(v).map_err(|e| format!("tensor `{shown}`: header: {e}"))?;
        if e.dtype != "F32" {
            return Err(format!(
                "tensor `{shown}` is {}, but the model's weights are F32",
                crate::io::name::shown(&e.dtype)
            ));
        }
        let [from, to] = e.data_offsets;
        let bytes = e.shape.iter().try_fold(4u64, |n, &d| n.checked_mul(d));
        if from > to || to > data || bytes != Some(to - from) {
            return Err(format!(
                "tensor `{shown}` of shape {:?} (F32) has data offsets [{from}, {to}] in \
                 {data} bytes of data: the header is damaged",
                e.shape
            ));
        }
        entries.push((name, e));
    }
    entries.sort_by_key(|(_, e)| e.data_offsets);
    let mut at = 0;
    for (name, e) in &entries {
        if e.data_offsets[0] != at {
            return Err(format!(
                "tensor `{}` starts at byte {} of the data, where the tensor before it ends \
                 at {at}: a tensor is missing or the header is damaged",
                crate::io::name::shown(name),
                e.data_offsets[0]
            ));
        }
        at = e.data_offsets[1];
    }
    if at != data {
        return Err(format!(
            "the tensors end at byte {at} of the data, but the file holds {data}: the file \
             is damaged"
        ));
    }
    Ok(entries)
}

/// Checks, before loading, that a safetensors file holds exactly the tensors of `varmap`,
/// each of its shape. Loading fills the model's tensors by name and ignores the rest, so a
/// config.json describing a smaller model (2 layers where 3 were trained) loaded without a
/// word and sampled with a third of the network missing; and candle's own errors named a
/// tensor of the wrong shape or type only with "lhs" and "rhs".
fn check_tensors(varmap: &VarMap, path: &Path, model: &DenoiserConfig) -> Result<(), String> {
    let entries = tensor_entries(path)?;
    let vars = varmap.data().lock().unwrap_or_else(|p| p.into_inner());
    let described = format!(
        "the model config.json describes (d {}, {} layers)",
        model.d, model.layers
    );
    let mut extra: Vec<&String> = entries
        .iter()
        .map(|(n, _)| n)
        .filter(|n| !vars.contains_key(*n))
        .collect();
    if !extra.is_empty() {
        extra.sort();
        return Err(format!(
            "holds {} tensors {described} has no place for ({}): the config and the weights \
             are of different models",
            extra.len(),
            crate::io::name::first_few(&extra, 3)
        ));
    }
    let mut names: Vec<&String> = vars.keys().collect();
    names.sort();
    for name in names {
        let want: Vec<u64> = vars[name].dims().iter().map(|&d| d as u64).collect();
        match entries.iter().find(|(n, _)| n == name) {
            None => {
                return Err(format!(
                    "has no tensor `{name}` (shape {want:?}), which {described} needs: the \
                     config and the weights are of different models, or the file is damaged"
                ))
            }
            Some((_, e)) if e.shape != want => {
                return Err(format!(
                    "tensor `{name}` has shape {:?}, but {described} needs {want:?}: the \
                     config and the weights are of different models",
                    e.shape
                ))
            }
            Some(_) => {}
        }
    }
    Ok(())
}

/// The first weight of `varmap` (tensors by name) that is not a number: its tensor, its
/// element and its value.
fn non_finite_weight(varmap: &VarMap) -> Result<Option<(String, usize, f64)>, String> {
    let vars = varmap.data().lock().unwrap_or_else(|p| p.into_inner());
    let mut names: Vec<&String> = vars.keys().collect();
    names.sort();
    for name in names {
        let values: Vec<f32> = vars[name]
            .as_tensor()
            .flatten_all()
            .and_then(|t| t.to_dtype(DType::F32))
            .and_then(|t| t.to_vec1())
            .map_err(|e| format!("tensor `{name}`: {}", candle_message(e)))?;
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Ok(Some((name.clone(), i, values[i] as f64)));
        }
    }
    Ok(None)
}

/// Checks that the weights loaded into `varmap` are numbers: a NaN weight made every
/// denoised output NaN, which the sampler's clamps turned into confident nonsense.
fn check_weights(varmap: &VarMap) -> Result<(), String> {
    match non_finite_weight(varmap)? {
        Some((name, i, v)) => Err(format!(
            "tensor `{name}` holds {v} at element {i}: the weights are damaged (or training \
             diverged); use another checkpoint"
        )),
        None => Ok(()),
    }
}

/// Refuses to resume `r` towards a total of `steps` it has already done. Said before the
/// corpus is read as well (`train --resume CK --steps N`): it came after every window was cut.
pub fn check_steps_left(r: &Trained, steps: usize) -> Result<(), TrainError> {
    if r.meta.steps_done >= steps {
        return Err(TrainError::Data(format!(
            "the checkpoint has already done {} steps; ask for more than that (--steps is a total)",
            r.meta.steps_done
        )));
    }
    Ok(())
}

/// Reads a checkpoint written by [`save`].
pub fn load(dir: &Path) -> Result<Trained, TrainError> {
    let io = |path: &Path, e: String| TrainError::Io {
        path: path.display().to_string(),
        message: e,
    };
    // A checkpoint is a directory: named as a file, it read as "config.json/config.json: Not
    // a directory".
    match std::fs::metadata(dir) {
        Ok(m) if !m.is_dir() => {
            // `/dev/null` or a FIFO was called "a file", which it is not.
            let what = if m.is_file() {
                "is a file"
            } else {
                "is not a regular file but a device, FIFO or socket"
            };
            return Err(io(
                dir,
                format!(
                    "{what}, not a checkpoint directory (one holding config.json and \
                     model.safetensors)"
                ),
            ));
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(io(dir, "no such checkpoint directory".into()))
        }
        _ => {}
    }
    let cfg_path = dir.join("config.json");
    // A directory of something else (`--checkpoint /tmp`, a run directory) said only
    // "DIR/config.json: No such file or directory".
    if std::fs::symlink_metadata(&cfg_path).is_err() {
        return Err(io(
            dir,
            "is not a checkpoint directory: it holds no config.json (a checkpoint directory \
             holds config.json and model.safetensors, as `drivescript train --out` writes them)"
                .into(),
        ));
    }
    // Only regular files, each within a cap: a FIFO named config.json waited for a writer
    // forever, and a device read without end.
    let text = crate::io::read_regular_text(&cfg_path, MAX_CONFIG_BYTES, "checkpoint config")
        .map_err(|e| io(&cfg_path, e.reason()))?;
    let meta: CheckpointMeta = serde_json::from_str(&text).map_err(|e| {
        io(
            &cfg_path,
            format!(
                "line {}, column {}: {}",
                e.line(),
                e.column(),
                crate::io::without_position(&e.to_string(), e.line(), e.column())
            ),
        )
    })?;
    if meta.version != CHECKPOINT_VERSION {
        return Err(io(
            &cfg_path,
            format!(
                "checkpoint format {} (this drivescript reads format {CHECKPOINT_VERSION}); retrain it",
                meta.version.max(1)
            ),
        ));
    }
    meta.validate().map_err(|e| io(&cfg_path, e))?;
    let mut varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    let model = Denoiser::new(meta.config.model, meta.config.edm, vb)?;
    let w = dir.join("model.safetensors");
    crate::io::open_regular(&w, MAX_WEIGHTS_BYTES, "checkpoint weights")
        .map_err(|e| io(&w, e.reason()))?;
    check_tensors(&varmap, &w, &meta.config.model).map_err(|m| io(&w, m))?;
    varmap.load(&w).map_err(|e| io(&w, message_in_file(e)))?;
    check_weights(&varmap).map_err(|m| io(&w, m))?;
    let weights = crate::io::read_regular(&w, MAX_WEIGHTS_BYTES, "checkpoint weights")
        .map_err(|e| io(&w, e.reason()))?;
    let origin = CheckpointOrigin {
        dir: std::path::absolute(dir).unwrap_or_else(|_| dir.to_path_buf()),
        crc32c: crc32c::crc32c_append(crc32c::crc32c(text.as_bytes()), &weights),
    };
    let opt_path = dir.join(OPTIMIZER_FILE);
    let optimizer = if opt_path.exists() {
        crate::io::open_regular(&opt_path, 2 * MAX_WEIGHTS_BYTES, "optimiser state")
            .map_err(|e| io(&opt_path, e.reason()))?;
        safetensors_header(&opt_path).map_err(|m| io(&opt_path, m))?;
        let mut opt = AdamW::new(&varmap, meta.config.lr, WEIGHT_DECAY);
        opt.load(&opt_path)
            .map_err(|e| io(&opt_path, message_in_file(e)))?;
        if opt.training_step() != meta.steps_done as u64 {
            return Err(io(
                &opt_path,
                format!(
                    "optimiser state of step {}, but the weights are of step {}",
                    opt.training_step(),
                    meta.steps_done
                ),
            ));
        }
        Some(opt)
    } else {
        None
    };
    Ok(Trained {
        origin: Some(origin),
        varmap,
        model,
        meta,
        optimizer,
        ema: None,
    })
}

/// [`load`] for `train --resume`: when the checkpoint keeps a moving average of its weights,
/// the network gets the weights training continues from ([`ONLINE_FILE`]) and the average
/// goes on from `model.safetensors`. A checkpoint without that file resumes from
/// `model.safetensors` (a run that asks for an average starts one there).
pub fn load_for_training(dir: &Path) -> Result<Trained, TrainError> {
    let mut t = load(dir)?;
    let online = dir.join(ONLINE_FILE);
    if online.symlink_metadata().is_err() {
        return Ok(t);
    }
    let io = |e: String| TrainError::Io {
        path: online.display().to_string(),
        message: e,
    };
    if t.meta.config.ema_half_life <= 0.0 {
        return Err(io(
            "the config keeps no moving average (ema_half_life 0), so these weights belong to \
             no run of it; remove the file to resume from model.safetensors"
                .into(),
        ));
    }
    // The reason only: `io` names the file, and the whole error named it a second time.
    crate::io::open_regular(&online, MAX_WEIGHTS_BYTES, "checkpoint weights")
        .map_err(|e| io(e.reason()))?;
    let averaged = super::ema::copies(&t.varmap)?;
    check_tensors(&t.varmap, &online, &t.meta.config.model).map_err(io)?;
    t.varmap.load(&online).map_err(|e| io(candle_message(e)))?;
    check_weights(&t.varmap).map_err(io)?;
    t.ema = Some(Ema::from_weights(
        averaged,
        t.meta.config.ema_half_life,
        t.meta.ema_updates,
    ));
    Ok(t)
}

/// A tiny configuration that trains in well under a second, for tests.
#[cfg(test)]
pub(crate) fn tiny_config(steps: usize, seed: u64, eval_every: usize) -> TrainConfig {
    let window = WindowConfig {
        max_agents: 6,
        max_lanes: 8,
        lane_points: 8,
        stride: 10,
        ..WindowConfig::ngsim()
    };
    TrainConfig {
        steps,
        batch: 4,
        lr: 3e-3,
        seed,
        window,
        model: DenoiserConfig {
            d: 16,
            layers: 1,
            k: 6,
            history: window.history,
            noise_freqs: 4,
            scores: Scores::Normalised,
            attrs: AGENT_ATTRS,
            agent_lane_features: 4,
            route_times: 0,
            goals: false,
            route_frame: false,
        },
        edm: Edm::default(),
        eval_every,
        val_fold: 0,
        val_towns: Vec::new(),
        ema_half_life: 0.0,
        component_scale: ComponentScale::Common,
        scale_cap: 1.0,
        across_weight: 1.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{load_scene, LoadOptions};

    fn scenes() -> Vec<Scene> {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes");
        [
            "highway.yaml",
            "highway_cut_in.yaml",
            "highway_left.yaml",
            "highway_right.yaml",
            "highway_crash.yaml",
            "highway_stop.yaml",
        ]
        .iter()
        .map(|f| load_scene(&dir.join(f), 0, &LoadOptions::default()).unwrap())
        .collect()
    }

    #[test]
    fn every_scene_lies_in_exactly_one_validation_fold() {
        // Fold 0 is the shipped checkpoint's split (data/checkpoint/README.md); fold 2 is the
        // cross-validation model's.
        assert!(is_validation("USA_Lanker-1_15_T-1", 0));
        assert!(is_validation("USA_US101-27_1_T-1", 0));
        assert!(is_validation("USA_Lanker-2_10_T-1", 2));
        for id in [
            "USA_Lanker-1_15_T-1",
            "USA_Lanker-2_10_T-1",
            "a",
            "",
            "USA_US101-4_1_T-1",
        ] {
            let folds: Vec<u64> = (0..VAL_FOLDS).filter(|&f| is_validation(id, f)).collect();
            assert_eq!(folds.len(), 1, "{id:?} validates in folds {folds:?}");
        }
    }

    fn weights(t: &Trained) -> Vec<(String, Vec<f32>)> {
        let data = t.varmap.data().lock().unwrap();
        let mut w: Vec<(String, Vec<f32>)> = data
            .iter()
            .map(|(k, v)| {
                (
                    k.clone(),
                    v.as_tensor().flatten_all().unwrap().to_vec1().unwrap(),
                )
            })
            .collect();
        w.sort_by(|a, b| a.0.cmp(&b.0));
        w
    }

    fn tensors(m: &std::collections::HashMap<String, Tensor>) -> Vec<(String, Vec<f32>)> {
        let mut w: Vec<(String, Vec<f32>)> = m
            .iter()
            .map(|(k, v)| (k.clone(), v.flatten_all().unwrap().to_vec1().unwrap()))
            .collect();
        w.sort_by(|a, b| a.0.cmp(&b.0));
        w
    }

    /// Trains 20 steps straight and 10 + 10 with a stop at step 10, and returns both runs and
    /// the stopped run's directory.
    fn stopped_and_resumed(ema: f64) -> (Trained, Trained, tempfile::TempDir) {
        let cfg = || TrainConfig {
            ema_half_life: ema,
            ..tiny_config(20, 5, 10)
        };
        let (dir, half) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        let whole = train(&scenes(), cfg(), Some(dir.path()), None, |step, _, _| {
            if step == 10 {
                for f in [
                    "model.safetensors",
                    "config.json",
                    OPTIMIZER_FILE,
                    ONLINE_FILE,
                ] {
                    if dir.path().join(f).exists() {
                        std::fs::copy(dir.path().join(f), half.path().join(f)).unwrap();
                    }
                }
            }
        })
        .unwrap();
        assert_eq!(
            load(half.path()).unwrap().optimizer.map(|o| o.steps()),
            Some(10)
        );
        let resumed = resume(half.path(), cfg());
        (whole, resumed, half)
    }

    fn resume(path: &Path, cfg: TrainConfig) -> Trained {
        let r = load_for_training(path).unwrap();
        train_from(
            &SceneWindows::new(&scenes(), &cfg.window, cfg.val_fold),
            cfg,
            Some(r),
            None,
            None,
            |_, _, _| (),
        )
        .unwrap()
    }

    fn differing(a: &Trained, b: &Trained) -> Vec<String> {
        weights(a)
            .into_iter()
            .zip(weights(b))
            .filter(|(x, y)| x != y)
            .map(|(x, _)| x.0)
            .collect()
    }

    #[test]
    fn a_resumed_run_is_identical_to_an_uninterrupted_one() {
        let (whole, resumed, half) = stopped_and_resumed(0.0);
        assert!(!half.path().join(ONLINE_FILE).exists());
        assert_eq!(differing(&whole, &resumed), Vec::<String>::new());
        assert_eq!(whole.meta.history, resumed.meta.history);
        // Without the optimiser state the moments restart, and the run differs.
        std::fs::remove_file(half.path().join(OPTIMIZER_FILE)).unwrap();
        assert!(!differing(&whole, &resume(half.path(), tiny_config(20, 5, 10))).is_empty());
    }

    /// A checkpoint resumed without optimiser state (a fine-tune from a shipped checkpoint)
    /// writes checkpoints that resume again: its restarted moments used to be saved as of
    /// step 5 beside weights of step 15, and every later resume was refused.
    #[test]
    fn a_run_whose_moments_restarted_resumes_again() {
        let (_, _, half) = stopped_and_resumed(0.0);
        std::fs::remove_file(half.path().join(OPTIMIZER_FILE)).unwrap();
        let on = tempfile::tempdir().unwrap();
        let cfg = tiny_config(15, 5, 5);
        train_from(
            &SceneWindows::new(&scenes(), &cfg.window, cfg.val_fold),
            cfg,
            Some(load_for_training(half.path()).unwrap()),
            Some(on.path()),
            None,
            |_, _, _| (),
        )
        .unwrap();
        let again = load_for_training(on.path()).unwrap();
        assert_eq!(again.meta.steps_done, 15);
        let opt = again.optimizer.as_ref().unwrap();
        // Bias correction counts the 5 steps the moments have seen, not the run's 15.
        assert_eq!((opt.steps(), opt.training_step()), (5, 15));
        resume(on.path(), tiny_config(20, 5, 10));
    }

    #[test]
    fn a_run_with_a_moving_average_resumes_exactly_and_samples_with_the_average() {
        let (whole, resumed, half) = stopped_and_resumed(4.0);
        // Both the weights training goes on from and their average continue exactly.
        assert_eq!(differing(&whole, &resumed), Vec::<String>::new());
        let (a, b) = (whole.ema.as_ref().unwrap(), resumed.ema.as_ref().unwrap());
        assert_eq!(tensors(a.weights()), tensors(b.weights()));
        assert_eq!((a.updates, b.updates), (20, 20));
        assert_eq!(whole.meta.history, resumed.meta.history);
        // The file sampling reads is the average, not the last step's weights; what samples
        // right after training is the same average.
        let stopped = load(half.path()).unwrap();
        assert!(stopped.ema.is_none());
        let online = super::super::ema::read(&half.path().join(ONLINE_FILE)).unwrap();
        let sampled = tensors(&stopped.detached_weights());
        assert_ne!(sampled, tensors(&online));
        let cont = load_for_training(half.path()).unwrap();
        assert_eq!(weights(&cont), tensors(&online));
        assert_eq!(tensors(cont.ema.as_ref().unwrap().weights()), sampled);
        assert_eq!(cont.meta.ema_updates, 10);
        assert_eq!(tensors(&whole.detached_weights()), tensors(a.weights()));
        // Resuming without the average trains on from the last step's weights and removes
        // their file, which would otherwise be taken for this run's.
        let dropped = train_from(
            &SceneWindows::new(&scenes(), &tiny_config(12, 5, 2).window, 0),
            tiny_config(12, 5, 2),
            Some(cont),
            Some(half.path()),
            None,
            |_, _, _| (),
        )
        .unwrap();
        assert!(dropped.ema.is_none());
        assert!(!half.path().join(ONLINE_FILE).exists());
        assert!(load_for_training(half.path()).unwrap().ema.is_none());
    }

    #[test]
    fn stray_online_weights_of_a_run_without_an_average_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        train(
            &scenes(),
            tiny_config(2, 5, 2),
            Some(dir.path()),
            None,
            |_, _, _| (),
        )
        .unwrap();
        std::fs::copy(
            dir.path().join("model.safetensors"),
            dir.path().join(ONLINE_FILE),
        )
        .unwrap();
        let e = load_for_training(dir.path()).err().unwrap().to_string();
        assert!(
            e.contains(ONLINE_FILE) && e.contains("ema_half_life 0"),
            "{e}"
        );
        // One space between words: a run of 14 in the middle of the message came from a
        // line continuation without its backslash (issue 32).
        assert!(
            !e.contains("  ") && e.contains("belong to no run of it"),
            "{e}"
        );
        // Sampling does not read it.
        assert!(load(dir.path()).is_ok());
    }

    #[cfg(unix)]
    #[test]
    fn online_weights_that_are_no_regular_file_are_named_once() {
        // The file's error came whole inside the error naming the file: "DIR/online.safetensors:
        // DIR/online.safetensors: file: not a regular file ..." (issue 32).
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = tiny_config(2, 5, 2);
        cfg.ema_half_life = 10.0;
        train(&scenes(), cfg, Some(dir.path()), None, |_, _, _| ()).unwrap();
        let online = dir.path().join(ONLINE_FILE);
        let _ = std::fs::remove_file(&online);
        let made = std::process::Command::new("mkfifo")
            .arg(&online)
            .status()
            .unwrap();
        assert!(made.success());
        let e = load_for_training(dir.path()).err().unwrap().to_string();
        assert_eq!(e.matches(ONLINE_FILE).count(), 1, "{e}");
        assert!(
            e.contains("not a regular file") && !e.contains("file: "),
            "{e}"
        );
    }

    #[test]
    fn a_save_removes_what_a_killed_save_left_and_keeps_a_live_one_s() {
        let dir = tempfile::tempdir().unwrap();
        // PIDs above the kernel's limit (at most 2^22) belong to no process.
        let dead = dir.path().join(".model.safetensors.4000000001.tmp");
        let dead_cfg = dir.path().join(".config.json.4000000002.tmp");
        let live = dir.path().join(format!(".{OPTIMIZER_FILE}.1.tmp"));
        let mine = dir.path().join(".model.safetensors.x.tmp");
        for p in [&dead, &dead_cfg, &live, &mine] {
            std::fs::write(p, "partial").unwrap();
        }
        train(
            &scenes(),
            tiny_config(1, 1, 1),
            Some(dir.path()),
            None,
            |_, _, _| (),
        )
        .unwrap();
        assert!(!dead.exists() && !dead_cfg.exists());
        // PID 1 lives; a name that is not a save's is not touched.
        assert!(live.exists() && mine.exists());
    }

    #[test]
    fn a_link_planted_at_a_save_s_temporary_name_is_removed_not_written_through() {
        // The tensor writer and fs::write opened `.config.json.PID.tmp` through a link there:
        // the checkpoint went into the file it named, whose mode was then set to 0644.
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("ckpt");
        std::fs::create_dir(&out).unwrap();
        let victim = dir.path().join("victim.txt");
        std::fs::write(&victim, "the user's").unwrap();
        let pid = std::process::id();
        for name in ["model.safetensors", "config.json", OPTIMIZER_FILE] {
            let link = out.join(format!(".{name}.{pid}.tmp"));
            std::os::unix::fs::symlink(&victim, &link).unwrap();
        }
        train(
            &scenes(),
            tiny_config(1, 1, 1),
            Some(&out),
            None,
            |_, _, _| (),
        )
        .unwrap();
        assert_eq!(std::fs::read_to_string(&victim).unwrap(), "the user's");
        assert!(load(&out).is_ok());
        for name in ["model.safetensors", "config.json", OPTIMIZER_FILE] {
            let p = out.join(name);
            let m = std::fs::symlink_metadata(&p).unwrap();
            assert!(m.is_file(), "{name} is not a regular file");
        }
    }

    #[test]
    fn a_missing_or_truncated_checkpoint_file_is_named_once() {
        // Each was named twice, the weights once as Rust's debug string (`path: "…"`).
        let dir = tempfile::tempdir().unwrap();
        let e = load(dir.path()).err().expect("no config.json").to_string();
        let shown = dir.path().display().to_string();
        assert_eq!(e.matches(&shown).count(), 1, "{e}");
        assert!(e.contains("holds no config.json"), "{e}");
        train(
            &scenes(),
            tiny_config(1, 1, 1),
            Some(dir.path()),
            None,
            |_, _, _| (),
        )
        .unwrap();
        let w = dir.path().join("model.safetensors");
        let bytes = std::fs::read(&w).unwrap();
        std::fs::write(&w, &bytes[..100]).unwrap();
        let e = load(dir.path())
            .err()
            .expect("truncated weights")
            .to_string();
        let shown = w.display().to_string();
        assert_eq!(e.matches(&shown).count(), 1, "{e}");
        assert!(!e.contains("path:"), "{e}");
    }

    #[test]
    fn a_checkpoint_named_as_a_file_or_absent_says_so() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("config.json");
        std::fs::write(&f, "{}").unwrap();
        let e = load(&f).err().expect("a file").to_string();
        assert!(
            e.contains("is a file, not a checkpoint directory")
                && !e.contains("config.json/config.json"),
            "{e}"
        );
        #[cfg(unix)]
        {
            let e = load(Path::new("/dev/null"))
                .err()
                .expect("a device")
                .to_string();
            assert!(
                e.contains(
                    "/dev/null: is not a regular file but a device, FIFO or socket, not a \
                     checkpoint directory"
                ) && !e.contains("is a file"),
                "{e}"
            );
        }
        let e = load(&dir.path().join("nowhere"))
            .err()
            .expect("absent")
            .to_string();
        assert!(e.contains("nowhere: no such checkpoint directory"), "{e}");
        // A directory of something else is named, not its absent config.json.
        let other = dir.path().join("other");
        std::fs::create_dir(&other).unwrap();
        let e = load(&other).err().expect("no config.json").to_string();
        assert!(
            e.starts_with(&format!(
                "{}: is not a checkpoint directory: it holds no config.json",
                other.display()
            )),
            "{e}"
        );
    }

    #[test]
    fn a_checkpoint_config_that_cannot_sample_is_refused_naming_the_field() {
        let dir = tempfile::tempdir().unwrap();
        train(
            &scenes(),
            tiny_config(1, 1, 1),
            Some(dir.path()),
            None,
            |_, _, _| (),
        )
        .unwrap();
        let path = dir.path().join("config.json");
        let good: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        let k = good["config"]["model"]["k"].as_u64().unwrap() as usize;
        let cases: Vec<(&str, serde_json::Value, &str)> = vec![
            (
                "/config/edm/sigma_data",
                0.0.into(),
                "config.edm.sigma_data = 0",
            ),
            ("/config/edm/rho", 0.0.into(), "config.edm.rho = 0"),
            ("/config/edm/p_std", (-1.0).into(), "config.edm.p_std = -1"),
            (
                "/config/edm/sigma_min",
                100.0.into(),
                "is not below sigma_max",
            ),
            (
                "/config/window/future",
                0.into(),
                "config.window.future = 0",
            ),
            (
                "/config/window/max_agents",
                1_000_000_000u64.into(),
                "max_agents = 1000000000",
            ),
            (
                "/config/model/layers",
                1_000_000u64.into(),
                "config.model.layers = 1000000",
            ),
            // Positive and finite, yet sampling ended in "non-finite sample at sampling step
            // 32", naming neither the file nor the field.
            (
                "/config/edm/sigma_min",
                1e-320.into(),
                "config.edm.sigma_min = 1e-320: must be 1e-6 to 1e6",
            ),
            (
                "/config/edm/sigma_max",
                1e308.into(),
                "config.edm.sigma_max = 1e308: must be 1e-6 to 1e6",
            ),
            (
                "/config/edm/rho",
                1e9.into(),
                "config.edm.rho = 1e9: must be at most 1000",
            ),
            ("/config/lr", (-1.0).into(), "config.lr = -1"),
            (
                "/ema_updates",
                1_000_000_000_000_000u64.into(),
                "ema_updates = 1000000000000000: more than the",
            ),
            (
                "/guidance_lambda",
                0.0.into(),
                "guidance_lambda = 0: must be above 0 and at most",
            ),
            (
                "/guidance_lambda",
                1e300.into(),
                "guidance_lambda = 1e300: must be above 0 and at most",
            ),
            ("/normaliser/std/0", 0.0.into(), "normaliser.std[0] = 0"),
            ("/normaliser/std/1", (-1.0).into(), "normaliser.std[1] = -1"),
            (
                "/normaliser/sigma_data",
                0.0.into(),
                "normaliser.sigma_data = 0",
            ),
            // Finite but overflowing in the first denoising step.
            (
                "/normaliser/pca/mean/0",
                1e308.into(),
                "normaliser.pca.mean[0] = 1e308: beyond",
            ),
            (
                "/normaliser/std/0",
                1e300.into(),
                "normaliser.std[0] = 1e300: beyond",
            ),
            (
                "/normaliser/pca/variances/0",
                1e300.into(),
                "normaliser.pca.variances[0] = 1e300",
            ),
        ];
        let write = |v: &serde_json::Value| {
            std::fs::write(&path, serde_json::to_string(v).unwrap()).unwrap();
        };
        let refused = |v: &serde_json::Value, want: &str| {
            write(v);
            let e = load(dir.path()).err().expect(want).to_string();
            assert!(e.contains("config.json") && e.contains(want), "{want}: {e}");
        };
        for (ptr, value, want) in cases {
            let mut v = good.clone();
            match v.pointer_mut(ptr) {
                Some(slot) => *slot = value,
                // A field training leaves out (guidance_lambda), at the top level.
                None => v[&ptr[1..]] = value,
            }
            refused(&v, want);
        }
        // A zero basis, and one a value short (it panicked in PCA decoding).
        let mut v = good.clone();
        for c in v["normaliser"]["pca"]["components"].as_array_mut().unwrap() {
            *c = 0.0.into();
        }
        refused(&v, "components must be unit vectors");
        let mut v = good.clone();
        v["normaliser"]["pca"]["components"]
            .as_array_mut()
            .unwrap()
            .pop();
        refused(&v, "normaliser.pca.components has");
        let mut v = good.clone();
        v["normaliser"]["std"]
            .as_array_mut()
            .unwrap()
            .truncate(k - 1);
        refused(&v, "normaliser.std has");
        write(&good);
        load(dir.path()).unwrap();
    }

    #[test]
    fn weights_the_config_has_no_place_for_or_that_are_not_numbers_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = tiny_config(1, 1, 1);
        cfg.model.layers = 2;
        train(&scenes(), cfg, Some(dir.path()), None, |_, _, _| ()).unwrap();
        let path = dir.path().join("config.json");
        let good = std::fs::read_to_string(&path).unwrap();
        // The config of a one-layer model over the weights of two: the second layer was
        // dropped without a word.
        let mut v: serde_json::Value = serde_json::from_str(&good).unwrap();
        v["config"]["model"]["layers"] = 1.into();
        std::fs::write(&path, serde_json::to_string(&v).unwrap()).unwrap();
        let e = load(dir.path()).err().expect("fewer layers").to_string();
        assert!(
            e.contains("model.safetensors")
                && e.contains("has no place for")
                && e.contains("1 layers")
                && e.contains("different models"),
            "{e}"
        );
        std::fs::write(&path, &good).unwrap();
        load(dir.path()).unwrap();
        // One weight NaN: every denoised output was NaN, and samples came out anyway.
        let w = dir.path().join("model.safetensors");
        let mut map = candle_core::safetensors::load(&w, &Device::Cpu).unwrap();
        let name = map.keys().min().unwrap().clone();
        let t = &map[&name];
        let mut values: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
        values[1] = f32::NAN;
        let damaged = Tensor::from_vec(values, t.shape(), &Device::Cpu).unwrap();
        map.insert(name.clone(), damaged);
        candle_core::safetensors::save(&map, &w).unwrap();
        let e = load(dir.path()).err().expect("a NaN weight").to_string();
        assert!(
            e.contains("model.safetensors")
                && e.contains(&format!("tensor `{name}` holds NaN at element 1")),
            "{e}"
        );
    }

    #[test]
    fn weights_a_step_made_not_numbers_are_an_error_not_a_checkpoint() {
        // `train --lr 1e300` wrote NaN weights, which every reader refuses, and exited 0.
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = tiny_config(1, 1, 1);
        cfg.lr = 1e300;
        let e = train(&scenes(), cfg, Some(dir.path()), None, |_, _, _| ())
            .err()
            .expect("diverged weights")
            .to_string();
        assert!(
            e.starts_with("step 1: tensor `") && e.contains("training diverged (lower --lr)"),
            "{e}"
        );
        assert!(!dir.path().join("model.safetensors").exists());
    }

    #[test]
    fn a_tiny_model_learns_and_round_trips_through_a_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let mut losses = Vec::new();
        let t = train(
            &scenes(),
            tiny_config(200, 7, 100),
            Some(dir.path()),
            Some("test".into()),
            |_, l, _| losses.push(l),
        )
        .unwrap();
        assert_eq!(losses.len(), 200);
        // Batch losses swing with the random noise levels; compare averages over many steps.
        let first: f64 = losses[..50].iter().sum::<f64>() / 50.0;
        let last: f64 = losses[150..].iter().sum::<f64>() / 50.0;
        assert!(
            last < first,
            "training loss did not fall: {first} -> {last}"
        );
        assert!(t.meta.pca_rmse_m < 0.5);
        assert_eq!(t.meta.history.len(), 2);
        let back = load(dir.path()).unwrap();
        assert_eq!(back.meta.steps_done, 200);
        assert_eq!(back.meta.config, t.meta.config);
        // Same seed, same run.
        let mut again = Vec::new();
        train(
            &scenes(),
            tiny_config(200, 7, 100),
            None,
            None,
            |_, l, _| again.push(l),
        )
        .unwrap();
        assert_eq!(losses, again, "training is not deterministic for a seed");
    }
}
