//! Time series of dual numbers over future steps, with vectorised arithmetic.
//!
//! A series stores one value, one validity flag and one sparse gradient row per step. Element
//! `i` of a series taken from an agent is future step `i` (0 = the step after the current one).
//! Series built from agent states carry a few *hidden* leading elements (the current state and
//! earlier history, all constants) so that derivatives of the first future steps use the real
//! previous states; arithmetic keeps them aligned and reductions never see them.
//!
//! Steps where an agent is not observed are invalid: elementwise results there are invalid and
//! reductions skip them. Domain errors (square root of a negative, log of a non-positive, division
//! by zero) are reported with the element, never turned into NaN.

use std::rc::Rc;

use super::dual::{accumulate, merge_into, Dual, Grad};

/// Result of a series operation; the message becomes a script error at the calling line.
pub type OpResult<T> = Result<T, String>;

thread_local! {
    /// Bytes held by the series alive on this thread: scripts run on one thread each, and a
    /// script that keeps thousands of series alive must stop at a limit, not abort the
    /// process when memory runs out.
    static LIVE_BYTES: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

/// Bytes held by the series alive on this thread (what [`Limits::max_series_bytes`] bounds).
///
/// [`Limits::max_series_bytes`]: super::Limits::max_series_bytes
pub fn live_series_bytes() -> usize {
    LIVE_BYTES.with(|c| c.get())
}

/// The data of a series (shared behind [`Series`]).
#[derive(Debug, PartialEq)]
pub struct SeriesData {
    pub(crate) val: Vec<f64>,
    pub(crate) valid: Vec<bool>,
    pub(crate) offs: Vec<u32>,
    pub(crate) ent: Grad,
    /// Hidden leading elements (history constants for derivatives).
    pub(crate) head: usize,
    /// Seconds per element.
    pub(crate) dt: f64,
    /// Time of the first visible element, seconds after the current step.
    pub(crate) time0: f64,
    /// Bytes counted in [`live_series_bytes`] while it lives.
    counted: usize,
}

impl Drop for SeriesData {
    fn drop(&mut self) {
        let n = self.counted;
        LIVE_BYTES.with(|c| c.set(c.get().saturating_sub(n)));
    }
}

/// A time series of dual numbers; cheap to clone.
#[derive(Debug, Clone, PartialEq)]
pub struct Series(pub(crate) Rc<SeriesData>);

/// Builds a series element by element.
pub(crate) struct Builder {
    d: SeriesData,
}

impl Builder {
    pub(crate) fn new(cap: usize, head: usize, dt: f64, time0: f64) -> Self {
        let mut offs = Vec::with_capacity(cap + 1);
        offs.push(0);
        Self {
            d: SeriesData {
                val: Vec::with_capacity(cap),
                valid: Vec::with_capacity(cap),
                offs,
                ent: Vec::with_capacity(cap * 4),
                head,
                dt,
                time0,
                counted: 0,
            },
        }
    }

    pub(crate) fn push_row(
        &mut self,
        val: f64,
        valid: bool,
        row: impl IntoIterator<Item = (u32, f64)>,
    ) {
        self.d.ent.extend(row);
        self.finish_element(val, valid);
    }

    /// The gradient buffer, for callers that merge rows into it directly.
    pub(crate) fn ent(&mut self) -> &mut Grad {
        &mut self.d.ent
    }

    pub(crate) fn finish_element(&mut self, val: f64, valid: bool) {
        // Invalid elements carry 0 so that nothing downstream computes with garbage.
        self.d.val.push(if valid { val } else { 0.0 });
        self.d.valid.push(valid);
        self.d.offs.push(self.d.ent.len() as u32);
    }

    pub(crate) fn build(mut self) -> Series {
        let d = &mut self.d;
        d.counted = std::mem::size_of::<SeriesData>()
            + d.val.capacity() * std::mem::size_of::<f64>()
            + d.valid.capacity()
            + d.offs.capacity() * std::mem::size_of::<u32>()
            + d.ent.capacity() * std::mem::size_of::<(u32, f64)>();
        let n = d.counted;
        LIVE_BYTES.with(|c| c.set(c.get().saturating_add(n)));
        Series(Rc::new(self.d))
    }
}

impl Series {
    /// Number of visible elements.
    pub fn len(&self) -> usize {
        self.0.val.len() - self.0.head
    }

    /// Whether it has no visible element.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Seconds per element.
    pub fn dt(&self) -> f64 {
        self.0.dt
    }

    /// Values of the visible elements (0 where invalid).
    pub fn values(&self) -> &[f64] {
        &self.0.val[self.0.head..]
    }

    /// Validity of the visible elements.
    pub fn valid(&self) -> &[bool] {
        &self.0.valid[self.0.head..]
    }

    /// Gradient row of storage element `k`.
    pub(crate) fn row(&self, k: usize) -> &[(u32, f64)] {
        &self.0.ent[self.0.offs[k] as usize..self.0.offs[k + 1] as usize]
    }

    /// Gradient of visible element `i`.
    pub fn grad_at(&self, i: usize) -> &[(u32, f64)] {
        self.row(self.0.head + i)
    }

    /// A constant series (no gradient) of `n` elements.
    pub fn constant(values: &[f64], dt: f64, time0: f64) -> Series {
        let mut b = Builder::new(values.len(), 0, dt, time0);
        for &v in values {
            b.push_row(v, v.is_finite(), std::iter::empty());
        }
        b.build()
    }

    fn like(&self, cap: usize, head: usize) -> Builder {
        Builder::new(cap, head, self.0.dt, self.0.time0)
    }

    /// Elementwise `f`, which returns the value and its derivative, or a domain error.
    pub fn map(&self, name: &str, f: impl Fn(f64) -> Option<(f64, f64)>) -> OpResult<Series> {
        self.map_or_say(f, |v, i| domain(name, v, i))
    }

    /// [`Series::map`] of a two-argument function whose other argument is the number `c`
    /// (`first`: the series is the first argument): a domain error names both arguments, as
    /// one between two series does (`pow: invalid arguments (62.4, 1e300) at element 0`), not
    /// the element alone as if it were at fault.
    pub fn map_with(
        &self,
        name: &str,
        c: f64,
        first: bool,
        f: impl Fn(f64) -> Option<(f64, f64)>,
    ) -> OpResult<Series> {
        self.map_or_say(f, |v, i| {
            let (a, b) = if first { (v, c) } else { (c, v) };
            domain2(name, a, b, i)
        })
    }

    /// Elementwise `f`; `say(value, step)` is the error where `f` has none.
    fn map_or_say(
        &self,
        f: impl Fn(f64) -> Option<(f64, f64)>,
        say: impl Fn(f64, isize) -> String,
    ) -> OpResult<Series> {
        let d = &self.0;
        let mut b = self.like(d.val.len(), d.head);
        for k in 0..d.val.len() {
            if !d.valid[k] {
                b.push_row(0.0, false, self.row(k).iter().map(|&(i, _)| (i, 0.0)));
                continue;
            }
            let Some((v, dv)) = f(d.val[k]) else {
                // History elements only feed derivatives of the first future steps: outside
                // the function's domain they become unobserved rather than an error.
                if k < d.head {
                    b.push_row(0.0, false, std::iter::empty());
                    continue;
                }
                return Err(say(d.val[k], k as isize - d.head as isize));
            };
            b.push_row(v, true, self.row(k).iter().map(|&(i, g)| (i, dv * g)));
        }
        Ok(b.build())
    }

    /// Elementwise binary `f(a, b) -> (value, ∂/∂a, ∂/∂b)` of two series of equal length.
    pub fn zip(
        &self,
        other: &Series,
        name: &str,
        f: impl Fn(f64, f64) -> Option<(f64, f64, f64)>,
    ) -> OpResult<Series> {
        let (a, o) = (&self.0, &other.0);
        if self.len() != other.len() {
            return Err(format!(
                "{name}: series lengths differ ({} and {} elements)",
                self.len(),
                other.len()
            ));
        }
        let head = a.head.min(o.head);
        let (sa, sb) = (a.head - head, o.head - head);
        let n = head + self.len();
        let mut b = self.like(n, head);
        for k in 0..n {
            let (ka, kb) = (k + sa, k + sb);
            let mut valid = a.valid[ka] && o.valid[kb];
            let (v, ca, cb) = match valid.then(|| f(a.val[ka], o.val[kb])) {
                Some(Some(r)) => r,
                Some(None) if k < head => {
                    valid = false;
                    (0.0, 0.0, 0.0)
                }
                Some(None) => {
                    return Err(domain2(
                        name,
                        a.val[ka],
                        o.val[kb],
                        k as isize - head as isize,
                    ))
                }
                None => (0.0, 0.0, 0.0),
            };
            merge_into(b.ent(), self.row(ka), ca, other.row(kb), cb);
            b.finish_element(v, valid);
        }
        Ok(b.build())
    }

    /// Elementwise binary `f(a, s)` of a series and a scalar dual.
    pub fn zip_dual(
        &self,
        s: &Dual,
        name: &str,
        f: impl Fn(f64, f64) -> Option<(f64, f64, f64)>,
    ) -> OpResult<Series> {
        let d = &self.0;
        let mut b = self.like(d.val.len(), d.head);
        for k in 0..d.val.len() {
            let mut valid = d.valid[k];
            let (v, ca, cb) = match valid.then(|| f(d.val[k], s.val)) {
                Some(Some(r)) => r,
                Some(None) if k < d.head => {
                    valid = false;
                    (0.0, 0.0, 0.0)
                }
                Some(None) => {
                    return Err(domain2(name, d.val[k], s.val, k as isize - d.head as isize))
                }
                None => (0.0, 0.0, 0.0),
            };
            merge_into(b.ent(), self.row(k), ca, &s.grad, cb);
            b.finish_element(v, valid);
        }
        Ok(b.build())
    }

    /// Derivative per second: backward differences; the first element uses the hidden
    /// previous state when there is one, else the forward difference.
    pub fn deriv(&self) -> Series {
        let d = &self.0;
        let n = d.val.len();
        let inv = 1.0 / d.dt;
        let mut b = self.like(n, d.head.saturating_sub(1));
        let start = if d.head >= 1 { 1 } else { 0 };
        for k in start..n {
            let (lo, hi) = if k == 0 {
                (0, 1.min(n - 1))
            } else {
                (k - 1, k)
            };
            if lo == hi {
                b.push_row(0.0, d.valid[k], self.row(k).iter().map(|&(i, _)| (i, 0.0)));
                continue;
            }
            let valid = d.valid[lo] && d.valid[hi];
            let v = (d.val[hi] - d.val[lo]) * inv;
            merge_into(b.ent(), self.row(hi), inv, self.row(lo), -inv);
            b.finish_element(v, valid);
        }
        b.build()
    }

    fn visible_rows(&self) -> impl Iterator<Item = (usize, f64, &[(u32, f64)])> + '_ {
        let d = &self.0;
        (d.head..d.val.len())
            .filter(|&k| d.valid[k])
            .map(move |k| (k - d.head, d.val[k], self.row(k)))
    }

    fn count_valid(&self, what: &str) -> OpResult<usize> {
        match self.valid().iter().filter(|v| **v).count() {
            0 => Err(format!("{what}: the series has no valid element")),
            n => Ok(n),
        }
    }

    /// Sum of the valid elements.
    pub fn sum(&self) -> Dual {
        let val = self.visible_rows().map(|(_, v, _)| v).sum();
        Dual::new(
            val,
            accumulate(self.visible_rows().map(|(_, _, r)| (r, 1.0))),
        )
    }

    /// Mean of the valid elements.
    pub fn mean(&self) -> OpResult<Dual> {
        let n = self.count_valid("mean")? as f64;
        Ok(self.sum().mul_f(1.0 / n))
    }

    /// Largest valid element (its gradient is that element's).
    pub fn max(&self) -> OpResult<Dual> {
        self.count_valid("max")?;
        let (_, v, r) = self
            .visible_rows()
            .fold(
                None,
                |best: Option<(usize, f64, &[(u32, f64)])>, e| match best {
                    Some(b) if b.1 >= e.1 => Some(b),
                    _ => Some(e),
                },
            )
            .expect("checked non-empty");
        Ok(Dual::new(v, r.to_vec()))
    }

    /// Smallest valid element.
    pub fn min(&self) -> OpResult<Dual> {
        self.count_valid("min")?;
        let (_, v, r) = self
            .visible_rows()
            .fold(
                None,
                |best: Option<(usize, f64, &[(u32, f64)])>, e| match best {
                    Some(b) if b.1 <= e.1 => Some(b),
                    _ => Some(e),
                },
            )
            .expect("checked non-empty");
        Ok(Dual::new(v, r.to_vec()))
    }

    /// Smooth maximum: the softmax-weighted mean `Σ softmax(β v)ᵢ vᵢ` (β > 0), which tends to
    /// `max` as β grows. It always lies between the mean and the maximum, so it never reports
    /// more than the maximum: equal elements give their value, where log-sum-exp would add up
    /// to `ln(N)/β` (a clearance of +0.018 m read as a collision over 40 steps at β = 4).
    pub fn smooth_max(&self, beta: f64) -> OpResult<Dual> {
        if !(beta.is_finite() && beta > 0.0) {
            return Err(format!(
                "smooth_max: beta must be positive, got {}",
                crate::geom::num(beta)
            ));
        }
        let m = self.max()?.val;
        let w: Vec<(f64, f64, &[(u32, f64)])> = self
            .visible_rows()
            .map(|(_, v, r)| ((beta * (v - m)).exp(), v, r))
            .collect();
        let z: f64 = w.iter().map(|(e, _, _)| e).sum();
        let val = w.iter().map(|(e, v, _)| e * v).sum::<f64>() / z;
        // ∂/∂vᵢ = pᵢ (1 + β (vᵢ − val)), pᵢ the softmax weight. An element whose weight
        // underflowed to 0 adds nothing (pᵢ falls faster than β (vᵢ − val) grows); written
        // out it was 0 × inf = NaN for a large beta ("a non-finite gradient").
        Ok(Dual::new(
            val,
            accumulate(
                w.iter()
                    .filter(|&&(e, _, _)| e > 0.0)
                    .map(|&(e, v, r)| (r, e / z * (1.0 + beta * (v - val)))),
            ),
        ))
    }

    /// Smooth minimum `-smooth_max(-v)`.
    pub fn smooth_min(&self, beta: f64) -> OpResult<Dual> {
        // Checked here: through `smooth_max` a bad beta was said to be smooth_max's.
        if !(beta.is_finite() && beta > 0.0) {
            return Err(format!(
                "smooth_min: beta must be positive, got {}",
                crate::geom::num(beta)
            ));
        }
        let neg = self.map("neg", |v| Some((-v, -1.0)))?;
        Ok(neg.smooth_max(beta)?.mul_f(-1.0))
    }

    /// Euclidean norm of the valid elements.
    pub fn norm(&self) -> Dual {
        let val: f64 = self
            .visible_rows()
            .map(|(_, v, _)| v * v)
            .sum::<f64>()
            .sqrt();
        let scale = if val > 0.0 { 1.0 / val } else { 0.0 };
        Dual::new(
            val,
            accumulate(self.visible_rows().map(|(_, v, r)| (r, v * scale))),
        )
    }

    /// Visible element `i` (negative counts from the end).
    pub fn at(&self, i: i64) -> OpResult<Dual> {
        let n = self.len() as i64;
        let j = if i < 0 { n + i } else { i };
        if j < 0 || j >= n {
            return Err(format!("index {i} is outside the series' {n} elements"));
        }
        let k = self.0.head + j as usize;
        if !self.0.valid[k] {
            return Err(format!(
                "element {j} is not valid (the agent is not observed then)"
            ));
        }
        Ok(Dual::new(self.0.val[k], self.row(k).to_vec()))
    }

    /// First valid element.
    pub fn first(&self) -> OpResult<Dual> {
        let j = self
            .valid()
            .iter()
            .position(|v| *v)
            .ok_or("first: the series has no valid element")?;
        self.at(j as i64)
    }

    /// Last valid element.
    pub fn last(&self) -> OpResult<Dual> {
        let j = self
            .valid()
            .iter()
            .rposition(|v| *v)
            .ok_or("last: the series has no valid element")?;
        self.at(j as i64)
    }

    /// The element at `t` seconds after the current step (nearest step).
    pub fn at_time(&self, t: f64) -> OpResult<Dual> {
        self.at(self.index_of_time(t, "at_time")?)
    }

    fn index_of_time(&self, t: f64, what: &str) -> OpResult<i64> {
        if !t.is_finite() {
            return Err(format!(
                "{what}: time {} is not finite",
                crate::geom::num(t)
            ));
        }
        let i = ((t - self.0.time0) / self.0.dt).round();
        let last_t = self.0.time0 + (self.len() as f64 - 1.0) * self.0.dt;
        if i < 0.0 || i >= self.len() as f64 {
            return Err(format!(
                "{what}: time {} s is outside the series ({:.2} s to {last_t:.2} s)",
                crate::geom::num(t),
                self.0.time0
            ));
        }
        Ok(i as i64)
    }

    /// Visible elements `i0..i1` (half-open; negative counts from the end). Earlier elements
    /// stay hidden so that derivatives of the slice still see its past.
    pub fn slice(&self, i0: i64, i1: i64) -> OpResult<Series> {
        let n = self.len() as i64;
        let fix = |i: i64| if i < 0 { n + i } else { i };
        let (a, b) = (fix(i0), fix(i1));
        if a < 0 || b > n || a >= b {
            return Err(format!(
                "slice({i0}, {i1}) is empty or outside the series' {n} elements"
            ));
        }
        let d = &self.0;
        let keep = (d.head + a as usize).min(3);
        let from = d.head + a as usize - keep;
        let to = d.head + b as usize;
        let mut out = Builder::new(to - from, keep, d.dt, d.time0 + a as f64 * d.dt);
        for k in from..to {
            out.push_row(d.val[k], d.valid[k], self.row(k).iter().copied());
        }
        Ok(out.build())
    }

    /// The elements between `t0` and `t1` seconds after the current step (inclusive).
    pub fn window(&self, t0: f64, t1: f64) -> OpResult<Series> {
        // Said in the times given: "slice(29, 10) is empty" named steps and a function the
        // script never called.
        if t1 < t0 {
            return Err(format!(
                "window({}, {}): the end is before the start; give window(t0, t1) with t0 <= t1 \
                 (seconds after the current step)",
                crate::geom::num(t0),
                crate::geom::num(t1)
            ));
        }
        let a = self.index_of_time(t0, "window")?;
        let b = self.index_of_time(t1, "window")?;
        self.slice(a, b + 1)
    }
}

fn domain(name: &str, v: f64, i: isize) -> String {
    format!(
        "{name}: invalid argument {} at element {i}",
        crate::geom::num(v)
    )
}

fn domain2(name: &str, a: f64, b: f64, i: isize) -> String {
    let num = crate::geom::num;
    format!(
        "{name}: invalid arguments ({}, {}) at element {i}",
        num(a),
        num(b)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(vals: &[f64], head: usize, var0: u32) -> Series {
        let mut b = Builder::new(vals.len(), head, 0.1, 0.1);
        for (k, &v) in vals.iter().enumerate() {
            let row: Vec<(u32, f64)> = if k < head {
                vec![]
            } else {
                vec![(var0 + k as u32, 1.0)]
            };
            b.push_row(v, true, row);
        }
        b.build()
    }

    #[test]
    fn deriv_uses_the_hidden_previous_state() {
        let x = s(&[0.0, 1.0, 3.0, 6.0], 1, 0);
        let v = x.deriv();
        assert_eq!(v.len(), 3);
        assert!((v.values()[0] - 10.0).abs() < 1e-9);
        assert_eq!(
            v.grad_at(0),
            &[(1, 10.0)],
            "the previous state is a constant"
        );
        assert_eq!(v.grad_at(1), &[(1, -10.0), (2, 10.0)]);
    }

    #[test]
    fn zip_aligns_hidden_heads() {
        let a = s(&[0.0, 0.0, 1.0, 2.0], 2, 0);
        let b = s(&[5.0, 1.0, 1.0], 1, 10);
        let c = a.zip(&b, "sub", |x, y| Some((x - y, 1.0, -1.0))).unwrap();
        assert_eq!(c.len(), 2);
        assert_eq!(c.values(), &[0.0, 1.0]);
        assert_eq!(c.0.head, 1);
        assert!(a
            .zip(&s(&[1.0], 0, 0), "sub", |x, y| Some((x - y, 1.0, -1.0)))
            .is_err());
    }

    #[test]
    fn reductions_and_indexing() {
        let x = s(&[9.0, 1.0, 4.0, 2.0], 1, 0);
        assert_eq!(x.sum().val, 7.0);
        assert_eq!(x.max().unwrap().grad.as_slice(), &[(2, 1.0)]);
        assert_eq!(x.min().unwrap().val, 1.0);
        assert_eq!(x.last().unwrap().val, 2.0);
        assert_eq!(x.at(-2).unwrap().val, 4.0);
        assert!((x.at_time(0.3).unwrap().val - 2.0).abs() < 1e-12);
        assert!(x.at(3).is_err() && x.at_time(5.0).is_err());
        let sm = x.smooth_max(50.0).unwrap();
        assert!((sm.val - 4.0).abs() < 1e-3);
        // Never beyond the extreme: equal elements give their value (log-sum-exp: + ln 4 / β).
        let flat = s(&[0.018, 0.018, 0.018, 0.018], 1, 0);
        assert!((flat.smooth_min(4.0).unwrap().val - 0.018).abs() < 1e-15);
        assert!((flat.smooth_max(4.0).unwrap().val - 0.018).abs() < 1e-15);
        for beta in [0.5, 4.0, 50.0] {
            let v = x.smooth_max(beta).unwrap().val;
            assert!(v <= 4.0 && v >= x.sum().val / 3.0, "beta {beta}: {v}");
            let v = x.smooth_min(beta).unwrap().val;
            assert!(v >= 1.0 && v <= x.sum().val / 3.0, "beta {beta}: {v}");
        }
        let w = x.window(0.2, 0.3).unwrap();
        assert_eq!(w.values(), &[4.0, 2.0]);
        assert_eq!(w.deriv().values()[0], 30.0, "a slice keeps its past hidden");
    }

    #[test]
    fn domain_errors_name_the_element() {
        let x = s(&[0.0, -1.0], 0, 0);
        let e = x
            .map("sqrt", |v| (v >= 0.0).then(|| (v.sqrt(), 0.5 / v.sqrt())))
            .unwrap_err();
        assert_eq!(e, "sqrt: invalid argument -1 at element 1");
        let e = x
            .map_with("pow", 0.5, true, |v| {
                (v >= 0.0).then(|| (v.sqrt(), 0.5 / v.sqrt()))
            })
            .unwrap_err();
        assert_eq!(e, "pow: invalid arguments (-1, 0.5) at element 1");
        let e = x.map_with("pow", 2.0, false, |_| None).unwrap_err();
        assert_eq!(e, "pow: invalid arguments (2, 0) at element 0");
    }
}
