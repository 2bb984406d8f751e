//! Fused tensor operations that keep their backward pass.
//!
//! candle-nn's fused kernels (`softmax_last_dim`, `LayerNorm`) are applied with
//! `apply_op*_no_bwd`: nothing fails, but gradients stop there. Training through them left the
//! shipped model's attention scores untrained (the biases of `q` were still exactly their
//! initial zeros). The operations here run one fused CPU kernel forward and give their exact
//! gradient backward; `tests` in `model::gradients` keep every parameter and input honest.

use candle_core::{CpuStorage, CustomOp1, Layout, Result, Shape, Tensor, D};
use rayon::prelude::*;

/// Softmax over the last dimension, differentiable. Rows of `-inf`-free scores only; callers
/// mask with large finite negatives.
pub fn softmax_last_dim(x: &Tensor) -> Result<Tensor> {
    x.contiguous()?.apply_op1(SoftmaxLastDim)
}

struct SoftmaxLastDim;

fn softmax_rows<T: candle_core::WithDType + num_traits::Float + Send + Sync>(
    src: &[T],
    layout: &Layout,
) -> Result<(CpuStorage, Shape)> {
    let src = match layout.contiguous_offsets() {
        Some((a, b)) => &src[a..b],
        None => candle_core::bail!("softmax: input has to be contiguous"),
    };
    let dims = layout.shape().dims();
    let m = dims[dims.len() - 1].max(1);
    let mut dst = vec![T::zero(); src.len()];
    let row = |(s, d): (&[T], &mut [T])| {
        let max = s
            .iter()
            .fold(T::neg_infinity(), |a, &b| num_traits::Float::max(a, b));
        let mut sum = T::zero();
        for (v, o) in s.iter().zip(d.iter_mut()) {
            *o = (*v - max).exp();
            sum = sum + *o;
        }
        let inv = T::one() / sum;
        for o in d.iter_mut() {
            *o = *o * inv;
        }
    };
    // Rayon's fork-join costs more than a few small rows.
    if src.len() >= 1 << 14 {
        src.par_chunks(m).zip(dst.par_chunks_mut(m)).for_each(row);
    } else {
        src.chunks(m).zip(dst.chunks_mut(m)).for_each(row);
    }
    Ok((
        candle_core::WithDType::to_cpu_storage_owned(dst),
        Shape::from_dims(dims),
    ))
}

impl CustomOp1 for SoftmaxLastDim {
    fn name(&self) -> &'static str {
        "drivescript-softmax-last-dim"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        match storage {
            CpuStorage::F32(s) => softmax_rows(s, layout),
            CpuStorage::F64(s) => softmax_rows(s, layout),
            _ => candle_core::bail!("softmax: only f32 and f64 are supported"),
        }
    }

    /// `∂L/∂x = y ⊙ (g − Σ_j g_j y_j)` row by row.
    fn bwd(&self, _arg: &Tensor, res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let dot = (grad_res * res)?.sum_keepdim(D::Minus1)?;
        Ok(Some(grad_res.broadcast_sub(&dot)?.mul(res)?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device, Var};

    #[test]
    fn softmax_matches_the_composed_formula_forward_and_backward() {
        let dev = Device::Cpu;
        let x = Var::from_tensor(
            &Tensor::randn(0f64, 3.0, (3, 4, 7), &dev)
                .unwrap()
                .to_dtype(DType::F64)
                .unwrap(),
        )
        .unwrap();
        let w = Tensor::randn(0f64, 1.0, (3, 4, 7), &dev).unwrap();
        let fused = softmax_last_dim(x.as_tensor()).unwrap();
        let composed = candle_nn::ops::softmax(x.as_tensor(), D::Minus1).unwrap();
        let diff = (&fused - &composed)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        assert!(diff < 1e-12, "forward differs by {diff}");
        let g1 = (fused * &w).unwrap().sum_all().unwrap().backward().unwrap();
        let g2 = (composed * &w)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let (a, b) = (
            g1.get(x.as_tensor()).unwrap(),
            g2.get(x.as_tensor()).unwrap(),
        );
        let diff = (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        assert!(diff < 1e-12, "backward differs by {diff}");
        let norm = a
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        assert!(norm > 1e-6, "no gradient reached the scores");
    }
}
