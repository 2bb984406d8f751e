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
//! A sixth term keeps every moved agent clear of every other agent's box by
//! [`Realism::clearance`]: guidance that pushes a car forwards would otherwise push it through
//! the one ahead, and the sample's other cars pay for the behaviour. Where an agent a script
//! names meets one it does not, only the other gives way: the traffic behind a car asked to
//! stop brakes, rather than shoving the stopped car on.
//!
//! The sampler adds the collision term last ([`Realism::keep_clear`]): it denoises, then
//! descends without it (every car takes its route), then with it (the boxes come apart). A
//! barrier while the route is still open locks a car on whichever side of another it happens
//! to be: at a Lankershim junction the guided denoiser put a northbound car in the southbound
//! lanes, and the term then held it there, head-on, 10 m from its recorded end. Conditional
//! simulation of the fold-0 validation instances collided 0.006 of vehicles with the term in
//! every stage, and 0.002 with it last, as without the term.
//!
//! A script exempts an agent from the reverse bound with `allow(a, "reverse")`, and a pair from
//! the collision term with `allow(a, "collide", b)`: a behaviour that asks a car to back up, or
//! to hit another, must not be fought by realism.

use std::time::Instant;

use super::fwd::box_clearance;
use super::report::{CostReport, TermReport};
use super::trajectory::{Coord, Trajectories};
use crate::geom::{pairs_within, Point};
use crate::scene::KinematicLimits;
use crate::scene::Scene;

/// Term names, in report order.
pub const TERMS: [&str; 6] = [
    "realism_speed",
    "realism_reverse",
    "realism_accel",
    "realism_swerve",
    "realism_crab",
    "realism_collision",
];

/// Sideways speed (m/s, relative to the heading) that the crab term allows beyond its angle
/// bound: over the checker's 0.6 s window, 0.3 m, more than a car's heading lags its path in a
/// slow turn, less than a slide across a lane.
const SLIDE: f64 = 0.5;

/// Realism settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Realism {
    /// Weight of every realism term (0 turns realism off).
    pub weight: f64,
    /// The cost's bounds as a fraction of the checker's (speeds, accelerations, crab angle).
    pub margin: f64,
    /// The checker's bounds.
    pub limits: KinematicLimits,
    /// The clearance (metres, box to box) a moved agent keeps from every other agent; the
    /// collision term is the squared shortfall.
    pub clearance: f64,
    /// Whether the collision term is evaluated (else it is 0). The sampler leaves it out
    /// until every route is chosen ([`crate::sample`]'s polish).
    pub keep_clear: bool,
}

/// What scripts allow that realism would otherwise hold back.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Allowed {
    /// Per scene agent, whether it may back up (`allow(a, "reverse")`); missing entries are
    /// false.
    pub reverse: Vec<bool>,
    /// Pairs of scene agents, smaller index first, whose boxes may touch
    /// (`allow(a, "collide", b)`).
    pub collide: Vec<(usize, usize)>,
    /// Per scene agent, whether a script names it (`agent(id)`): others give way to it.
    pub named: Vec<bool>,
}

impl Allowed {
    /// What any of `reports`' scripts (evaluated on `scene`) allowed and named.
    pub fn from_reports(reports: &[CostReport], scene: &Scene) -> Self {
        let agents = scene.agents.len();
        let mut out = Self {
            reverse: vec![false; agents],
            collide: Vec::new(),
            named: vec![false; agents],
        };
        for r in reports {
            for id in &r.named {
                if let Some(i) = scene.agents.iter().position(|a| a.id == *id) {
                    out.named[i] = true;
                }
            }
            for &a in &r.may_reverse {
                if let Some(x) = out.reverse.get_mut(a) {
                    *x = true;
                }
            }
            for p in &r.may_collide {
                if !out.collide.contains(p) {
                    out.collide.push(*p);
                }
            }
        }
        out
    }

    fn may_collide(&self, a: usize, b: usize) -> bool {
        self.collide.contains(&(a.min(b), a.max(b)))
    }

    fn is_named(&self, a: usize) -> bool {
        self.named.get(a).copied().unwrap_or(false)
    }
}

impl Default for Realism {
    fn default() -> Self {
        Self {
            weight: 1.0,
            margin: 0.75,
            limits: KinematicLimits::default(),
            clearance: 0.3,
            keep_clear: true,
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
    /// Evaluates the realism terms on `traj` for the agents with `moved[a]` true, with the
    /// exemptions in `allowed`. Values are unweighted; the report's terms carry
    /// [`Realism::weight`].
    pub fn evaluate(
        &self,
        scene: &Scene,
        traj: &Trajectories,
        moved: &[bool],
        allowed: &Allowed,
    ) -> CostReport {
        let t0 = Instant::now();
        let dt = scene.meta.dt;
        let h = ((self.limits.window / (2.0 * dt)) - 1e-9).ceil().max(1.0) as usize;
        let span = 2.0 * h as f64 * dt;
        let m = self.margin;
        let mut vals = [0.0; 6];
        let mut grads: [Vec<(u32, f64)>; 6] = Default::default();
        for (a, agent) in scene.agents.iter().enumerate() {
            if !moved.get(a).copied().unwrap_or(false) {
                continue;
            }
            // Each road user within the checker's bounds for its type.
            let Some(lim) = self.limits.for_type(agent.agent_type) else {
                continue;
            };
            let lim = &lim;
            let Some(tr) = track(scene, traj, a, 2 * h) else {
                continue;
            };
            let n = tr.p.len();
            if n < 2 * h + 1 {
                continue;
            }
            let c = scene.meta.current_step;
            let v0 = agent.states[c].vx.hypot(agent.states[c].vy);
            // The margin applies to the speed-up the checker allows, not to the speed: a car
            // cruising at 30 m/s is not held back. Like the checker's bound, it grows with time.
            let cap = |t: usize| {
                let tau = (t + 1 - tr.first_future) as f64 * dt;
                v0 + m * (lim.sprint_bound(v0, tau) - v0).max(0.0)
            };
            let reverse_ok = allowed.reverse.get(a).copied().unwrap_or(false);
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
                let x = speed - cap(t);
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
                // A pedestrian steps any way it faces: no crab bound. Below the checker's
                // `moving` speed, where it judges no crabbing (a tracked car's heading is noise
                // there), a guided car still may not slide sideways more than SLIDE: samples
                // of standing cars slid 3 m sideways and back across the road into oncoming
                // traffic, heading held.
                if lim.max_crab < std::f64::consts::FRAC_PI_2 {
                    let tan = (m * lim.max_crab).tan();
                    let x = lat.abs() - tan * along.abs() - SLIDE;
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
            // the track is long enough, against the step's heading; and, as the checker looks
            // closer there, over two short windows meeting at the current step (the joint of
            // history and future) and before the track's last step.
            let j = lim.joint_steps(dt);
            let mut short = vec![];
            if ff > j && ff - 1 + j < n {
                short.push(ff - 1);
            }
            if n > ff + 2 * j {
                short.push(n - 1 - j);
            }
            if n < 4 * h + 1 && short.is_empty() {
                continue;
            }
            let long = if n < 4 * h + 1 { 0..0 } else { ff..n };
            let wins = long
                .map(|t| (t.clamp(2 * h, n - 1 - 2 * h), 2 * h, t))
                .chain(short.into_iter().map(|m| (m, j, m)));
            for (mid, w, t) in wins {
                let span = w as f64 * dt;
                let (p, q, r) = (tr.p[mid - w], tr.p[mid], tr.p[mid + w]);
                let s2 = span * span;
                let acc = [
                    (r[0] - 2.0 * q[0] + p[0]) / s2,
                    (r[1] - 2.0 * q[1] + p[1]) / s2,
                ];
                let (sn, cs) = tr.head[t].sin_cos();
                let along = acc[0] * cs + acc[1] * sn;
                let lat = -acc[0] * sn + acc[1] * cs;
                let taps = [(mid + w, 1.0 / s2), (mid, -2.0 / s2), (mid - w, 1.0 / s2)];
                let x = along.abs() - m * lim.max_accel;
                if x > 0.0 {
                    vals[2] += x * x;
                    let k = 2.0 * x * along.signum();
                    push(2, &taps, [k * cs, k * sn], Some((t, k * lat)));
                }
                // Lateral acceleration over the long windows only: over short ones it is
                // tracking noise.
                let moving = w == 2 * h && {
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
        let (v, g) = self.collisions(scene, traj, moved, allowed);
        vals[5] = v;
        grads[5] = g;
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

    /// The collision term: Σ over steps and pairs with a moved agent (and not allowed to touch)
    /// of relu(clearance − box clearance)², and its gradient w.r.t. the poses of the agents
    /// that give way. Agents the sampler does not move are obstacles, as they
    /// are to a driver; of a named and an unnamed moved agent, the unnamed one gives way.
    fn collisions(
        &self,
        scene: &Scene,
        traj: &Trajectories,
        moved: &[bool],
        allowed: &Allowed,
    ) -> (f64, Vec<(u32, f64)>) {
        let lay = traj.layout;
        let margin = self.clearance;
        let is_moved = |a: usize| moved.get(a).copied().unwrap_or(false);
        if !self.keep_clear || !(0..lay.agents).any(is_moved) {
            return (0.0, Vec::new());
        }
        let size = |a: usize| (scene.agents[a].length, scene.agents[a].width);
        let reach: Vec<f64> = (0..lay.agents)
            .map(|a| 0.5 * scene.agents[a].length.hypot(scene.agents[a].width))
            .collect();
        let mut val = 0.0;
        let mut grad = Vec::new();
        let mut centres = vec![Point::new(f64::NAN, f64::NAN); lay.agents];
        for t in 0..lay.steps {
            for (a, c) in centres.iter_mut().enumerate() {
                let (p, valid) = traj.state(a, t);
                *c = if valid {
                    Point::new(p[0], p[1])
                } else {
                    Point::new(f64::NAN, f64::NAN)
                };
            }
            for (i, j) in pairs_within(&centres, &reach, margin) {
                if !(is_moved(i) || is_moved(j)) || allowed.may_collide(i, j) {
                    continue;
                }
                let (p, _) = traj.state(i, t);
                let (q, _) = traj.state(j, t);
                let c = box_clearance(p, size(i), q, size(j));
                let short = margin - c.v;
                if short <= 0.0 {
                    continue;
                }
                val += short * short;
                let k = -2.0 * short;
                for (side, a, b) in [(0, i, j), (3, j, i)] {
                    let leads = allowed.is_named(a) && !allowed.is_named(b) && is_moved(b);
                    if is_moved(a) && !leads {
                        grad.push((lay.var(a, t, Coord::X), k * c.g[side]));
                        grad.push((lay.var(a, t, Coord::Y), k * c.g[side + 1]));
                        grad.push((lay.var(a, t, Coord::Heading), k * c.g[side + 2]));
                    }
                }
            }
        }
        (val, grad)
    }
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
        let r = on().evaluate(&s, &t, &all, &Allowed::default());
        assert_eq!(values(&r), vec![0.0; 6], "{:?}", r.terms);
    }

    #[test]
    fn the_speed_term_grows_with_the_horizon_as_the_checker_does() {
        // 8 s of future: from 1 m/s, speeding up at 1.5 m/s² stays within realism's share (3/4) of
        // the speed-up the checker lets a car make, whose bound grows after 4 s; at 4 m/s² it is
        // a sprint by 4 s.
        let scene = |accel: f64| {
            let text = format!(
                "steps: 91\ncurrent_step: 10\nroad: {{lanes: 3, lane_width: 3.6, length: 800}}\nagents:\n  - {{id: 1, lane: 0, s: 50, speed: 1, accel: {accel}}}\n"
            );
            crate::io::yaml::parse(std::path::Path::new("eight.yaml"), &text).unwrap()
        };
        let speed = |accel: f64| {
            let s = scene(accel);
            let r = on().evaluate(
                &s,
                &Trajectories::recorded(&s),
                &[true],
                &Allowed::default(),
            );
            r.term("realism_speed").unwrap().value
        };
        assert_eq!(speed(1.5), 0.0);
        assert!(speed(4.0) > 1.0, "{}", speed(4.0));
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
            let r = on().evaluate(&s, &t, &all, &Allowed::default());
            assert!(r.term(term).unwrap().value > 1.0, "{term}: {:?}", r.terms);
            // Only the moved agents count.
            let mut none = all.clone();
            none[0] = false;
            assert_eq!(
                values(&on().evaluate(&s, &t, &none, &Allowed::default())),
                vec![0.0; 6]
            );
        }
        // A hard brake (10 m/s² from t = 1 s) and a 1 Hz weave of ±2 m (lateral ≈ 8 m/s²).
        let mut t = rec.clone();
        edit(&s, &mut t, 0, |t| {
            let b = (t - 1.0).max(0.0);
            [-5.0 * b * b, 0.0, 0.0]
        });
        assert!(
            on().evaluate(&s, &t, &all, &Allowed::default())
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
            on().evaluate(&s, &t, &all, &Allowed::default())
                .term("realism_swerve")
                .unwrap()
                .value
                > 1.0
        );
        // A plausible lane change (3.6 m over 4 s) into the gap behind agent 2 costs nothing
        // (the left lane would put it in the way of agent 3, which catches up at 6 m/s).
        let mut t = rec.clone();
        edit(&s, &mut t, 0, |t| {
            let u = (t / 4.0).min(1.0);
            [0.0, -3.6 * (3.0 * u * u - 2.0 * u * u * u), 0.0]
        });
        assert_eq!(
            values(&on().evaluate(&s, &t, &all, &Allowed::default())),
            vec![0.0; 6]
        );
        // Stopped, then sliding sideways at 1.5 m/s: below the speed where the checker judges
        // crabbing, and still no motion a car makes (the stop costs acceleration, and the cars
        // behind, collisions).
        let mut t = rec.clone();
        edit(&s, &mut t, 0, |t| [-20.0 * t, 1.5 * t, 0.0]);
        let crab = |moved: &[bool]| {
            let r = on().evaluate(&s, &t, moved, &Allowed::default());
            r.term("realism_crab").unwrap().value
        };
        assert!(crab(&all) > 1.0);
        let mut none = all.clone();
        none[0] = false;
        assert_eq!(crab(&none), 0.0);
        // Creeping on at 1 m/s, drifting 0.3 m/s to the side as a slow turn's lagging heading
        // would: no crab cost.
        let mut t = rec.clone();
        edit(&s, &mut t, 0, |t| [-19.0 * t, 0.3 * t, 0.0]);
        let r = on().evaluate(&s, &t, &all, &Allowed::default());
        assert_eq!(r.term("realism_crab").unwrap().value, 0.0, "{:?}", r.terms);
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
        let may = Allowed::from_reports(&[rep], &s);
        assert_eq!(may.reverse, vec![true, false, false, false]);
        assert!(
            on().evaluate(&s, &t, &all, &Allowed::default())
                .term("realism_reverse")
                .unwrap()
                .value
                > 1.0
        );
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
            e.contains("only \"reverse\" and \"collide\"") && e.contains("bad.rhai:1"),
            "{e}"
        );
    }

    #[test]
    fn moved_cars_keep_clear_of_every_other_box() {
        let s = highway();
        let n = s.agents.len();
        let rec = Trajectories::recorded(&s);
        let all = vec![true; n];
        let collision = |t: &Trajectories, moved: &[bool], allowed: &Allowed| {
            on().evaluate(&s, t, moved, allowed)
                .term("realism_collision")
                .unwrap()
                .clone()
        };
        // Agent 2 (index 1, lane 0, 10 m ahead, 4 m/s faster) moved across into lane 1 and
        // back onto agent 1 (index 0): from t = 1 s it sits on agent 1, aligned in its lane.
        let mut t = rec.clone();
        edit(&s, &mut t, 1, |t| {
            let u = t.min(1.0);
            [-14.0 * u, 3.6 * u, 0.0]
        });
        let hit = collision(&t, &all, &Allowed::default());
        assert!(hit.value > 1.0, "{hit:?}");
        // Both are moved: both are pushed, and apart (a small step along the descent direction
        // lowers the term).
        let agents_in = |g: &[(u32, f64)]| {
            let mut a: Vec<usize> = g
                .iter()
                .filter(|e| e.1 != 0.0)
                .map(|e| t.layout.decode(e.0).0)
                .collect();
            a.dedup();
            a
        };
        assert_eq!(agents_in(&hit.grad), vec![0, 1]);
        let mut down = t.clone();
        for &(k, g) in hit.grad.iter() {
            let (a, step, c) = t.layout.decode(k);
            down.xyh[a * t.layout.steps + step][c as usize] -= 1e-3 * g;
        }
        assert!(collision(&down, &all, &Allowed::default()).value < hit.value);
        // An agent the sampler does not move is an obstacle: it is not pushed.
        let mut only = vec![false; n];
        only[1] = true;
        let one = collision(&t, &only, &Allowed::default());
        assert!(one.value > 1.0);
        assert_eq!(agents_in(&one.grad), vec![1]);
        // Neither moved: nothing to guide.
        assert_eq!(
            collision(&t, &vec![false; n], &Allowed::default()).value,
            0.0
        );
        // A script that asks for the accident exempts the pair, and only it.
        let allowed = Allowed {
            collide: vec![(0, 1)],
            ..Allowed::default()
        };
        assert_eq!(collision(&t, &all, &allowed).value, 0.0);
        let other = Allowed {
            collide: vec![(1, 2)],
            ..Allowed::default()
        };
        assert_eq!(collision(&t, &all, &other).value, hit.value);
        // Where a script names agent 1, agent 2 gives way alone.
        let named = Allowed {
            named: vec![true, false, false, false],
            ..Allowed::default()
        };
        let yields = collision(&t, &all, &named);
        assert_eq!(yields.value, hit.value);
        assert_eq!(agents_in(&yields.grad), vec![1]);
        // Unless it cannot: an agent the sampler does not move is an obstacle to named ones too.
        let mut only0 = vec![false; n];
        only0[0] = true;
        assert_eq!(agents_in(&collision(&t, &only0, &named).grad), vec![0]);
        // Passing in the next lane, 3.6 m apart centre to centre, is clear.
        assert_eq!(collision(&rec, &all, &Allowed::default()).value, 0.0);
        // Left out (the sampler's route stage), the term is 0 and the others are as they were.
        let full = on().evaluate(&s, &t, &all, &Allowed::default());
        let routes = Realism {
            keep_clear: false,
            ..on()
        }
        .evaluate(&s, &t, &all, &Allowed::default());
        let clear = routes.term("realism_collision").unwrap();
        assert_eq!((clear.value, clear.grad.len()), (0.0, 0));
        for name in &TERMS[..5] {
            assert_eq!(
                routes.term(name).unwrap().value,
                full.term(name).unwrap().value,
                "{name}"
            );
        }
    }

    #[test]
    fn a_script_that_asks_for_an_accident_exempts_the_pair() {
        let s = Rc::new(highway());
        let run = |src: &str| {
            CostScript::compile(
                src,
                "acc.rhai",
                s.clone(),
                &Params::default(),
                &Limits::default(),
            )
            .and_then(|c| c.evaluate(&Trajectories::recorded(&s)))
        };
        let rep = run(
            "let a = agent(2); let b = agent(1); allow(a, \"collide\", hold(b)); \
             allow(b, \"collide\", a); term(\"x\", clearance(a, b).min());",
        )
        .unwrap();
        assert_eq!(rep.may_collide, vec![(0, 1)]);
        assert!(rep.may_reverse.is_empty());
        let allowed = Allowed::from_reports(&[rep], &s);
        assert_eq!(allowed.collide, vec![(0, 1)]);
        assert_eq!(allowed.reverse, vec![false; 4]);
        assert_eq!(allowed.named, vec![true, true, false, false]);
        for (src, says) in [
            (
                "allow(agent(1), \"collide\"); term(\"x\", 0.0);",
                "needs the other agent",
            ),
            (
                "allow(agent(1), \"collide\", agent(1)); term(\"x\", 0.0);",
                "cannot collide with itself",
            ),
            (
                "allow(agent(1), \"reverse\", agent(2)); term(\"x\", 0.0);",
                "only allow(a, \"collide\", b)",
            ),
        ] {
            let e = run(src).unwrap_err().to_string();
            assert!(e.contains(says) && e.contains("acc.rhai:1"), "{src}: {e}");
        }
    }

    #[test]
    fn a_jump_in_speed_across_the_current_step_costs_and_is_pulled_back() {
        // Agent 1 records 20 m/s; a future that starts 3 m/s faster changes speed at 10 m/s²
        // across the current step, which the 0.6 s windows alone read as 4.2 m/s².
        let s = highway();
        let all = vec![true; s.agents.len()];
        let mut t = Trajectories::recorded(&s);
        edit(&s, &mut t, 0, |t| [3.0 * t, 0.0, 0.0]);
        let r = on().evaluate(&s, &t, &all, &Allowed::default());
        let acc = r.term("realism_accel").unwrap();
        assert!(acc.value > 1.0, "{:?}", r.terms);
        // The gradient pushes the first future steps back, towards the recorded speed.
        let n = t.layout.steps;
        let first = acc
            .grad
            .iter()
            .find(|(v, _)| *v == t.layout.var(0, 2, Coord::X))
            .map(|g| g.1)
            .unwrap_or(0.0);
        assert!(first > 0.0, "d/dx at step 3: {first} (n = {n})");
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
        let r = on().evaluate(&s, &t, &all, &Allowed::default());
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
                let fd = (on().evaluate(&s, &up, &all, &Allowed::default()).terms[i].value
                    - on().evaluate(&s, &dn, &all, &Allowed::default()).terms[i].value)
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
