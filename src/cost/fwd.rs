//! A forward-mode dual number with a fixed number of derivative slots, for the few native
//! functions whose geometry is too branchy to differentiate by hand (oriented-box clearance):
//! the same code computes the value and the exact gradient.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// A value with derivatives w.r.t. `N` inputs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fwd<const N: usize> {
    /// The value.
    pub v: f64,
    /// ∂value/∂input.
    pub g: [f64; N],
}

impl<const N: usize> Fwd<N> {
    /// A constant.
    pub fn c(v: f64) -> Self {
        Self { v, g: [0.0; N] }
    }

    /// Input number `i` with value `v`.
    pub fn var(v: f64, i: usize) -> Self {
        let mut g = [0.0; N];
        g[i] = 1.0;
        Self { v, g }
    }

    fn chain(self, v: f64, d: f64) -> Self {
        let mut g = self.g;
        g.iter_mut().for_each(|x| *x *= d);
        Self { v, g }
    }

    /// Square root (derivative 0 at 0, where it is unbounded).
    pub fn sqrt(self) -> Self {
        let r = self.v.max(0.0).sqrt();
        self.chain(r, if r > 0.0 { 0.5 / r } else { 0.0 })
    }

    /// Sine.
    pub fn sin(self) -> Self {
        self.chain(self.v.sin(), self.v.cos())
    }

    /// Cosine.
    pub fn cos(self) -> Self {
        self.chain(self.v.cos(), -self.v.sin())
    }

    /// Whether two values tie: then min and max average the derivatives, the smallest
    /// subgradient, so that symmetric configurations (two boxes exactly aligned) are not pushed
    /// one way by the order of the corners.
    fn ties(self, o: Self) -> bool {
        (self.v - o.v).abs() <= 1e-12 * (1.0 + self.v.abs().max(o.v.abs()))
    }

    fn average(self, o: Self) -> Self {
        let mut g = self.g;
        for i in 0..N {
            g[i] = 0.5 * (g[i] + o.g[i]);
        }
        Self { v: self.v, g }
    }

    /// The smaller by value (its derivatives follow).
    pub fn min(self, o: Self) -> Self {
        if self.ties(o) {
            self.average(o)
        } else if self.v < o.v {
            self
        } else {
            o
        }
    }

    /// The larger by value.
    pub fn max(self, o: Self) -> Self {
        if self.ties(o) {
            self.average(o)
        } else if self.v > o.v {
            self
        } else {
            o
        }
    }
}

impl<const N: usize> Add for Fwd<N> {
    type Output = Self;
    fn add(mut self, o: Self) -> Self {
        self.v += o.v;
        for i in 0..N {
            self.g[i] += o.g[i];
        }
        self
    }
}

impl<const N: usize> Sub for Fwd<N> {
    type Output = Self;
    fn sub(mut self, o: Self) -> Self {
        self.v -= o.v;
        for i in 0..N {
            self.g[i] -= o.g[i];
        }
        self
    }
}

impl<const N: usize> Mul for Fwd<N> {
    type Output = Self;
    fn mul(self, o: Self) -> Self {
        let mut g = [0.0; N];
        for i in 0..N {
            g[i] = self.g[i] * o.v + o.g[i] * self.v;
        }
        Self { v: self.v * o.v, g }
    }
}

impl<const N: usize> Div for Fwd<N> {
    type Output = Self;
    fn div(self, o: Self) -> Self {
        let q = self.v / o.v;
        let mut g = [0.0; N];
        for i in 0..N {
            g[i] = (self.g[i] - q * o.g[i]) / o.v;
        }
        Self { v: q, g }
    }
}

impl<const N: usize> Neg for Fwd<N> {
    type Output = Self;
    fn neg(self) -> Self {
        self.chain(-self.v, -1.0)
    }
}

impl<const N: usize> Mul<f64> for Fwd<N> {
    type Output = Self;
    fn mul(self, c: f64) -> Self {
        self.chain(self.v * c, c)
    }
}

/// A 2-D vector of forward duals.
#[derive(Debug, Clone, Copy)]
pub struct V2<const N: usize> {
    /// x.
    pub x: Fwd<N>,
    /// y.
    pub y: Fwd<N>,
}

impl<const N: usize> V2<N> {
    fn sub(self, o: Self) -> Self {
        V2 {
            x: self.x - o.x,
            y: self.y - o.y,
        }
    }
    fn dot(self, o: Self) -> Fwd<N> {
        self.x * o.x + self.y * o.y
    }
    fn scale(self, c: Fwd<N>) -> Self {
        V2 {
            x: self.x * c,
            y: self.y * c,
        }
    }
    fn add(self, o: Self) -> Self {
        V2 {
            x: self.x + o.x,
            y: self.y + o.y,
        }
    }
}

/// Corners of a box (counter-clockwise) and its two unit axes.
fn corners<const N: usize>(
    x: Fwd<N>,
    y: Fwd<N>,
    h: Fwd<N>,
    l: f64,
    w: f64,
) -> ([V2<N>; 4], [V2<N>; 2]) {
    let (c, s) = (h.cos(), h.sin());
    let u = V2 { x: c, y: s };
    let v = V2 { x: -s, y: c };
    let centre = V2 { x, y };
    let hl = u.scale(Fwd::c(0.5 * l));
    let hw = v.scale(Fwd::c(0.5 * w));
    let k = |a: f64, b: f64| centre.add(hl.scale(Fwd::c(a))).add(hw.scale(Fwd::c(b)));
    (
        [k(-1.0, -1.0), k(1.0, -1.0), k(1.0, 1.0), k(-1.0, 1.0)],
        [u, v],
    )
}

fn point_segment<const N: usize>(p: V2<N>, a: V2<N>, b: V2<N>) -> Fwd<N> {
    let e = b.sub(a);
    let len2 = e.dot(e);
    let t = if len2.v > 0.0 {
        p.sub(a).dot(e) / len2
    } else {
        Fwd::c(0.0)
    };
    let t = if t.v < 0.0 {
        Fwd::c(0.0)
    } else if t.v > 1.0 {
        Fwd::c(1.0)
    } else {
        t
    };
    let d = p.sub(a.add(e.scale(t)));
    d.dot(d).sqrt()
}

fn corners_f64(p: [f64; 3], l: f64, w: f64) -> ([[f64; 2]; 4], [[f64; 2]; 2]) {
    let (s, c) = p[2].sin_cos();
    let (u, v) = ([c, s], [-s, c]);
    let k = |a: f64, b: f64| {
        [
            p[0] + u[0] * 0.5 * l * a + v[0] * 0.5 * w * b,
            p[1] + u[1] * 0.5 * l * a + v[1] * 0.5 * w * b,
        ]
    };
    (
        [k(-1.0, -1.0), k(1.0, -1.0), k(1.0, 1.0), k(-1.0, 1.0)],
        [u, v],
    )
}

fn point_segment_f64(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let e = [b[0] - a[0], b[1] - a[1]];
    let len2 = e[0] * e[0] + e[1] * e[1];
    let t = if len2 > 0.0 {
        (((p[0] - a[0]) * e[0] + (p[1] - a[1]) * e[1]) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (p[0] - a[0] - t * e[0]).hypot(p[1] - a[1] - t * e[1])
}

/// Whether `x` ties with the best value `best` (then both are averaged).
fn near(x: f64, best: f64) -> bool {
    (x - best).abs() <= 1e-12 * (1.0 + x.abs().max(best.abs()))
}

/// The mean of `v`; NaN when `v` is empty, which happens only when a coordinate is not finite
/// (no candidate is then "near" the best), so that the caller's finiteness check reports it
/// rather than this panicking.
fn mean<const N: usize>(v: &[Fwd<N>]) -> Fwd<N> {
    let Some((first, rest)) = v.split_first() else {
        return Fwd {
            v: f64::NAN,
            g: [f64::NAN; N],
        };
    };
    let mut out = *first;
    for x in rest {
        out = out + *x;
    }
    out * (1.0 / v.len() as f64)
}

/// Signed clearance between two oriented boxes `(x, y, heading)` with sizes `(length, width)`:
/// the distance between them when apart, minus the penetration depth (the smallest overlap
/// along the four box axes) when they overlap. Continuous at contact, where both are zero.
/// Inputs 0..3 are box A's `(x, y, heading)`, 3..6 box B's.
///
/// The active feature (the nearest vertex-edge pair, or the axis of least overlap) is found in
/// plain floating point and only it is differentiated, which keeps this cheap enough to call
/// for every pair of agents at every step. Ties between axes and corners are averaged (the
/// smallest subgradient), so that aligned boxes are not pushed one way by the order of the
/// corners; overlapping boxes whose centres are aligned get a non-zero derivative all the same
/// (see the code), because a zero one would leave them stacked.
pub fn box_clearance(a: [f64; 3], sa: (f64, f64), b: [f64; 3], sb: (f64, f64)) -> Fwd<6> {
    let (fa, axa) = corners_f64(a, sa.0, sa.1);
    let (fb, axb) = corners_f64(b, sb.0, sb.1);
    let proj = |cs: &[[f64; 2]; 4], ax: [f64; 2]| {
        cs.iter()
            .map(|c| c[0] * ax[0] + c[1] * ax[1])
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                (lo.min(p), hi.max(p))
            })
    };
    let axes = [axa[0], axa[1], axb[0], axb[1]];
    let overlaps: Vec<f64> = axes
        .iter()
        .map(|&ax| {
            let ((alo, ahi), (blo, bhi)) = (proj(&fa, ax), proj(&fb, ax));
            (ahi - blo).min(bhi - alo)
        })
        .collect();
    let (ca, ua) = corners(
        Fwd::var(a[0], 0),
        Fwd::var(a[1], 1),
        Fwd::var(a[2], 2),
        sa.0,
        sa.1,
    );
    let (cb, ub) = corners(
        Fwd::var(b[0], 3),
        Fwd::var(b[1], 4),
        Fwd::var(b[2], 5),
        sb.0,
        sb.1,
    );
    if overlaps.iter().all(|o| *o > 0.0) {
        let depth = overlaps.iter().copied().fold(f64::INFINITY, f64::min);
        let fwd_axes = [ua[0], ua[1], ub[0], ub[1]];
        // The overlap along `axis` from either side: (a's far end − b's near end, and the other
        // way round); the penetration depth along it is the smaller.
        let sides = |axis: V2<6>| {
            let p = |cs: &[V2<6>; 4]| {
                let v: Vec<Fwd<6>> = cs.iter().map(|c| c.dot(axis)).collect();
                (
                    v.iter().copied().reduce(Fwd::min).expect("4"),
                    v.iter().copied().reduce(Fwd::max).expect("4"),
                )
            };
            let ((alo, ahi), (blo, bhi)) = (p(&ca), p(&cb));
            (ahi - blo, bhi - alo)
        };
        let tied: Vec<Fwd<6>> = overlaps
            .iter()
            .zip(fwd_axes)
            .filter(|(o, _)| near(**o, depth))
            .filter_map(|(_, axis)| {
                let (f1, f2) = sides(axis);
                (!f1.ties(f2)).then(|| f1.min(f2))
            })
            .collect();
        if !tied.is_empty() {
            return -mean(&tied);
        }
        // The centres are aligned on every axis of least overlap (two cars stacked in one
        // lane): there the depth's smallest subgradient is 0, and guidance could never separate
        // them. The value stays the depth, but the derivative is that of the least overlap
        // along an axis where the centres differ (along the lane for cars in one lane), or, for
        // boxes exactly on top of each other, of moving a back and b forward along a's heading.
        let alt = overlaps
            .iter()
            .zip(fwd_axes)
            .filter_map(|(o, axis)| {
                let (f1, f2) = sides(axis);
                (!f1.ties(f2)).then(|| (*o, f1.min(f2)))
            })
            .min_by(|x, y| x.0.total_cmp(&y.0))
            .map_or_else(|| sides(ua[0]).0, |(_, f)| f);
        return Fwd {
            v: -depth,
            g: (-alt).g,
        };
    }
    // Apart: the nearest vertex-edge pair, found in f64, differentiated alone.
    let mut cand: Vec<(f64, bool, usize, usize)> = Vec::with_capacity(32);
    for (i, p) in fa.iter().enumerate() {
        for j in 0..4 {
            cand.push((point_segment_f64(*p, fb[j], fb[(j + 1) % 4]), true, i, j));
        }
    }
    for (i, p) in fb.iter().enumerate() {
        for j in 0..4 {
            cand.push((point_segment_f64(*p, fa[j], fa[(j + 1) % 4]), false, i, j));
        }
    }
    let best = cand.iter().map(|c| c.0).fold(f64::INFINITY, f64::min);
    let tied: Vec<Fwd<6>> = cand
        .iter()
        .filter(|c| near(c.0, best))
        .map(|&(_, a_vertex, i, j)| {
            if a_vertex {
                point_segment(ca[i], cb[j], cb[(j + 1) % 4])
            } else {
                point_segment(cb[i], ca[j], ca[(j + 1) % 4])
            }
        })
        .collect();
    mean(&tied)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::OrientedBox;

    #[test]
    fn a_box_with_a_non_finite_coordinate_gives_nan_not_a_panic() {
        let s = (4.5, 1.8);
        for bad in [f64::NAN, f64::INFINITY] {
            let c = box_clearance([bad, 0.0, 0.0], s, [10.0, 0.0, 0.0], s);
            assert!(!c.v.is_finite(), "{c:?}");
            let c = box_clearance([0.0, 0.0, 0.0], s, [1.0, bad, 0.0], s);
            assert!(!c.v.is_finite(), "{c:?}");
        }
    }

    #[test]
    fn overlapping_aligned_boxes_are_pushed_apart() {
        let s = (4.5, 1.8);
        // One car 1 m behind another in the same lane: the least overlap is sideways (1.8 m
        // against 3.5 m), where the centres are aligned. The push is along the lane: a back,
        // b forward, nothing sideways.
        let c = box_clearance([0.0, 0.0, 0.0], s, [1.0, 0.0, 0.0], s);
        assert!((c.v + 1.8).abs() < 1e-12, "{}", c.v);
        assert!(c.g[0] < -0.5 && c.g[3] > 0.5, "{:?}", c.g);
        assert!(c.g[1].abs() < 1e-12 && c.g[4].abs() < 1e-12, "{:?}", c.g);
        // b behind a: the other way round.
        let c = box_clearance([0.0, 0.0, 0.0], s, [-1.0, 0.0, 0.0], s);
        assert!(c.g[0] > 0.5 && c.g[3] < -0.5, "{:?}", c.g);
        // Side by side, overlapping by 0.8 m, centres level: pushed sideways apart.
        let c = box_clearance([0.0, 0.0, 0.0], s, [0.0, 1.0, 0.0], s);
        assert!((c.v + 0.8).abs() < 1e-12, "{}", c.v);
        assert!(c.g[1] < -0.5 && c.g[4] > 0.5, "{:?}", c.g);
        // Exactly on top of each other: still a push.
        let c = box_clearance([2.0, 3.0, 0.4], s, [2.0, 3.0, 0.4], s);
        assert!(c.g.iter().any(|g| g.abs() > 0.5), "{:?}", c.g);
    }

    #[test]
    fn clearance_matches_box_distance_and_finite_differences() {
        let cases = [
            ([0.0, 0.0, 0.2], [7.0, 1.0, -0.4]),
            ([0.0, 0.0, 0.0], [3.0, 0.5, 0.3]),
            ([1.0, 2.0, 1.0], [1.5, 2.2, -0.7]),
            ([0.0, 0.0, 0.0], [0.0, 3.0, 1.2]),
        ];
        let (sa, sb) = ((4.5, 1.9), (4.0, 1.8));
        for (a, b) in cases {
            let c = box_clearance(a, sa, b, sb);
            let ba = OrientedBox::new(a[0], a[1], a[2], sa.0, sa.1);
            let bb = OrientedBox::new(b[0], b[1], b[2], sb.0, sb.1);
            if c.v > 0.0 {
                assert!((c.v - ba.distance(&bb)).abs() < 1e-9, "{a:?} {b:?}");
            } else {
                assert!(ba.overlaps(&bb));
            }
            let h = 1e-6;
            for i in 0..6 {
                let (mut a1, mut b1, mut a0, mut b0) = (a, b, a, b);
                if i < 3 {
                    a1[i] += h;
                    a0[i] -= h;
                } else {
                    b1[i - 3] += h;
                    b0[i - 3] -= h;
                }
                let fd =
                    (box_clearance(a1, sa, b1, sb).v - box_clearance(a0, sa, b0, sb).v) / (2.0 * h);
                assert!(
                    (fd - c.g[i]).abs() < 1e-5,
                    "slot {i} for {a:?} {b:?}: fd {fd} vs {}",
                    c.g[i]
                );
            }
        }
    }
}
