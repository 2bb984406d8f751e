//! Route features: where each agent's noisy future runs against the lanes. At a few future
//! times the noisy coefficients are decoded to a pose, and the pose is measured against the
//! nearest lane point (lateral and longitudinal offset, heading difference), so that the
//! denoiser sees how far a candidate future is from a lane instead of having to infer it from
//! pooled lane embeddings and the coefficients. Without these, the cities model placed cars
//! no closer than about a metre to a lane even from the recorded future with little noise
//! (`data/cities-wip/README.md`).

use candle_core::{DType, Result, Tensor, D};

/// Scale (metres) of the lateral offset feature: `tanh(offset / LATERAL_SCALE)`.
const LATERAL_SCALE: f64 = 2.0;
/// Scale (metres) of the longitudinal offset feature: points are up to a lane's length / 19
/// apart, so this offset says how well the nearest point stands for the lane.
const LONGITUDINAL_SCALE: f64 = 5.0;

/// Why a checkpoint with route features cannot go to the PyTorch port (`train --export`,
/// `bench sample --export`).
pub const NOT_PORTED: &str = "the checkpoint measures futures against the lanes (route_times > \
     0), which the PyTorch port (benches/torch) does not compute";

/// Features per route time: lateral offset, longitudinal offset, cos and sin of the heading
/// difference.
pub const FEATURES_PER_TIME: usize = 4;

/// The tensors route features are measured with (built by `train::batch::build`).
#[derive(Debug, Clone)]
pub struct RouteInputs {
    /// Every lane point of the window in each agent's current frame, metres, with the lane's
    /// direction there: `(x, y, cos θ, sin θ)`, `[B, N, L, 4]`. Absent lanes' points lie far
    /// away, so that they are never the nearest.
    pub points: Tensor,
    /// Normalised coefficient → `(x, y, heading)` at each route time, `[K, T·3]`.
    pub basis: Tensor,
    /// What the coefficients add to: the basis mean plus the agent's constant-velocity anchor,
    /// `[B, N, T·3]`.
    pub offset: Tensor,
}

impl RouteInputs {
    /// The same inputs with their float tensors in `dtype`.
    pub fn to_dtype(&self, dtype: DType) -> Result<Self> {
        Ok(Self {
            points: self.points.to_dtype(dtype)?,
            basis: self.basis.to_dtype(dtype)?,
            offset: self.offset.to_dtype(dtype)?,
        })
    }

    /// Every tensor.
    pub fn tensors(&self) -> [&Tensor; 3] {
        [&self.points, &self.basis, &self.offset]
    }
}

/// Future steps (0-based, of `future`) at which route features are measured: `times` evenly
/// spaced, the last at the end of the future.
pub fn route_steps(future: usize, times: usize) -> Vec<usize> {
    (1..=times)
        .map(|i| (i * future).div_ceil(times.max(1)).clamp(1, future.max(1)) - 1)
        .collect()
}

/// Route features of noisy coefficients `x` `[B, N, K]`: `[B, N, T·4]`. Differentiable in `x`
/// (the choice of nearest point is not).
pub fn route_features(x: &Tensor, r: &RouteInputs) -> Result<Tensor> {
    let (b, n, _) = x.dims3()?;
    let l = r.points.dim(2)?;
    let t = r.basis.dim(1)? / 3;
    let dt = x.dtype();
    let pose = x
        .reshape((b * n, ()))?
        .matmul(&r.basis)?
        .reshape((b, n, t, 3))?
        .broadcast_add(&r.offset.reshape((b, n, t, 3))?)?;
    let xy = pose.narrow(3, 0, 2)?;
    let heading = pose.narrow(3, 2, 1)?.squeeze(3)?;
    // Squared distances to every lane point, [B, N, T, L]; no gradient is needed to choose.
    let pts_xy = r.points.narrow(3, 0, 2)?;
    let d2 = xy
        .detach()
        .unsqueeze(3)?
        .broadcast_sub(&pts_xy.unsqueeze(2)?)?
        .sqr()?
        .sum(D::Minus1)?;
    let nearest = d2.argmin(D::Minus1)?; // [B, N, T], u32
    let base: Vec<u32> = (0..(b * n) as u32)
        .flat_map(|i| std::iter::repeat_n(i * l as u32, t))
        .collect();
    let base = Tensor::from_vec(base, (b, n, t), x.device())?;
    let flat = (nearest + base)?.flatten_all()?;
    let near = r
        .points
        .reshape((b * n * l, 4))?
        .index_select(&flat, 0)?
        .reshape((b, n, t, 4))?;
    let d = (xy - near.narrow(3, 0, 2)?)?;
    let (dx, dy) = (
        d.narrow(3, 0, 1)?.squeeze(3)?,
        d.narrow(3, 1, 1)?.squeeze(3)?,
    );
    let (c, s) = (
        near.narrow(3, 2, 1)?.squeeze(3)?,
        near.narrow(3, 3, 1)?.squeeze(3)?,
    );
    let lon = ((&dx * &c)? + (&dy * &s)?)?;
    let lat = ((&dy * &c)? - (&dx * &s)?)?;
    let (hc, hs) = (heading.cos()?, heading.sin()?);
    let cos_dh = ((&hc * &c)? + (&hs * &s)?)?;
    let sin_dh = ((&hs * &c)? - (&hc * &s)?)?;
    let f = Tensor::stack(
        &[
            (lat / LATERAL_SCALE)?.tanh()?,
            (lon / LONGITUDINAL_SCALE)?.tanh()?,
            cos_dh,
            sin_dh,
        ],
        3,
    )?;
    f.reshape((b, n, t * FEATURES_PER_TIME))?.to_dtype(dt)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn route_steps_end_at_the_last_future_step() {
        assert_eq!(route_steps(80, 8), vec![9, 19, 29, 39, 49, 59, 69, 79]);
        assert_eq!(route_steps(40, 3), vec![13, 26, 39]);
        assert_eq!(route_steps(5, 5), vec![0, 1, 2, 3, 4]);
    }

    #[test]
    fn offsets_are_measured_in_the_nearest_points_frame() {
        let dev = Device::Cpu;
        // One agent, one route time; the coefficient is the pose's y. Two lane points: one
        // heading along +x at (0, 0), one heading along +y at (10, 10).
        let basis = Tensor::new(&[[0f32, 1.0, 0.0]], &dev).unwrap();
        let offset = Tensor::new(&[[[1f32, 0.0, 0.0]]], &dev).unwrap();
        let points =
            Tensor::new(&[[[[0f32, 0.0, 1.0, 0.0], [10.0, 10.0, 0.0, 1.0]]]], &dev).unwrap();
        let r = RouteInputs {
            points,
            basis,
            offset,
        };
        // Pose (1, 0.5, 0): nearest (0, 0); 1 m along, 0.5 m to the left, same heading.
        // Pose (1, 9.5, 0): nearest (10, 10), heading +y; 0.5 m short of it along the lane,
        // 9 m to its left, heading 90° to its right.
        for (y, want) in [
            (
                0.5f32,
                [(0.5f32 / 2.0).tanh(), (1.0f32 / 5.0).tanh(), 1.0, 0.0],
            ),
            (
                9.5,
                [(9f32 / 2.0).tanh(), (-0.5f32 / 5.0).tanh(), 0.0, -1.0],
            ),
        ] {
            let x = Tensor::new(&[[[y]]], &dev).unwrap();
            let f: Vec<f32> = route_features(&x, &r)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            for (a, b) in f.iter().zip(want) {
                assert!((a - b).abs() < 1e-6, "{y}: {f:?}");
            }
        }
    }
}
