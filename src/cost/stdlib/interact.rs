//! Interactions between agents: gaps along a path, distances, box clearance, time to collision
//! and collision penalties.

use rhai::{Array, Dynamic, Engine};

use super::agents::{coord_series, AgentRef};
use super::frenet::{frenet, PathRef};
use super::{doc, err, number, over_time, DocEntry, RResult, Shared};
use crate::cost::dual::{accumulate, Dual};
use crate::cost::fwd::{box_clearance, Fwd};
use crate::cost::series::{Builder, Series};
use crate::cost::trajectory::Coord;
use crate::geom::{pairs_within, Point};

/// TTC reported when the agents are not closing in, seconds.
const TTC_CAP: f64 = 10.0;

fn lift<T>(r: Result<T, String>) -> RResult<T> {
    r.or_else(|m| err(m))
}

/// A series over the aligned steps of two agents from `f(state_a, state_b) -> Fwd<6>`.
fn pair_series(
    shared: &Shared,
    a: AgentRef,
    b: AgentRef,
    f: impl Fn([f64; 3], [f64; 3]) -> Fwd<6>,
) -> Series {
    pair_series_opt(shared, a, b, |p, q| Some(f(p, q)))
}

/// Like [`pair_series`]; where `f` returns `None` the element is 0 with zero partials (kept for
/// structure), which lets callers skip work for pairs that are far apart.
fn pair_series_opt(
    shared: &Shared,
    a: AgentRef,
    b: AgentRef,
    f: impl Fn([f64; 3], [f64; 3]) -> Option<Fwd<6>>,
) -> Series {
    let sa = [Coord::X, Coord::Y, Coord::Heading].map(|c| coord_series(shared, a, c));
    let sb = [Coord::X, Coord::Y, Coord::Heading].map(|c| coord_series(shared, b, c));
    let (ha, hb) = (sa[0].0.head, sb[0].0.head);
    let head = ha.min(hb);
    let n = head + sa[0].len();
    let mut out = Builder::new(n, head, sa[0].dt(), sa[0].0.time0);
    for k in 0..n {
        let (ka, kb) = (k + ha - head, k + hb - head);
        let valid = sa.iter().all(|s| s.0.valid[ka]) && sb.iter().all(|s| s.0.valid[kb]);
        if !valid {
            out.push_row(0.0, false, std::iter::empty());
            continue;
        }
        let xa = [sa[0].0.val[ka], sa[1].0.val[ka], sa[2].0.val[ka]];
        let xb = [sb[0].0.val[kb], sb[1].0.val[kb], sb[2].0.val[kb]];
        let v = f(xa, xb).unwrap_or(Fwd::c(0.0));
        // Rows go straight into the series' buffer: this runs for every pair at every step.
        let ent = out.ent();
        let start = ent.len();
        for (i, s) in sa.iter().enumerate() {
            if let Some(&(var, _)) = s.row(ka).first() {
                ent.push((var, v.g[i]));
            }
        }
        for (i, s) in sb.iter().enumerate() {
            if let Some(&(var, _)) = s.row(kb).first() {
                ent.push((var, v.g[3 + i]));
            }
        }
        ent[start..].sort_unstable_by_key(|e| e.0);
        out.finish_element(v.v, true);
    }
    out.build()
}

fn sizes(shared: &Shared, a: AgentRef, b: AgentRef) -> ((f64, f64), (f64, f64)) {
    let ctx = shared.borrow();
    let (x, y) = (&ctx.scene.agents[a.idx], &ctx.scene.agents[b.idx]);
    ((x.length, x.width), (y.length, y.width))
}

fn distinct(a: &AgentRef, b: &AgentRef, what: &str) -> RResult<()> {
    if a.idx == b.idx {
        return err(format!("{what}: both arguments are agent {}", a.id));
    }
    Ok(())
}

/// Signed box clearance series of two agents.
pub(crate) fn clearance(shared: &Shared, a: AgentRef, b: AgentRef) -> Series {
    let (za, zb) = sizes(shared, a, b);
    pair_series(shared, a, b, move |p, q| box_clearance(p, za, q, zb))
}

fn ttc(shared: &Shared, a: &AgentRef, b: &AgentRef, cap: f64) -> RResult<Series> {
    distinct(a, b, "ttc")?;
    if !(cap.is_finite() && cap > 0.0) {
        return err(format!(
            "ttc: cap must be positive, got {}",
            crate::geom::num(cap)
        ));
    }
    let c = clearance(shared, *a, *b);
    let rate = c.deriv();
    lift(c.zip(&rate, "ttc", move |gap, dgap| {
        let closing = -dgap;
        Some(if gap <= 0.0 {
            (0.0, 0.0, 0.0)
        } else if closing <= gap / cap {
            (cap, 0.0, 0.0)
        } else {
            (gap / closing, 1.0 / closing, gap / (closing * closing))
        })
    }))
}

/// Σ over pairs and steps of relu(margin - clearance)², with a broad phase on centre distance.
/// `agents` are indices with their held flags: a held agent's coordinates get no gradient.
pub(crate) fn no_collision_cost(
    shared: &Shared,
    list: &[(usize, bool)],
    margin: f64,
) -> RResult<Dual> {
    let agents: Vec<usize> = list.iter().map(|a| a.0).collect();
    let free: Vec<f64> = list.iter().map(|a| if a.1 { 0.0 } else { 1.0 }).collect();
    let ctx = shared.borrow();
    let lay = ctx.traj.layout;
    let reach: Vec<f64> = agents
        .iter()
        .map(|&i| 0.5 * ctx.scene.agents[i].length.hypot(ctx.scene.agents[i].width))
        .collect();
    let mut val = 0.0;
    let mut rows: Vec<[(u32, f64); 6]> = Vec::new();
    // Only pairs within reach at a step are looked at: the cost grows with the agents, not
    // their pairs (3,000 cars took 31 s per evaluation).
    let mut centres: Vec<Point> = vec![Point::new(f64::NAN, f64::NAN); agents.len()];
    // Thousands of agents stacked in one place make every pair near: a long native call, so
    // the wall time is checked inside it. Once per 16,384 units of work (an agent placed or a
    // pair looked at, each well under a microsecond), not per step: a bench-size call (24
    // agents, 80 steps) is a few hundred microseconds, where reading the clock at every step
    // is a cost of its own.
    const CHECK_EVERY: usize = 16_384;
    let mut work = 0usize;
    let mut tick = |n: usize| -> RResult<()> {
        work += n;
        if work >= CHECK_EVERY {
            work = 0;
            over_time(&ctx)?;
        }
        Ok(())
    };
    for t in 0..lay.steps {
        tick(agents.len())?;
        for (ii, &i) in agents.iter().enumerate() {
            let (p, valid) = ctx.traj.state(i, t);
            centres[ii] = if valid {
                Point::new(p[0], p[1])
            } else {
                Point::new(f64::NAN, f64::NAN)
            };
        }
        for (ii, jj) in pairs_within(&centres, &reach, margin) {
            tick(1)?;
            let (i, j) = (agents[ii], agents[jj]);
            let (zi, zj) = (
                (ctx.scene.agents[i].length, ctx.scene.agents[i].width),
                (ctx.scene.agents[j].length, ctx.scene.agents[j].width),
            );
            let (p, _) = ctx.traj.state(i, t);
            let (q, _) = ctx.traj.state(j, t);
            let c = box_clearance(p, zi, q, zj);
            let short = margin - c.v;
            if short <= 0.0 {
                continue;
            }
            val += short * short;
            let k = -2.0 * short;
            let (ki, kj) = (k * free[ii], k * free[jj]);
            let mut row = [(0u32, 0.0); 6];
            for (s, coord) in [Coord::X, Coord::Y, Coord::Heading].into_iter().enumerate() {
                row[s] = (lay.var(i, t, coord), ki * c.g[s]);
                row[3 + s] = (lay.var(j, t, coord), kj * c.g[3 + s]);
            }
            rows.push(row);
        }
    }
    // Keep the structural dependence on every agent's first step even when nothing is near,
    // so that the validator sees a term that depends on the trajectory.
    let mut zero: Vec<(u32, f64)> = agents
        .iter()
        .map(|&i| (lay.var(i, 0, Coord::X), 0.0))
        .collect();
    zero.sort_unstable_by_key(|e| e.0);
    let grad = accumulate(
        rows.iter()
            .map(|r| (&r[..], 1.0))
            .chain(std::iter::once((&zero[..], 1.0))),
    );
    Ok(Dual::new(val, grad))
}

/// A clearance margin, metres: a NaN one made every penalty 0 (a term that never steers), a
/// negative one penalised only boxes already overlapping by more than it.
fn margin(m: &Dynamic, what: &str) -> RResult<f64> {
    let v = number(m, &format!("{what} margin"))?;
    if !(0.0..=1000.0).contains(&v) {
        return err(format!(
            "{what}: margin {} must be 0 to 1000 metres",
            crate::geom::num(v)
        ));
    }
    Ok(v)
}

pub(super) fn register(e: &mut Engine, shared: &Shared, docs: &mut Vec<DocEntry>) {
    const S: &str = "Interactions";
    doc(docs, S, "gap(a, b, path) -> Series", "Bumper-to-bumper gap from a to b along the path: s_b - s_a - (length_a + length_b) / 2 (negative when b is behind a).");
    let sh = shared.clone();
    e.register_fn(
        "gap",
        move |a: AgentRef, b: AgentRef, p: PathRef| -> RResult<Series> {
            distinct(&a, &b, "gap")?;
            let (fa, fb) = (frenet(&sh, a, &p), frenet(&sh, b, &p));
            let half = {
                let ctx = sh.borrow();
                0.5 * (ctx.scene.agents[a.idx].length + ctx.scene.agents[b.idx].length)
            };
            lift(fb.s.zip(&fa.s, "gap", move |sb, sa| {
                Some((sb - sa - half, 1.0, -1.0))
            }))
        },
    );
    doc(
        docs,
        S,
        "pass_time(a, b, path) -> float or ()",
        "Seconds after the current step at which a's centre first gets ahead of b's along the path (s_a > s_b after s_a <= s_b), or () when it never does in the candidate; a plain number (for if and print, not a cost).",
    );
    let sh = shared.clone();
    e.register_fn(
        "pass_time",
        move |a: AgentRef, b: AgentRef, p: PathRef| -> RResult<Dynamic> {
            distinct(&a, &b, "pass_time")?;
            let (fa, fb) = (frenet(&sh, a, &p), frenet(&sh, b, &p));
            let (sa, sb) = (&fa.s.0, &fb.s.0);
            let mut behind = None;
            for k in 0..sa.val.len() {
                if !(sa.valid[k] && sb.valid[k]) {
                    continue;
                }
                let ahead = sa.val[k] > sb.val[k];
                if ahead && behind == Some(true) && k >= sa.head {
                    return Ok(Dynamic::from(sa.time0 + (k - sa.head) as f64 * sa.dt));
                }
                behind = Some(!ahead);
            }
            Ok(Dynamic::UNIT)
        },
    );
    doc(
        docs,
        S,
        "distance(a, b) -> Series",
        "Distance between the two agents' centres, metres.",
    );
    let sh = shared.clone();
    e.register_fn(
        "distance",
        move |a: AgentRef, b: AgentRef| -> RResult<Series> {
            distinct(&a, &b, "distance")?;
            Ok(pair_series(&sh, a, b, |p, q| {
                let dx = Fwd::<6>::var(q[0], 3) - Fwd::var(p[0], 0);
                let dy = Fwd::<6>::var(q[1], 4) - Fwd::var(p[1], 1);
                (dx * dx + dy * dy).sqrt()
            }))
        },
    );
    doc(docs, S, "clearance(a, b) -> Series", "Signed clearance between the two boxes: their distance when apart, minus the penetration depth when they overlap (negative = collision).");
    let sh = shared.clone();
    e.register_fn(
        "clearance",
        move |a: AgentRef, b: AgentRef| -> RResult<Series> {
            distinct(&a, &b, "clearance")?;
            Ok(clearance(&sh, a, b))
        },
    );
    doc(docs, S, "ttc(a, b) or ttc(a, b, cap) -> Series", "Time until the boxes touch at the current closing rate of their clearance, seconds: 0 when overlapping, cap (10 s by default) when not closing in.");
    let sh = shared.clone();
    e.register_fn("ttc", move |a: AgentRef, b: AgentRef| {
        ttc(&sh, &a, &b, TTC_CAP)
    });
    let sh = shared.clone();
    e.register_fn("ttc", move |a: AgentRef, b: AgentRef, cap: Dynamic| {
        ttc(&sh, &a, &b, number(&cap, "ttc cap")?)
    });
    doc(
        docs,
        S,
        "collision_penalty(a, b, margin) -> Series",
        "relu(margin - clearance(a, b))²: zero while the boxes stay margin metres apart.",
    );
    let sh = shared.clone();
    e.register_fn(
        "collision_penalty",
        move |a: AgentRef, b: AgentRef, m: Dynamic| -> RResult<Series> {
            distinct(&a, &b, "collision_penalty")?;
            let m = margin(&m, "collision_penalty")?;
            let (za, zb) = sizes(&sh, a, b);
            // Boxes whose centres are farther apart than their half-diagonals plus the margin
            // cannot come within the margin: skip the exact clearance there.
            let near = 0.5 * za.0.hypot(za.1) + 0.5 * zb.0.hypot(zb.1) + m;
            Ok(pair_series_opt(&sh, a, b, move |p, q| {
                if (p[0] - q[0]).hypot(p[1] - q[1]) > near {
                    return None;
                }
                let c = box_clearance(p, za, q, zb);
                let s = (m - c.v).max(0.0);
                Some(Fwd {
                    v: s * s,
                    g: c.g.map(|g| -2.0 * s * g),
                })
            }))
        },
    );
    doc(docs, S, "no_collision_cost(agents, margin) -> Dual", "Sum over all pairs of the agents and all future steps of relu(margin - clearance)², skipping pairs whose centres are far apart.");
    let sh = shared.clone();
    e.register_fn(
        "no_collision_cost",
        move |list: Array, m: Dynamic| -> RResult<Dual> {
            let m = margin(&m, "no_collision_cost")?;
            let mut idx = Vec::with_capacity(list.len());
            for (k, v) in list.iter().enumerate() {
                match v.clone().try_cast::<AgentRef>() {
                    Some(a) => idx.push((a.idx, a.held)),
                    None => {
                        return err(format!(
                            "no_collision_cost: element {k} is {}, not an Agent",
                            super::a_type(v)
                        ))
                    }
                }
            }
            // An agent listed both held and free is free.
            idx.sort_unstable();
            idx.dedup_by(|later, first| {
                let same = later.0 == first.0;
                if same {
                    first.1 &= later.1;
                }
                same
            });
            if idx.len() < 2 {
                return err("no_collision_cost needs at least two distinct agents");
            }
            no_collision_cost(&sh, &idx, m)
        },
    );
}
