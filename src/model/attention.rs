//! Relative attention: `s_ij = (x_i W_q)·(x_j W_k + MLP(r_ij)) / √d`, values
//! `x_j W_v + MLP(r_ij)`, with `r_ij = (Δx, Δy, cos Δθ, sin Δθ)` of j in i's frame (plus a
//! connectivity embedding between lanes). Followed by the usual residual, layer norm and
//! feed-forward (pre-norm). Everything stays in relative coordinates, so the model does not depend on
//! where the scene sits in the world.

use candle_core::{Module, Result, Tensor, D};
use candle_nn::{embedding, linear, Embedding, Linear, VarBuilder};

/// Number of lane-pair connectivity kinds: none, predecessor, successor, left, right.
pub const CONNECTIONS: usize = 5;

/// Layer normalisation built from differentiable tensor ops. candle-nn's `LayerNorm` module
/// runs a fused kernel without a backward pass (`apply_op3_no_bwd`), which silently stops
/// gradients at every normalisation; training through it barely learns.
#[derive(Debug, Clone)]
pub struct Norm {
    weight: Tensor,
    bias: Tensor,
}

impl Norm {
    /// A normalisation over the last dimension of width `d` (gain 1, bias 0 at creation).
    pub fn new(d: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get_with_hints(d, "weight", candle_nn::Init::Const(1.0))?,
            bias: vb.get_with_hints(d, "bias", candle_nn::Init::Const(0.0))?,
        })
    }
}

impl Module for Norm {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        candle_nn::ops::layer_norm_slow(x, &self.weight, &self.bias, 1e-5)
    }
}

/// One relative-attention block.
#[derive(Debug, Clone)]
pub struct RelAttention {
    q: Linear,
    k: Linear,
    v: Linear,
    o: Linear,
    rk1: Linear,
    rk2: Linear,
    rv1: Linear,
    rv2: Linear,
    conn: Option<Embedding>,
    ln1: Norm,
    ln2: Norm,
    ff1: Linear,
    ff2: Linear,
    d: usize,
}

impl RelAttention {
    /// A block of width `d`; `with_connectivity` adds the lane connectivity embedding.
    pub fn new(d: usize, with_connectivity: bool, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            q: linear(d, d, vb.pp("q"))?,
            k: linear(d, d, vb.pp("k"))?,
            v: linear(d, d, vb.pp("v"))?,
            o: linear(d, d, vb.pp("o"))?,
            rk1: linear(4, d, vb.pp("rk1"))?,
            rk2: linear(d, d, vb.pp("rk2"))?,
            rv1: linear(4, d, vb.pp("rv1"))?,
            rv2: linear(d, d, vb.pp("rv2"))?,
            conn: if with_connectivity {
                Some(embedding(CONNECTIONS, d, vb.pp("conn"))?)
            } else {
                None
            },
            ln1: Norm::new(d, vb.pp("ln1"))?,
            ln2: Norm::new(d, vb.pp("ln2"))?,
            ff1: linear(d, 2 * d, vb.pp("ff1"))?,
            ff2: linear(2 * d, d, vb.pp("ff2"))?,
            d,
        })
    }

    /// Updates queries `xq` `[B, N, d]` from keys `xk` `[B, M, d]` with relative features
    /// `rel` `[B, N, M, 4]`, key mask `mask` `[B, M]` (1 = present) and, for lanes,
    /// connectivity `conn` `[B, N, M]` (u32 kinds).
    pub fn forward(
        &self,
        xq: &Tensor,
        xk: &Tensor,
        rel: &Tensor,
        mask: &Tensor,
        conn: Option<&Tensor>,
    ) -> Result<Tensor> {
        // Pre-norm: the residual stream carries the raw features (the agents' history and noisy
        // coefficients) straight through, which trains much faster than post-norm here.
        let hq = self.ln1.forward(xq)?;
        let q = self.q.forward(&hq)?.unsqueeze(2)?; // [B, N, 1, d]
        let k = self.k.forward(xk)?.unsqueeze(1)?; // [B, 1, M, d]
        let v = self.v.forward(xk)?.unsqueeze(1)?;
        let mut hk = self.rk1.forward(rel)?;
        let mut hv = self.rv1.forward(rel)?;
        if let (Some(emb), Some(c)) = (&self.conn, conn) {
            let e = emb.forward(c)?;
            hk = (hk + &e)?;
            hv = (hv + e)?;
        }
        let rk = self.rk2.forward(&hk.relu()?)?; // [B, N, M, d]
        let rv = self.rv2.forward(&hv.relu()?)?;
        let s =
            (q.broadcast_mul(&k.broadcast_add(&rk)?)?.sum(D::Minus1)? / (self.d as f64).sqrt())?; // [B, N, M]
                                                                                                  // Absent keys get a large negative score; a row with no key at all attends uniformly
                                                                                                  // to padding, whose values are zero-masked below.
        let bias = ((mask.unsqueeze(1)? - 1.0)? * 1e9)?;
        let a = candle_nn::ops::softmax_last_dim(&s.broadcast_add(&bias)?)?;
        let vals = v
            .broadcast_add(&rv)?
            .broadcast_mul(&mask.unsqueeze(1)?.unsqueeze(3)?)?;
        let out = a.unsqueeze(3)?.broadcast_mul(&vals)?.sum(2)?; // [B, N, d]
        let x = (xq + self.o.forward(&out)?)?;
        let f = self
            .ff2
            .forward(&self.ff1.forward(&self.ln2.forward(&x)?)?.relu()?)?;
        x + f
    }
}
