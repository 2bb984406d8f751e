//! Closed-loop simulation: re-plan at 2 Hz. Each round samples a full future, executes its
//! first 0.5 s (appended to the history as if observed), and samples again from there, until
//! the model's horizon is covered. The scripts are compiled once, at the first current step,
//! and every round's guidance judges the executed steps followed by the round's sample: the
//! request's horizon stays where the user put it.

use std::rc::Rc;
use std::sync::atomic::AtomicBool;

use super::config::{SampleConfig, SampleError};
use super::guided::{
    modelled, prepare, prepare_for, sample_after, sampled_horizon, Executed, Sample,
};
use crate::cost::{CostScript, ScriptSpec};
use crate::scene::Scene;
use crate::train::Trained;

/// Simulates `scene` in closed loop, executing `execute` steps per round (5 = 0.5 s at 10 Hz).
/// Returns one sample per `cfg.samples`, each over the model's horizon from the original
/// current step; `initial_reports` are the first round's, `reports` score the executed
/// trajectory over the whole horizon.
pub fn closed_loop(
    trained: &Trained,
    scene: &Scene,
    scripts: &[ScriptSpec],
    cfg: &SampleConfig,
    execute: usize,
) -> Result<Vec<Sample>, SampleError> {
    closed_loop_until(
        trained,
        scene,
        scripts,
        cfg,
        execute,
        &AtomicBool::new(false),
    )
}

/// [`closed_loop`] that another thread may stop by setting `stop`
/// ([`sample_until`](super::guided::sample_until)).
pub fn closed_loop_until(
    trained: &Trained,
    scene: &Scene,
    scripts: &[ScriptSpec],
    cfg: &SampleConfig,
    execute: usize,
    stop: &AtomicBool,
) -> Result<Vec<Sample>, SampleError> {
    cfg.validate().map_err(SampleError::Settings)?;
    let future = sampled_horizon(trained, cfg)?;
    let execute = execute.clamp(1, future);
    let start = prepare_for(scene, future)?;
    let c0 = start.meta.current_step;
    let compiled = scripts
        .iter()
        .map(|s| {
            CostScript::compile(
                &s.source,
                &s.name,
                Rc::new(start.clone()),
                &s.params,
                &s.limits,
            )
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut out = Vec::with_capacity(cfg.samples.max(1));
    for k in 0..cfg.samples.max(1) {
        let mut state = start.clone();
        let mut done = 0;
        let mut first_reports: Option<Vec<crate::cost::CostReport>> = None;
        let mut first_realism = None;
        let mut fixed = Vec::new();
        let mut round = 0u64;
        let mut last: Option<Scene> = None;
        while done < future {
            // Every modelled agent has ended (its recording stopped, in the conditional task)
            // or left the map: the round would have nothing to simulate, and failed the whole
            // run with "no vehicle is observed at the current step". The last round's sample
            // already says what the rest of the horizon holds (the ended agents unobserved, the
            // others on their log or their fixed velocity), so it is kept as it is.
            if let Some(prev) = &last {
                let now = c0 + done;
                let anyone = state
                    .agents
                    .iter()
                    .any(|a| modelled(trained, a) && a.states.get(now).is_some_and(|s| s.valid));
                if !anyone {
                    for (a, b) in state.agents.iter_mut().zip(&prev.agents) {
                        let end = (c0 + future + 1).min(a.states.len()).min(b.states.len());
                        for step in now + 1..end {
                            a.states[step] = b.states[step];
                        }
                    }
                    break;
                }
            }
            // The scene as seen from the round's current step, with the model's full horizon.
            let mut view = state.clone();
            view.meta.current_step = c0 + done;
            let view = prepare(&view, trained)?;
            let round_cfg = SampleConfig {
                samples: 1,
                seed: cfg.seed.wrapping_add(1000 * k as u64 + round),
                ..*cfg
            };
            // The scripts judge the original horizon, the executed steps followed by the
            // round's sample: a request for the end of the horizon keeps its deadline.
            let executed = crate::cost::Trajectories::recorded(&state);
            let executed = Executed {
                trajectories: &executed,
                steps: done,
            };
            let s = sample_after(trained, &view, &compiled, Some(executed), &round_cfg, stop)?
                .remove(0);
            let take = execute.min(future - done);
            for (a, b) in state.agents.iter_mut().zip(&s.scene.agents) {
                for t in 0..take {
                    let step = c0 + done + 1 + t;
                    if step < a.states.len() {
                        a.states[step] = b.states[step];
                    }
                }
            }
            done += take;
            round += 1;
            if first_reports.is_none() {
                first_reports = Some(s.initial_reports.clone());
                first_realism = s.realism.as_ref().map(|r| r.0.clone());
                fixed = s.fixed.clone();
            }
            last = Some(s.scene);
        }
        // Score the executed trajectory over the whole horizon, as seen from the start.
        let traj = crate::cost::Trajectories::recorded(&state);
        let reports = compiled
            .iter()
            .map(|s| s.evaluate(&traj))
            .collect::<Result<Vec<_>, _>>()?;
        // Realism on the executed trajectory, for the agents the model moved.
        let realism = first_realism.map(|first| {
            let moved: Vec<bool> = start
                .agents
                .iter()
                .map(|a| modelled(trained, a) && a.states[c0].valid)
                .collect();
            let exempt = crate::cost::Allowed::from_reports(&reports, &start);
            (first, cfg.realism.evaluate(&start, &traj, &moved, &exempt))
        });
        out.push(Sample {
            scene: state,
            initial_reports: first_reports.take().unwrap_or_default(),
            reports,
            realism,
            fixed,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cost::Params;
    use crate::sample::guided::tests::{quick, setup};

    #[test]
    fn a_recording_that_ends_before_the_horizon_ends_the_rounds_not_the_run() {
        // A conditional run ends each agent where its recording stops: with 12 recorded steps
        // of a 40-step horizon, the round at the 15th step found no agent to simulate and the
        // whole run failed ("no vehicle is observed at the current step"), as `simulate
        // --closed-loop` did on every NGSIM sample shorter than the horizon.
        let (t, scene) = setup();
        let c = scene.meta.current_step;
        let cut = scene.over_horizon(12);
        let short = Scene::new(cut.meta.clone(), cut.map.clone(), cut.agents).unwrap();
        let cfg = SampleConfig {
            samples: 1,
            task: crate::sample::Task::Conditional,
            ..quick()
        };
        let future = sampled_horizon(&t, &cfg).unwrap();
        assert!(future > 20, "the model's horizon is {future} steps");
        let out = closed_loop(&t, &short, &[], &cfg, 5).unwrap().remove(0);
        for (a, log) in out.scene.agents.iter().zip(&short.agents) {
            if !modelled(&t, log) {
                continue;
            }
            // Observed while the log lasts, unobserved after it.
            let end = (c + 1..log.states.len())
                .rev()
                .find(|&k| log.states[k].valid)
                .unwrap_or(c);
            assert!(a.states[end].valid, "agent {} at its last step {end}", a.id);
            assert!(
                a.states[end + 1..].iter().all(|s| !s.valid),
                "agent {} after step {end}",
                a.id
            );
        }
    }

    #[test]
    fn every_round_guides_towards_the_deadline_the_user_gave() {
        let (t, scene) = setup();
        let c = scene.meta.current_step;
        let a = &scene.agents[0];
        // Agent 1, 15 m past its recorded position 2 s on: the rounds after the first must
        // still aim at that step, not at 2 s after their own start.
        let target = a.states[c + 20].x + 15.0;
        let spec = ScriptSpec::new(
            "term(\"at\", square(agent(param(\"id\")).x.at(19) - param(\"x\")));",
            "deadline",
            Params::numbers(&[("id", a.id as f64), ("x", target)]),
        );
        let cfg = SampleConfig {
            samples: 1,
            polish: 100,
            ..quick()
        };
        let run = |scripts: &[ScriptSpec]| closed_loop(&t, &scene, scripts, &cfg, 5).unwrap();
        let guided = run(std::slice::from_ref(&spec)).remove(0);
        let miss = guided.reports[0].term("at").unwrap().value.sqrt();
        let unguided = run(&[]).remove(0).scene.agents[0].states[c + 20].x;
        assert!(
            miss < 1.0 && (unguided - target).abs() > 5.0,
            "guided ends {miss:.2} m from the target, unguided {:.2} m",
            (unguided - target).abs()
        );
        // The executed trajectory is what the reports judge.
        let x = guided.scene.agents[0].states[c + 20].x;
        assert!((x - target).abs() - miss < 1e-9, "{x} vs {target}");
    }
}
