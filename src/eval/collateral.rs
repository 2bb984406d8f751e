//! Collateral: what guidance did to the vehicles a behaviour does not name. A guided sample
//! that makes its cutter cut in while two cars behind it pile into each other has not shown a
//! cut-in a user can use, so a behaviour passes only when the rest of the scene fares no worse
//! than in the same sample drawn unguided (same scene, same seed), within a tolerance.
//!
//! Both counts are of vehicles the behaviour does not name: how many collide with anything
//! (box overlap at some future step, the pair a behaviour asks to collide excepted) and how
//! many a car could not drive ([`super::kinematic`]). The guided sample may exceed the
//! unguided one by [`Collateral::allowance`] vehicles: the larger of [`TOLERANCE_VEHICLES`]
//! and [`TOLERANCE_FRACTION`] of the vehicles counted, because the model samples every agent
//! jointly, so guiding one car moves the others too, and an unguided sample's own collisions
//! come and go with that.

use serde::Serialize;

use super::kinematic::{self, KinematicLimits, Violation};
use super::metrics::collided_except;
use crate::scene::{AgentType, Scene};

/// Extra vehicles (collided, or implausible) a guided sample may have over its unguided twin.
pub const TOLERANCE_VEHICLES: usize = 2;

/// The same as a fraction of the vehicles counted; the larger of the two applies.
pub const TOLERANCE_FRACTION: f64 = 0.05;

/// What guidance did to the vehicles a behaviour does not name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Collateral {
    /// Vehicles not named, with a future in both samples.
    pub others: usize,
    /// Of them, how many collide in the guided sample.
    pub collided: usize,
    /// ... and in the unguided one.
    pub collided_unguided: usize,
    /// Of them, how many a car could not drive in the guided sample.
    pub implausible: usize,
    /// ... and in the unguided one.
    pub implausible_unguided: usize,
}

/// Why two samples cannot be compared.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CollateralError {
    /// The unguided sample is of another scene.
    #[error("the unguided sample is of scene {unguided:?}, the guided one of {guided:?}")]
    OtherScene {
        /// The guided sample's scene.
        guided: String,
        /// The unguided sample's scene.
        unguided: String,
    },
}

impl Collateral {
    /// How many more vehicles the guided sample may have in each count.
    pub fn allowance(&self) -> usize {
        TOLERANCE_VEHICLES.max((TOLERANCE_FRACTION * self.others as f64).ceil() as usize)
    }

    /// What the guidance did beyond the allowance, in words (empty when nothing).
    pub fn violations(&self) -> Vec<String> {
        let tol = self.allowance();
        let mut out = Vec::new();
        if self.collided > self.collided_unguided + tol {
            out.push(format!(
                "{} other vehicles collide (unguided: {})",
                self.collided, self.collided_unguided
            ));
        }
        if self.implausible > self.implausible_unguided + tol {
            out.push(format!(
                "{} other vehicles drive as no car can (unguided: {})",
                self.implausible, self.implausible_unguided
            ));
        }
        out
    }
}

/// Compares the vehicles of `guided` that are not in `named` (agent ids) with the same
/// vehicles of `unguided`, the pairs in `may_touch` (ids, either order) excepted from
/// collisions and the motion in `allowed` (id, kind: what the request's scripts allow)
/// from implausibility. Agents are matched by id; a vehicle counts when it has a future in
/// both.
pub fn collateral(
    guided: &Scene,
    unguided: &Scene,
    named: &[i64],
    may_touch: &[(i64, i64)],
    allowed: &[(i64, Violation)],
    lim: &KinematicLimits,
) -> Result<Collateral, CollateralError> {
    if guided.meta.scenario_id != unguided.meta.scenario_id {
        return Err(CollateralError::OtherScene {
            guided: guided.meta.scenario_id.clone(),
            unguided: unguided.meta.scenario_id.clone(),
        });
    }
    // Per agent id: (collided, implausible), for the vehicles not named.
    let counts = |s: &Scene| {
        let hit = collided_except(s, may_touch);
        let judged = kinematic::judge(s, lim);
        s.agents
            .iter()
            .enumerate()
            .filter(|(_, a)| a.agent_type == AgentType::Vehicle && !named.contains(&a.id))
            .filter_map(|(i, a)| {
                let kinds: Vec<Violation> = allowed
                    .iter()
                    .filter(|(id, _)| *id == a.id)
                    .map(|(_, k)| *k)
                    .collect();
                let bad = judged[i]
                    .as_ref()
                    .is_some_and(|j| !j.without(&kinds).plausible());
                Some((a.id, (hit[i]?, bad)))
            })
            .collect::<std::collections::BTreeMap<i64, (bool, bool)>>()
    };
    let (g, u) = (counts(guided), counts(unguided));
    let mut c = Collateral {
        others: 0,
        collided: 0,
        collided_unguided: 0,
        implausible: 0,
        implausible_unguided: 0,
    };
    for (id, (gc, gi)) in &g {
        let Some((uc, ui)) = u.get(id) else {
            continue;
        };
        c.others += 1;
        c.collided += *gc as usize;
        c.collided_unguided += *uc as usize;
        c.implausible += *gi as usize;
        c.implausible_unguided += *ui as usize;
    }
    Ok(c)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{load_scene, LoadOptions};
    use std::path::Path;

    fn highway() -> Scene {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        load_scene(&p, 0, &LoadOptions::default()).unwrap()
    }

    /// Moves agent `id`'s future by `f(seconds after the current step)`.
    fn edit(s: &mut Scene, id: i64, f: impl Fn(f64) -> [f64; 2]) {
        let (c, dt) = (s.meta.current_step, s.meta.dt);
        let a = s.agents.iter_mut().find(|a| a.id == id).unwrap();
        for (t, st) in a.states.iter_mut().enumerate().skip(c + 1) {
            let d = f((t - c) as f64 * dt);
            st.x += d[0];
            st.y += d[1];
        }
    }

    #[test]
    fn guidance_that_wrecks_the_rest_of_the_scene_is_named() {
        let lim = KinematicLimits::default();
        let clean = highway();
        // The same scene, unguided and guided alike: nothing to blame.
        let same = collateral(&clean, &clean, &[1], &[], &[], &lim).unwrap();
        assert_eq!(
            same,
            Collateral {
                others: 3,
                collided: 0,
                collided_unguided: 0,
                implausible: 0,
                implausible_unguided: 0
            }
        );
        assert!(same.violations().is_empty());
        // Agent 4 (lane 0, 50 m behind agent 2, 6 m/s slower) sprints into agent 2 and then
        // backs away from it: two other vehicles collide, one of them at a sprint, then in
        // reverse.
        let mut wreck = clean.clone();
        edit(&mut wreck, 4, |t| {
            let u = (t / 3.0).min(1.0);
            [72.0 * u * u - 48.0 * (t - 3.0).max(0.0), 0.0]
        });
        let c = collateral(&wreck, &clean, &[1], &[], &[], &lim).unwrap();
        assert_eq!((c.others, c.collided, c.collided_unguided), (3, 2, 0));
        assert_eq!((c.implausible, c.implausible_unguided), (1, 0));
        // Two vehicles are within the allowance of two...
        assert_eq!(c.allowance(), 2);
        assert!(c.violations().is_empty(), "{:?}", c.violations());
        // ... four are not: agent 3 (lane 2, 30 m behind agent 1) also moves over onto agent 1.
        edit(&mut wreck, 3, |t| {
            let u = (t / 2.0).min(1.0);
            [18.0 * u, -3.6 * u]
        });
        let c = collateral(&wreck, &clean, &[], &[], &[], &lim).unwrap();
        assert_eq!((c.others, c.collided), (4, 4), "{c:?}");
        let v = c.violations();
        assert!(
            v.iter()
                .any(|m| m.contains("other vehicles collide (unguided: 0)")),
            "{v:?}"
        );
        // Naming the wreckers, or allowing their collisions, takes them out of the count.
        let named = collateral(&wreck, &clean, &[3, 4], &[], &[], &lim).unwrap();
        assert_eq!(named.others, 2);
        let touch = collateral(&wreck, &clean, &[], &[(4, 2), (1, 3)], &[], &lim).unwrap();
        assert_eq!(touch.collided, 0, "{touch:?}");
        // The other way round (unguided worse than guided) is never blamed on guidance.
        assert!(collateral(&clean, &wreck, &[], &[], &[], &lim)
            .unwrap()
            .violations()
            .is_empty());
        let mut other = clean.clone();
        other.meta.scenario_id = "elsewhere".into();
        assert!(matches!(
            collateral(&clean, &other, &[], &[], &[], &lim),
            Err(CollateralError::OtherScene { .. })
        ));
    }
}
