//! What the model reads after sampling (low-level refinement): per term, its first estimate and
//! final value with the spread over the samples; per sample, the checkers' verdicts, the named
//! agents' motion at 1 Hz in world and Frenet coordinates, gaps between them, and their
//! collisions, road departures and implausible motion. Also the acceptance test an ACCEPT must
//! pass.

use std::fmt::Write as _;

use crate::eval::behaviors::Behavior;
use crate::eval::metrics::{collided, road_departure, RoadDeparture};
use crate::sample::{Attempt, AttemptReport, Carried, SampleOutcome};
use crate::scene::{Scene, Turn};

/// When a sample counts as meeting the request.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Acceptance {
    /// Largest unweighted value of any script term (realism's excluded: plausibility is judged
    /// on the motion itself).
    pub tolerance: f64,
}

impl Default for Acceptance {
    fn default() -> Self {
        Self { tolerance: 0.05 }
    }
}

impl Acceptance {
    /// Why `o`, a sample of `report`, does not meet the request (empty when it does): script
    /// terms above tolerance, failed checkers, implausible motion of the named agents, and
    /// their departures from the road that the request does not ask for (with size and time).
    pub fn reasons(&self, o: &SampleOutcome, report: &AttemptReport) -> Vec<String> {
        let named = &report.named;
        let mut out = Vec::new();
        for t in o.terms.iter().filter(|t| t.script != "realism") {
            let tol = t.tolerance.unwrap_or(self.tolerance);
            if !(t.value <= tol) {
                out.push(format!(
                    "term {} = {:.4} is above {} tolerance {} (line {}){}",
                    t.term,
                    t.value,
                    if t.tolerance.is_some() { "its" } else { "the" },
                    tol,
                    t.line,
                    t.carried_by
                        .as_ref()
                        .map_or(String::new(), |c| format!("; {}", carriers(c)))
                ));
            }
        }
        for (v, c) in o.verdicts.iter().zip(&report.checks) {
            if !v.passed {
                out.push(format!("checker {}: {}", c.behaviour, v.reason));
            }
        }
        for e in o.implausible(named) {
            out.push(format!(
                "implausible motion: {}{} {}",
                e.role.as_deref().map_or(String::new(), |r| format!("{r} ")),
                e.agent,
                e.text
            ));
        }
        for d in unasked_departures(o, report) {
            out.push(format!(
                "named agent {} leaves the road: {d} (the request does not send it there)",
                d.agent
            ));
        }
        out
    }
}

/// Who carries a term over many agents, in words, with what the numbers mean: "carried by
/// 2974 (62 %), 139 (31 %) and 2981 (5 %) of the 14 agents it reads (...)".
pub fn carriers(c: &Carried) -> String {
    let pct = |x: f64| {
        if x < 0.005 {
            "<1 %".to_string()
        } else {
            format!("{:.0} %", 100.0 * x)
        }
    };
    let mut names: Vec<String> = c
        .top
        .iter()
        .map(|a| format!("{} ({})", a.agent, pct(a.share)))
        .collect();
    if c.others > 0 {
        names.push(format!("{} more", c.others));
    }
    let list = match names.len() {
        0 => String::new(),
        1 => names[0].clone(),
        n => format!("{} and {}", names[..n - 1].join(", "), names[n - 1]),
    };
    format!(
        "carried by {list} of the {} agents it reads (each one's share of how fast the term \
         falls when that agent alone moves to lower it)",
        c.reads
    )
}

/// The departures from the road of `report`'s named agents in `o` that the request does not
/// ask for: a named agent that escapes its task by swerving off the road (a car told to keep
/// 10 m from everyone, say) has not met the request, however its terms read. The request
/// sends an agent off the road when an `off_road` checker names it.
fn unasked_departures<'a>(
    o: &'a SampleOutcome,
    report: &'a AttemptReport,
) -> impl Iterator<Item = &'a RoadDeparture> {
    o.off_road.iter().filter(move |d| {
        report.named.contains(&d.agent)
            && !report.checks.iter().any(|c| {
                c.behaviour == Behavior::OffRoad.name()
                    && Behavior::OffRoad
                        .roles()
                        .iter()
                        .any(|r| c.params.number(r) == Some(d.agent as f64))
            })
    })
}

impl Acceptance {
    /// The script terms of `o` above their tolerance when the independent checkers all pass
    /// it and no named agent moves implausibly: the script asks for more than the request, and
    /// those terms (not the behaviour) are what to repair. Empty otherwise, and without
    /// checkers (then the terms are all the request there is).
    pub fn stricter_than_checked(&self, o: &SampleOutcome, report: &AttemptReport) -> Vec<String> {
        let checked = !o.verdicts.is_empty()
            && o.verdicts.iter().all(|v| v.passed)
            && o.implausible(&report.named).next().is_none()
            && unasked_departures(o, report).next().is_none();
        if !checked {
            return Vec::new();
        }
        o.terms
            .iter()
            .filter(|t| {
                t.script != "realism" && !(t.value <= t.tolerance.unwrap_or(self.tolerance))
            })
            .map(|t| t.term.clone())
            .collect()
    }
}

/// The refinement text for an attempt. `max_agents` caps the agents whose motion is listed
/// (the named ones first).
pub fn feedback(a: &Attempt, acc: &Acceptance) -> String {
    let r = &a.report;
    let mut s = String::new();
    let named = &r.named;
    let _ = writeln!(
        s,
        "Agents your script names: {}.",
        if named.is_empty() {
            "none".to_string()
        } else {
            named
                .iter()
                .map(|i| i.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        }
    );
    if !r.checks.is_empty() {
        let _ = writeln!(
            s,
            "Independent checkers of the request: {}.",
            r.checks
                .iter()
                .map(|c| format!("{} ({})", c.behaviour, c.params))
                .collect::<Vec<_>>()
                .join("; ")
        );
    }
    let _ = writeln!(
        s,
        "A sample meets the request when every term is at most its tolerance (unweighted; {} \
         unless the script gives one with term(name, value, weight, tolerance)), every checker \
         passes and no named agent moves implausibly (beyond what a checker asks or your \
         script allows) or leaves the road unasked.",
        acc.tolerance
    );
    s.push_str("\n## Terms (unweighted values; the total is the weighted sum)\n\n");
    s.push_str(&term_table(r, acc));
    let stricter: Vec<(usize, Vec<String>)> = r
        .samples
        .iter()
        .enumerate()
        .map(|(k, o)| (k, acc.stricter_than_checked(o, r)))
        .filter(|(_, t)| !t.is_empty())
        .collect();
    if !stricter.is_empty() {
        let mut terms: Vec<&String> = stricter.iter().flat_map(|(_, t)| t).collect();
        terms.sort();
        terms.dedup();
        let _ =
            writeln!(
            s,
            "\nThe checkers say the request is met in sample{} {}, but your term{} {} exceed{} \
             {} tolerance there: the script asks for more than the request. Relax exactly \
             th{} (a larger tolerance, the fourth argument of term, or a looser margin) rather \
             than pulling harder.",
            if stricter.len() > 1 { "s" } else { "" },
            stricter
                .iter()
                .map(|(k, _)| k.to_string())
                .collect::<Vec<_>>()
                .join(", "),
            if terms.len() > 1 { "s" } else { "" },
            terms.iter().map(|t| t.as_str()).collect::<Vec<_>>().join(", "),
            if terms.len() > 1 { "" } else { "s" },
            if terms.len() > 1 { "their" } else { "its" },
            if terms.len() > 1 { "ose terms" } else { "at term" },
        );
    }
    for (k, o) in r.samples.iter().enumerate() {
        let scene = &a.samples[k].scene;
        let reasons = acc.reasons(o, r);
        let stricter = acc.stricter_than_checked(o, r);
        let _ = writeln!(
            s,
            "\n## Sample {k}: {} (total cost {:.4})",
            if reasons.is_empty() {
                "meets the request".to_string()
            } else if !stricter.is_empty() {
                format!(
                    "the checkers say it meets the request, but your terms {} exceed their \
                     tolerance",
                    stricter.join(", ")
                )
            } else {
                format!("does not meet it ({} reasons)", reasons.len())
            },
            o.total
        );
        for (v, c) in o.verdicts.iter().zip(&r.checks) {
            let _ = writeln!(
                s,
                "- checker {}: {}: {}",
                c.behaviour,
                if v.passed {
                    "PASS"
                } else if v.achieved {
                    "fail (achieved, implausibly)"
                } else {
                    "fail"
                },
                v.reason
            );
        }
        for why in reasons.iter().filter(|w| !w.starts_with("checker")) {
            let _ = writeln!(s, "- {why}");
        }
        motion(&mut s, scene, named);
    }
    s
}

/// What the model is told when its script ran past the run's budget for script evaluation
/// (`--script-budget`, [`crate::sample::SampleError::ScriptBudget`]): a slow script is the
/// model's to fix, like one that fails validation, so it goes back for the next round
/// instead of ending the run. `used` is what the scripts had taken when sampling stopped.
pub fn over_budget(budget: std::time::Duration, used: &crate::cost::Usage) -> String {
    format!(
        "your script took {:.1} s over {} evaluations (mean {:.1} ms each); the budget for \
         script evaluation is {} s per sampling run, so sampling stopped and nothing was \
         sampled. A sampling run evaluates the script hundreds of times (every denoising step \
         and polish iteration, for every sample): simplify it (fewer operations per \
         evaluation, no long loops over steps or agents) and send it again in one ```rhai \
         block.",
        used.time.as_secs_f64(),
        used.evaluations,
        used.mean().as_secs_f64() * 1e3,
        budget.as_secs_f64()
    )
}

/// What the model is told when its script passed validation but failed while being sampled
/// ([`crate::sample::SampleError::Cost`]): sampling evaluates it on trajectories validation
/// never tried (every denoising step's estimate of every sample, then polish), so an index
/// or a value only some of them reach can still fail. The script is the model's, so the
/// error goes back for the next round instead of ending the run.
pub fn failed_in_sampling(error: &crate::cost::CostError) -> String {
    format!(
        "your script passed validation but failed while it was being sampled, so nothing was \
         sampled: {error}. Validation runs it on the recorded future (and probes it on a few \
         perturbed ones); sampling runs it on every denoising step's estimate of every sample, \
         which can be far from the log early on. Make it run on any trajectories of the scene's \
         agents (no index that only some of them reach, no error raised on values the log \
         does not have) and send it again in one ```rhai block."
    )
}

/// Every term's weight, first estimate (mean over the samples) and final value (min, mean,
/// max over the samples), with a note where a term never moves, dominates, or is met
/// everywhere: a markdown table.
pub fn term_table(r: &AttemptReport, acc: &Acceptance) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| term | line | weight | first estimate (mean) | final min | final mean | final max | note |\n\
         |---|---|---|---|---|---|---|---|"
    );
    let first = r.samples.first();
    let n = r.samples.len().max(1) as f64;
    for (i, t) in first
        .map(|o| o.terms.as_slice())
        .unwrap_or(&[])
        .iter()
        .enumerate()
    {
        let finals: Vec<f64> = r
            .samples
            .iter()
            .filter_map(|o| o.terms.get(i).map(|x| x.value))
            .collect();
        let inits: Vec<f64> = r
            .samples
            .iter()
            .filter_map(|o| o.terms.get(i).and_then(|x| x.initial))
            .collect();
        let mean = finals.iter().sum::<f64>() / n;
        let min = finals.iter().copied().fold(f64::INFINITY, f64::min);
        let max = finals.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let init = (!inits.is_empty()).then(|| inits.iter().sum::<f64>() / inits.len() as f64);
        let tol = t.tolerance.unwrap_or(acc.tolerance);
        let mut note = Vec::new();
        if t.script == "realism" {
            note.push("sampler's realism term".to_string());
        } else {
            if let Some(i0) = init {
                if mean > tol && (mean - i0).abs() <= 0.05 * i0.abs().max(1e-3) {
                    note.push("never moves: this term is not pulling".into());
                }
            }
            let total: f64 = r.samples.iter().map(|o| o.total).sum::<f64>() / n;
            let share = t.weight * mean / total.max(1e-12);
            if share > 0.8 && first.is_some_and(|o| o.terms.len() > 1) && mean > tol {
                note.push(format!("dominates ({:.0} % of the total)", 100.0 * share));
            }
            if max <= tol {
                note.push("met in every sample".into());
            }
        }
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {:.4} | {:.4} | {:.4} | {} |",
            t.term,
            if t.line > 0 {
                t.line.to_string()
            } else {
                "-".into()
            },
            t.weight,
            init.map_or("-".into(), |v| format!("{v:.4}")),
            min,
            mean,
            max,
            note.join("; ")
        );
    }
    s
}

/// The named agents at 1 Hz: world position, speed, acceleration, lane, Frenet s and d on
/// the agent's starting lane path, gaps to the other named agents; then their events.
fn motion(s: &mut String, scene: &Scene, named: &[i64]) {
    let c = scene.meta.current_step;
    let dt = scene.meta.dt;
    let every = ((1.0 / dt).round() as usize).max(1);
    let hits = collided(scene);
    for id in named {
        let Some(idx) = scene.agents.iter().position(|a| a.id == *id) else {
            continue;
        };
        let a = &scene.agents[idx];
        let st0 = a.states[c];
        let lane0 = st0
            .valid
            .then(|| scene.map.lane_at(st0.position(), st0.heading))
            .flatten();
        let path = lane0.and_then(|l| {
            let s0 = scene.map.lane(l)?.centerline.nearest(&st0.position()).s;
            scene
                .map
                .lane_path(l, s0 + 300.0, 50.0, Turn::Straight)
                .ok()
        });
        let _ = writeln!(
            s,
            "\nAgent {id}{}{}: t (s), x, y (m), speed (m/s), accel (m/s²), lane, s, d (m) on the path of lane {}{}",
            left_map(scene, a).map_or(String::new(), |t| format!(
                " (leaves the map after {t:.1} s: its .last() is then)"
            )),
            match (hits[idx], road_departure(scene, a)) {
                (Some(true), Some(d)) => format!(" (collides; leaves the road: {d})"),
                (Some(true), None) => " (collides)".into(),
                (_, Some(d)) => format!(" (leaves the road: {d})"),
                _ => String::new(),
            },
            lane0.map_or("-".into(), |l| l.to_string()),
            if named.len() > 1 { ", gaps (centre distance, m)" } else { "" }
        );
        let mut t = c;
        while t < scene.num_steps() {
            let st = a.states[t];
            if st.valid {
                let speed = velocity(a, t, dt).map_or(0.0, |(vx, vy)| vx.hypot(vy));
                let accel = accel_at(a, t, dt);
                let lane = scene.map.lane_at(st.position(), st.heading);
                let fr = path.as_ref().map(|p| p.frenet.project(st.position()));
                let mut gaps = Vec::new();
                for other in named.iter().filter(|o| *o != id) {
                    if let Some(b) = scene.agent(*other) {
                        let sb = b.states[t];
                        if sb.valid {
                            gaps.push(format!(
                                "{other}: {:.1}",
                                (sb.position() - st.position()).norm()
                            ));
                        }
                    }
                }
                let _ = writeln!(
                    s,
                    "  {:.0} s: ({:.1}, {:.1}), {:.1}, {}, {}, {}{}",
                    (t - c) as f64 * dt,
                    st.x,
                    st.y,
                    speed,
                    accel.map_or("-".into(), |x| format!("{x:+.1}")),
                    lane.map_or("off lane".into(), |l| l.to_string()),
                    fr.map_or("-, -".into(), |f| format!("{:.1}, {:+.2}", f.s, f.d)),
                    if gaps.is_empty() {
                        String::new()
                    } else {
                        format!("; {}", gaps.join(", "))
                    }
                );
            } else {
                let _ = writeln!(s, "  {:.0} s: not in the scene", (t - c) as f64 * dt);
            }
            t += every;
        }
    }
}

/// When agent `a`, in the scene at the current step, leaves it before the horizon ends: the
/// seconds after the current step of its last valid step. A script's `.last()` then means
/// that step, not the horizon's end, which the model cannot see from the numbers alone.
fn left_map(scene: &Scene, a: &crate::scene::Agent) -> Option<f64> {
    let c = scene.meta.current_step;
    let end = scene.num_steps().checked_sub(1)?;
    if !a.is_valid(c) || a.is_valid(end) {
        return None;
    }
    let last = (c..end).rev().find(|&t| a.is_valid(t))?;
    Some((last - c) as f64 * scene.meta.dt)
}

/// Velocity at step `t` from positions (sampled scenes carry positions; their velocity
/// fields are not the model's): central where both neighbours are valid, else one-sided.
fn velocity(a: &crate::scene::Agent, t: usize, dt: f64) -> Option<(f64, f64)> {
    let at = |k: usize| a.states.get(k).filter(|s| s.valid);
    let here = at(t)?;
    let prev = t.checked_sub(1).and_then(at);
    let next = at(t + 1);
    Some(match (prev, next) {
        (Some(p), Some(q)) => ((q.x - p.x) / (2.0 * dt), (q.y - p.y) / (2.0 * dt)),
        (Some(p), None) => ((here.x - p.x) / dt, (here.y - p.y) / dt),
        (None, Some(q)) => ((q.x - here.x) / dt, (q.y - here.y) / dt),
        (None, None) => return None,
    })
}

/// Acceleration along the direction of travel at step `t`, from positions.
fn accel_at(a: &crate::scene::Agent, t: usize, dt: f64) -> Option<f64> {
    let (vx, vy) = velocity(a, t, dt)?;
    let speed = vx.hypot(vy);
    let (p, q) = (velocity(a, t.checked_sub(1)?, dt)?, velocity(a, t + 1, dt)?);
    let (ux, uy) = if speed > 0.1 {
        (vx / speed, vy / speed)
    } else {
        let h = a.states[t].heading;
        (h.cos(), h.sin())
    };
    Some(((q.0 - p.0) * ux + (q.1 - p.1) * uy) / (2.0 * dt))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cost::Params;
    use crate::io::{load_scene, LoadOptions};
    use crate::sample::attempt::CheckSpec;
    use crate::sample::Settings;

    /// highway.yaml with vehicle 3 (leftmost lane) drifting `by` metres to its left over the
    /// future, from 1 s on.
    fn drifting(by: f64) -> Scene {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let mut s = load_scene(
            &root.join("scripts/scenes/highway.yaml"),
            0,
            &LoadOptions::default(),
        )
        .unwrap();
        let (c, dt) = (s.meta.current_step, s.meta.dt);
        let a = s.agents.iter_mut().find(|a| a.id == 3).unwrap();
        for t in c + 1..a.states.len() {
            let st = &mut a.states[t];
            let k = (((t - c) as f64 * dt - 1.0) / 3.0).clamp(0.0, 1.0);
            st.x -= st.heading.sin() * by * k;
            st.y += st.heading.cos() * by * k;
        }
        s
    }

    #[test]
    fn a_named_car_that_leaves_the_map_mid_horizon_is_said_with_its_last_step() {
        let mut s = drifting(0.0);
        let c = s.meta.current_step;
        assert_eq!(left_map(&s, s.agent(3).unwrap()), None);
        let a = s.agents.iter_mut().find(|a| a.id == 3).unwrap();
        for st in &mut a.states[c + 18..] {
            st.valid = false;
        }
        let t = left_map(&s, s.agent(3).unwrap()).unwrap();
        assert!((t - 1.7).abs() < 1e-9, "{t}");
        let mut text = String::new();
        motion(&mut text, &s, &[3]);
        assert!(
            text.contains("Agent 3 (leaves the map after 1.7 s: its .last() is then)"),
            "{text}"
        );
    }

    fn report(named: Vec<i64>, checks: Vec<CheckSpec>) -> AttemptReport {
        AttemptReport {
            scenario: "highway".into(),
            checks,
            scripts: vec!["script.rhai".into()],
            named,
            settings: Settings {
                task: "conditional",
                guidance: "output",
                lambda: 1.0,
                steps: 1,
                samples: 1,
                seed: 1,
                realism: 1.0,
                replan: None,
            },
            seconds: 0.0,
            samples: Vec::new(),
            not_sampled: Vec::new(),
            warnings: Vec::new(),
            scene_crc32c: "00000000".into(),
        }
    }

    fn outcome(off_road: Vec<RoadDeparture>) -> SampleOutcome {
        SampleOutcome {
            sample: 0,
            total: 0.0,
            terms: Vec::new(),
            verdicts: Vec::new(),
            realism: Vec::new(),
            off_road,
            allowed: Vec::new(),
        }
    }

    #[test]
    fn a_term_over_many_agents_names_the_ones_that_carry_it() {
        use crate::sample::{AgentShare, TermOutcome};
        let term = |carried_by| TermOutcome {
            script: "s.rhai".into(),
            term: "no_collisions".into(),
            line: 7,
            weight: 1.0,
            initial: None,
            value: 4.2,
            tolerance: None,
            carried_by,
        };
        let share = |agent, share| AgentShare { agent, share };
        let carried = Carried {
            reads: 14,
            top: vec![share(2974, 0.62), share(139, 0.31), share(2981, 0.05)],
            others: 2,
        };
        let mut o = outcome(Vec::new());
        o.terms = vec![term(Some(carried))];
        let why = Acceptance::default().reasons(&o, &report(vec![139], Vec::new()));
        assert_eq!(
            why,
            vec![
                "term no_collisions = 4.2000 is above the tolerance 0.05 (line 7); carried by \
                 2974 (62 %), 139 (31 %), 2981 (5 %) and 2 more of the 14 agents it reads (each \
                 one's share of how fast the term falls when that agent alone moves to lower it)"
                    .to_string()
            ]
        );
        o.terms = vec![term(None)];
        let why = Acceptance::default().reasons(&o, &report(vec![139], Vec::new()));
        assert_eq!(
            why,
            vec!["term no_collisions = 4.2000 is above the tolerance 0.05 (line 7)".to_string()]
        );
    }

    #[test]
    fn a_named_agent_off_the_road_is_a_reason_with_size_and_time_unless_requested() {
        let s = drifting(6.0);
        let a = s.agent(3).unwrap();
        let d = road_departure(&s, a).expect("6 m to the left leaves the road");
        assert!(d.corner.ends_with("left"), "{d}");
        assert!(d.distance > 1.0 && d.time > d.first && d.first > 1.0, "{d}");
        let said = d.to_string();
        assert!(
            said.contains(&format!(
                "corner {:.2} m off the road at {:.1} s",
                d.distance, d.time
            )),
            "{said}"
        );
        // On the road throughout: no departure.
        let straight = drifting(0.0);
        assert_eq!(road_departure(&straight, straight.agent(3).unwrap()), None);
        let acc = Acceptance::default();
        let o = outcome(vec![d.clone()]);
        // Named, and nothing asks it off the road: a reason, with the corner, size and time.
        let why = acc.reasons(&o, &report(vec![3], Vec::new()));
        assert_eq!(
            why,
            vec![format!(
                "named agent 3 leaves the road: {said} (the request does not send it there)"
            )]
        );
        // An agent no script names is not the request's concern here.
        assert!(acc.reasons(&o, &report(vec![1], Vec::new())).is_empty());
        // The request sends it there: an off_road checker names it.
        let sent = CheckSpec {
            behaviour: "off_road",
            params: Params::numbers(&[("vehicle", 3.0)]),
        };
        assert!(acc.reasons(&o, &report(vec![3], vec![sent])).is_empty());
        // An off_road checker for another car does not excuse this one.
        let other = CheckSpec {
            behaviour: "off_road",
            params: Params::numbers(&[("vehicle", 1.0)]),
        };
        assert_eq!(acc.reasons(&o, &report(vec![3], vec![other])).len(), 1);
    }
}
