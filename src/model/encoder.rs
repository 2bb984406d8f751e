//! Encoders: MiniPointNet for lanes (per-point MLP, max-pool) and the agent encoder (history,
//! noisy PCA coefficients and the noise level).

use candle_core::{Module, Result, Tensor, D};
use candle_nn::VarBuilder;

use super::ops::{linear, Linear};

/// MiniPointNet: lane points in the lane's own frame → one vector per lane.
#[derive(Debug, Clone)]
pub struct MiniPointNet {
    l1: Linear,
    l2: Linear,
    l3: Linear,
}

impl MiniPointNet {
    /// Encoder of width `d`.
    pub fn new(d: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            l1: linear(2, d, vb.pp("l1"))?,
            l2: linear(d, d, vb.pp("l2"))?,
            l3: linear(d, d, vb.pp("l3"))?,
        })
    }

    /// `points` `[B, M, P, 2]` → `[B, M, d]`.
    pub fn forward(&self, points: &Tensor) -> Result<Tensor> {
        let h = self.l2.forward(&self.l1.forward(points)?.relu()?)?.relu()?;
        self.l3.forward(&h.max(D::Minus2)?)
    }
}

/// Fourier features of the EDM noise input `c_noise` `[B]` → `[B, 2·freqs]`.
pub fn noise_features(c_noise: &Tensor, freqs: usize) -> Result<Tensor> {
    let f: Vec<f32> = (0..freqs).map(|i| 2f32.powi(i as i32)).collect();
    let f = Tensor::from_vec(f, (1, freqs), c_noise.device())?.to_dtype(c_noise.dtype())?;
    let x = c_noise.unsqueeze(1)?.broadcast_mul(&f)?;
    Tensor::cat(&[x.sin()?, x.cos()?], 1)
}

/// The agent encoder: `[history features, c_in·x, noise features]` → `[B, N, d]`.
#[derive(Debug, Clone)]
pub struct AgentEncoder {
    l1: Linear,
    l2: Linear,
}

impl AgentEncoder {
    /// Encoder from `inputs` features to width `d`.
    pub fn new(inputs: usize, d: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            l1: linear(inputs, d, vb.pp("l1"))?,
            l2: linear(d, d, vb.pp("l2"))?,
        })
    }

    /// `features` `[B, N, inputs]` → `[B, N, d]`.
    pub fn forward(&self, features: &Tensor) -> Result<Tensor> {
        self.l2.forward(&self.l1.forward(features)?.relu()?)
    }
}
