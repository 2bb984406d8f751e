//! The Frenet frame of a path: `s` is arc length along it, `d` the signed lateral offset (left
//! positive).
//!
//! Projecting onto the nearest segment gives an `(s, d)` that jumps where two segments meet at an
//! angle, and a jump in a guidance cost is a spike in its gradient. Instead every vertex gets the
//! bisector of its two segment normals, the normal is interpolated linearly along each segment,
//! and a point maps to the `t` where it lies on the interpolated normal line through `P(t)`. That
//! map is continuous across joints (both sides share the vertex normal) and smooth inside each
//! segment, and `to_cartesian(project(p)) == p` within the tube where normal lines do not cross
//! (|d| below the local radius of curvature). Beyond both ends the path continues straight.

use super::{cross, left_normal, Point, Polyline};

/// A point expressed in a path's Frenet frame, with its derivatives w.r.t. the world point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrenetPoint {
    /// Arc length along the path (negative before its start, above its length past its end).
    pub s: f64,
    /// Signed lateral offset, positive to the left of the direction of travel.
    pub d: f64,
    /// ∂s/∂x, ∂s/∂y.
    pub ds: [f64; 2],
    /// ∂d/∂x, ∂d/∂y.
    pub dd: [f64; 2],
}

/// A Frenet point taken to the world ([`FrenetPath::frame_at`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FramePoint {
    /// The world point.
    pub point: Point,
    /// ∂point/∂s.
    pub along: Point,
    /// ∂point/∂d: the unit normal, left of the direction of travel.
    pub across: Point,
    /// The path's heading at `s` (radians), as [`FrenetPath::heading_at`].
    pub heading: f64,
    /// ∂heading/∂s, as [`FrenetPath::curvature_at`].
    pub curvature: f64,
}

/// A reference path with smooth, continuous Frenet coordinates.
#[derive(Debug, Clone, PartialEq)]
pub struct FrenetPath {
    line: Polyline,
    /// Unit normal at every vertex (segment normal at the ends, bisector inside).
    normals: Vec<Point>,
    /// Bounding boxes of runs of [`CHUNK`] segments, to skip far parts of long paths.
    chunks: Vec<(Point, Point)>,
}

/// Segments per bounding box in the projection's broad phase.
const CHUNK: usize = 8;

/// One piece of the path: a segment, or the straight extension before the start / after the end.
#[derive(Clone, Copy)]
struct Piece {
    a: Point,
    e: Point,
    n0: Point,
    n1: Point,
    /// Arc length at `t = 0`.
    s0: f64,
    /// Metres of arc length per unit `t`.
    scale: f64,
    t_min: f64,
    t_max: f64,
}

impl Piece {
    fn normal(&self, t: f64) -> Point {
        self.n0 + (self.n1 - self.n0) * t
    }

    /// Roots `t` of cross(p - A - t e, n0 + t m) = 0 inside the piece's range.
    fn roots(&self, p: &Point) -> [Option<f64>; 2] {
        let m = self.n1 - self.n0;
        let q = p - self.a;
        let a = -cross(&self.e, &m);
        let b = cross(&q, &m) - cross(&self.e, &self.n0);
        let c = cross(&q, &self.n0);
        let tol = 1e-9;
        let ok = |t: f64| {
            (t.is_finite() && t >= self.t_min - tol && t <= self.t_max + tol)
                .then_some(t.clamp(self.t_min, self.t_max))
        };
        if a.abs() <= 1e-12 * (b.abs() + c.abs()).max(1e-300) {
            if b == 0.0 {
                return [None, None];
            }
            return [ok(-c / b), None];
        }
        let disc = b * b - 4.0 * a * c;
        if disc < 0.0 {
            return [None, None];
        }
        let qq = -0.5 * (b + b.signum() * disc.sqrt());
        if qq == 0.0 {
            return [ok(0.0), None];
        }
        [ok(qq / a), ok(c / qq)]
    }

    fn evaluate(&self, p: &Point, t: f64) -> FrenetPoint {
        let m = self.n1 - self.n0;
        let n = self.normal(t);
        let nn = n.norm().max(1e-12);
        let r = p - (self.a + self.e * t);
        let d = r.dot(&n) / nn;
        // dF/dt of F(t, p) = cross(p - P(t), n(t)), for the implicit-function derivative of t.
        let a = -cross(&self.e, &m);
        let b = cross(&(p - self.a), &m) - cross(&self.e, &self.n0);
        let mut ft = 2.0 * a * t + b;
        if ft.abs() < 1e-12 {
            ft = 1e-12_f64.copysign(ft);
        }
        let dt = [-n.y / ft, n.x / ft];
        let dd_dt = (-self.e.dot(&n) + r.dot(&m)) / nn - r.dot(&n) * n.dot(&m) / (nn * nn * nn);
        FrenetPoint {
            s: self.s0 + self.scale * t,
            d,
            ds: [self.scale * dt[0], self.scale * dt[1]],
            dd: [n.x / nn + dd_dt * dt[0], n.y / nn + dd_dt * dt[1]],
        }
    }
}

impl FrenetPath {
    /// Builds the frame of a polyline.
    pub fn new(line: Polyline) -> Self {
        let pts = line.points();
        let n = pts.len();
        let seg_normals: Vec<Point> = (0..n - 1)
            .map(|i| left_normal(&line.segment_direction(i)))
            .collect();
        let mut normals = Vec::with_capacity(n);
        normals.push(seg_normals[0]);
        for i in 1..n - 1 {
            let b = seg_normals[i - 1] + seg_normals[i];
            // A hairpin has no bisector; keep the incoming normal there.
            normals.push(if b.norm() < 1e-6 {
                seg_normals[i - 1]
            } else {
                b.normalize()
            });
        }
        normals.push(seg_normals[n - 2]);
        let chunks = pts
            .windows(2)
            .collect::<Vec<_>>()
            .chunks(CHUNK)
            .map(|c| {
                c.iter().fold((c[0][0], c[0][0]), |(lo, hi), w| {
                    (lo.inf(&w[0]).inf(&w[1]), hi.sup(&w[0]).sup(&w[1]))
                })
            })
            .collect();
        Self {
            line,
            normals,
            chunks,
        }
    }

    /// The underlying polyline.
    pub fn polyline(&self) -> &Polyline {
        &self.line
    }

    /// Length of the path.
    pub fn length(&self) -> f64 {
        self.line.length()
    }

    fn segment_piece(&self, i: usize) -> Piece {
        let p = self.line.points();
        let cum = self.line.arc_lengths();
        Piece {
            a: p[i],
            e: p[i + 1] - p[i],
            n0: self.normals[i],
            n1: self.normals[i + 1],
            s0: cum[i],
            scale: cum[i + 1] - cum[i],
            t_min: 0.0,
            t_max: 1.0,
        }
    }

    fn before_piece(&self) -> Piece {
        let n = self.normals[0];
        Piece {
            a: self.line.first(),
            e: self.line.segment_direction(0),
            n0: n,
            n1: n,
            s0: 0.0,
            scale: 1.0,
            t_min: f64::NEG_INFINITY,
            t_max: 0.0,
        }
    }

    fn after_piece(&self) -> Piece {
        let n = *self.normals.last().expect("two vertices");
        Piece {
            a: self.line.last(),
            e: self.line.segment_direction(self.line.segment_count() - 1),
            n0: n,
            n1: n,
            s0: self.line.length(),
            scale: 1.0,
            t_min: 0.0,
            t_max: f64::INFINITY,
        }
    }

    /// The piece and its parameter `t` at arc length `s`.
    fn piece_at(&self, s: f64) -> (Piece, f64) {
        if s < 0.0 {
            (self.before_piece(), s)
        } else if s > self.length() {
            (self.after_piece(), s - self.length())
        } else {
            let i = self.line.segment_at(s);
            let piece = self.segment_piece(i);
            (piece, (s - piece.s0) / piece.scale)
        }
    }

    /// Frenet coordinates of `p` and their derivatives w.r.t. `p`.
    pub fn project(&self, p: Point) -> FrenetPoint {
        let pts = self.line.points();
        let nseg = self.line.segment_count();
        let seg_dist = |i: usize| super::point_segment_distance(&p, &pts[i], &pts[i + 1]).0;
        // Broad phase: chunks in order of their boxes' distance, so that the nearest segment is
        // found after a few chunks and the rest are skipped.
        let mut order: Vec<(f64, usize)> = self
            .chunks
            .iter()
            .enumerate()
            .map(|(k, (lo, hi))| {
                let dx = (lo.x - p.x).max(p.x - hi.x).max(0.0);
                let dy = (lo.y - p.y).max(p.y - hi.y).max(0.0);
                (dx.hypot(dy), k)
            })
            .collect();
        order.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        let segs = |k: usize| k * CHUNK..((k + 1) * CHUNK).min(nseg);
        let mut dmin = f64::INFINITY;
        for &(lb, k) in &order {
            if lb > dmin {
                break;
            }
            for i in segs(k) {
                dmin = dmin.min(seg_dist(i));
            }
        }
        // The interpolated-normal foot is at most ~1/cos(half the joint angle) farther than the
        // nearest point, so segments much farther than that cannot hold the best root.
        let reach = 2.0 * dmin + 1e-6;
        let mut best: Option<FrenetPoint> = None;
        let consider = |piece: &Piece, best: &mut Option<FrenetPoint>| {
            for t in piece.roots(&p).into_iter().flatten() {
                let fp = piece.evaluate(&p, t);
                if best.is_none_or(|b| fp.d.abs() < b.d.abs()) {
                    *best = Some(fp);
                }
            }
        };
        consider(&self.before_piece(), &mut best);
        consider(&self.after_piece(), &mut best);
        for &(lb, k) in &order {
            if lb > reach {
                break;
            }
            for i in segs(k) {
                if seg_dist(i) <= reach {
                    consider(&self.segment_piece(i), &mut best);
                }
            }
        }
        if best.is_none() {
            for i in 0..nseg {
                consider(&self.segment_piece(i), &mut best);
            }
        }
        best.unwrap_or_else(|| self.orthogonal_fallback(&p))
    }

    /// Projection onto the nearest segment, for points past every normal line (far inside a
    /// tight bend): never used inside the tube where the smooth map is defined.
    fn orthogonal_fallback(&self, p: &Point) -> FrenetPoint {
        let hit = self.line.nearest(p);
        let dir = self.line.segment_direction(hit.segment);
        let n = left_normal(&dir);
        let a = self.line.points()[hit.segment];
        FrenetPoint {
            s: hit.s,
            d: (p - a).dot(&n),
            ds: [dir.x, dir.y],
            dd: [n.x, n.y],
        }
    }

    /// The world point at Frenet coordinates `(s, d)`.
    pub fn to_cartesian(&self, s: f64, d: f64) -> Point {
        let (piece, t) = self.piece_at(s);
        let n = piece.normal(t);
        piece.a + piece.e * t + n * (d / n.norm().max(1e-12))
    }

    /// The world point at `(s, d)` with the frame's derivatives there: what a computation
    /// graph needs to take Frenet coordinates to the plane.
    pub fn frame_at(&self, s: f64, d: f64) -> FramePoint {
        let (piece, t) = self.piece_at(s);
        let n = piece.normal(t);
        let len = n.norm().max(1e-12);
        let unit = n / len;
        let m = piece.n1 - piece.n0;
        // d(n/|n|)/dt: the normal turns as it is interpolated along the piece.
        let turn = (m - unit * unit.dot(&m)) / len;
        FramePoint {
            point: piece.a + piece.e * t + unit * d,
            along: (piece.e + turn * d) / piece.scale,
            across: unit,
            heading: (-n.x).atan2(n.y),
            curvature: cross(&n, &m) / (len * len * piece.scale),
        }
    }

    /// Heading (radians) of the path's tangent at `s`, consistent with the Frenet frame.
    pub fn heading_at(&self, s: f64) -> f64 {
        let (piece, t) = self.piece_at(s);
        let n = piece.normal(t);
        (-n.x).atan2(n.y)
    }

    /// Signed curvature (1/m, positive turning left) at `s`: dθ/ds of [`Self::heading_at`].
    pub fn curvature_at(&self, s: f64) -> f64 {
        let (piece, t) = self.piece_at(s);
        let n = piece.normal(t);
        let m = piece.n1 - piece.n0;
        cross(&n, &m) / (n.norm_squared().max(1e-24) * piece.scale)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn arc(radius: f64, sweep: f64, n: usize) -> FrenetPath {
        let pts = (0..n).map(|k| {
            let a = sweep * k as f64 / (n - 1) as f64;
            Point::new(radius * a.sin(), radius * (1.0 - a.cos()))
        });
        FrenetPath::new(Polyline::new(pts).unwrap())
    }

    fn zigzag() -> FrenetPath {
        FrenetPath::new(
            Polyline::new([
                Point::new(0.0, 0.0),
                Point::new(20.0, 0.0),
                Point::new(35.0, 10.0),
                Point::new(50.0, 5.0),
                Point::new(80.0, 6.0),
            ])
            .unwrap(),
        )
    }

    #[test]
    fn straight_path_is_cartesian() {
        let f =
            FrenetPath::new(Polyline::new([Point::new(0.0, 0.0), Point::new(10.0, 0.0)]).unwrap());
        let fp = f.project(Point::new(3.0, 2.0));
        assert!((fp.s - 3.0).abs() < 1e-12 && (fp.d - 2.0).abs() < 1e-12);
        assert_eq!(fp.ds, [1.0, 0.0]);
        assert_eq!(fp.dd, [0.0, 1.0]);
        let before = f.project(Point::new(-4.0, -1.0));
        assert!((before.s + 4.0).abs() < 1e-12 && (before.d + 1.0).abs() < 1e-12);
        let after = f.project(Point::new(14.0, 1.0));
        assert!((after.s - 14.0).abs() < 1e-12 && (after.d - 1.0).abs() < 1e-12);
    }

    #[test]
    fn left_turn_arc_has_positive_curvature_and_d_left() {
        let f = arc(50.0, 1.2, 40);
        assert!((f.curvature_at(30.0) - 1.0 / 50.0).abs() < 2e-3);
        // A point towards the arc's centre is to the left (the chords tilt the first normal
        // by half a chord angle, hence the loose tolerance).
        let fp = f.project(Point::new(0.0, 3.0));
        assert!((fp.d - 3.0).abs() < 1e-2 && fp.s.abs() < 0.1, "{fp:?}");
        assert!((f.heading_at(f.length()) - 1.2).abs() < 0.02);
    }

    #[test]
    fn continuous_across_a_sharp_joint() {
        let f = zigzag();
        // Walk a line that crosses the joint at (20, 0) on both sides of the path.
        for y in [-3.0, 2.5] {
            let mut prev = f.project(Point::new(15.0, y));
            for k in 1..=2000 {
                let p = Point::new(15.0 + k as f64 * 0.005, y);
                let fp = f.project(p);
                assert!(
                    (fp.s - prev.s).abs() < 0.02,
                    "s jumps at {p:?}: {prev:?} -> {fp:?}"
                );
                assert!((fp.d - prev.d).abs() < 0.02, "d jumps at {p:?}");
                prev = fp;
            }
        }
    }

    fn fd_check(f: &FrenetPath, p: Point) {
        let fp = f.project(p);
        let h = 1e-6;
        let px = f.project(p + Point::new(h, 0.0));
        let mx = f.project(p - Point::new(h, 0.0));
        let py = f.project(p + Point::new(0.0, h));
        let my = f.project(p - Point::new(0.0, h));
        let fd = [
            (px.s - mx.s) / (2.0 * h),
            (py.s - my.s) / (2.0 * h),
            (px.d - mx.d) / (2.0 * h),
            (py.d - my.d) / (2.0 * h),
        ];
        let an = [fp.ds[0], fp.ds[1], fp.dd[0], fp.dd[1]];
        for k in 0..4 {
            assert!(
                (fd[k] - an[k]).abs() < 1e-4 * (1.0 + an[k].abs()),
                "derivative {k} at {p:?}: analytic {an:?} vs fd {fd:?}"
            );
        }
    }

    proptest! {
        #[test]
        fn round_trip_sd_point_sd(s in -20.0f64..100.0, d in -4.0f64..4.0) {
            let f = zigzag();
            let p = f.to_cartesian(s, d);
            let fp = f.project(p);
            prop_assert!((fp.s - s).abs() < 1e-7, "s {} -> {}", s, fp.s);
            prop_assert!((fp.d - d).abs() < 1e-7, "d {} -> {}", d, fp.d);
        }

        #[test]
        fn round_trip_on_an_arc(s in -10.0f64..70.0, d in -8.0f64..8.0) {
            let f = arc(30.0, 2.0, 25);
            let p = f.to_cartesian(s, d);
            let fp = f.project(p);
            prop_assert!((fp.s - s).abs() < 1e-7 && (fp.d - d).abs() < 1e-7);
        }

        #[test]
        fn derivatives_match_finite_differences(s in -10.0f64..95.0, d in -4.0f64..4.0) {
            let f = zigzag();
            // Keep clear of the vertices themselves, where t hits a piece boundary and the
            // one-sided derivatives legitimately differ.
            let cum = f.polyline().arc_lengths().to_vec();
            prop_assume!(cum.iter().all(|c| (s - c).abs() > 1e-3) && s.abs() > 1e-3);
            fd_check(&f, f.to_cartesian(s, d));
        }

        #[test]
        fn derivatives_on_an_arc(s in 0.5f64..55.0, d in -8.0f64..8.0) {
            let f = arc(30.0, 2.0, 25);
            let cum = f.polyline().arc_lengths().to_vec();
            prop_assume!(cum.iter().all(|c| (s - c).abs() > 1e-3));
            fd_check(&f, f.to_cartesian(s, d));
        }
    }

    #[test]
    fn the_frame_at_a_point_is_the_derivative_of_the_map_to_the_plane() {
        // A quarter circle of radius 20 m, then straight on: points on the bend, at its
        // vertices, on the straight and beyond both ends.
        let mut pts: Vec<Point> = (0..=12)
            .map(|k| {
                let a = std::f64::consts::FRAC_PI_2 * k as f64 / 12.0;
                Point::new(20.0 * a.sin(), 20.0 * (1.0 - a.cos()))
            })
            .collect();
        pts.push(Point::new(20.0, 60.0));
        let path = FrenetPath::new(Polyline::new(pts).unwrap());
        let eps = 1e-6;
        for (s, d) in [
            (-5.0, 0.5),
            (2.5, 0.3),
            (9.0, -0.8),
            (16.0, 1.5),
            (24.0, -2.0),
            (30.5, 0.0),
            (45.0, 0.7),
            (90.0, -1.0),
        ] {
            let f = path.frame_at(s, d);
            assert!((f.point - path.to_cartesian(s, d)).norm() < 1e-12, "at {s}");
            assert_eq!(f.heading, path.heading_at(s));
            assert!((f.curvature - path.curvature_at(s)).abs() < 1e-12, "at {s}");
            let ds = (path.to_cartesian(s + eps, d) - path.to_cartesian(s - eps, d)) / (2.0 * eps);
            let dd = (path.to_cartesian(s, d + eps) - path.to_cartesian(s, d - eps)) / (2.0 * eps);
            assert!(
                (f.along - ds).norm() < 1e-6,
                "at {s}: along {:?} against {ds:?}",
                f.along
            );
            assert!(
                (f.across - dd).norm() < 1e-6,
                "at {s}: across {:?} against {dd:?}",
                f.across
            );
            let dh = (path.heading_at(s + eps) - path.heading_at(s - eps)) / (2.0 * eps);
            assert!(
                (f.curvature - dh).abs() < 1e-5,
                "at {s}: curvature {} against {dh}",
                f.curvature
            );
        }
    }
}
