//! Which agents carry a term: for a term over many agents (`no_collision_cost(vehicles(), 2)`,
//! "every vehicle keeps 10 m from 139"), the value alone does not say whose motion makes it,
//! and a repair needs to know.
//!
//! The attribution is read off the term's gradient, which every evaluation computes anyway:
//! agent `a`'s share is `|g_a|² / Σ_b |g_b|²`, `g_a` the gradient over `a`'s coordinates.
//! It is the share of the term's first-order fall that moving `a` alone down the gradient
//! would bring (a step `−η·g_a` lowers the term by `η·|g_a|²`): which agents guidance pulls
//! on to lower it, and so which ones carry it. It is not a split of the value (a pair term
//! pulls on both of its agents alike), and it is 0 for every agent of a term that is flat
//! where it stands, met or saturated. Held agents (`hold(a)`) get no gradient and so no share.

use super::report::TermReport;
use super::trajectory::VarLayout;

/// How one term's gradient is spread over the agents.
#[derive(Debug, Clone, PartialEq)]
pub struct Attribution {
    /// Agents (scene indices) the term depends on, where its gradient is 0 too: how many
    /// agents it reads.
    pub reads: Vec<usize>,
    /// Agents (scene indices) with a nonzero share, and the share (0 to 1, summing to 1),
    /// largest first (ties by index).
    pub shares: Vec<(usize, f64)>,
}

/// The attribution of `term`, evaluated on trajectories laid out as `layout`.
pub fn attribute(term: &TermReport, layout: &VarLayout) -> Attribution {
    let per = (layout.steps * 3).max(1);
    let mut squared: Vec<(usize, f64)> = Vec::new();
    // The gradient is sorted by variable, and an agent's variables are contiguous.
    for &(v, g) in &term.grad {
        let a = v as usize / per;
        match squared.last_mut() {
            Some((last, s)) if *last == a => *s += g * g,
            _ => squared.push((a, g * g)),
        }
    }
    let reads = squared.iter().map(|(a, _)| *a).collect();
    let total: f64 = squared.iter().map(|(_, s)| s).sum();
    let mut shares: Vec<(usize, f64)> = if total > 0.0 && total.is_finite() {
        squared
            .into_iter()
            .filter(|(_, s)| *s > 0.0)
            .map(|(a, s)| (a, s / total))
            .collect()
    } else {
        Vec::new()
    };
    shares.sort_by(|x, y| y.1.total_cmp(&x.1).then(x.0.cmp(&y.0)));
    Attribution { reads, shares }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cost::{CostScript, Limits, Params, Trajectories};
    use crate::io::{load_scene, LoadOptions};
    use std::path::Path;
    use std::rc::Rc;

    #[test]
    fn a_collision_term_over_every_vehicle_is_carried_by_the_pair_that_overlaps() {
        // Highway: vehicle 2 (rightmost lane) moved 3.6 m left onto vehicle 1's lane, right
        // behind it, so that only that pair comes within the margin.
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        let mut scene = load_scene(&p, 0, &LoadOptions::default()).unwrap();
        let c = scene.meta.current_step;
        let one = scene.agents.iter().find(|a| a.id == 1).unwrap().clone();
        let two = scene.agents.iter_mut().find(|a| a.id == 2).unwrap();
        for t in c + 1..two.states.len() {
            two.states[t].x = one.states[t].x - 5.0;
            two.states[t].y = one.states[t].y;
            two.states[t].heading = one.states[t].heading;
        }
        let src = "term(\"apart\", no_collision_cost(vehicles(), 1.0));\n\
                   term(\"slow\", relu(agent(3).speed - 100.0).mean());\n";
        let script = CostScript::compile(
            src,
            "t.rhai",
            Rc::new(scene.clone()),
            &Params::default(),
            &Limits::default(),
        )
        .unwrap();
        let r = script.evaluate(&Trajectories::recorded(&scene)).unwrap();
        let idx = |id: i64| scene.agents.iter().position(|a| a.id == id).unwrap();
        let apart = attribute(r.term("apart").unwrap(), &r.layout);
        // It reads every vehicle, and the two that overlap carry it, half each: a pair term
        // pulls on both of its agents alike.
        assert_eq!(apart.reads.len(), scene.agents.len());
        assert_eq!(apart.shares.len(), 2, "{apart:?}");
        let mut carriers: Vec<usize> = apart.shares.iter().map(|s| s.0).collect();
        carriers.sort();
        let mut want = vec![idx(1), idx(2)];
        want.sort();
        assert_eq!(carriers, want);
        for (_, share) in &apart.shares {
            assert!((share - 0.5).abs() < 0.05, "{apart:?}");
        }
        // A term that is flat where it stands has no carrier, though it reads its agent.
        let slow = attribute(r.term("slow").unwrap(), &r.layout);
        assert_eq!((slow.reads, slow.shares), (vec![idx(3)], Vec::new()));
    }
}
