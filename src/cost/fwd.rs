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

/// Signed clearance between two oriented boxes `(x, y, heading)` with sizes `(length, width)`:
/// the distance between them when apart, minus the penetration depth (the smallest overlap
/// along the four box axes) when they overlap. Continuous at contact, where both are zero.
/// Inputs 0..3 are box A's `(x, y, heading)`, 3..6 box B's.
pub fn box_clearance(a: [f64; 3], sa: (f64, f64), b: [f64; 3], sb: (f64, f64)) -> Fwd<6> {
    let (ca, axa) = corners(
        Fwd::var(a[0], 0),
        Fwd::var(a[1], 1),
        Fwd::var(a[2], 2),
        sa.0,
        sa.1,
    );
    let (cb, axb) = corners(
        Fwd::var(b[0], 3),
        Fwd::var(b[1], 4),
        Fwd::var(b[2], 5),
        sb.0,
        sb.1,
    );
    let mut depth: Option<Fwd<6>> = None;
    for axis in axa.iter().chain(axb.iter()) {
        let proj = |cs: &[V2<6>; 4]| {
            let p: Vec<Fwd<6>> = cs.iter().map(|c| c.dot(*axis)).collect();
            let lo = p.iter().copied().reduce(Fwd::min).expect("four corners");
            let hi = p.iter().copied().reduce(Fwd::max).expect("four corners");
            (lo, hi)
        };
        let (alo, ahi) = proj(&ca);
        let (blo, bhi) = proj(&cb);
        let overlap = (ahi - blo).min(bhi - alo);
        if overlap.v <= 0.0 {
            depth = None;
            break;
        }
        depth = Some(match depth {
            Some(d) => d.min(overlap),
            None => overlap,
        });
    }
    if let Some(d) = depth {
        return -d;
    }
    let mut best: Option<Fwd<6>> = None;
    for (ps, qs) in [(&ca, &cb), (&cb, &ca)] {
        for p in ps.iter() {
            for j in 0..4 {
                let d = point_segment(*p, qs[j], qs[(j + 1) % 4]);
                best = Some(match best {
                    Some(b) => b.min(d),
                    None => d,
                });
            }
        }
    }
    best.expect("sixteen pairs")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::OrientedBox;

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
