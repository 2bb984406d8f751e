//! Fused tensor operations that keep their backward pass.
//!
//! candle-nn's fused kernels (`softmax_last_dim`, `LayerNorm`) are applied with
//! `apply_op*_no_bwd`: nothing fails, but gradients stop there. Training through them left the
//! shipped model's attention scores untrained (the biases of `q` were still exactly their
//! initial zeros). The operations here run one fused CPU kernel forward and give their exact
//! gradient backward; `tests` in `model::gradients` keep every parameter and input honest.

use candle_core::backend::BackendStorage;
use candle_core::{
    CpuStorage, CustomOp1, CustomOp2, CustomOp3, DType, Layout, Module, Result, Shape, Tensor, D,
};
use candle_nn::VarBuilder;
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

/// Batched matrix product `a·b` (`[..., m, k]·[..., k, n]`, equal leading dimensions) whose
/// backward pass computes only the gradients that something upstream needs. candle's own
/// product always computes both: with constant weights and scene features (guidance through
/// the denoiser), half of the backward pass was products nobody read, among them the largest
/// (the per-pair agent-lane features).
pub fn matmul(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    a.apply_op2(b, MatMul)
}

struct MatMul;

impl CustomOp2 for MatMul {
    fn name(&self) -> &'static str {
        "drivescript-matmul"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (a, b) = (l1.dims(), l2.dims());
        let r = a.len();
        if r < 2 || b.len() != r || a[..r - 2] != b[..r - 2] || a[r - 1] != b[r - 2] {
            candle_core::bail!("matmul: shapes {a:?} and {b:?} do not multiply");
        }
        let (m, k, n) = (a[r - 2], a[r - 1], b[r - 1]);
        let batch: usize = a[..r - 2].iter().product();
        let out = s1.matmul(s2, (batch, m, n, k), l1, l2)?;
        let mut dims = a[..r - 2].to_vec();
        dims.extend([m, n]);
        Ok((out, Shape::from_dims(&dims)))
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let r = a.rank();
        let ga = if a.track_op() {
            Some(matmul(grad, &b.transpose(r - 2, r - 1)?)?)
        } else {
            None
        };
        let gb = if b.track_op() {
            Some(matmul(&a.transpose(r - 2, r - 1)?, grad)?)
        } else {
            None
        };
        Ok((ga, gb))
    }
}

/// A linear layer `x Wᵀ + b` over the last dimension, for inputs of any rank. candle-nn's
/// `Linear` multiplies a 3-D or 4-D input by the weight broadcast to every leading index, so
/// backward sums a weight-sized gradient over thousands of lane or agent pairs, and the bias
/// gradient over as many rows, with candle's strided reduction: a fifth of a training step.
/// Here the leading dimensions are flattened into one matrix product, and the bias is added
/// by an op whose backward is a product with a ones row.
#[derive(Debug, Clone)]
pub struct Linear {
    weight: Tensor,
    bias: Option<Tensor>,
}

/// A [`Linear`] from `inputs` to `outputs` with a bias, its variables `weight` and `bias`
/// under `vb` (as candle-nn names them, so checkpoints load either way).
pub fn linear(inputs: usize, outputs: usize, vb: VarBuilder) -> Result<Linear> {
    let l = candle_nn::linear(inputs, outputs, vb)?;
    Ok(Linear {
        weight: l.weight().clone(),
        bias: l.bias().cloned(),
    })
}

/// A [`Linear`] without bias.
pub fn linear_no_bias(inputs: usize, outputs: usize, vb: VarBuilder) -> Result<Linear> {
    let l = candle_nn::linear_no_bias(inputs, outputs, vb)?;
    Ok(Linear {
        weight: l.weight().clone(),
        bias: None,
    })
}

impl Linear {
    /// The weight, `[outputs, inputs]`.
    pub fn weight(&self) -> &Tensor {
        &self.weight
    }

    /// The bias, `[outputs]`, where there is one.
    pub fn bias(&self) -> Option<&Tensor> {
        self.bias.as_ref()
    }
}

impl Module for Linear {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let dims = x.dims();
        let (lead, k) = dims.split_at(dims.len() - 1);
        let rows: usize = lead.iter().product();
        let y = x.reshape((rows, k[0]))?.matmul(&self.weight.t()?)?;
        let y = match &self.bias {
            Some(b) => y.apply_op2(b, AddBias)?,
            None => y,
        };
        let mut out = lead.to_vec();
        out.push(self.weight.dim(0)?);
        y.reshape(out)
    }
}

/// `x + b` for `x` `[rows, n]` and `b` `[n]`.
struct AddBias;

fn add_bias<T: candle_core::WithDType + num_traits::Float>(
    x: &[T],
    lx: &Layout,
    b: &[T],
    lb: &Layout,
) -> Result<(CpuStorage, Shape)> {
    let (Some((x0, x1)), Some((b0, b1))) = (lx.contiguous_offsets(), lb.contiguous_offsets())
    else {
        candle_core::bail!("bias: inputs have to be contiguous");
    };
    let (x, b) = (&x[x0..x1], &b[b0..b1]);
    let n = b.len();
    if n == 0 || x.len() % n != 0 {
        candle_core::bail!("bias of {n} for {} values", x.len());
    }
    let mut out = Vec::with_capacity(x.len());
    for row in x.chunks(n) {
        out.extend(row.iter().zip(b).map(|(v, c)| *v + *c));
    }
    Ok((
        candle_core::WithDType::to_cpu_storage_owned(out),
        lx.shape().clone(),
    ))
}

impl CustomOp2 for AddBias {
    fn name(&self) -> &'static str {
        "drivescript-add-bias"
    }

    fn cpu_fwd(
        &self,
        x: &CpuStorage,
        lx: &Layout,
        b: &CpuStorage,
        lb: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        match (x, b) {
            (CpuStorage::F32(x), CpuStorage::F32(b)) => add_bias(x, lx, b, lb),
            (CpuStorage::F64(x), CpuStorage::F64(b)) => add_bias(x, lx, b, lb),
            _ => candle_core::bail!("bias: only f32 and f64 of one type are supported"),
        }
    }

    fn bwd(
        &self,
        x: &Tensor,
        _b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let rows = x.dim(0)?;
        let ones = Tensor::ones((1, rows), grad.dtype(), grad.device())?;
        let gb = ones.matmul(&grad.contiguous()?)?.squeeze(0)?;
        Ok((Some(grad.clone()), Some(gb)))
    }
}

/// Layer normalisation over the last dimension, `(x − mean) / √(var + eps) · w + b` (biased
/// variance, as candle-nn's `layer_norm_slow` and PyTorch), in one pass forward and one
/// backward. Built from tensor ops it took a dozen passes each way over the per-pair features
/// of the normalised attention scores, most of a training step.
pub fn layer_norm(x: &Tensor, w: &Tensor, b: &Tensor, eps: f64) -> Result<Tensor> {
    x.contiguous()?
        .apply_op3(&w.contiguous()?, &b.contiguous()?, LayerNorm { eps })
}

struct LayerNorm {
    eps: f64,
}

/// Rows handed to one rayon task.
const NORM_ROWS: usize = 64;

fn contiguous<'a, T>(s: &'a [T], l: &Layout, what: &str) -> Result<&'a [T]> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&s[a..b]),
        None => candle_core::bail!("layer norm: {what} has to be contiguous"),
    }
}

/// A row's mean and `1/√(var + eps)` (biased variance); `n` is the row's length.
fn row_stats<T: num_traits::Float>(xr: &[T], n: T, eps: T) -> (T, T) {
    let mean = xr.iter().fold(T::zero(), |a, &v| a + v) / n;
    let var = xr
        .iter()
        .fold(T::zero(), |a, &v| a + (v - mean) * (v - mean))
        / n;
    (mean, T::one() / (var + eps).sqrt())
}

fn norm_fwd<T: candle_core::WithDType + num_traits::Float + Send + Sync>(
    x: &[T],
    w: &[T],
    b: &[T],
    eps: f64,
) -> Vec<T> {
    let d = w.len().max(1);
    let eps = T::from(eps).expect("eps fits");
    let n = T::from(d).expect("width fits");
    let mut y = vec![T::zero(); x.len()];
    let row = |(xr, yr): (&[T], &mut [T])| {
        let (mean, rstd) = row_stats(xr, n, eps);
        for i in 0..xr.len() {
            yr[i] = (xr[i] - mean) * rstd * w[i] + b[i];
        }
    };
    if x.len() >= 1 << 14 {
        x.par_chunks(d).zip(y.par_chunks_mut(d)).for_each(row);
    } else {
        x.chunks(d).zip(y.chunks_mut(d)).for_each(row);
    }
    y
}

/// `∂L/∂x`, `∂L/∂w` and `∂L/∂b` of [`layer_norm`] for upstream gradient `g`.
fn norm_bwd<T: candle_core::WithDType + num_traits::Float + Send + Sync>(
    x: &[T],
    w: &[T],
    g: &[T],
    eps: f64,
) -> (Vec<T>, Vec<T>, Vec<T>) {
    let d = w.len().max(1);
    let eps = T::from(eps).expect("eps fits");
    let n = T::from(d).expect("width fits");
    let mut dx = vec![T::zero(); x.len()];
    let chunk = |((xc, gc), dxc): ((&[T], &[T]), &mut [T])| {
        let (mut dw, mut db) = (vec![T::zero(); d], vec![T::zero(); d]);
        let mut xhat = vec![T::zero(); d];
        for ((xr, gr), dxr) in xc.chunks(d).zip(gc.chunks(d)).zip(dxc.chunks_mut(d)) {
            let (mean, rstd) = row_stats(xr, n, eps);
            let (mut m1, mut m2) = (T::zero(), T::zero());
            for i in 0..d {
                xhat[i] = (xr[i] - mean) * rstd;
                let gw = gr[i] * w[i];
                m1 = m1 + gw;
                m2 = m2 + gw * xhat[i];
                dw[i] = dw[i] + gr[i] * xhat[i];
                db[i] = db[i] + gr[i];
            }
            let (m1, m2) = (m1 / n, m2 / n);
            for i in 0..d {
                dxr[i] = rstd * (gr[i] * w[i] - m1 - xhat[i] * m2);
            }
        }
        (dw, db)
    };
    let add = |(mut w1, mut b1): (Vec<T>, Vec<T>), (w2, b2): (Vec<T>, Vec<T>)| {
        for i in 0..w1.len() {
            w1[i] = w1[i] + w2[i];
            b1[i] = b1[i] + b2[i];
        }
        (w1, b1)
    };
    let zero = || (vec![T::zero(); d], vec![T::zero(); d]);
    let rows = d * NORM_ROWS;
    let (dw, db) = if x.len() >= 1 << 14 {
        x.par_chunks(rows)
            .zip(g.par_chunks(rows))
            .zip(dx.par_chunks_mut(rows))
            .map(chunk)
            .reduce(zero, add)
    } else {
        x.chunks(rows)
            .zip(g.chunks(rows))
            .zip(dx.chunks_mut(rows))
            .map(chunk)
            .fold(zero(), add)
    };
    (dx, dw, db)
}

impl CustomOp3 for LayerNorm {
    fn name(&self) -> &'static str {
        "drivescript-layer-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let d = *l1.dims().last().unwrap_or(&0);
        if l2.dims() != [d] || l3.dims() != [d] {
            candle_core::bail!(
                "layer norm: input {:?} with gain {:?} and bias {:?}",
                l1.dims(),
                l2.dims(),
                l3.dims()
            );
        }
        let shape = Shape::from_dims(l1.dims());
        let out = match (s1, s2, s3) {
            (CpuStorage::F32(x), CpuStorage::F32(w), CpuStorage::F32(b)) => {
                CpuStorage::F32(norm_fwd(
                    contiguous(x, l1, "input")?,
                    contiguous(w, l2, "gain")?,
                    contiguous(b, l3, "bias")?,
                    self.eps,
                ))
            }
            (CpuStorage::F64(x), CpuStorage::F64(w), CpuStorage::F64(b)) => {
                CpuStorage::F64(norm_fwd(
                    contiguous(x, l1, "input")?,
                    contiguous(w, l2, "gain")?,
                    contiguous(b, l3, "bias")?,
                    self.eps,
                ))
            }
            _ => candle_core::bail!("layer norm: only f32 and f64 of one type are supported"),
        };
        Ok((out, shape))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let shape = x.shape().clone();
        let d = w.dims1()?;
        macro_rules! run {
            ($t:ty) => {{
                let (dx, dw, db) = norm_bwd::<$t>(
                    &x.flatten_all()?.to_vec1::<$t>()?,
                    &w.to_vec1::<$t>()?,
                    &grad.contiguous()?.flatten_all()?.to_vec1::<$t>()?,
                    self.eps,
                );
                (
                    Tensor::from_vec(dx, shape, x.device())?,
                    Tensor::from_vec(dw, d, x.device())?,
                    Tensor::from_vec(db, d, x.device())?,
                )
            }};
        }
        let (dx, dw, db) = match x.dtype() {
            DType::F32 => run!(f32),
            DType::F64 => run!(f64),
            t => candle_core::bail!("layer norm: {t:?} is not supported"),
        };
        Ok((
            x.track_op().then_some(dx),
            w.track_op().then_some(dw),
            b.track_op().then_some(db),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device, Var};
    use candle_nn::VarMap;

    #[test]
    fn layer_norm_matches_the_op_by_op_form_and_its_gradients() {
        let dev = Device::Cpu;
        // Large enough for the parallel path (≥ 2^14 elements) and a small one.
        for shape in [vec![2usize, 3, 5, 8], vec![4, 40, 30, 16]] {
            let d = shape[shape.len() - 1];
            let x = Var::from_tensor(&Tensor::randn(0.5f64, 2.0, shape.as_slice(), &dev).unwrap())
                .unwrap();
            let w = Var::from_tensor(&Tensor::randn(1f64, 0.3, d, &dev).unwrap()).unwrap();
            let b = Var::from_tensor(&Tensor::randn(0f64, 0.3, d, &dev).unwrap()).unwrap();
            let up = Tensor::randn(0f64, 1.0, shape.as_slice(), &dev).unwrap();
            let ours = layer_norm(x.as_tensor(), w.as_tensor(), b.as_tensor(), 1e-5).unwrap();
            let theirs =
                candle_nn::ops::layer_norm_slow(x.as_tensor(), w.as_tensor(), b.as_tensor(), 1e-5)
                    .unwrap();
            // Summation order differs (one pass here, op by op there): f64 round-off only,
            // measured at 2e-13 to 3e-12.
            let d = max_diff(&ours, &theirs);
            assert!(d < 1e-9, "{shape:?}: {d}");
            let g1 = (&ours * &up)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            let g2 = (&theirs * &up)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            for v in [&x, &w, &b] {
                let (p, q) = (
                    g1.get(v.as_tensor()).unwrap(),
                    g2.get(v.as_tensor()).unwrap(),
                );
                assert!(max_diff(p, q) < 1e-9, "{shape:?}: {}", max_diff(p, q));
            }
        }
        // Constant gain and bias (the frozen model): only the input's gradient is computed.
        let x = Var::from_tensor(&Tensor::randn(0f64, 1.0, (3, 8), &dev).unwrap()).unwrap();
        let (w, b) = (
            Tensor::ones(8, DType::F64, &dev).unwrap(),
            Tensor::zeros(8, DType::F64, &dev).unwrap(),
        );
        let g = layer_norm(x.as_tensor(), &w, &b, 1e-5)
            .unwrap()
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert!(g.get(x.as_tensor()).is_some() && g.get(&w).is_none() && g.get(&b).is_none());
    }

    #[test]
    fn matmul_matches_candle_and_skips_constant_operands() {
        let dev = Device::Cpu;
        let a = Var::from_tensor(&Tensor::randn(0f64, 1.0, (2, 3, 4, 5), &dev).unwrap()).unwrap();
        let b = Var::from_tensor(&Tensor::randn(0f64, 1.0, (2, 3, 6, 5), &dev).unwrap()).unwrap();
        let w = Tensor::randn(0f64, 1.0, (2, 3, 4, 6), &dev).unwrap();
        let bt = b.as_tensor().transpose(2, 3).unwrap();
        let ours = matmul(a.as_tensor(), &bt).unwrap();
        let theirs = a.as_tensor().matmul(&bt).unwrap();
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f64>().unwrap();
        assert_eq!(flat(&ours), flat(&theirs));
        let g1 = (&ours * &w).unwrap().sum_all().unwrap().backward().unwrap();
        let g2 = (&theirs * &w)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        for v in [&a, &b] {
            let (x, y) = (
                flat(g1.get(v.as_tensor()).unwrap()),
                flat(g2.get(v.as_tensor()).unwrap()),
            );
            let diff = x
                .iter()
                .zip(&y)
                .fold(0f64, |m, (p, q)| m.max((p - q).abs()));
            assert!(diff < 1e-12, "{diff}");
        }
        // A constant right operand: only the left gradient is computed.
        let c = b.as_tensor().detach().transpose(2, 3).unwrap();
        let g = (matmul(a.as_tensor(), &c).unwrap() * &w)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert!(g.get(a.as_tensor()).is_some() && g.get(&c).is_none());
    }

    #[test]
    fn linear_matches_candle_nn_forward_and_backward() {
        let dev = Device::Cpu;
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F64, &dev);
        let ours = linear(4, 6, vb.pp("l")).unwrap();
        let theirs = candle_nn::Linear::new(ours.weight().clone(), ours.bias().cloned());
        let x = Var::from_tensor(&Tensor::randn(0f64, 1.0, (2, 3, 5, 4), &dev).unwrap()).unwrap();
        let w = Tensor::randn(0f64, 1.0, (2, 3, 5, 6), &dev).unwrap();
        let mut got = Vec::new();
        for y in [ours.forward(x.as_tensor()), theirs.forward(x.as_tensor())] {
            let y = y.unwrap();
            let g = (&y * &w).unwrap().sum_all().unwrap().backward().unwrap();
            let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f64>().unwrap();
            got.push([
                flat(&y),
                flat(g.get(x.as_tensor()).unwrap()),
                flat(g.get(ours.weight()).unwrap()),
                flat(g.get(ours.bias().unwrap()).unwrap()),
            ]);
        }
        for (i, name) in [
            "output",
            "input gradient",
            "weight gradient",
            "bias gradient",
        ]
        .iter()
        .enumerate()
        {
            let diff = got[0][i]
                .iter()
                .zip(&got[1][i])
                .fold(0f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(diff < 1e-12, "{name} differs by {diff}");
        }
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f64 {
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap()
    }

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
        let diff = max_diff(&fused, &composed);
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
        let diff = max_diff(a, b);
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
