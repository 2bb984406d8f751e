//! What a request asks of its agents that the plausibility checks would otherwise hold against
//! them: the motion a checked behaviour asks of the agents it names (`reverse`'s backing up,
//! [`Behavior::allowed_motion`]), and the motion the request's cost scripts allow
//! (`allow(a, "reverse")`), which is what the model (or the user) read the request to ask.
//!
//! `ask` and `simulate` judge their samples here as they sample them, and `eval` judges the
//! rollouts they wrote here too, with the allowances each rollout carries
//! ([`crate::io::rollout::Rollout::allowed`]): one judgement, so that `eval` and `ask` give
//! the same verdict on the same trajectories.

use super::behaviors::{check_against_unguided, check_allowing, Behavior, CheckError, Verdict};
use super::kinematic::{self, Judgement, KinematicLimits, Violation};
use crate::cost::Params;
use crate::io::rollout::{Allowance, AllowedMotion};
use crate::scene::Scene;

/// The allowances as (agent id, violation) pairs, the form the checkers take.
pub fn kinds(allowed: &[Allowance]) -> Vec<(i64, Violation)> {
    let mut out = Vec::new();
    for a in allowed {
        let kind = match a.motion {
            AllowedMotion::Reverse => Violation::Reverse,
        };
        if !out.contains(&(a.agent, kind)) {
            out.push((a.agent, kind));
        }
    }
    out
}

/// Whether the request asks motion of this kind of agent `id`: one of `checks` names it in a
/// role and asks it ([`Behavior::allowed_motion`]), or a script allows it (`allowed`, from
/// [`kinds`]). What a script allows is what the model read the request to ask (the prompt
/// tells it so, and the sampler honours it), so the verdict must not hold it against the
/// agent: `ask` once refused an ACCEPT for "2976 reverses" that the script had allowed with
/// `allow(a, "reverse")`.
pub fn requested(
    checks: &[(Behavior, Params)],
    allowed: &[(i64, Violation)],
    id: i64,
    kind: Violation,
) -> bool {
    allowed.contains(&(id, kind))
        || checks.iter().any(|(b, p)| {
            b.allowed_motion().contains(&kind)
                && b.roles().iter().any(|r| p.number(r) == Some(id as f64))
        })
}

/// Each checker's verdict on `scene`, against its unguided `twin` where there is one, with
/// the motion the scripts allow (`allowed`, from [`kinds`]) counted as asked: an `off_road`
/// checker for a car its script lets reverse does not fail it for reversing.
pub fn verdicts(
    checks: &[(Behavior, Params)],
    scene: &Scene,
    twin: Option<&Scene>,
    allowed: &[(i64, Violation)],
) -> Result<Vec<Verdict>, CheckError> {
    checks
        .iter()
        .map(|(b, p)| match twin {
            Some(u) => check_against_unguided(*b, scene, u, p, allowed),
            None => check_allowing(*b, scene, p, allowed),
        })
        .collect()
}

/// Every agent's kinematic judgement in `scene` ([`kinematic::judge`]), less the motion the
/// request asks of it ([`requested`]): what counts as implausible.
pub fn judged(
    scene: &Scene,
    checks: &[(Behavior, Params)],
    allowed: &[(i64, Violation)],
    lim: &KinematicLimits,
) -> Vec<Option<Judgement>> {
    let mut judged = kinematic::judge(scene, lim);
    for (j, a) in judged.iter_mut().zip(&scene.agents) {
        if let Some(j) = j.as_mut() {
            let asked: Vec<Violation> = Violation::ALL
                .into_iter()
                .filter(|k| requested(checks, allowed, a.id, *k))
                .collect();
            if !asked.is_empty() {
                *j = j.without(&asked);
            }
        }
    }
    judged
}
