//! Realism: costs that keep guided vehicles driving as cars can, for every agent the sampler
//! moves, whatever the scripts ask. Native code with analytic gradients, evaluated beside the
//! scripts at every guided step and reported as terms of their own (`realism_speed`, ...).
//!
//! The quantities are those the kinematic checker ([`crate::eval::kinematic`]) judges, from
//! the same centred differences of positions over its window (history included, so the first
//! future steps are judged against the recorded motion), with bounds a fraction
//! ([`Realism::margin`]) of the checker's so that a sample at zero realism cost passes the
//! checker with room. Each term is the sum over agents and windows of the squared excess over
//! its bound: zero for plausible motion, smooth where it starts.
//!
//! A script exempts an agent from the reverse bound with `allow(a, "reverse")`: a behaviour
//! that asks a car to back up must not be fought by realism.

use std::time::Instant;

use super::report::{CostReport, TermReport};
use super::trajectory::{Coord, Trajectories};
use crate::eval::kinematic::KinematicLimits;
use crate::scene::Scene;

/// Term names, in report order.
pub const TERMS: [&str; 5] = [
    "realism_speed",
    "realism_reverse",
    "realism_accel",
    "realism_swerve",
    "realism_crab",
];

/// Realism settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Realism {
    /// Weight of every realism term (0 turns realism off).
    pub weight: f64,
    /// The cost's bounds as a fraction of the checker's (speeds, accelerations, crab angle).
    pub margin: f64,
    /// The checker's bounds.
    pub limits: KinematicLimits,
}

impl Default for Realism {
    fn default() -> Self {
        Self {
            weight: 1.0,
            margin: 0.75,
            limits: KinematicLimits::default(),
        }
    }
}

/// One agent's positions and headings over the run that holds its current step: history
/// constants, then the candidate's future (with coordinate indices for gradients).
struct Track {
    p: Vec<[f64; 2]>,
    head: Vec<f64>,
    /// Layout index of x (y and heading follow) for future entries.
    var: Vec<Option<u32>>,
    /// Index of the first future entry.
    first_future: usize,
}

impl Realism {
    /// Evaluates the realism terms on `traj` for the agents with `moved[a]` true, exempting
    /// those with `may_reverse[a]` from the reverse term. Values are unweighted; the report's
    /// terms carry [`Realism::weight`].
    pub fn evaluate(
        &self,
        scene: &Scene,
        traj: &Trajectories,
        moved: &[bool],
        may_reverse: &[bool],
    ) -> CostReport {
        let t0 = Instant::now();
        let lim = &self.limits;
        let dt = scene.meta.dt;
        let h = ((lim.window / (2.0 * dt)) - 1e-9).ceil().max(1.0) as usize;
        let span = 2.0 * h as f64 * dt;
        let m = self.margin;
        let mut vals = [0.0; 5];
        let mut grads: [Vec<(u32, f64)>; 5] = Default::default();
        for (a, agent) in scene.agents.iter().enumerate() {
            if !moved.get(a).copied().unwrap_or(false) {
                continue;
            }
            let Some(tr) = track(scene, traj, a, 2 * h) else {
                continue;
            };
            let n = tr.p.len();
            if n < 2 * h + 1 {
                continue;
            }
            let c = scene.meta.current_step;
            let v0 = agent.states[c].vx.hypot(agent.states[c].vy);
            let sprint = lim
                .max_speed
                .min(lim.sprint_factor * v0 + lim.sprint_margin);
            // The margin applies to the speed-up the checker allows, not to the speed: a car
            // cruising at 30 m/s is not held back.
            let cap = v0 + m * (sprint - v0).max(0.0);
            let reverse_ok = may_reverse.get(a).copied().unwrap_or(false);
            // Adds `coef · d(quantity)/d(coordinates)` for a velocity-like vector built from
            // positions `taps` (index, factor) and a heading at `th`.
            let mut push =
                |term: usize, taps: &[(usize, f64)], dv: [f64; 2], th: Option<(usize, f64)>| {
                    for &(j, f) in taps {
                        if let Some(x) = tr.var[j] {
                            grads[term].push((x, f * dv[0]));
                            grads[term].push((x + 1, f * dv[1]));
                        }
                    }
                    if let Some((j, g)) = th {
                        if let Some(x) = tr.var[j] {
                            grads[term].push((x + 2, g));
                        }
                    }
                };
            let vel = |t: usize| {
                let (p, q) = (tr.p[t - h], tr.p[t + h]);
                [(q[0] - p[0]) / span, (q[1] - p[1]) / span]
            };
            // As the checker judges: at every future step, the velocity of the window centred
            // there (shifted inwards near the ends of the track) against the step's heading.
            let ff = tr.first_future;
            for t in ff..n {
                let w = t.clamp(h, n - 1 - h);
                let v = vel(w);
                let (sn, cs) = tr.head[t].sin_cos();
                let along = v[0] * cs + v[1] * sn;
                let lat = -v[0] * sn + v[1] * cs;
                let speed = v[0].hypot(v[1]);
                let taps = [(w + h, 1.0 / span), (w - h, -1.0 / span)];
                let x = speed - cap;
                if x > 0.0 && speed > 0.0 {
                    vals[0] += x * x;
                    let k = 2.0 * x / speed;
                    push(0, &taps, [k * v[0], k * v[1]], None);
                }
                let x = -along + m * lim.reverse_speed;
                if x > 0.0 && !reverse_ok {
                    vals[1] += x * x;
                    // d(-along) = -(u·dv) - lat·dθ
                    let k = 2.0 * x;
                    push(1, &taps, [-k * cs, -k * sn], Some((t, -k * lat)));
                }
                if speed > lim.moving {
                    let tan = (m * lim.max_crab).tan();
                    let x = lat.abs() - tan * along.abs();
                    if x > 0.0 {
                        vals[4] += x * x;
                        let (sl, sa) = (lat.signum(), along.signum());
                        let k = 2.0 * x;
                        // d|lat| = sl·(n·dv - along·dθ); d|along| = sa·(u·dv + lat·dθ)
                        let dv = [
                            k * (sl * -sn - tan * sa * cs),
                            k * (sl * cs - tan * sa * sn),
                        ];
                        let dth = k * (-sl * along - tan * sa * lat);
                        push(4, &taps, dv, Some((t, dth)));
                    }
                }
            }
            // Accelerations: second differences over two windows, centred at the step where
            // the track is long enough, against the step's heading.
            if n < 4 * h + 1 {
                continue;
            }
            for t in ff..n {
                let mid = t.clamp(2 * h, n - 1 - 2 * h);
                let (p, q, r) = (tr.p[mid - 2 * h], tr.p[mid], tr.p[mid + 2 * h]);
                let s2 = span * span;
                let acc = [
                    (r[0] - 2.0 * q[0] + p[0]) / s2,
                    (r[1] - 2.0 * q[1] + p[1]) / s2,
                ];
                let (sn, cs) = tr.head[t].sin_cos();
                let along = acc[0] * cs + acc[1] * sn;
                let lat = -acc[0] * sn + acc[1] * cs;
                let taps = [
                    (mid + 2 * h, 1.0 / s2),
                    (mid, -2.0 / s2),
                    (mid - 2 * h, 1.0 / s2),
                ];
                let x = along.abs() - m * lim.max_accel;
                if x > 0.0 {
                    vals[2] += x * x;
                    let k = 2.0 * x * along.signum();
                    push(2, &taps, [k * cs, k * sn], Some((t, k * lat)));
                }
                let moving = {
                    let (va, vb) = (vel(mid - h), vel(mid + h));
                    va[0].hypot(va[1]) > lim.moving && vb[0].hypot(vb[1]) > lim.moving
                };
                let x = lat.abs() - m * lim.max_lateral;
                if moving && x > 0.0 {
                    vals[3] += x * x;
                    let k = 2.0 * x * lat.signum();
                    push(3, &taps, [-k * sn, k * cs], Some((t, -k * along)));
                }
            }
        }
        let terms = TERMS
            .iter()
            .zip(vals)
            .zip(grads)
            .map(|((name, value), mut g)| {
                g.sort_unstable_by_key(|e| e.0);
                g.dedup_by(|b, a| {
                    if a.0 == b.0 {
                        a.1 += b.1;
                        true
                    } else {
                        false
                    }
                });
                TermReport {
                    name: name.to_string(),
                    weight: self.weight,
                    value,
                    line: 0,
                    tolerance: None,
                    grad: g.into(),
                }
            })
            .collect();
        CostReport::new(terms, traj.layout, Vec::new(), t0.elapsed())
    }
}

/// Per agent of a scene with `agents` agents, whether any of `reports`' scripts allowed it to
/// reverse (`allow(a, "reverse")`).
pub fn may_reverse(reports: &[CostReport], agents: usize) -> Vec<bool> {
    let mut out = vec![false; agents];
    for r in reports {
        for &a in &r.may_reverse {
            if let Some(x) = out.get_mut(a) {
                *x = true;
            }
        }
    }
    out
}

/// Agent `a`'s track: up to `history` recorded steps before and including the current one
/// (within its valid run), then its valid future in `traj` up to the first gap.
fn track(scene: &Scene, traj: &Trajectories, a: usize, history: usize) -> Option<Track> {
    let c = scene.meta.current_step;
    let st = &scene.agents[a].states;
    if !st[c].valid {
        return None;
    }
    let mut start = c;
    while start > 0 && c - start < history && st[start - 1].valid {
        start -= 1;
    }
    let mut tr = Track {
        p: Vec::new(),
        head: Vec::new(),
        var: Vec::new(),
        first_future: c - start + 1,
    };
    for s in &st[start..=c] {
        tr.p.push([s.x, s.y]);
        tr.head.push(s.heading);
        tr.var.push(None);
    }
    for k in 0..traj.layout.steps {
        let (xyh, valid) = traj.state(a, k);
        if !valid {
            break;
        }
        tr.p.push([xyh[0], xyh[1]]);
        tr.head.push(xyh[2]);
        tr.var.push(Some(traj.layout.var(a, k, Coord::X)));
    }
    Some(tr)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cost::{CostScript, Limits, Params};
    use crate::io::{load_scene, LoadOptions};
    use std::path::Path;
    use std::rc::Rc;

    fn highway() -> Scene {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        load_scene(&p, 0, &LoadOptions::default()).unwrap()
    }

    fn on() -> Realism {
        Realism::default()
    }

    fn values(r: &CostReport) -> Vec<f64> {
        r.terms.iter().map(|t| t.value).collect()
    }

    /// Moves agent `a`'s future by `f(seconds after the current step)`.
    fn edit(s: &Scene, t: &mut Trajectories, a: usize, f: impl Fn(f64) -> [f64; 3]) {
        let n = t.layout.steps;
        for k in 0..n {
            let d = f((k + 1) as f64 * s.meta.dt);
            for (c, dv) in d.iter().enumerate() {
                t.xyh[a * n + k][c] += dv;
            }
        }
    }

    #[test]
    fn recorded_highway_driving_costs_nothing() {
        let s = highway();
        let t = Trajectories::recorded(&s);
        let all = vec![true; s.agents.len()];
        let r = on().evaluate(&s, &t, &all, &[]);
        assert_eq!(values(&r), vec![0.0; 5], "{:?}", r.terms);
    }

    #[test]
    fn each_implausible_motion_raises_its_own_term() {
        let s = highway();
        let all = vec![true; s.agents.len()];
        let rec = Trajectories::recorded(&s);
        // Agent 1 (index 0) drives at 20 m/s along +x (heading 0).
        let cases: Vec<(&str, Box<dyn Fn(f64) -> [f64; 3]>)> = vec![
            // Back at 10 m/s: 30 m/s behind where it would be per second.
            ("realism_reverse", Box::new(|t| [-30.0 * t, 0.0, 0.0])),
            // 60 m/s after 1 s: far over 1.6·20 + 8.
            (
                "realism_speed",
                Box::new(|t| [40.0 * (t - 1.0).max(0.0), 0.0, 0.0]),
            ),
            // Sideways at 16 m/s while heading along the road at 20 (39° off).
            ("realism_crab", Box::new(|t| [0.0, 16.0 * t, 0.0])),
        ];
        for (term, f) in cases {
            let mut t = rec.clone();
            edit(&s, &mut t, 0, f);
            let r = on().evaluate(&s, &t, &all, &[]);
            assert!(r.term(term).unwrap().value > 1.0, "{term}: {:?}", r.terms);
            // Only the moved agents count.
            let mut none = all.clone();
            none[0] = false;
            assert_eq!(values(&on().evaluate(&s, &t, &none, &[])), vec![0.0; 5]);
        }
        // A hard brake (10 m/s² from t = 1 s) and a 1 Hz weave of ±2 m (lateral ≈ 8 m/s²).
        let mut t = rec.clone();
        edit(&s, &mut t, 0, |t| {
            let b = (t - 1.0).max(0.0);
            [-5.0 * b * b, 0.0, 0.0]
        });
        assert!(
            on().evaluate(&s, &t, &all, &[])
                .term("realism_accel")
                .unwrap()
                .value
                > 1.0
        );
        let mut t = rec.clone();
        edit(&s, &mut t, 0, |t| {
            [0.0, 2.0 * (std::f64::consts::TAU * t).sin(), 0.0]
        });
        assert!(
            on().evaluate(&s, &t, &all, &[])
                .term("realism_swerve")
                .unwrap()
                .value
                > 1.0
        );
        // A plausible lane change (3.6 m over 4 s) costs nothing.
        let mut t = rec.clone();
        edit(&s, &mut t, 0, |t| {
            let u = (t / 4.0).min(1.0);
            [0.0, 3.6 * (3.0 * u * u - 2.0 * u * u * u), 0.0]
        });
        assert_eq!(values(&on().evaluate(&s, &t, &all, &[])), vec![0.0; 5]);
    }

    #[test]
    fn a_script_that_asks_for_reversing_exempts_its_agent() {
        let s = Rc::new(highway());
        let c = CostScript::compile(
            "let a = agent(1); allow(a, \"reverse\"); term(\"x\", a.long_speed.mean());",
            "rev.rhai",
            s.clone(),
            &Params::default(),
            &Limits::default(),
        )
        .unwrap();
        let mut t = Trajectories::recorded(&s);
        edit(&s, &mut t, 0, |t| [-30.0 * t, 0.0, 0.0]);
        let rep = c.evaluate(&t).unwrap();
        assert_eq!(rep.may_reverse, vec![0]);
        let all = vec![true; s.agents.len()];
        let mut may = vec![false; s.agents.len()];
        may[0] = true;
        assert_eq!(
            on().evaluate(&s, &t, &all, &may)
                .term("realism_reverse")
                .unwrap()
                .value,
            0.0
        );
        let e = CostScript::compile(
            "allow(agent(1), \"sprint\"); term(\"x\", 0.0);",
            "bad.rhai",
            s.clone(),
            &Params::default(),
            &Limits::default(),
        )
        .unwrap()
        .evaluate(&t)
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("only \"reverse\"") && e.contains("bad.rhai:1"),
            "{e}"
        );
    }

    #[test]
    fn gradients_match_finite_differences() {
        let s = highway();
        let all = vec![true; s.agents.len()];
        let mut t = Trajectories::recorded(&s);
        // Every violation at once on agent 1, and a wobbling heading so that heading
        // derivatives matter.
        edit(&s, &mut t, 0, |t| {
            [
                -25.0 * t + 12.0 * (3.0 * t).sin(),
                6.0 * t + 2.0 * (7.0 * t).sin(),
                0.4 * (5.0 * t).sin(),
            ]
        });
        edit(&s, &mut t, 2, |t| {
            [30.0 * t * t, 3.0 * (4.0 * t).cos(), 0.2 * t]
        });
        let r = on().evaluate(&s, &t, &all, &[]);
        for term in &r.terms {
            assert!(term.value > 0.0, "{} is not exercised", term.name);
        }
        // Values are sums of squares over hundreds of windows: a smaller step loses digits.
        let eps = 1e-4;
        for (i, term) in r.terms.iter().enumerate() {
            let dense = {
                let mut g = vec![0.0; t.layout.len()];
                for &(k, v) in &term.grad {
                    g[k as usize] += v;
                }
                g
            };
            for var in 0..t.layout.len() {
                let (a, k, c) = t.layout.decode(var as u32);
                if a != 0 && a != 2 {
                    continue;
                }
                let idx = a * t.layout.steps + k;
                let mut up = t.clone();
                up.xyh[idx][c as usize] += eps;
                let mut dn = t.clone();
                dn.xyh[idx][c as usize] -= eps;
                let fd = (on().evaluate(&s, &up, &all, &[]).terms[i].value
                    - on().evaluate(&s, &dn, &all, &[]).terms[i].value)
                    / (2.0 * eps);
                let tol = 1e-4 * (1.0 + fd.abs());
                assert!(
                    (fd - dense[var]).abs() < tol,
                    "{} d/d(agent {a} step {k} {c:?}): analytic {} vs {fd}",
                    term.name,
                    dense[var]
                );
            }
        }
    }
}
