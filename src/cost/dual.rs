//! Dual numbers: a value and its gradient w.r.t. the trajectory coordinates it depends on.
//!
//! Coordinates are numbered by [`super::VarLayout`]: agent, future step, then x | y | heading.
//! Gradients are sparse lists of `(variable, derivative)` sorted by variable, because almost
//! every quantity a cost script forms touches a handful of coordinates. Entries with a zero
//! derivative are kept: they record *structural* dependence, which the validator uses to tell a
//! term that depends on the trajectory (but is momentarily flat, like an inactive relu) from a
//! constant.

use std::cell::RefCell;
use std::rc::Rc;

/// A sparse gradient: `(variable, ∂/∂variable)` sorted by variable, no duplicates.
pub type Grad = Vec<(u32, f64)>;

/// `ca·a + cb·b` for sorted sparse gradients, appended to `out`.
pub(crate) fn merge_into(out: &mut Grad, a: &[(u32, f64)], ca: f64, b: &[(u32, f64)], cb: f64) {
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        let (ia, ga) = a[i];
        let (ib, gb) = b[j];
        if ia == ib {
            out.push((ia, ca * ga + cb * gb));
            i += 1;
            j += 1;
        } else if ia < ib {
            out.push((ia, ca * ga));
            i += 1;
        } else {
            out.push((ib, cb * gb));
            j += 1;
        }
    }
    out.extend(a[i..].iter().map(|&(k, g)| (k, ca * g)));
    out.extend(b[j..].iter().map(|&(k, g)| (k, cb * g)));
}

thread_local! {
    static SCRATCH: RefCell<(Vec<f64>, Vec<bool>, Vec<u32>)> = const { RefCell::new((Vec::new(), Vec::new(), Vec::new())) };
}

/// Accumulates many weighted sparse rows densely and returns the sparse sum, sorted.
///
/// This is where reductions pay for the sparsity: overlapping rows (a speed at step t and at
/// t + 1 share step t's coordinates) are summed in a dense scratch buffer instead of merged
/// pairwise.
pub(crate) fn accumulate<'a>(rows: impl IntoIterator<Item = (&'a [(u32, f64)], f64)>) -> Grad {
    SCRATCH.with(|s| {
        let (acc, touched, list) = &mut *s.borrow_mut();
        for (row, c) in rows {
            for &(k, g) in row {
                let k = k as usize;
                if k >= acc.len() {
                    acc.resize(k + 1, 0.0);
                    touched.resize(k + 1, false);
                }
                if !touched[k] {
                    touched[k] = true;
                    list.push(k as u32);
                }
                acc[k] += c * g;
            }
        }
        list.sort_unstable();
        let out = list
            .iter()
            .map(|&k| {
                let v = acc[k as usize];
                acc[k as usize] = 0.0;
                touched[k as usize] = false;
                (k, v)
            })
            .collect();
        list.clear();
        out
    })
}

/// A scalar dual number. Cheap to clone: the gradient is shared.
#[derive(Debug, Clone, PartialEq)]
pub struct Dual {
    /// The value.
    pub val: f64,
    /// Its sparse gradient.
    pub grad: Rc<Grad>,
}

impl Dual {
    /// A constant (no dependence on any coordinate).
    pub fn constant(val: f64) -> Self {
        Self {
            val,
            grad: Rc::new(Vec::new()),
        }
    }

    /// A value with a gradient.
    pub fn new(val: f64, grad: Grad) -> Self {
        Self {
            val,
            grad: Rc::new(grad),
        }
    }

    /// Whether it depends on any coordinate (even with a zero derivative right now).
    pub fn depends(&self) -> bool {
        !self.grad.is_empty()
    }

    /// Euclidean norm of the gradient.
    pub fn grad_norm(&self) -> f64 {
        self.grad.iter().map(|(_, g)| g * g).sum::<f64>().sqrt()
    }

    /// `f(self)` with derivative `df` at the value.
    pub fn map(&self, val: f64, df: f64) -> Self {
        Self::new(val, self.grad.iter().map(|&(k, g)| (k, df * g)).collect())
    }

    /// `ca·self + cb·other + val` style combination: value `val`, gradient `ca·∇a + cb·∇b`.
    pub fn combine(&self, other: &Dual, val: f64, ca: f64, cb: f64) -> Self {
        let mut out = Vec::with_capacity(self.grad.len() + other.grad.len());
        merge_into(&mut out, &self.grad, ca, &other.grad, cb);
        Self::new(val, out)
    }

    /// Sum.
    pub fn add(&self, o: &Dual) -> Self {
        self.combine(o, self.val + o.val, 1.0, 1.0)
    }

    /// Difference.
    pub fn sub(&self, o: &Dual) -> Self {
        self.combine(o, self.val - o.val, 1.0, -1.0)
    }

    /// Product.
    pub fn mul(&self, o: &Dual) -> Self {
        self.combine(o, self.val * o.val, o.val, self.val)
    }

    /// Quotient.
    pub fn div(&self, o: &Dual) -> Self {
        let q = self.val / o.val;
        self.combine(o, q, 1.0 / o.val, -q / o.val)
    }

    /// Plus a constant.
    pub fn add_f(&self, c: f64) -> Self {
        Self {
            val: self.val + c,
            grad: self.grad.clone(),
        }
    }

    /// Times a constant.
    pub fn mul_f(&self, c: f64) -> Self {
        self.map(self.val * c, c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn merge_unions_sorted_indices() {
        let mut out = Vec::new();
        merge_into(
            &mut out,
            &[(1, 1.0), (4, 2.0)],
            2.0,
            &[(0, 1.0), (4, 1.0), (9, 3.0)],
            -1.0,
        );
        assert_eq!(out, vec![(0, -1.0), (1, 2.0), (4, 3.0), (9, -3.0)]);
    }

    #[test]
    fn accumulate_sums_overlaps_and_keeps_zeros() {
        let a = [(3u32, 1.0), (5, 1.0)];
        let b = [(5u32, -1.0), (7, 2.0)];
        let g = accumulate([(&a[..], 1.0), (&b[..], 1.0)]);
        assert_eq!(g, vec![(3, 1.0), (5, 0.0), (7, 2.0)]);
        // The scratch buffer is clean for the next call.
        assert_eq!(accumulate([(&a[..], 2.0)]), vec![(3, 2.0), (5, 2.0)]);
    }

    #[test]
    fn product_and_quotient_rules() {
        let x = Dual::new(3.0, vec![(0, 1.0)]);
        let y = Dual::new(2.0, vec![(1, 1.0)]);
        let p = x.mul(&y);
        assert_eq!((p.val, p.grad.as_slice()), (6.0, &[(0, 2.0), (1, 3.0)][..]));
        let q = x.div(&y);
        assert_eq!(
            (q.val, q.grad.as_slice()),
            (1.5, &[(0, 0.5), (1, -0.75)][..])
        );
    }
}
