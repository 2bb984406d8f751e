//! Arithmetic, elementwise functions and reductions on series, duals and numbers.

use rhai::{Dynamic, Engine};

use super::{doc, err, number, real, DocEntry, RResult, Val};
use crate::cost::dual::Dual;
use crate::cost::series::Series;

type Bin = fn(f64, f64) -> Option<(f64, f64, f64)>;
type Un = fn(f64) -> Option<(f64, f64)>;

fn lift<T>(r: Result<T, String>) -> RResult<T> {
    r.or_else(|m| err(m))
}

/// `f(a, b)` for any mix of series, duals and numbers.
pub(crate) fn binary(
    a: Val,
    b: Val,
    name: &str,
    f: impl Fn(f64, f64) -> Option<(f64, f64, f64)>,
) -> RResult<Val> {
    let num = crate::geom::num;
    let bad = |x: f64, y: f64| format!("{name}: invalid arguments ({}, {})", num(x), num(y));
    Ok(match (a, b) {
        (Val::S(s), Val::S(o)) => Val::S(lift(s.zip(&o, name, f))?),
        (Val::S(s), Val::D(d)) => Val::S(lift(s.zip_dual(&d, name, f))?),
        (Val::D(d), Val::S(s)) => {
            Val::S(lift(s.zip_dual(&d, name, |x, y| {
                f(y, x).map(|(v, dy, dx)| (v, dx, dy))
            }))?)
        }
        (Val::S(s), Val::F(c)) => {
            Val::S(lift(s.map_with(name, c, true, |x| {
                f(x, c).map(|(v, da, _)| (v, da))
            }))?)
        }
        (Val::F(c), Val::S(s)) => {
            Val::S(lift(s.map_with(name, c, false, |x| {
                f(c, x).map(|(v, _, db)| (v, db))
            }))?)
        }
        (Val::D(x), Val::D(y)) => {
            let (v, da, db) = f(x.val, y.val)
                .ok_or_else(|| bad(x.val, y.val))
                .or_else(err)?;
            Val::D(x.combine(&y, v, da, db))
        }
        (Val::D(x), Val::F(c)) => {
            let (v, da, _) = f(x.val, c).ok_or_else(|| bad(x.val, c)).or_else(err)?;
            Val::D(x.map(v, da))
        }
        (Val::F(c), Val::D(y)) => {
            let (v, _, db) = f(c, y.val).ok_or_else(|| bad(c, y.val)).or_else(err)?;
            Val::D(y.map(v, db))
        }
        (Val::F(x), Val::F(y)) => Val::F(f(x, y).ok_or_else(|| bad(x, y)).or_else(err)?.0),
    })
}

/// `f(x)` for a series, dual or number.
pub(crate) fn unary(x: Val, name: &str, f: impl Fn(f64) -> Option<(f64, f64)>) -> RResult<Val> {
    Ok(match x {
        Val::S(s) => Val::S(lift(s.map(name, f))?),
        Val::D(d) => {
            let (v, dv) = f(d.val)
                .ok_or_else(|| format!("{name}: invalid argument {}", crate::geom::num(d.val)))
                .or_else(err)?;
            Val::D(d.map(v, dv))
        }
        Val::F(v) => Val::F(
            f(v).ok_or_else(|| format!("{name}: invalid argument {}", crate::geom::num(v)))
                .or_else(err)?
                .0,
        ),
    })
}

fn finite(v: f64, d: f64) -> Option<(f64, f64)> {
    (v.is_finite() && d.is_finite()).then_some((v, d))
}

fn add(a: f64, b: f64) -> Option<(f64, f64, f64)> {
    Some((a + b, 1.0, 1.0))
}
fn sub(a: f64, b: f64) -> Option<(f64, f64, f64)> {
    Some((a - b, 1.0, -1.0))
}
fn mul(a: f64, b: f64) -> Option<(f64, f64, f64)> {
    Some((a * b, b, a))
}
fn div(a: f64, b: f64) -> Option<(f64, f64, f64)> {
    (b != 0.0).then(|| (a / b, 1.0 / b, -a / (b * b)))
}
fn pow2(a: f64, p: f64) -> Option<(f64, f64, f64)> {
    let v = a.powf(p);
    let d = if a == 0.0 && p >= 1.0 {
        if p == 1.0 {
            1.0
        } else {
            0.0
        }
    } else {
        p * a.powf(p - 1.0)
    };
    let dp = if a > 0.0 { v * a.ln() } else { 0.0 };
    (v.is_finite() && d.is_finite()).then_some((v, d, dp))
}
fn min2(a: f64, b: f64) -> Option<(f64, f64, f64)> {
    Some(if a <= b { (a, 1.0, 0.0) } else { (b, 0.0, 1.0) })
}
fn max2(a: f64, b: f64) -> Option<(f64, f64, f64)> {
    Some(if a >= b { (a, 1.0, 0.0) } else { (b, 0.0, 1.0) })
}
fn hypot2(a: f64, b: f64) -> Option<(f64, f64, f64)> {
    let h = a.hypot(b);
    Some(if h > 0.0 {
        (h, a / h, b / h)
    } else {
        (0.0, 0.0, 0.0)
    })
}
fn atan2_(y: f64, x: f64) -> Option<(f64, f64, f64)> {
    let r2 = x * x + y * y;
    (r2 > 0.0).then(|| (y.atan2(x), x / r2, -y / r2))
}

fn relu(v: f64) -> Option<(f64, f64)> {
    Some(if v > 0.0 { (v, 1.0) } else { (0.0, 0.0) })
}
/// -1, 0 or 1 (`f64::signum` gives ±1 at ±0).
fn sign(v: f64) -> f64 {
    if v > 0.0 {
        1.0
    } else if v < 0.0 {
        -1.0
    } else {
        0.0
    }
}

fn abs(v: f64) -> Option<(f64, f64)> {
    Some((v.abs(), sign(v)))
}
fn sqrt(v: f64) -> Option<(f64, f64)> {
    (v >= 0.0).then(|| {
        let r = v.sqrt();
        (r, if r > 0.0 { 0.5 / r } else { 0.0 })
    })
}
fn exp(v: f64) -> Option<(f64, f64)> {
    let e = v.exp();
    finite(e, e)
}
fn log(v: f64) -> Option<(f64, f64)> {
    (v > 0.0).then(|| (v.ln(), 1.0 / v))
}
fn sin(v: f64) -> Option<(f64, f64)> {
    Some((v.sin(), v.cos()))
}
fn cos(v: f64) -> Option<(f64, f64)> {
    Some((v.cos(), -v.sin()))
}
fn tanh(v: f64) -> Option<(f64, f64)> {
    let t = v.tanh();
    Some((t, 1.0 - t * t))
}
fn square(v: f64) -> Option<(f64, f64)> {
    finite(v * v, 2.0 * v)
}
fn neg(v: f64) -> Option<(f64, f64)> {
    Some((-v, -1.0))
}

fn softplus(v: f64, beta: f64) -> Option<(f64, f64)> {
    let z = beta * v;
    // log(1 + e^z) without overflow.
    let sig = 1.0 / (1.0 + (-z).exp());
    if z > 30.0 {
        // log(1 + e^z) / beta = v within 1e-13 here; z / beta overflowed for a huge beta.
        return Some((v, sig));
    }
    Some((z.exp().ln_1p() / beta, sig))
}
fn sigmoid(v: f64, k: f64) -> Option<(f64, f64)> {
    let s = 1.0 / (1.0 + (-k * v).exp());
    Some((s, k * s * (1.0 - s)))
}
fn smooth_abs(v: f64, eps: f64) -> Option<(f64, f64)> {
    let r = (v * v + eps * eps).sqrt();
    Some((r - eps, v / r))
}

fn positive(x: f64, what: &str) -> RResult<f64> {
    if x.is_finite() && x > 0.0 {
        Ok(x)
    } else {
        err(format!(
            "{what} must be positive, got {}",
            crate::geom::num(x)
        ))
    }
}

macro_rules! binop {
    ($e:ident, $name:literal, $f:expr) => {{
        let f: Bin = $f;
        $e.register_fn($name, move |a: Series, b: Series| {
            binary(Val::S(a), Val::S(b), $name, f).map(Val::into_dynamic)
        });
        $e.register_fn($name, move |a: Series, b: Dual| {
            binary(Val::S(a), Val::D(b), $name, f).map(Val::into_dynamic)
        });
        $e.register_fn($name, move |a: Dual, b: Series| {
            binary(Val::D(a), Val::S(b), $name, f).map(Val::into_dynamic)
        });
        $e.register_fn($name, move |a: Dual, b: Dual| {
            binary(Val::D(a), Val::D(b), $name, f).map(Val::into_dynamic)
        });
        $e.register_fn($name, move |a: Series, b: f64| {
            binary(Val::S(a), Val::F(b), $name, f).map(Val::into_dynamic)
        });
        $e.register_fn($name, move |a: f64, b: Series| {
            binary(Val::F(a), Val::S(b), $name, f).map(Val::into_dynamic)
        });
        $e.register_fn($name, move |a: Series, b: i64| {
            binary(Val::S(a), Val::F(b as f64), $name, f).map(Val::into_dynamic)
        });
        $e.register_fn($name, move |a: i64, b: Series| {
            binary(Val::F(a as f64), Val::S(b), $name, f).map(Val::into_dynamic)
        });
        $e.register_fn($name, move |a: Dual, b: f64| {
            binary(Val::D(a), Val::F(b), $name, f).map(Val::into_dynamic)
        });
        $e.register_fn($name, move |a: f64, b: Dual| {
            binary(Val::F(a), Val::D(b), $name, f).map(Val::into_dynamic)
        });
        $e.register_fn($name, move |a: Dual, b: i64| {
            binary(Val::D(a), Val::F(b as f64), $name, f).map(Val::into_dynamic)
        });
        $e.register_fn($name, move |a: i64, b: Dual| {
            binary(Val::F(a as f64), Val::D(b), $name, f).map(Val::into_dynamic)
        });
    }};
}

macro_rules! cmpop {
    ($e:ident, $name:literal, $op:tt) => {{
        $e.register_fn($name, |a: Dual, b: Dual| a.val $op b.val);
        $e.register_fn($name, |a: Dual, b: f64| a.val $op b);
        $e.register_fn($name, |a: f64, b: Dual| a $op b.val);
        $e.register_fn($name, |a: Dual, b: i64| a.val $op b as f64);
        $e.register_fn($name, |a: i64, b: Dual| (a as f64) $op b.val);
    }};
}

fn un(e: &mut Engine, name: &'static str, f: Un) {
    e.register_fn(name, move |x: Dynamic| {
        unary(Val::from_dynamic(&x, name)?, name, f).map(Val::into_dynamic)
    });
}

/// Registers `name(x)` (with the parameter at `default`) and `name(x, p)`, for elementwise
/// functions with one shape parameter; `positive_only` requires p > 0.
fn unary_with_param(
    e: &mut Engine,
    name: &'static str,
    default: f64,
    positive_only: bool,
    f: fn(f64, f64) -> Option<(f64, f64)>,
) {
    e.register_fn(name, move |x: Dynamic| {
        unary(Val::from_dynamic(&x, name)?, name, move |v| f(v, default)).map(Val::into_dynamic)
    });
    e.register_fn(name, move |x: Dynamic, p: Dynamic| {
        let what = format!("{name} parameter");
        let p = real(&p, &what)?;
        let p = if positive_only {
            positive(p, &what)?
        } else if p.is_finite() {
            p
        } else {
            // sigmoid's k: an infinite one is a step with no gradient, and NaN at 0.
            return err(format!(
                "{what} must be a finite number, got {}",
                crate::geom::num(p)
            ));
        };
        unary(Val::from_dynamic(&x, name)?, name, move |v| f(v, p)).map(Val::into_dynamic)
    });
}

fn bin(e: &mut Engine, name: &'static str, f: Bin) {
    e.register_fn(name, move |a: Dynamic, b: Dynamic| {
        binary(
            Val::from_dynamic(&a, name)?,
            Val::from_dynamic(&b, name)?,
            name,
            f,
        )
        .map(Val::into_dynamic)
    });
}

pub(super) fn register(e: &mut Engine, docs: &mut Vec<DocEntry>) {
    const S: &str = "Arithmetic and elementwise math";
    doc(docs, S, "a + b, a - b, a * b, a / b", "Elementwise on any mix of Series, Dual, float and int: a Series if either side is one, else a Dual (two plain numbers stay numbers). Division by zero is an error.");
    binop!(e, "+", add);
    binop!(e, "-", sub);
    binop!(e, "*", mul);
    binop!(e, "/", div);
    doc(docs, S, "-x", "Negation of a Series or Dual.");
    e.register_fn("-", |x: Series| {
        unary(Val::S(x), "-", neg).map(Val::into_dynamic)
    });
    e.register_fn("-", |x: Dual| {
        unary(Val::D(x), "-", neg).map(Val::into_dynamic)
    });
    doc(
        docs,
        S,
        "a < b, a <= b, a > b, a >= b",
        "Compare the values of Duals and numbers (for `if`; the result has no gradient).",
    );
    cmpop!(e, "<", <);
    cmpop!(e, "<=", <=);
    cmpop!(e, ">", >);
    cmpop!(e, ">=", >=);

    let unary_docs: [(&'static str, &'static str, &'static str, Un); 10] = [
        (
            "relu",
            "relu(x) -> same kind",
            "max(x, 0) elementwise.",
            relu,
        ),
        (
            "abs",
            "abs(x) -> same kind",
            "|x| elementwise (derivative 0 at 0).",
            abs,
        ),
        (
            "sqrt",
            "sqrt(x) -> same kind",
            "Square root; a negative argument is an error.",
            sqrt,
        ),
        (
            "exp",
            "exp(x) -> same kind",
            "e^x; overflow is an error.",
            exp,
        ),
        (
            "log",
            "log(x) -> same kind",
            "Natural logarithm; a non-positive argument is an error.",
            log,
        ),
        ("sin", "sin(x) -> same kind", "Sine.", sin),
        ("cos", "cos(x) -> same kind", "Cosine.", cos),
        ("tanh", "tanh(x) -> same kind", "Hyperbolic tangent.", tanh),
        ("square", "square(x) -> same kind", "x².", square),
        ("neg", "neg(x) -> same kind", "-x.", neg),
    ];
    for (name, sig, d, f) in unary_docs {
        doc(docs, S, sig, d);
        un(e, name, f);
    }

    doc(
        docs,
        S,
        "softplus(x) or softplus(x, beta) -> same kind",
        "log(1 + e^(beta·x)) / beta, a smooth relu (beta = 1 by default; larger is sharper).",
    );
    unary_with_param(e, "softplus", 1.0, true, softplus);
    doc(
        docs,
        S,
        "sigmoid(x) or sigmoid(x, k) -> same kind",
        "1 / (1 + e^(-k·x)), k = 1 by default: a soft step from 0 to 1.",
    );
    unary_with_param(e, "sigmoid", 1.0, false, sigmoid);
    doc(
        docs,
        S,
        "smooth_abs(x) or smooth_abs(x, eps) -> same kind",
        "sqrt(x² + eps²) - eps (eps = 0.1 by default): |x| with a rounded bottom.",
    );
    unary_with_param(e, "smooth_abs", 0.1, true, smooth_abs);
    doc(docs, S, "pow(x, p) -> same kind", "x^p; p may itself be a Series or Dual. A negative base with a fractional power is an error.");
    bin(e, "pow", pow2);
    doc(
        docs,
        S,
        "clamp(x, lo, hi) -> same kind",
        "x limited to [lo, hi] (numbers); derivative 1 inside, 0 outside.",
    );
    e.register_fn("clamp", |x: Dynamic, lo: Dynamic, hi: Dynamic| {
        let (lo, hi) = (real(&lo, "clamp lo")?, real(&hi, "clamp hi")?);
        if lo > hi {
            let num = crate::geom::num;
            return err(format!("clamp: lo {} is above hi {}", num(lo), num(hi)));
        }
        unary(Val::from_dynamic(&x, "clamp")?, "clamp", move |v| {
            Some(if v < lo {
                (lo, 0.0)
            } else if v > hi {
                (hi, 0.0)
            } else {
                (v, 1.0)
            })
        })
        .map(Val::into_dynamic)
    });
    doc(
        docs,
        S,
        "hinge(x, margin) -> same kind",
        "relu(margin - x): how far x falls short of margin.",
    );
    e.register_fn("hinge", |x: Dynamic, m: Dynamic| {
        let m = real(&m, "hinge margin")?;
        unary(Val::from_dynamic(&x, "hinge")?, "hinge", move |v| {
            relu(m - v).map(|(r, d)| (r, -d))
        })
        .map(Val::into_dynamic)
    });
    doc(
        docs,
        S,
        "min(a, b), max(a, b) -> Series|Dual",
        "Elementwise minimum / maximum (the gradient follows the chosen side).",
    );
    bin(e, "min", min2);
    bin(e, "max", max2);
    doc(
        docs,
        S,
        "smooth_max(a, b, beta), smooth_min(a, b, beta) -> Series|Dual",
        "Elementwise log-sum-exp maximum / minimum of two values, sharper as beta grows: above the max (below the min) by at most ln(2)/beta, reached where a = b.",
    );
    e.register_fn("smooth_max", |a: Dynamic, b: Dynamic, beta: Dynamic| {
        let beta = positive(number(&beta, "smooth_max beta")?, "smooth_max beta")?;
        pair_lse(&a, &b, beta, "smooth_max")
    });
    e.register_fn("smooth_min", |a: Dynamic, b: Dynamic, beta: Dynamic| {
        let beta = positive(number(&beta, "smooth_min beta")?, "smooth_min beta")?;
        pair_lse(&a, &b, -beta, "smooth_min")
    });
    doc(
        docs,
        S,
        "sign(x) -> same kind",
        "-1, 0 or 1 elementwise, without gradient (a direction to multiply by, not a cost).",
    );
    e.register_fn("sign", |x: Dynamic| {
        unary(Val::from_dynamic(&x, "sign")?, "sign", |v| {
            Some((sign(v), 0.0))
        })
        .map(Val::into_dynamic)
    });
    doc(
        docs,
        S,
        "norm(x, y) -> same kind",
        "sqrt(x² + y²) elementwise (derivative 0 at the origin).",
    );
    bin(e, "norm", hypot2);
    doc(
        docs,
        S,
        "atan2(y, x) -> same kind",
        "Angle of the vector (x, y); (0, 0) is an error.",
    );
    bin(e, "atan2", atan2_);

    const R: &str = "Series and Dual";
    doc(
        docs,
        R,
        "s.len() -> int",
        "Number of elements (future steps).",
    );
    e.register_fn("len", |s: &mut Series| s.len() as i64);
    doc(
        docs,
        R,
        "s.valid_count() -> int",
        "Number of valid elements (0 for an agent with no future, e.g. one that appears later).",
    );
    e.register_fn("valid_count", |s: &mut Series| {
        s.valid().iter().filter(|v| **v).count() as i64
    });
    doc(
        docs,
        R,
        "s.first(), s.last() -> Dual",
        "First / last valid element.",
    );
    e.register_fn("first", |s: &mut Series| lift(s.first()));
    e.register_fn("last", |s: &mut Series| lift(s.last()));
    doc(
        docs,
        R,
        "s.at(i) -> Dual",
        "Element i (0 = first future step; negative counts from the end).",
    );
    e.register_fn("at", |s: &mut Series, i: i64| lift(s.at(i)));
    doc(
        docs,
        R,
        "s.at_time(t) -> Dual",
        "The element t seconds after the current step.",
    );
    e.register_fn("at_time", |s: &mut Series, t: Dynamic| {
        lift(s.at_time(number(&t, "at_time")?))
    });
    doc(
        docs,
        R,
        "s.slice(i0, i1) -> Series",
        "Elements i0 .. i1 (end excluded; negative counts from the end).",
    );
    e.register_fn("slice", |s: &mut Series, a: i64, b: i64| {
        lift(s.slice(a, b))
    });
    doc(
        docs,
        R,
        "s.window(t0, t1) -> Series",
        "Elements from t0 to t1 seconds after the current step, both included.",
    );
    e.register_fn("window", |s: &mut Series, a: Dynamic, b: Dynamic| {
        lift(s.window(number(&a, "window")?, number(&b, "window")?))
    });
    doc(
        docs,
        R,
        "s.sum(), s.mean() -> Dual",
        "Sum / mean of the valid elements.",
    );
    e.register_fn("sum", |s: &mut Series| s.sum());
    e.register_fn("mean", |s: &mut Series| lift(s.mean()));
    doc(
        docs,
        R,
        "s.max(), s.min() -> Dual",
        "Largest / smallest valid element.",
    );
    e.register_fn("max", |s: &mut Series| lift(s.max()));
    e.register_fn("min", |s: &mut Series| lift(s.min()));
    doc(
        docs,
        R,
        "s.smooth_max(beta), s.smooth_min(beta) -> Dual",
        "Softmax-weighted mean of the elements, Σ softmax(beta·v)·v (beta > 0, sharper as it grows): between the mean and the max (min), never beyond it, and equal to the common value when all elements are equal.",
    );
    e.register_fn("smooth_max", |s: &mut Series, b: Dynamic| {
        lift(s.smooth_max(number(&b, "smooth_max beta")?))
    });
    e.register_fn("smooth_min", |s: &mut Series, b: Dynamic| {
        lift(s.smooth_min(number(&b, "smooth_min beta")?))
    });
    doc(
        docs,
        R,
        "s.ever_below(v), s.always_below(v), s.ever_above(v), s.always_above(v) -> Dual",
        "\"At some step\" / \"at every step\" as costs that are 0 when it holds, else how far it misses: ever_below = relu(min - v), always_below = relu(max - v), ever_above = relu(v - max), always_above = relu(v - min). The gradient moves the step that decides.",
    );
    for (name, use_min, below) in [
        ("ever_below", true, true),
        ("always_below", false, true),
        ("ever_above", false, false),
        ("always_above", true, false),
    ] {
        e.register_fn(name, move |s: &mut Series, v: Dynamic| -> RResult<Dual> {
            let v = real(&v, name)?;
            let m = lift(if use_min { s.min() } else { s.max() })?;
            let miss = if below {
                m.add_f(-v)
            } else {
                m.mul_f(-1.0).add_f(v)
            };
            Ok(if miss.val > 0.0 {
                miss
            } else {
                Dual::constant(0.0)
            })
        });
    }
    doc(
        docs,
        R,
        "s.norm() -> Dual",
        "Euclidean norm of the valid elements.",
    );
    e.register_fn("norm", |s: &mut Series| s.norm());
    doc(docs, R, "s.deriv() -> Series", "Derivative per second (backward differences; the first element uses the current state when the series comes from an agent).");
    e.register_fn("deriv", |s: &mut Series| s.deriv());
    doc(
        docs,
        R,
        "s.values() -> array",
        "The values as floats (for print).",
    );
    e.register_fn("values", |s: &mut Series| {
        s.values()
            .iter()
            .map(|v| Dynamic::from(*v))
            .collect::<rhai::Array>()
    });
    doc(
        docs,
        R,
        "value(x) -> float",
        "The value of a Dual (a number stays itself).",
    );
    e.register_fn("value", |d: Dual| d.val);
    e.register_fn("value", |d: f64| d);
    e.register_fn("value", |d: i64| d as f64);
    e.register_fn("to_string", |d: &mut Dual| format!("{:.4}", d.val));
    e.register_fn("to_debug", |d: &mut Dual| {
        format!("Dual({:.6}, {} partials)", d.val, d.grad.len())
    });
    e.register_fn("to_string", |s: &mut Series| fmt_series(s));
    e.register_fn("to_debug", |s: &mut Series| fmt_series(s));
}

fn fmt_series(s: &Series) -> String {
    let parts: Vec<String> = s
        .values()
        .iter()
        .zip(s.valid())
        .map(|(v, ok)| if *ok { format!("{v:.3}") } else { "-".into() })
        .collect();
    format!("[{}]", parts.join(", "))
}

/// Elementwise log-sum-exp of two values; a negative beta gives the smooth minimum.
fn pair_lse(a: &Dynamic, b: &Dynamic, beta: f64, name: &'static str) -> RResult<Dynamic> {
    let f = move |x: f64, y: f64| {
        let m = if beta > 0.0 { x.max(y) } else { x.min(y) };
        let (ex, ey) = ((beta * (x - m)).exp(), (beta * (y - m)).exp());
        let z = ex + ey;
        Some((m + z.ln() / beta, ex / z, ey / z))
    };
    binary(
        Val::from_dynamic(a, name)?,
        Val::from_dynamic(b, name)?,
        name,
        f,
    )
    .map(Val::into_dynamic)
}
