//! Requests no car can meet in the horizon, found before anything is sampled.
//!
//! A checker judges fixed time windows: `speed_limit` the speed from `from` seconds on,
//! `stop` the speed from `within` seconds on, `reverse` and `target_point` the state at the end
//! of the horizon. From the named agent's state at the current step, the kinematic checker's
//! bounds for its type (a car brakes and accelerates at most 7 m/s², drives at most 40 m/s)
//! say when a window cannot be met at all: a car at 22 m/s asked to stay below 50 km/h from
//! t = 0 would have to brake at 150 m/s² over the first step. Guidance cannot change that, so
//! `ask` says so before spending a round on it ([`infeasible`]). Only what the bounds prove is
//! reported: a request that may be met, or that this cannot judge, passes.

use serde::Serialize;

use super::behaviors::Behavior;
use super::kinematic::KinematicLimits;
use crate::cost::Params;
use crate::scene::{Agent, Scene};

/// The checker's slack on a speed bound, m/s (`speed_limit` allows `limit` + 0.5, `stop` 0.5).
const SPEED_SLACK: f64 = 0.5;

/// How far behind its start `reverse` wants the car, metres.
const REVERSE_BEHIND: f64 = 1.0;

/// One event of a request that no plausible motion can meet within the horizon.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Infeasible {
    /// The behaviour.
    pub behaviour: Behavior,
    /// Its parameters, as the checker reads them.
    pub params: Params,
    /// Why, with the numbers, and what would be feasible where there is such a thing.
    pub reason: String,
}

impl std::fmt::Display for Infeasible {
    /// `speed_limit (vehicle=3 limit=13.9): vehicle 3 moves at ...`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({}): {}",
            self.behaviour.name(),
            self.params,
            self.reason
        )
    }
}

/// Why `behaviour` with `params` cannot be met on `scene` (as read: its current step is where
/// sampling starts) within `horizon` future steps by any motion within the kinematic
/// checker's bounds; `None` when it may be, or when the bounds cannot tell. Also named: an
/// agent the scene lacks, or does not observe at the current step (its checker would fail
/// every sample).
pub fn infeasible(
    behaviour: Behavior,
    scene: &Scene,
    params: &Params,
    horizon: usize,
) -> Option<Infeasible> {
    let c = scene.meta.current_step;
    let say = |reason: String| {
        Some(Infeasible {
            behaviour,
            params: params.clone(),
            reason,
        })
    };
    for role in behaviour.roles() {
        let Some(id) = params.number(role) else {
            continue;
        };
        match scene.agent(id as i64) {
            None => return say(format!("the scene has no agent {id} (the {role})")),
            Some(a) if !a.is_valid(c) => {
                return say(format!(
                    "agent {id} (the {role}) is not observed at the current step, where \
                     sampling starts"
                ))
            }
            Some(_) => {}
        }
    }
    let dt = scene.meta.dt;
    let seconds = horizon as f64 * dt;
    let vehicle = || scene.agent(params.number("vehicle")? as i64);
    let limits = |a: &Agent| KinematicLimits::default().for_type(a.agent_type);
    match behaviour {
        Behavior::SpeedLimit => {
            let a = vehicle()?;
            let lim = limits(a)?;
            let limit = params.number("limit")?;
            let from = params.number("from").unwrap_or(0.0);
            // The checker's first speed is over the step after `from` (rounded to a step).
            let k = (from / dt).round().max(0.0);
            if k as usize >= horizon {
                return None;
            }
            let bound = limit + SPEED_SLACK;
            braking(a, c, lim, bound, (k + 0.5) * dt)
                .map(|need| {
                    let earliest =
                        ((a.states[c].speed() - bound) / lim.max_accel - 0.5 * dt).max(0.0);
                    format!(
                    "vehicle {} moves at {:.1} m/s ({:.0} km/h) at the current step; the checker \
                     wants at most {bound:.1} m/s (the limit, {limit:.1} m/s or {:.0} km/h, + \
                     {SPEED_SLACK}) from t = {:.1} s on, which needs braking at {need:.1} m/s², \
                     and a {} brakes at most {} m/s² (the kinematic checker's bound): no \
                     plausible motion meets it. Braking at that bound, it could be under the \
                     limit from about {:.1} s on",
                    a.id,
                    a.states[c].speed(),
                    3.6 * a.states[c].speed(),
                    3.6 * limit,
                    k * dt,
                    a.agent_type.name(),
                    lim.max_accel,
                    (earliest * 10.0).ceil() / 10.0
                )
                })
                .and_then(say)
        }
        Behavior::Stop => {
            let a = vehicle()?;
            let lim = limits(a)?;
            let within = params.number("within").unwrap_or(4.0);
            let k = (within / dt).round().max(0.0);
            if k > horizon as f64 {
                return say(format!(
                    "the checker wants it standing from {within} s on, and the horizon ends at \
                     {seconds:.1} s: no step is checked, so every sample fails"
                ));
            }
            // Speeds are over steps: the first checked one ends at `within` (at least one step).
            let k = k.max(1.0);
            braking(a, c, lim, SPEED_SLACK, (k - 0.5) * dt)
                .map(|need| {
                    let earliest = (a.states[c].speed() - SPEED_SLACK) / lim.max_accel + 0.5 * dt;
                    format!(
                        "vehicle {} moves at {:.1} m/s at the current step; to be at most \
                     {SPEED_SLACK} m/s from {within} s on it would brake at {need:.1} m/s², and \
                     a {} brakes at most {} m/s² (the kinematic checker's bound): no plausible \
                     motion meets it. Braking at that bound, it could stand from about {:.1} s \
                     on",
                        a.id,
                        a.states[c].speed(),
                        a.agent_type.name(),
                        lim.max_accel,
                        (earliest * 10.0).ceil() / 10.0
                    )
                })
                .and_then(say)
        }
        Behavior::Reverse => {
            let a = vehicle()?;
            let lim = limits(a)?;
            let s = a.states[c];
            let forward = s.vx * s.heading.cos() + s.vy * s.heading.sin();
            if forward <= 0.0 {
                return None;
            }
            // Braking to a stop, then backing up past the start, both at the bound: the least
            // time any plausible motion takes.
            let stop = forward / lim.max_accel;
            let ahead = forward * forward / (2.0 * lim.max_accel);
            let back = (2.0 * (ahead + REVERSE_BEHIND) / lim.max_accel).sqrt();
            (stop + back > seconds)
                .then(|| {
                    format!(
                    "vehicle {} moves forward at {forward:.1} m/s: braking to a stop at {} m/s² \
                     ({stop:.1} s, {ahead:.1} m) and backing up to {REVERSE_BEHIND} m behind its \
                     start takes at least {:.1} s, and the horizon is {seconds:.1} s",
                    a.id,
                    lim.max_accel,
                    stop + back
                )
                })
                .and_then(say)
        }
        Behavior::TargetPoint => {
            let a = vehicle()?;
            let lim = limits(a)?;
            let (x, y) = (params.number("x")?, params.number("y")?);
            let tol = params.number("tol").unwrap_or(1.0);
            let s = a.states[c];
            let far = (x - s.x).hypot(y - s.y) - tol;
            let v0 = s.speed();
            // Accelerating at the bound up to the top speed, then holding it.
            let ramp = ((lim.max_speed - v0) / lim.max_accel).clamp(0.0, seconds);
            let reach = v0 * ramp
                + 0.5 * lim.max_accel * ramp * ramp
                + (v0 + lim.max_accel * ramp) * (seconds - ramp);
            (far > reach)
                .then(|| {
                    format!(
                    "the target is {:.1} m from vehicle {} (less the tolerance {tol} m), and from \
                     {v0:.1} m/s a {} covers at most {reach:.1} m in the horizon's {seconds:.1} s \
                     (accelerating at {} m/s² up to {} m/s)",
                    far + tol,
                    a.id,
                    a.agent_type.name(),
                    lim.max_accel,
                    lim.max_speed
                )
                })
                .and_then(say)
        }
        _ => None,
    }
}

/// The braking agent `a` would need to bring its speed from the current step's to `bound`
/// (m/s) by `t` seconds (the middle of the first step a checker measures), when that is more
/// than its bound allows; `None` when it can.
fn braking(a: &Agent, c: usize, lim: KinematicLimits, bound: f64, t: f64) -> Option<f64> {
    let v0 = a.states[c].speed();
    if v0 <= bound {
        return None;
    }
    // The speed over a step is at least the braked speed at its middle (a linear ramp).
    let need = if t > 0.0 {
        (v0 - bound) / t
    } else {
        f64::INFINITY
    };
    (need > lim.max_accel).then_some(need)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{load_scene, LoadOptions};

    fn highway() -> Scene {
        let p =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        load_scene(&p, 0, &LoadOptions::default()).unwrap()
    }

    fn check(b: Behavior, kv: &[(&str, f64)]) -> Option<String> {
        infeasible(b, &highway(), &Params::numbers(kv), 40).map(|i| i.to_string())
    }

    #[test]
    fn a_speed_bound_from_t0_below_a_fast_car_is_infeasible_and_a_reachable_one_is_not() {
        // Vehicle 3 drives at 26 m/s; 50 km/h from t = 0 needs (26 - 14.4) / 0.05 = 232 m/s².
        let why =
            check(Behavior::SpeedLimit, &[("vehicle", 3.0), ("limit", 13.9)]).expect("infeasible");
        assert!(
            why.contains("vehicle 3 moves at 26.0 m/s (94 km/h)")
                && why.contains("needs braking at 232.0 m/s²")
                && why.contains("at most 7 m/s²")
                && why.contains("under the limit from about 1.7 s on"),
            "{why}"
        );
        // Given the time braking at 7 m/s² takes, or a limit above its speed, it may be met.
        assert_eq!(
            check(
                Behavior::SpeedLimit,
                &[("vehicle", 3.0), ("limit", 13.9), ("from", 1.7)]
            ),
            None
        );
        assert_eq!(
            check(Behavior::SpeedLimit, &[("vehicle", 3.0), ("limit", 30.0)]),
            None
        );
        // Just beyond the bound from 1.5 s on (it needs 11.6 / 1.55 = 7.5 m/s²).
        assert!(check(
            Behavior::SpeedLimit,
            &[("vehicle", 3.0), ("limit", 13.9), ("from", 1.5)]
        )
        .is_some());
    }

    #[test]
    fn stops_reversals_targets_and_absent_agents_are_judged_from_the_current_state() {
        // 20 m/s to standing by 1 s: 19.5 / 0.95 = 20.5 m/s²; by 3.5 s: 5.7 m/s², feasible.
        let why = check(Behavior::Stop, &[("vehicle", 1.0), ("within", 1.0)]).unwrap();
        assert!(why.contains("brake at 20.5 m/s²"), "{why}");
        assert_eq!(
            check(Behavior::Stop, &[("vehicle", 1.0), ("within", 3.5)]),
            None
        );
        let why = check(Behavior::Stop, &[("vehicle", 1.0), ("within", 5.0)]).unwrap();
        assert!(why.contains("horizon ends at 4.0 s"), "{why}");
        // 20 m/s forward: 2.9 s to stop in 28.6 m and 2.9 s to back up 29.6 m: beyond 4 s.
        let why = check(Behavior::Reverse, &[("vehicle", 1.0)]).unwrap();
        assert!(why.contains("at least 5.8 s"), "{why}");
        // 500 m ahead is beyond what 4 s at up to 40 m/s covers; 60 m is not.
        let s = highway();
        let p = s.agent(1).unwrap().states[s.meta.current_step];
        let (h, far, near) = (p.heading, 500.0, 60.0);
        let at = |d: f64| {
            [
                ("vehicle", 1.0),
                ("x", p.x + d * h.cos()),
                ("y", p.y + d * h.sin()),
            ]
        };
        let why = check(Behavior::TargetPoint, &at(far)).unwrap();
        assert!(
            why.contains("the target is 500.0 m from vehicle 1"),
            "{why}"
        );
        assert_eq!(check(Behavior::TargetPoint, &at(near)), None);
        let why = check(Behavior::CutIn, &[("cutter", 9.0), ("victim", 1.0)]).unwrap();
        assert!(why.contains("no agent 9 (the cutter)"), "{why}");
        // What the bounds cannot judge passes.
        assert_eq!(
            check(Behavior::CutIn, &[("cutter", 2.0), ("victim", 1.0)]),
            None
        );
    }
}
