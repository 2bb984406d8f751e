//! Relative attention: `s_ij = q_i·(k_j + MLP(r_ij)) / √d`, values `x_j W_v + MLP(r_ij)`, with
//! `r_ij = (Δx, Δy, cos Δθ, sin Δθ)` of j in i's frame (plus a connectivity embedding between
//! lanes). Followed by the usual residual, layer norm and feed-forward (pre-norm). Everything
//! stays in relative coordinates, so the model does not depend on where the scene sits in the
//! world.
//!
//! Two forms of the scores ([`Scores`]): checkpoints trained before the softmax had a backward
//! pass read raw keys; once the scores train, raw keys let them grow without bound and the
//! attention collapses, so new models normalise queries, keys and key pair features.

use candle_core::{Module, Result, Tensor, D};
use candle_nn::{embedding, Embedding, VarBuilder};
use serde::{Deserialize, Serialize};

use super::ops::{layer_norm, linear, linear_no_bias, matmul, softmax_last_dim, Linear};

/// Number of lane-pair connectivity kinds: none, predecessor, successor, left, right.
pub const CONNECTIONS: usize = 5;

/// How attention scores are formed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Scores {
    /// `q_i = W_q LN(x_i)`, `k_j = W_k x_j`, pair term `W h_ij`: the keys read the raw residual
    /// stream. The form of every checkpoint trained before the attention softmax had a backward
    /// pass (a config without `scores` means this); with trained scores it collapses: on NGSIM
    /// the agent-agent scores reached a spread of 50 and every agent attended to one other.
    #[default]
    Raw,
    /// Pre-norm on both sides (`k_j` and `v_j` read `LN(x_j)`), and the query, the key and the
    /// key pair term each normalised again after their projection (QK-norm), so that the
    /// scores' spread is set by the norms' gains and cannot run away with the weights.
    Normalised,
}

/// Layer normalisation with a backward pass ([`layer_norm`]). candle-nn's `LayerNorm` module
/// runs a fused kernel without one (`apply_op3_no_bwd`), which silently stops gradients at
/// every normalisation; training through it barely learns.
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

impl Norm {
    /// A normalisation with a gain only (bias fixed at 0), for inputs to a score where a learned
    /// bias would add the same amount to every score of a row and could never learn.
    pub fn gain_only(d: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get_with_hints(d, "weight", candle_nn::Init::Const(1.0))?,
            bias: Tensor::zeros(d, vb.dtype(), vb.device())?,
        })
    }
}

impl Module for Norm {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        layer_norm(x, &self.weight, &self.bias, 1e-5)
    }
}

/// A block's pair features for every (query, key) pair, `[B, N, M, d]` each: the key pair term
/// (its hidden layer for [`Scores::Raw`], the whole normalised term for
/// [`Scores::Normalised`]) and the value MLP's hidden layer. They depend only on the relative
/// poses (and lane connectivity), which do not change while a scene is sampled, so they are
/// computed once per scene.
#[derive(Debug, Clone)]
pub struct Pairs {
    hk: Tensor,
    hv: Tensor,
}

impl Pairs {
    /// Both tensors.
    pub fn tensors(&self) -> [&Tensor; 2] {
        [&self.hk, &self.hv]
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
    /// [`Scores::Normalised`]: the key side's pre-norm, and the query, key and key pair norms.
    qk_norm: Option<QkNorm>,
    ff1: Linear,
    ff2: Linear,
}

#[derive(Debug, Clone)]
struct QkNorm {
    lnk: Norm,
    q: Norm,
    k: Norm,
    r: Norm,
}

impl RelAttention {
    /// A block of width `d` over pairs described by `rel` features whose scores take the form
    /// `scores`; `with_connectivity` adds the lane connectivity embedding.
    pub fn new(
        d: usize,
        rel: usize,
        scores: Scores,
        with_connectivity: bool,
        vb: VarBuilder,
    ) -> Result<Self> {
        let qk_norm = match scores {
            Scores::Raw => None,
            Scores::Normalised => Some(QkNorm {
                lnk: Norm::new(d, vb.pp("ln_kv"))?,
                q: Norm::new(d, vb.pp("ln_q"))?,
                k: Norm::gain_only(d, vb.pp("ln_k"))?,
                r: Norm::gain_only(d, vb.pp("ln_r"))?,
            }),
        };
        Ok(Self {
            qk_norm,
            q: linear(d, d, vb.pp("q"))?,
            // No bias on keys or on the key MLP's output: either adds the same q·b to every
            // score of a row, which the softmax ignores, so it could never learn.
            k: linear_no_bias(d, d, vb.pp("k"))?,
            v: linear(d, d, vb.pp("v"))?,
            o: linear(d, d, vb.pp("o"))?,
            rk1: linear(rel, d, vb.pp("rk1"))?,
            rk2: linear_no_bias(d, d, vb.pp("rk2"))?,
            rv1: linear(rel, d, vb.pp("rv1"))?,
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
        })
    }

    /// The pair features of relative poses `rel` `[B, N, M, 4]` and, for lanes, connectivity
    /// `conn` `[B, N, M]` (u32 kinds).
    pub fn pairs(&self, rel: &Tensor, conn: Option<&Tensor>) -> Result<Pairs> {
        let (hk, hv) = self.pair_hidden(rel, conn)?;
        let hk = match &self.qk_norm {
            None => hk,
            // Normalised per pair, the key term cannot be applied after the reduction over keys
            // as the raw form's is; it is computed once per scene, so that costs little.
            Some(n) => n.r.forward(&self.rk2.forward(&hk)?)?,
        };
        Ok(Pairs { hk, hv })
    }

    /// Updates queries `xq` `[B, N, d]` from keys `xk` `[B, M, d]` with their
    /// [`RelAttention::pairs`] and key mask `mask` `[B, M]` (1 = present).
    pub fn forward(
        &self,
        xq: &Tensor,
        xk: &Tensor,
        pairs: &Pairs,
        mask: &Tensor,
    ) -> Result<Tensor> {
        // Pre-norm: the residual stream carries the raw features (the agents' history and noisy
        // coefficients) straight through, which trains much faster than post-norm here.
        let hq = self.ln1.forward(xq)?;
        let (q, k, v) = match &self.qk_norm {
            None => {
                let q = self.q.forward(&hq)?; // [B, N, d]
                (q, self.k.forward(xk)?, self.v.forward(xk)?) // [B, M, d]
            }
            Some(n) => {
                let hk = n.lnk.forward(xk)?;
                let q = n.q.forward(&self.q.forward(&hq)?)?;
                (q, n.k.forward(&self.k.forward(&hk)?)?, self.v.forward(&hk)?)
            }
        };
        let (hk, hv) = (&pairs.hk, &pairs.hv); // [B, N, M, d] each
        let (b, n, m, d) = hk.dims4()?;
        // The second layers of the relative MLPs are linear, so they are applied after the
        // reduction over keys instead of to every pair:
        //   q·(W h_ij) = (Wᵀq)·h_ij   and   Σ_j a_ij (W h_ij + c) = W (Σ_j a_ij h_ij) + c Σ_j a_ij.
        // This is the same function as the direct form (a test checks it) but replaces two
        // d×d products per pair and the [B, N, M, d] broadcasts by batched matrix products:
        // about 3x faster training on NGSIM windows.
        let qw = match self.qk_norm {
            None => q.broadcast_matmul(self.rk2.weight())?, // [B, N, d]
            Some(_) => q.clone(),
        };
        let qh =
            matmul(&hk.reshape((b * n, m, d))?, &qw.reshape((b * n, d, 1))?)?.reshape((b, n, m))?;
        let s = ((matmul(&q, &k.t()?)? + qh)? / (d as f64).sqrt())?;
        // Absent keys get a large negative score and zero weight afterwards, so a row with no
        // key at all reads nothing.
        let keep = mask.unsqueeze(1)?; // [B, 1, M]
        let bias = ((&keep - 1.0)? * 1e9)?;
        let a = softmax_last_dim(&s.broadcast_add(&bias)?)?.broadcast_mul(&keep)?;
        let (wv, cv) = (
            self.rv2.weight(),
            self.rv2.bias().expect("linear has a bias"),
        );
        let ah =
            matmul(&a.reshape((b * n, 1, m))?, &hv.reshape((b * n, m, d))?)?.reshape((b, n, d))?;
        let out = ((matmul(&a, &v)? + ah.broadcast_matmul(&wv.t()?)?)?
            + a.sum_keepdim(D::Minus1)?.broadcast_mul(cv)?)?;
        self.finish(xq, &out)
    }

    /// Hidden layers of the key and value relative MLPs for every pair, after the ReLU.
    fn pair_hidden(&self, rel: &Tensor, conn: Option<&Tensor>) -> Result<(Tensor, Tensor)> {
        let mut hk = self.rk1.forward(rel)?;
        let mut hv = self.rv1.forward(rel)?;
        if let (Some(emb), Some(c)) = (&self.conn, conn) {
            let e = emb.forward(c)?;
            hk = (hk + &e)?;
            hv = (hv + e)?;
        }
        Ok((hk.relu()?, hv.relu()?))
    }

    /// Output projection, residual and feed-forward.
    fn finish(&self, xq: &Tensor, out: &Tensor) -> Result<Tensor> {
        let x = (xq + self.o.forward(out)?)?;
        let f = self
            .ff2
            .forward(&self.ff1.forward(&self.ln2.forward(&x)?)?.relu()?)?;
        x + f
    }

    /// The formula as written in the paper, every pair materialised: the reference that
    /// [`RelAttention::forward`] must equal.
    #[cfg(test)]
    fn forward_direct(
        &self,
        xq: &Tensor,
        xk: &Tensor,
        rel: &Tensor,
        mask: &Tensor,
        conn: Option<&Tensor>,
    ) -> Result<Tensor> {
        let hq = self.ln1.forward(xq)?;
        let xk = match &self.qk_norm {
            None => xk.clone(),
            Some(n) => n.lnk.forward(xk)?,
        };
        let (mut q, mut k) = (self.q.forward(&hq)?, self.k.forward(&xk)?);
        let (hk, hv) = self.pair_hidden(rel, conn)?;
        let mut rk = self.rk2.forward(&hk)?;
        if let Some(n) = &self.qk_norm {
            (q, k, rk) = (n.q.forward(&q)?, n.k.forward(&k)?, n.r.forward(&rk)?);
        }
        let (q, k) = (q.unsqueeze(2)?, k.unsqueeze(1)?); // [B, N, 1, d], [B, 1, M, d]
        let v = self.v.forward(&xk)?.unsqueeze(1)?;
        let rv = self.rv2.forward(&hv)?;
        let s = (q.broadcast_mul(&k.broadcast_add(&rk)?)?.sum(D::Minus1)?
            / (hk.dim(3)? as f64).sqrt())?;
        let bias = ((mask.unsqueeze(1)? - 1.0)? * 1e9)?;
        let a = softmax_last_dim(&s.broadcast_add(&bias)?)?;
        let vals = v
            .broadcast_add(&rv)?
            .broadcast_mul(&mask.unsqueeze(1)?.unsqueeze(3)?)?;
        let out = a.unsqueeze(3)?.broadcast_mul(&vals)?.sum(2)?;
        self.finish(xq, &out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use candle_nn::VarMap;

    #[test]
    fn the_factored_form_equals_the_direct_formula() {
        for scores in [Scores::Raw, Scores::Normalised] {
            factored_equals_direct(scores);
        }
    }

    fn factored_equals_direct(scores: Scores) {
        let dev = Device::Cpu;
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
        let att = RelAttention::new(8, 4, scores, true, vb).unwrap();
        // Gains and biases away from their initial 1 and 0, so that a norm applied to the wrong
        // tensor shows.
        for (name, var) in vm.data().lock().unwrap().iter() {
            if name.contains("ln") {
                let r = Tensor::randn(0f32, 0.3, var.shape(), &dev).unwrap();
                var.set(&(var.as_tensor() + r).unwrap()).unwrap();
            }
        }
        let (b, n, m) = (2, 3, 5);
        let xq = Tensor::randn(0f32, 1.0, (b, n, 8), &dev).unwrap();
        let xk = Tensor::randn(0f32, 1.0, (b, m, 8), &dev).unwrap();
        let rel = Tensor::randn(0f32, 1.0, (b, n, m, 4), &dev).unwrap();
        let conn = Tensor::from_vec(
            (0..b * n * m)
                .map(|i| (i % CONNECTIONS) as u32)
                .collect::<Vec<_>>(),
            (b, n, m),
            &dev,
        )
        .unwrap();
        // Second window: only two keys present; a third window-row pattern with none present
        // is covered by the zero-key case below.
        let mask = Tensor::from_vec(
            vec![1f32, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 1.0, 0.0, 0.0],
            (b, m),
            &dev,
        )
        .unwrap();
        let pairs = att.pairs(&rel, Some(&conn)).unwrap();
        let fast = att.forward(&xq, &xk, &pairs, &mask).unwrap();
        let slow = att
            .forward_direct(&xq, &xk, &rel, &mask, Some(&conn))
            .unwrap();
        let diff = (fast - slow).unwrap().abs().unwrap().max_all().unwrap();
        assert!(
            diff.to_scalar::<f32>().unwrap() < 1e-4,
            "{scores:?}: {diff}"
        );
        let none = Tensor::zeros((b, m), DType::F32, &dev).unwrap();
        let fast = att.forward(&xq, &xk, &pairs, &none).unwrap();
        let slow = att
            .forward_direct(&xq, &xk, &rel, &none, Some(&conn))
            .unwrap();
        let diff = (fast - slow).unwrap().abs().unwrap().max_all().unwrap();
        assert!(
            diff.to_scalar::<f32>().unwrap() < 1e-4,
            "{scores:?}, no keys: {diff}"
        );
    }
}
