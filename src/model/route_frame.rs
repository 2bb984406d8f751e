//! The frame of each agent's route: a future told as distance along a lane route and offset
//! across it (`scene::routes`), taken to the plane inside the computation graph so that
//! guidance costs in the plane reach the coordinates the model generates.
//!
//! Told against its route, an urban car's 8 s future spreads 0.78 m across, against 10.90 m
//! across the line of its heading (data/cities-wip/README.md, "Routes"): a model that is
//! imprecise across keeps the car on its lane.

use candle_core::{DType, Result, Tensor};

use crate::geom::FrenetPath;

/// One route per agent row.
#[derive(Debug, Clone)]
pub struct RouteFrames {
    paths: Vec<FrenetPath>,
}

impl RouteFrames {
    /// The frames of `paths`, the `i`-th for the `i`-th agent row.
    pub fn new(paths: Vec<FrenetPath>) -> Self {
        Self { paths }
    }

    /// How many agent rows.
    pub fn len(&self) -> usize {
        self.paths.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.paths.is_empty()
    }

    /// The path of agent row `i`.
    pub fn path(&self, i: usize) -> &FrenetPath {
        &self.paths[i]
    }

    /// Plane poses of Frenet coordinates `s` and `d` (`[A, T]`, row `i` on path `i`):
    /// `[A, T, 3]`, the point and the path's heading at `s`.
    ///
    /// The values are [`FrenetPath::frame_at`]'s, as [`FrenetPath::to_cartesian`] and
    /// [`FrenetPath::heading_at`] give them. The derivatives are the frame's
    /// own: along the path's tangent (bent by the turning normal away from it) for `s`, along
    /// its normal for `d`, and the heading by the path's curvature. They enter the graph as
    /// `value + J·(x − detach(x))`, which adds exactly zero to the value: the piece of path
    /// each point falls on is chosen from the values, and is constant under a small change.
    pub fn to_plane(&self, s: &Tensor, d: &Tensor) -> Result<Tensor> {
        let (a, t) = s.dims2()?;
        if d.dims() != s.dims() || a != self.paths.len() {
            candle_core::bail!(
                "route frames: s {:?} and d {:?} for {} routes",
                s.dims(),
                d.dims(),
                self.paths.len()
            );
        }
        let sv = s.to_dtype(DType::F64)?.to_vec2::<f64>()?;
        let dv = d.to_dtype(DType::F64)?.to_vec2::<f64>()?;
        let (mut base, mut js, mut jd) = (
            Vec::with_capacity(a * t * 3),
            Vec::with_capacity(a * t * 3),
            Vec::with_capacity(a * t * 3),
        );
        for (i, path) in self.paths.iter().enumerate() {
            for k in 0..t {
                let f = path.frame_at(sv[i][k], dv[i][k]);
                base.extend([f.point.x, f.point.y, f.heading]);
                js.extend([f.along.x, f.along.y, f.curvature]);
                jd.extend([f.across.x, f.across.y, 0.0]);
            }
        }
        let (dev, dt) = (s.device(), s.dtype());
        let table = |v: Vec<f64>| Tensor::from_vec(v, (a, t, 3), dev)?.to_dtype(dt);
        let ds = (s - s.detach())?.unsqueeze(2)?;
        let dd = (d - d.detach())?.unsqueeze(2)?;
        table(base)? + table(js)?.broadcast_mul(&ds)? + table(jd)?.broadcast_mul(&dd)?
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{Point, Polyline};
    use candle_core::{Device, Var};

    /// A quarter circle of radius 20 m, then straight on north.
    fn bend() -> FrenetPath {
        let mut pts: Vec<Point> = (0..=12)
            .map(|k| {
                let a = std::f64::consts::FRAC_PI_2 * k as f64 / 12.0;
                Point::new(20.0 * a.sin(), 20.0 * (1.0 - a.cos()))
            })
            .collect();
        pts.push(Point::new(20.0, 60.0));
        FrenetPath::new(Polyline::new(pts).unwrap())
    }

    fn straight() -> FrenetPath {
        FrenetPath::new(Polyline::new([Point::new(0.0, 0.0), Point::new(100.0, 0.0)]).unwrap())
    }

    #[test]
    fn the_plane_pose_is_the_paths_own_and_inverts_the_projection() {
        let frames = RouteFrames::new(vec![bend(), straight()]);
        let sv = [[3.0, 17.5, 31.0, 70.0], [0.0, 10.0, 50.0, 120.0]];
        let dv = [[0.4, -1.2, 2.0, 0.0], [1.0, -3.0, 0.0, 0.5]];
        let s = Tensor::new(&sv, &Device::Cpu).unwrap();
        let d = Tensor::new(&dv, &Device::Cpu).unwrap();
        let out = frames.to_plane(&s, &d).unwrap().to_vec3::<f64>().unwrap();
        for i in 0..2 {
            for k in 0..4 {
                let path = frames.path(i);
                let p = path.to_cartesian(sv[i][k], dv[i][k]);
                let want = [p.x, p.y, path.heading_at(sv[i][k])];
                let got = &out[i][k];
                assert!(
                    (0..3).all(|j| (got[j] - want[j]).abs() < 1e-12),
                    "{got:?} {want:?}"
                );
                let back = path.project(p);
                assert!((back.s - sv[i][k]).abs() < 1e-9 && (back.d - dv[i][k]).abs() < 1e-9);
            }
        }
        // Past the end of the straight path it goes on straight.
        assert!((out[1][3][0] - 120.0).abs() < 1e-12 && (out[1][3][1] - 0.5).abs() < 1e-12);
        // A row count or shape that does not match is an error, not a panic.
        assert!(frames
            .to_plane(&s.narrow(0, 0, 1).unwrap(), &d.narrow(0, 0, 1).unwrap())
            .is_err());
        assert!(frames.to_plane(&s, &d.narrow(1, 0, 2).unwrap()).is_err());
    }

    #[test]
    fn gradients_match_finite_differences_on_a_bend() {
        let frames = RouteFrames::new(vec![bend()]);
        let sv = [2.5, 9.0, 16.0, 24.0, 30.5, 45.0];
        let dv = [0.3, -0.8, 1.5, -2.0, 0.0, 0.7];
        let s = Var::new(&[sv], &Device::Cpu).unwrap();
        let d = Var::new(&[dv], &Device::Cpu).unwrap();
        // A weighted sum of every output, so that each output's derivative counts.
        let w: Vec<f64> = (0..sv.len() * 3).map(|i| 0.3 + 0.1 * i as f64).collect();
        let wt = Tensor::from_vec(w.clone(), (1, sv.len(), 3), &Device::Cpu).unwrap();
        let out = frames.to_plane(s.as_tensor(), d.as_tensor()).unwrap();
        let grads = (out * &wt).unwrap().sum_all().unwrap().backward().unwrap();
        let gs = grads.get(&s).unwrap().to_vec2::<f64>().unwrap();
        let gd = grads.get(&d).unwrap().to_vec2::<f64>().unwrap();
        let path = frames.path(0);
        let value = |k: usize, s: f64, d: f64| {
            let p = path.to_cartesian(s, d);
            let h = path.heading_at(s);
            w[k * 3] * p.x + w[k * 3 + 1] * p.y + w[k * 3 + 2] * h
        };
        let eps = 1e-5;
        for k in 0..sv.len() {
            let fs = (value(k, sv[k] + eps, dv[k]) - value(k, sv[k] - eps, dv[k])) / (2.0 * eps);
            let fd = (value(k, sv[k], dv[k] + eps) - value(k, sv[k], dv[k] - eps)) / (2.0 * eps);
            assert!(
                (gs[0][k] - fs).abs() < 1e-6,
                "point {k}: ∂/∂s {} against {fs}",
                gs[0][k]
            );
            assert!(
                (gd[0][k] - fd).abs() < 1e-6,
                "point {k}: ∂/∂d {} against {fd}",
                gd[0][k]
            );
        }
    }
}
