//! Kinematic plausibility: whether a vehicle's future is motion a car can make. A pure function
//! of a scene, applied alike to logged and simulated futures.
//!
//! The anchor is Waymax's kinematic-infeasibility metric (a transition is infeasible when the
//! inverse of a kinematic bicycle model needs more than a bound on acceleration or on steering
//! curvature), made robust to 10 Hz tracking noise and extended by the failures guidance
//! produces: every quantity comes from centred differences of positions over a window of at
//! least [`KinematicLimits::window`] seconds (0.6 s at 10 Hz), near the ends of a track the
//! window is shifted inwards rather than shortened, and a track shorter than one window is
//! not judged. A vehicle is flagged when at any future step it
//!
//! - **reverses**: its speed along its heading is below `reverse_speed` (−1 m/s);
//! - **sprints**: its speed exceeds `max_speed` (40 m/s), or `sprint_factor` × its current
//!   speed + `sprint_margin` (1.6 × v₀ + 8 m/s), a bound that grows by `sprint_accel` (3 m/s²)
//!   per second after `sprint_after` (4 s);
//! - **brakes or accelerates** harder than `max_accel` (7 m/s², the change of its signed
//!   speed along its heading);
//! - **swerves**: its lateral acceleration v·ω exceeds `max_lateral` (5 m/s²) while faster
//!   than `moving` (3 m/s);
//! - **crabs**: its velocity points more than `max_crab` (35°) off its heading axis while
//!   faster than `moving`;
//! - **over-steers**: its path's curvature ω/v exceeds Waymax's `max_curvature` (0.3 1/m, a
//!   3.3 m turning radius) while faster than `moving`.
//!
//! Two places get a closer look, because the long windows smooth away exactly what goes wrong
//! there: the **joint** of history and future, where a sample that jumps in speed across the
//! recorded current state has changed its speed faster than any car (a rear-end request gave
//! +8.6 m/s² there while every 0.6 s window read below 7), and the **end** of a track, where
//! a sample braking into a recorded end point does so in its last steps (12.3 → 3.5 m/s in
//! 0.6 s read as 7 m/s² once the windows were shifted inwards). At both, the acceleration is
//! also taken from two windows of `joint_window` (0.3 s) meeting at the current step or at
//! the track's last-but-`joint_window` step, against the same `max_accel`. Over a whole NGSIM
//! track such short windows would flag a sixth of the recorded cars for tracking noise; at
//! these two places alone they flag few.
//!
//! The bounds are a car's; cyclists and pedestrians are judged against their own
//! ([`KinematicLimits::for_type`]), other objects not at all.

use crate::geom::wrap_angle;
use crate::scene::{Agent, Scene};

// The bounds live with the road users they describe: realism (cost) and the sampler need
// them too, and take them from there rather than from evaluation.
pub use crate::scene::KinematicLimits;

/// The kinds of implausible motion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Violation {
    /// Speed along the heading below the reverse bound.
    Reverse,
    /// Speed above the sprint bound.
    Sprint,
    /// Longitudinal acceleration beyond the bound.
    Accel,
    /// Lateral acceleration beyond the bound.
    Swerve,
    /// Velocity too far off the heading axis.
    Crab,
    /// Path curvature beyond the bound.
    Curvature,
}

impl Violation {
    /// Every kind, in table order.
    pub const ALL: [Violation; 6] = [
        Violation::Reverse,
        Violation::Sprint,
        Violation::Accel,
        Violation::Swerve,
        Violation::Crab,
        Violation::Curvature,
    ];

    /// Short name for tables and JSON.
    pub fn name(self) -> &'static str {
        match self {
            Violation::Reverse => "reverse",
            Violation::Sprint => "sprint",
            Violation::Accel => "accel",
            Violation::Swerve => "swerve",
            Violation::Crab => "crab",
            Violation::Curvature => "curvature",
        }
    }
}

/// The worst instance of one violation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Event {
    /// What.
    pub kind: Violation,
    /// Seconds after the current step.
    pub time: f64,
    /// The offending value in SI units (m/s, m/s², radians or 1/m; signed where the sign
    /// matters).
    pub value: f64,
}

impl std::fmt::Display for Event {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let t = self.time;
        match self.kind {
            Violation::Reverse => write!(f, "reverses at {:.1} m/s at t = {t:.1} s", self.value),
            Violation::Sprint => write!(f, "sprints at {:.1} m/s at t = {t:.1} s", self.value),
            Violation::Accel if self.value < 0.0 => {
                write!(f, "brakes at {:.1} m/s² at t = {t:.1} s", -self.value)
            }
            Violation::Accel => write!(f, "accelerates at {:.1} m/s² at t = {t:.1} s", self.value),
            Violation::Swerve => write!(
                f,
                "swerves at {:.1} m/s² lateral at t = {t:.1} s",
                self.value.abs()
            ),
            Violation::Crab => write!(
                f,
                "moves {:.0}° off its heading at t = {t:.1} s",
                self.value.abs().to_degrees()
            ),
            Violation::Curvature => write!(
                f,
                "turns on a {:.1} m radius at t = {t:.1} s",
                1.0 / self.value.abs()
            ),
        }
    }
}

/// One vehicle's judgement: the worst event of each violation it commits (empty when
/// plausible).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Judgement {
    /// At most one event per [`Violation`], in [`Violation::ALL`] order.
    pub events: Vec<Event>,
}

impl Judgement {
    /// Whether the motion is plausible.
    pub fn plausible(&self) -> bool {
        self.events.is_empty()
    }

    /// Whether it commits `v`.
    pub fn has(&self, v: Violation) -> bool {
        self.events.iter().any(|e| e.kind == v)
    }

    /// The same judgement, with the violations `allowed` removed (a behaviour that asks for
    /// reversing allows reversing).
    pub fn without(&self, allowed: &[Violation]) -> Judgement {
        Judgement {
            events: self
                .events
                .iter()
                .filter(|e| !allowed.contains(&e.kind))
                .copied()
                .collect(),
        }
    }
}

/// Velocity from positions `p[t ± h]`, the window shifted inside the valid run `[lo, hi]`.
fn velocity(a: &Agent, t: usize, h: usize, lo: usize, hi: usize, dt: f64) -> [f64; 2] {
    let start = t.saturating_sub(h).max(lo).min(hi - 2 * h);
    let (p, q) = (&a.states[start], &a.states[start + 2 * h]);
    let span = 2.0 * h as f64 * dt;
    [(q.x - p.x) / span, (q.y - p.y) / span]
}

/// The valid run of steps containing `t`.
fn run_around(a: &Agent, t: usize) -> (usize, usize) {
    let (mut lo, mut hi) = (t, t);
    while lo > 0 && a.states[lo - 1].valid {
        lo -= 1;
    }
    while hi + 1 < a.states.len() && a.states[hi + 1].valid {
        hi += 1;
    }
    (lo, hi)
}

/// Judges one agent's future (steps after `s.meta.current_step`) against the bounds of its
/// type ([`KinematicLimits::for_type`] of `lim`, a car's); `None` for a static obstacle, an
/// object of unknown type, or where no future step lies in a valid run long enough for one
/// window.
pub fn judge_agent(s: &Scene, a: &Agent, lim: &KinematicLimits) -> Option<Judgement> {
    if a.is_static {
        return None;
    }
    let lim = &lim.for_type(a.agent_type)?;
    let (c, dt) = (s.meta.current_step, s.meta.dt);
    let h = ((lim.window / (2.0 * dt)) - 1e-9).ceil().max(1.0) as usize;
    let len = a.states.len();
    // The current speed: the recorded state's, or the motion over the history window. A road
    // user that comes into view later is judged from when it does, at the speed it has then
    // (from 0 m/s, a car driving into the recording at 12 m/s would "sprint").
    let first = (c..len).find(|&t| a.states[t].valid);
    let v0 = match first {
        Some(t0) if t0 == c => {
            let (lo, hi) = run_around(a, c);
            if c >= lo + 2 * h {
                let v = velocity(a, c - h, h, lo, c.min(hi), dt);
                v[0].hypot(v[1])
            } else {
                a.states[c].vx.hypot(a.states[c].vy)
            }
        }
        Some(t0) => {
            let (lo, hi) = run_around(a, t0);
            let recorded = a.states[t0].vx.hypot(a.states[t0].vy);
            if hi >= lo + 2 * h {
                let v = velocity(a, t0, h, lo, hi, dt);
                v[0].hypot(v[1]).max(recorded)
            } else {
                recorded
            }
        }
        None => 0.0,
    };
    let since = first.unwrap_or(c);
    // Per violation, the event furthest beyond its bound.
    let mut worst: Vec<Option<(f64, Event)>> = vec![None; Violation::ALL.len()];
    let mut note = |kind: Violation, t: usize, value: f64, beyond: f64| {
        let slot = &mut worst[kind as usize];
        if slot.is_none_or(|(b, _)| beyond > b) {
            let time = (t - c) as f64 * dt;
            *slot = Some((beyond, Event { kind, time, value }));
        }
    };
    let mut judged = false;
    for t in c + 1..len {
        if !a.states[t].valid {
            continue;
        }
        let (lo, hi) = run_around(a, t);
        if hi - lo < 2 * h {
            continue;
        }
        judged = true;
        let st = &a.states[t];
        let (sn, cs) = st.heading.sin_cos();
        let v = velocity(a, t, h, lo, hi, dt);
        let speed = v[0].hypot(v[1]);
        let along = v[0] * cs + v[1] * sn;
        if along < lim.reverse_speed {
            note(Violation::Reverse, t, along, lim.reverse_speed - along);
        }
        let sprint = lim.sprint_bound(v0, (t - since) as f64 * dt);
        if speed > sprint {
            note(Violation::Sprint, t, speed, speed - sprint);
        }
        if speed > lim.moving {
            let off = wrap_angle(v[1].atan2(v[0]) - st.heading).abs();
            let crab = off.min(std::f64::consts::PI - off);
            if crab > lim.max_crab {
                note(Violation::Crab, t, crab, crab - lim.max_crab);
            }
        }
        // Second differences: velocities a window apart, the pair shifted inside the run.
        if hi - lo < 4 * h {
            continue;
        }
        let mid = t.max(lo + 2 * h).min(hi - 2 * h);
        let (va, vb) = (
            velocity(a, mid - h, h, lo, hi, dt),
            velocity(a, mid + h, h, lo, hi, dt),
        );
        let span = 2.0 * h as f64 * dt;
        let signed = |v: [f64; 2]| {
            let s = v[0].hypot(v[1]);
            if v[0] * cs + v[1] * sn < 0.0 {
                -s
            } else {
                s
            }
        };
        let accel = (signed(vb) - signed(va)) / span;
        if accel.abs() > lim.max_accel {
            note(Violation::Accel, t, accel, accel.abs() - lim.max_accel);
        }
        let (sa, sb) = (va[0].hypot(va[1]), vb[0].hypot(vb[1]));
        if sa > lim.moving && sb > lim.moving {
            // The direction the car's nose travels: a car that goes from forwards to reverse
            // along its axis does not turn.
            let nose = |v: [f64; 2]| {
                let d = v[1].atan2(v[0]);
                if signed(v) < 0.0 {
                    d + std::f64::consts::PI
                } else {
                    d
                }
            };
            let omega = wrap_angle(nose(vb) - nose(va)) / span;
            let lateral = speed * omega;
            if lateral.abs() > lim.max_lateral {
                note(
                    Violation::Swerve,
                    t,
                    lateral,
                    lateral.abs() - lim.max_lateral,
                );
            }
            let kappa = omega / speed.max(lim.moving);
            if kappa.abs() > lim.max_curvature {
                note(
                    Violation::Curvature,
                    t,
                    kappa,
                    kappa.abs() - lim.max_curvature,
                );
            }
        }
    }
    if judged {
        // The joint and the end, with short windows: speeds along the middle point's heading
        // before and after it.
        let j = lim.joint_steps(dt);
        let span = j as f64 * dt;
        let mut short = |m: usize, at: usize| {
            if m < j || m + j >= len || !(m - j..=m + j).all(|t| a.states[t].valid) {
                return;
            }
            let (sn, cs) = a.states[m].heading.sin_cos();
            let along = |p: &crate::scene::AgentState, q: &crate::scene::AgentState| {
                ((q.x - p.x) * cs + (q.y - p.y) * sn) / span
            };
            let s = &a.states;
            let accel = (along(&s[m], &s[m + j]) - along(&s[m - j], &s[m])) / span;
            if accel.abs() > lim.max_accel {
                note(Violation::Accel, at, accel, accel.abs() - lim.max_accel);
            }
        };
        short(c, c);
        let last = (c + 1..len).rev().find(|&t| a.states[t].valid);
        if let Some(last) = last.filter(|&l| l >= c + 2 * j) {
            let (lo, _) = run_around(a, last);
            if last >= lo + 2 * j {
                short(last - j, last);
            }
        }
    }
    judged.then(|| Judgement {
        events: worst.into_iter().flatten().map(|(_, e)| e).collect(),
    })
}

/// Every agent's judgement (see [`judge_agent`]), in scene order.
pub fn judge(s: &Scene, lim: &KinematicLimits) -> Vec<Option<Judgement>> {
    s.agents.iter().map(|a| judge_agent(s, a, lim)).collect()
}

/// Per agent, whether it commits `v` (`None` for agents not judged): for [`super::metrics::rate`].
pub fn flags(judged: &[Option<Judgement>], v: Option<Violation>) -> Vec<Option<bool>> {
    judged
        .iter()
        .map(|j| {
            j.as_ref().map(|j| match v {
                Some(v) => j.has(v),
                None => !j.plausible(),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::yaml;
    use crate::scene::AgentType;
    use std::path::Path;

    /// A straight three-lane road with the given agents (YAML flow mappings).
    fn road(agents: &[&str]) -> Scene {
        let mut text = String::from(
            "steps: 51\ncurrent_step: 10\nroad: {lanes: 3, lane_width: 3.6, length: 800}\nagents:\n",
        );
        for a in agents {
            text.push_str(&format!("  - {a}\n"));
        }
        yaml::parse(Path::new("kinematic.yaml"), &text).unwrap()
    }

    fn only(s: &Scene) -> Judgement {
        judge(s, &KinematicLimits::default())[0].clone().unwrap()
    }

    /// Moves the agent's future by `f(seconds after the current step)`, headings kept.
    fn shift(s: &mut Scene, f: impl Fn(f64) -> (f64, f64)) {
        let (c, dt) = (s.meta.current_step, s.meta.dt);
        for t in c + 1..s.agents[0].states.len() {
            let (dx, dy) = f((t - c) as f64 * dt);
            s.agents[0].states[t].x += dx;
            s.agents[0].states[t].y += dy;
        }
    }

    #[test]
    fn steady_driving_and_a_lane_change_are_plausible() {
        for a in [
            "{id: 1, lane: 0, s: 50, speed: 25}",
            "{id: 1, lane: 0, s: 50, speed: 15, lane_change: {to: 1, start: 0.5, duration: 3.0}}",
            "{id: 1, lane: 1, s: 50, speed: 20, accel: -4}",
            "{id: 1, lane: 1, s: 50, speed: 0}",
        ] {
            let j = only(&road(&[a]));
            assert!(j.plausible(), "{a}: {:?}", j.events);
        }
    }

    #[test]
    fn a_jump_in_speed_across_the_current_step_is_flagged_there() {
        // 20 m/s recorded, then a future that starts at 23 m/s: 10 m/s² across the joint,
        // while every 0.6 s window reads at most 4.2 m/s².
        let mut s = road(&["{id: 1, lane: 0, s: 100, speed: 20}"]);
        shift(&mut s, |t| (3.0 * t, 0.0));
        let j = only(&s);
        assert_eq!(
            j.events.iter().map(|e| e.kind).collect::<Vec<_>>(),
            vec![Violation::Accel],
            "{:?}",
            j.events
        );
        let e = j.events[0];
        assert!((e.value - 10.0).abs() < 0.1 && e.time == 0.0, "{e:?}");
        assert_eq!(e.to_string(), "accelerates at 10.0 m/s² at t = 0.0 s");
        // Half the jump reads 5 m/s²: plausible.
        let mut s = road(&["{id: 1, lane: 0, s: 100, speed: 20}"]);
        shift(&mut s, |t| (1.5 * t, 0.0));
        assert!(only(&s).plausible(), "{:?}", only(&s).events);
    }

    #[test]
    fn braking_into_the_end_of_a_track_is_flagged_there() {
        // 10 m/s, then 6 m/s over the last 0.3 s: 13.3 m/s² into the end point, which the
        // 0.6 s windows, shifted inwards at the end, read as 3.3 m/s².
        let mut s = road(&["{id: 1, lane: 0, s: 100, speed: 10}"]);
        let (c, n) = (s.meta.current_step, s.agents[0].states.len());
        let brake = n - 4;
        let x_at = |t: usize| {
            let base = s.agents[0].states[c].x + 10.0 * (t - c) as f64 * 0.1;
            if t <= brake {
                base
            } else {
                base - 4.0 * (t - brake) as f64 * 0.1
            }
        };
        let xs: Vec<f64> = (0..n).map(x_at).collect();
        for (t, x) in xs.iter().enumerate().skip(c + 1) {
            s.agents[0].states[t].x = *x;
        }
        let j = only(&s);
        let e = j
            .events
            .iter()
            .find(|e| e.kind == Violation::Accel)
            .unwrap_or_else(|| panic!("not flagged: {:?}", j.events));
        assert!((e.value + 13.33).abs() < 0.1, "{e:?}");
        assert!((e.time - (n - 1 - c) as f64 * 0.1).abs() < 1e-9, "{e:?}");
    }

    #[test]
    fn cyclists_are_judged_against_a_cyclist_s_bounds() {
        // 9 m/s braking at 4.5 m/s² is plausible for a car and for a cyclist; 12 m/s at 6
        // m/s² is plausible for a car only; a static object is not judged at all.
        let brake = |v: f64, a: f64| {
            let mut s = road(&[&format!(
                "{{id: 1, lane: 0, s: 100, speed: {v}, accel: {a}, type: cyclist}}"
            )]);
            s.agents[0].length = 1.8;
            s
        };
        assert!(only(&brake(9.0, -4.5)).plausible());
        let j = only(&brake(12.0, -6.0));
        assert!(j.has(Violation::Accel), "{:?}", j.events);
        let mut car = brake(12.0, -6.0);
        car.agents[0].agent_type = AgentType::Vehicle;
        assert!(only(&car).plausible(), "{:?}", only(&car).events);
        car.agents[0].is_static = true;
        assert!(judge(&car, &KinematicLimits::default())[0].is_none());
    }

    #[test]
    fn a_reversing_car_is_flagged_and_named() {
        let j = only(&road(&["{id: 1, lane: 0, s: 200, speed: -5}"]));
        assert_eq!(
            j.events.iter().map(|e| e.kind).collect::<Vec<_>>(),
            vec![Violation::Reverse]
        );
        let e = j.events[0];
        assert!((e.value + 5.0).abs() < 0.05, "{e:?}");
        assert!(
            e.to_string().starts_with("reverses at -5.0 m/s at t = "),
            "{e}"
        );
        assert!(j.without(&[Violation::Reverse]).plausible());
    }

    #[test]
    fn a_sprint_is_flagged_at_50_m_s_and_against_the_current_speed() {
        let j = only(&road(&["{id: 1, lane: 0, s: 50, speed: 50}"]));
        assert!(
            j.has(Violation::Sprint) && !j.has(Violation::Accel),
            "{:?}",
            j.events
        );
        // 10 m/s now, 30 m/s two seconds later: beyond 1.6·10 + 8 and at 10 m/s².
        let mut s = road(&["{id: 1, lane: 0, s: 50, speed: 10}"]);
        shift(&mut s, |t| (5.0 * t * t, 0.0));
        let j = only(&s);
        assert!(
            j.has(Violation::Sprint) && j.has(Violation::Accel),
            "{:?}",
            j.events
        );
        let a = j
            .events
            .iter()
            .find(|e| e.kind == Violation::Accel)
            .unwrap();
        assert!((a.value - 10.0).abs() < 0.1, "{a:?}");
    }

    #[test]
    fn the_sprint_bound_grows_after_4_s_and_starts_where_a_car_comes_into_view() {
        let eight = |a: &str| {
            let text = format!(
                "steps: 91\ncurrent_step: 10\nroad: {{lanes: 3, lane_width: 3.6, length: 800}}\nagents:\n  - {a}\n"
            );
            yaml::parse(Path::new("eight.yaml"), &text).unwrap()
        };
        // From 1 m/s at 1.8 m/s² for 8 s: 15.4 m/s at the end, which 1.6·v0 + 8 alone calls a
        // sprint from about 4.5 s on; at 4 m/s² the car is at 17 m/s by 4 s, and that is one.
        let brisk = only(&eight("{id: 1, lane: 0, s: 50, speed: 1, accel: 1.8}"));
        assert!(brisk.plausible(), "{:?}", brisk.events);
        let hard = only(&eight("{id: 1, lane: 0, s: 50, speed: 1, accel: 4}"));
        assert!(hard.has(Violation::Sprint), "{:?}", hard.events);
        let lim = KinematicLimits::default();
        assert_eq!(lim.sprint_bound(1.0, 2.0), lim.sprint_bound(1.0, 4.0));
        assert!((lim.sprint_bound(1.0, 8.0) - 21.6).abs() < 1e-9);
        assert_eq!(lim.sprint_bound(30.0, 8.0), 40.0);
        // A car that comes into view 2 s in at 12 m/s and holds it is judged from then, not
        // from 0 m/s.
        let mut s = eight("{id: 1, lane: 0, s: 50, speed: 12}");
        for t in 0..30 {
            s.agents[0].states[t].valid = false;
        }
        let late = only(&s);
        assert!(late.plausible(), "{:?}", late.events);
    }

    #[test]
    fn crabbing_sideways_is_flagged_but_tracking_jitter_is_not() {
        let mut s = road(&["{id: 1, lane: 0, s: 50, speed: 10}"]);
        shift(&mut s, |t| (0.0, 8.0 * t));
        let j = only(&s);
        assert!(j.has(Violation::Crab), "{:?}", j.events);
        // ±5 cm of 10 Hz noise on a car at 12 m/s: nothing.
        let mut s = road(&["{id: 1, lane: 1, s: 50, speed: 12}"]);
        shift(&mut s, |t| {
            let k = (t * 10.0).round() as i64;
            (
                0.05 * ((k * 7) % 3 - 1) as f64,
                0.05 * ((k * 5) % 3 - 1) as f64,
            )
        });
        assert!(only(&s).plausible(), "{:?}", only(&s).events);
    }

    #[test]
    fn a_swerve_is_flagged() {
        // 1.8 m of lateral motion over 0.6 s at 20 m/s, and back: a slalom no car makes.
        let mut s = road(&["{id: 1, lane: 1, s: 50, speed: 20}"]);
        shift(&mut s, |t| {
            (0.0, 1.8 * (std::f64::consts::TAU * t / 1.2).sin())
        });
        let j = only(&s);
        assert!(j.has(Violation::Swerve), "{:?}", j.events);
    }

    #[test]
    fn only_road_users_with_a_long_enough_future_are_judged() {
        let s = road(&[
            "{id: 1, lane: 0, s: 50, speed: 10, type: other}",
            "{id: 2, lane: 1, s: 50, speed: 10}",
            "{id: 3, lane: 2, s: 50, speed: 10, type: pedestrian}",
        ]);
        let j = judge(&s, &KinematicLimits::default());
        assert!(j[0].is_none() && j[1].is_some());
        assert_eq!(
            flags(&j, None),
            vec![None, Some(false), Some(true)],
            "the object is not counted; a pedestrian at 10 m/s sprints"
        );
        assert!(j[2].as_ref().unwrap().has(Violation::Sprint));
    }
}
