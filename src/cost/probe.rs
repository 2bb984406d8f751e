//! Perturbed futures on which validation probes a script's terms, beside the recorded one.
//!
//! A term that is 0 with a zero gradient on the recorded future may be a guard that sampling
//! will wake (no collision on the log, but samples may collide) or a term that can never act
//! (`relu(speed - 1000)`, anything times 0). The two are told apart by evaluating the script
//! on futures that depart from the log the ways requests ask about: standing still, half and
//! double speed, full speed straight ahead, sideways by a lane and off the road, turned,
//! weaving, backing up, every other car stopped in front of the rest (and the other way
//! round), and every car crowded onto one path. A term that stays 0 with a zero gradient on
//! all of them can never steer sampling ([`super::CostScript::dead_terms`]).

use super::trajectory::Trajectories;
use crate::scene::Scene;

/// The highest speed the probes drive at, m/s: the kinematic checker's top speed for a car
/// (a term that needs more never acts on a plausible car).
pub const PROBE_TOP_SPEED: f64 = 40.0;

/// The probes, in words, in the order [`probe_futures`] builds them.
pub const PROBES: &[&str] = &[
    "standing still",
    "half speed",
    "double speed",
    "40 m/s straight ahead",
    "a lane (3.5 m) to the left at once",
    "a lane to the right at once",
    "10 m to the left over 2 s",
    "10 m to the right over 2 s",
    "turned by 0.6 rad",
    "weaving 2 m either side",
    "backing up at 10 m/s",
    "every other car stopped, the rest at double speed",
    "the same the other way round",
    "every car crowded onto one path",
];

/// The futures of [`PROBES`] for `scene`, each built from the recorded future with gaps
/// filled ([`Trajectories::filled`]) and every agent's state at the current step. Agents not
/// observed at the current step keep the filled log (they have no pose to start from).
pub fn probe_futures(scene: &Scene) -> Vec<Trajectories> {
    let base = Trajectories::filled(scene);
    let n = base.layout.steps;
    let dt = scene.meta.dt;
    let c = scene.meta.current_step;
    // Each agent's pose at the current step, where it has one.
    let start: Vec<Option<[f64; 3]>> = scene
        .agents
        .iter()
        .map(|a| {
            let s = a.states.get(c).filter(|s| s.valid)?;
            Some([s.x, s.y, s.heading])
        })
        .collect();
    // `f(agent, step, log state, start pose)` applied to every agent with a start.
    let map = |f: &dyn Fn(usize, usize, [f64; 3], [f64; 3]) -> [f64; 3]| {
        let mut t = base.clone();
        for (a, p0) in start.iter().enumerate() {
            let Some(p0) = p0 else { continue };
            for k in 0..n {
                let i = a * n + k;
                t.xyh[i] = f(a, k, base.xyh[i], *p0);
            }
        }
        t
    };
    let scaled = |s: f64| {
        move |_: usize, _: usize, x: [f64; 3], p0: [f64; 3]| {
            [
                p0[0] + s * (x[0] - p0[0]),
                p0[1] + s * (x[1] - p0[1]),
                if s == 0.0 { p0[2] } else { x[2] },
            ]
        }
    };
    // A lane over happens at once: a term on the first step alone (a cut-in's cutter starting
    // beside its victim) must see it move. Farther offsets grow from nothing over the first
    // 2 s: a 10 m jump at the first step would be a speed of 100 m/s, waking any speed term,
    // and a term dead on every plausible motion would pass for alive.
    let ramp = |k: usize| ((k + 1) as f64 * dt / 2.0).min(1.0);
    let sideways = move |d: f64, at_once: bool| {
        move |_: usize, k: usize, x: [f64; 3], _: [f64; 3]| {
            let d = if at_once { d } else { d * ramp(k) };
            [x[0] - d * x[2].sin(), x[1] + d * x[2].cos(), x[2]]
        }
    };
    // The first agent with a pose: the path every car is crowded onto.
    let lead = start.iter().position(Option::is_some);
    vec![
        map(&scaled(0.0)),
        map(&scaled(0.5)),
        map(&scaled(2.0)),
        map(&|_, k, _, p0| {
            let d = PROBE_TOP_SPEED * (k + 1) as f64 * dt;
            [p0[0] + d * p0[2].cos(), p0[1] + d * p0[2].sin(), p0[2]]
        }),
        map(&sideways(3.5, true)),
        map(&sideways(-3.5, true)),
        map(&sideways(10.0, false)),
        map(&sideways(-10.0, false)),
        map(&|_, _, x, _| [x[0], x[1], x[2] + 0.6]),
        map(&|_, k, x, _| {
            // One swerve either way every 2 s, from the log's line at the current step.
            let d = 2.0 * (std::f64::consts::PI * (k + 1) as f64 * dt).sin();
            [x[0] - d * x[2].sin(), x[1] + d * x[2].cos(), x[2]]
        }),
        map(&|_, k, _, p0| {
            let d = -10.0 * (k + 1) as f64 * dt;
            [p0[0] + d * p0[2].cos(), p0[1] + d * p0[2].sin(), p0[2]]
        }),
        // Followers run into stopped leaders, and a car that was to wait goes first.
        map(&|a, k, x, p0| scaled(if a % 2 == 0 { 0.0 } else { 2.0 })(a, k, x, p0)),
        map(&|a, k, x, p0| scaled(if a % 2 == 0 { 2.0 } else { 0.0 })(a, k, x, p0)),
        // The one probe faster than a car: cars far apart cannot meet in a few seconds, but a
        // term between any two of them (a collision guard) must wake somewhere. They converge
        // over the first 2 s onto the lead's path, at most 0.7 m apart side by side, so every
        // two boxes overlap (or come within any margin).
        map(&|a, k, x, _| {
            let Some(l) = lead else { return x };
            let y = base.xyh[l * n + k];
            let d = 0.1 * (a % 8) as f64;
            let on = [y[0] - d * y[2].sin(), y[1] + d * y[2].cos(), y[2]];
            let r = ramp(k);
            [
                x[0] + r * (on[0] - x[0]),
                x[1] + r * (on[1] - x[1]),
                x[2] + r * crate::geom::wrap_angle(on[2] - x[2]),
            ]
        }),
    ]
}
