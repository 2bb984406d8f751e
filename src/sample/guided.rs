//! The guided EDM sampler: Heun steps over the PCA coefficients of every modelled agent, with
//! the denoised estimate pushed against the gradient of the cost (known states plus cost
//! scripts), clamped to (-1, 1) per coordinate as in the paper.
//!
//! Guidance acts on the denoised estimate: `D̃ = D - λ·clamp(g)`, where `g` is the cost's
//! gradient w.r.t. the coefficients, either taken at `D` (output space, cheap) or pulled back
//! through the denoiser to `x` with candle's backward (the paper's rule). The map is encoded
//! once per scene; the K samples of a scene run as one batch.

use std::sync::atomic::AtomicBool;

use candle_core::{Device, Tensor, Var};

use crate::cost::{CostReport, CostScript, Realism, Trajectories};
use crate::scene::{velocities_from_positions, AgentId, AgentState, AgentType, Scene};
use crate::train::{build, Goals, RouteHint, Trained, Window};

use super::config::*;
use super::heun::{heun, polish};
use super::plan::{tile, Aligned, Plan, Slot, Tiling};

/// The scene cut to the model's horizon: `current + 1 + future` steps, unobserved beyond the
/// recording. Cost scripts are compiled against this scene.
pub fn prepare(scene: &Scene, trained: &Trained) -> Result<Scene, SampleError> {
    prepare_for(scene, trained.meta.config.window.future)
}

/// Why `steps` Heun steps cannot sample with `trained`, if they cannot: fewer than its noise
/// schedule denoises with ([`crate::model::Edm::min_steps`]) leave error of metres per step in
/// the trajectories (at 2 steps a median speed of kilometres a second), which a closed loop
/// then starts its next round from.
pub fn too_few_steps(trained: &Trained, steps: usize) -> Option<String> {
    let min = trained.meta.config.edm.min_steps();
    (steps < min).then(|| {
        format!(
            "fewer than {min} Heun steps leave noise in the samples with this checkpoint's \
             noise schedule (its last step would start at σ = {:.3}, far above σ_min = {}), so \
             they are not the model's trajectories; use {min} or more (default 32)",
            trained.meta.config.edm.schedule(steps.max(2))[steps.max(2) - 2],
            trained.meta.config.edm.sigma_min
        )
    })
}

/// The future steps `cfg` samples with `trained`: its `horizon`, or the model's whole one;
/// an error names both when more is asked than the model generates.
pub fn sampled_horizon(trained: &Trained, cfg: &SampleConfig) -> Result<usize, SampleError> {
    let model = trained.meta.config.window.future;
    match cfg.horizon {
        None => Ok(model),
        Some(h) if h <= model => Ok(h),
        Some(h) => Err(SampleError::Settings(format!(
            "horizon = {h} steps: the model samples at most {model}"
        ))),
    }
}

/// [`prepare`] for a horizon of `future` steps (at most the model's: see
/// [`sampled_horizon`]).
pub fn prepare_for(scene: &Scene, future: usize) -> Result<Scene, SampleError> {
    if let Some(m) = crate::train::dataset::step_mismatch(scene) {
        return Err(SampleError::Scene(m));
    }
    let s = scene.over_horizon(future);
    Scene::new(s.meta.clone(), s.map.clone(), s.agents)
        .map_err(|e| SampleError::Scene(e.to_string()))
}

/// Whether the model moves `agent`: a road user that is not a static obstacle, of a type
/// the checkpoint learnt from ([`crate::train::CheckpointMeta::models`]; the NGSIM checkpoint
/// saw vehicles only). Others follow their log in the conditional task and keep their
/// current velocity otherwise ([`Sample::fixed`]); static obstacles stay where they are.
pub fn modelled(trained: &Trained, agent: &crate::scene::Agent) -> bool {
    trained.meta.models(agent)
}

/// How many steps `scene` records after its current step (up to the last step at which any
/// agent is observed).
pub fn recorded_future(scene: &Scene) -> usize {
    let c = scene.meta.current_step;
    (c + 1..scene.num_steps())
        .rev()
        .find(|&t| scene.agents.iter().any(|a| a.states[t].valid))
        .map_or(0, |t| t - c)
}

/// What a run samples against what `scene` records after its current step, when they differ:
/// the sampled horizon (`model` steps, [`sampled_horizon`]) is fixed, so a longer recording is simulated only
/// in part and a shorter one leaves steps with nothing to compare with. `None` when they match.
pub fn horizon_note(scene: &Scene, model: usize) -> Option<String> {
    let recorded = recorded_future(scene);
    let secs = |n: usize| n as f64 * scene.meta.dt;
    let what = if recorded > model {
        "the rest is not simulated"
    } else if recorded < model {
        "the steps past the recording have no log to compare with"
    } else {
        return None;
    };
    Some(format!(
        "the run samples {:.1} s ({model} steps) after the current step; {} records {:.1} s \
         ({recorded} steps): {what}",
        secs(model),
        scene.meta.scenario_id,
        secs(recorded)
    ))
}

/// One sample's outcome.
#[derive(Debug, Clone)]
pub struct Sample {
    /// The simulated scene (history kept, future generated).
    pub scene: Scene,
    /// The cost scripts' report on the first denoised estimate (before any guidance), per
    /// script.
    pub initial_reports: Vec<CostReport>,
    /// The cost scripts' report on the final trajectories, per script.
    pub reports: Vec<CostReport>,
    /// Realism's report on the first denoised estimate and on the final trajectories, when
    /// realism guided ([`SampleConfig::realism`]).
    pub realism: Option<(CostReport, CostReport)>,
    /// Agents observed at the current step that the model does not move
    /// ([`modelled`]): they followed their log (conditional task) or kept their current
    /// velocity (unconditional).
    pub fixed: Vec<(AgentId, AgentType)>,
}

/// What a run fixes once per scene: the windows, their batch, the inference model and the
/// scene encoding, the noise schedule and the initial noise.
struct Setup<'a> {
    plan: Plan<'a>,
    batch: crate::train::Batch,
    model: crate::model::Denoiser,
    map: crate::model::SceneEncoding,
    sigmas: Vec<f64>,
    x0: Tensor,
    /// Batch rows (samples × windows).
    rows: usize,
}

/// The most numbers one layer of the denoiser holds for a whole sampling batch: samples ×
/// windows rows, [`crate::train::trainer::window_values`] each. About 6 bytes for each such
/// number guided at the output, 12 through the denoiser (1.5 and 3 MB a row measured for the
/// NGSIM checkpoint's 262,144), so 6 to 12 GB here: 1,024 samples of a scene of 4 windows.
/// 1,024 samples of a scene of 300 vehicles (25 windows) asked 38 GB and aborted on
/// allocation, exit 134, or took the machine's memory.
pub const MAX_SAMPLE_BATCH_VALUES: usize = 1 << 30;

/// Refuses `samples` samples of a scene cut into `windows` windows where the batch would not
/// fit in memory ([`MAX_SAMPLE_BATCH_VALUES`]), saying how many do.
fn check_batch_memory(
    trained: &Trained,
    samples: usize,
    windows: usize,
) -> Result<(), SampleError> {
    let c = &trained.meta.config;
    let per = crate::train::trainer::window_values(&c.window, &c.model).max(1);
    let rows = samples.saturating_mul(windows);
    let values = rows.saturating_mul(per);
    if values <= MAX_SAMPLE_BATCH_VALUES {
        return Ok(());
    }
    let fit = MAX_SAMPLE_BATCH_VALUES / per.saturating_mul(windows.max(1));
    let advice = if fit == 0 {
        "not one sample of this scene fits: simulate fewer of its agents".to_string()
    } else {
        format!("at most {fit} samples of this scene fit")
    };
    Err(SampleError::Settings(format!(
        "samples = {samples}: the scene takes {windows} windows of {} agents, so {samples} \
         samples are {rows} windows in one batch, {values} numbers a layer of the denoiser ({per} \
         each), past the {MAX_SAMPLE_BATCH_VALUES} one sampling run holds (6 to 12 GB); {advice}",
        c.window.max_agents,
    )))
}

/// Refuses `samples` samples of `scene` (as read, before [`prepare`]) where their batch would
/// not fit in memory, as sampling itself would refuse them, without sampling: `ask` checks it
/// with its flags, before the run directory is made or a model is asked (1,024 samples of a
/// large scene were refused only when round 0 began sampling). A scene the sampler cannot cut
/// into windows passes here: sampling says why.
pub fn check_samples_fit(
    trained: &Trained,
    scene: &Scene,
    samples: usize,
) -> Result<(), SampleError> {
    let s = prepare(scene, trained)?;
    let c = s.meta.current_step;
    let Some(centre) = centre_agent(trained, &s) else {
        return Ok(());
    };
    // The route hint shapes each window's routes, not which agents it holds.
    let tiling = tile(
        &s,
        &trained.meta.config.window,
        c,
        centre,
        &trained.meta,
        RouteHint::Unknown,
    );
    check_batch_memory(trained, samples.max(1), tiling.windows.len())
}

/// The agent the sampler's first window is centred on: the ego where it is observed at the
/// current step and modelled, else the first such agent.
fn centre_agent(trained: &Trained, scene: &Scene) -> Option<usize> {
    let c = scene.meta.current_step;
    scene
        .meta
        .ego
        .and_then(|e| scene.agents.iter().position(|a| a.id == e))
        .filter(|&i| scene.agents[i].is_valid(c) && modelled(trained, &scene.agents[i]))
        .or_else(|| {
            scene
                .agents
                .iter()
                .position(|a| a.is_valid(c) && modelled(trained, a))
        })
}

/// `route_cost`, where guidance asks for something: what an unconditional run's routes are
/// chosen by, for the agents whose routes it tells apart ([`Plan::cheapest_routes`], for a
/// checkpoint that tells futures against routes); each sample draws the others' routes
/// ([`Plan::draw_routes`]) as its unguided twin does.
fn setup<'a>(
    trained: &'a Trained,
    scene: &Scene,
    cfg: &SampleConfig,
    route_cost: Option<&dyn Fn(&Trajectories) -> Result<f64, SampleError>>,
) -> Result<Setup<'a>, SampleError> {
    cfg.validate().map_err(SampleError::Settings)?;
    if let Some(why) = too_few_steps(trained, cfg.steps) {
        return Err(SampleError::Settings(format!(
            "steps = {}: {why}",
            cfg.steps
        )));
    }
    let dev = Device::Cpu;
    let wcfg = trained.meta.config.window;
    let c = scene.meta.current_step;
    let centre = centre_agent(trained, scene).ok_or_else(|| {
        SampleError::Scene(
            "no vehicle is observed at the current step: the model has nothing to simulate".into(),
        )
    })?;
    // Conditional simulation is given where each agent ends, and takes the route that leads
    // there; unconditional knows nothing of the future.
    let hint = match cfg.task {
        Task::Conditional => RouteHint::EndPoint,
        Task::Unconditional => RouteHint::Unknown,
    };
    let Tiling {
        windows,
        slots,
        copies,
        routes,
    } = tile(scene, &wcfg, c, centre, &trained.meta, hint);
    let mut base = Trajectories::filled(scene);
    let mut modelled = vec![false; scene.agents.len()];
    for sl in &slots {
        modelled[sl.agent] = true;
    }
    let n = base.layout.steps;
    let mut fixed = Vec::new();
    for (ai, m) in modelled.iter().enumerate() {
        let agent = &scene.agents[ai];
        if *m {
            continue;
        }
        if !agent.is_valid(c) {
            base.valid[ai * n..(ai + 1) * n].fill(false);
            continue;
        }
        // A static obstacle holds its pose. A type the model never saw: its log where
        // recorded (conditional), or its current velocity (unconditional: the future is not
        // known).
        if !agent.is_static {
            fixed.push((agent.id, agent.agent_type));
        }
        let s = agent.states[c];
        for k in 0..n {
            let i = ai * n + k;
            if agent.is_static {
                base.xyh[i] = [s.x, s.y, s.heading];
                base.valid[i] = true;
            } else if cfg.task == Task::Conditional {
                let r = agent.states[c + 1 + k];
                base.xyh[i] = [r.x, r.y, r.heading];
                base.valid[i] = r.valid;
            } else {
                let tau = (k + 1) as f64 * scene.meta.dt;
                base.xyh[i] = [s.x + s.vx * tau, s.y + s.vy * tau, s.heading];
                base.valid[i] = true;
            }
        }
    }
    let mut plan = Plan {
        trained,
        windows,
        slots,
        copies,
        base,
        fixed,
        held: Vec::new(),
        routes,
        drawn: Vec::new(),
    };
    let (n, k, _, nw) = plan.dims();
    let kk = cfg.samples.max(1);
    check_batch_memory(trained, kk, nw)?;
    if cfg.task == Task::Unconditional {
        let decided = match route_cost {
            Some(cost) => plan.cheapest_routes(scene, cost)?,
            None => Vec::new(),
        };
        // Its own stream: the initial noise stays what the seed gave before routes.
        plan.draw_routes(scene, kk, cfg.seed ^ 0x5EED_2047, &decided);
    }
    // Batch row `s·W + w` is window w of sample s.
    let refs: Vec<&Window> = (0..kk).flat_map(|s| plan.windows_of(s)).collect();
    let rows = kk * nw;
    // A model that reads end points is given the recorded ones where they are known.
    let goals = match cfg.task {
        Task::Conditional => Goals::Recorded,
        Task::Unconditional => Goals::Hidden,
    };
    let batch = build(&refs, &wcfg, &trained.meta.normaliser, goals, &dev)?;
    // Weights as constants: a backward pass for guidance through the denoiser then walks only
    // from the output to the noisy coefficients, not into 400,000 weights and the map encoder
    // (10x the work, all of it thrown away).
    let model = trained.frozen()?;
    let map = model.encode_scene(&batch.ctx)?;
    let sigmas = trained.meta.config.edm.schedule(cfg.steps.max(1));
    let mut rng = crate::train::rng::Rng::new(cfg.seed);
    let mut init: Vec<f32> = (0..rows * n * k)
        .map(|_| (rng.normal() * sigmas[0]) as f32)
        .collect();
    // Every copy of an agent starts from its owner's noise: they are one variable.
    plan.consensus(&mut init, None, 0.0, cfg.clamp);
    let x0 = Tensor::from_vec(init, (rows, n, k), &dev)?;
    Ok(Setup {
        plan,
        batch,
        model,
        map,
        sigmas,
        x0,
        rows,
    })
}

/// Every sample's guidance cost and the gradient w.r.t. the owners' coefficients.
type CostsAndGradient = Result<(Vec<f64>, Vec<f32>), SampleError>;

/// An unguided run's tensors, for checking a port of the denoiser against this one: the
/// batch's context (`lane_points`, `lane_mask`, `lane_rel`, `lane_conn`, `agent_hist`,
/// `agent_mask`, `agent_lane_rel`, `agent_rel`, and `agent_route` for a checkpoint that tells
/// futures against routes), the initial noise `x0`, the noise levels
/// `sigmas`, the first denoised estimate `d0` (`D(x0; σ_0)`) and the final coefficients
/// `x_final`. `benches/torch/` reads them.
pub fn reference_run(
    trained: &Trained,
    scene: &Scene,
    cfg: &SampleConfig,
) -> Result<Vec<(String, Tensor)>, SampleError> {
    if trained.meta.config.window.route_times > 0 {
        return Err(SampleError::Settings(format!(
            "{}: there is no port to check",
            crate::model::route::NOT_PORTED
        )));
    }
    if trained.meta.config.window.goals {
        return Err(SampleError::Settings(
            "the checkpoint reads agents' end points (window.goals), which the PyTorch port \
             (benches/torch) does not: there is no port to check"
                .into(),
        ));
    }
    let su = setup(trained, scene, cfg, None)?;
    let unguided = |x: &Tensor, sigma: f64, _| -> Result<Tensor, SampleError> {
        let d = su
            .model
            .denoise(&su.batch.ctx, &su.map, x, &vec![sigma; su.rows])?;
        let mut dv: Vec<f32> = d.flatten_all()?.to_vec1()?;
        su.plan.consensus(&mut dv, None, 0.0, cfg.clamp);
        Ok(Tensor::from_vec(dv, d.dims(), d.device())?)
    };
    let d0 = unguided(&su.x0, su.sigmas[0], 0)?;
    let last = heun(su.x0.clone(), &su.sigmas, unguided)?;
    let c = &su.batch.ctx;
    let sig = Tensor::new(su.sigmas.as_slice(), &Device::Cpu)?;
    let route = c.agent_route.clone().map(|r| ("agent_route", r));
    Ok(route
        .into_iter()
        .chain([
            ("lane_points", c.lane_points.clone()),
            ("lane_mask", c.lane_mask.clone()),
            ("lane_rel", c.lane_rel.clone()),
            ("lane_conn", c.lane_conn.clone()),
            ("agent_hist", c.agent_hist.clone()),
            ("agent_mask", c.agent_mask.clone()),
            ("agent_attr", c.agent_attr.clone()),
            ("agent_lane_rel", c.agent_lane_rel.clone()),
            ("agent_rel", c.agent_rel.clone()),
            ("x0", su.x0.clone()),
            ("sigmas", sig),
            ("d0", d0),
            ("x_final", last),
        ])
        .map(|(k, v)| (k.to_string(), v))
        .collect())
}

/// Samples `cfg.samples` futures of `scene` (already [`prepare`]d), guided by `scripts`
/// (compiled against that scene; their weights are inside them).
pub fn sample(
    trained: &Trained,
    scene: &Scene,
    scripts: &[CostScript],
    cfg: &SampleConfig,
) -> Result<Vec<Sample>, SampleError> {
    sample_until(trained, scene, scripts, cfg, &AtomicBool::new(false))
}

/// [`sample`] that another thread may stop by setting `stop` (Python's Ctrl-C): it is read
/// before every denoising step and every polish iteration, and once set the run ends with
/// [`SampleError::Stopped`] within one step. A 64-sample run on an 8 s scene held Ctrl-C for
/// minutes.
pub fn sample_until(
    trained: &Trained,
    scene: &Scene,
    scripts: &[CostScript],
    cfg: &SampleConfig,
    stop: &AtomicBool,
) -> Result<Vec<Sample>, SampleError> {
    sample_after(trained, scene, scripts, None, cfg, stop)
}

/// What a closed loop has executed so far: the trajectories over the original horizon (in
/// the layout of the scene the scripts were compiled against, its current step the loop's
/// first) and how many of their steps are executed.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Executed<'a> {
    pub(crate) trajectories: &'a Trajectories,
    pub(crate) steps: usize,
}

/// [`sample`], with `scripts` compiled at the closed loop's first current step rather than
/// `scene`'s when `executed` is given: each candidate is spliced after the executed steps
/// ([`Trajectories::spliced`]), so that a request keeps the deadline it was given instead
/// of moving it a round further every round.
pub(crate) fn sample_after(
    trained: &Trained,
    scene: &Scene,
    scripts: &[CostScript],
    executed: Option<Executed>,
    cfg: &SampleConfig,
    stop: &AtomicBool,
) -> Result<Vec<Sample>, SampleError> {
    // Every evaluation of the run is counted against its budget, the closed loop's rounds
    // (which share the compiled scripts) included.
    let evaluate = |script: &CostScript, t: &Trajectories| -> Result<CostReport, SampleError> {
        let report = match executed {
            None => script.evaluate(t)?,
            Some(e) => script
                .evaluate(&e.trajectories.spliced(e.steps, t))?
                .shifted(e.steps, t.layout),
        };
        check_script_budget(scripts, cfg)?;
        Ok(report)
    };
    // Each script's cost, as guidance weighs them.
    let route_cost = |t: &Trajectories| -> Result<f64, SampleError> {
        scripts
            .iter()
            .map(|script| evaluate(script, t).map(|r| r.total))
            .sum()
    };
    let dev = Device::Cpu;
    let c = scene.meta.current_step;
    let Setup {
        mut plan,
        batch,
        model,
        map,
        sigmas,
        x0,
        rows,
    } = setup(
        trained,
        scene,
        cfg,
        (!scripts.is_empty() && cfg.lambda > 0.0).then_some(&route_cost),
    )?;
    let model = &model;
    let (n, k, _, _) = plan.dims();
    let kk = cfg.samples.max(1);
    let edm = trained.meta.config.edm;
    // An agent's end point is its last recorded future state: the end of the horizon, or
    // earlier where its recording stops (it left the cameras' view, or the recording ends).
    // Without it such an agent would be free, and drift wherever the prior takes it.
    let recorded_end: Vec<Option<(usize, f64, f64)>> = scene
        .agents
        .iter()
        .map(|a| {
            (c + 1..a.states.len())
                .rev()
                .find(|&t| a.states[t].valid)
                .map(|t| (t - c - 1, a.states[t].x, a.states[t].y))
        })
        .collect();
    if cfg.task == Task::Conditional {
        plan.held = plan.standing(scene, &recorded_end, plan.base.layout.steps);
    }
    let plan = plan;
    // Cars leave the scene where they reach the end of the map, as recorded ones do; in
    // conditional simulation, also where their recording stops: when an agent leaves is as
    // much a known state as where it ends up.
    let retire = |t: &mut Trajectories| {
        t.retire_exited(scene);
        if cfg.task == Task::Conditional {
            let n = t.layout.steps;
            for &Slot { agent: ai, .. } in &plan.slots {
                let gone = recorded_end[ai].map_or(0, |(k, _, _)| k + 1);
                t.valid[ai * n + gone.min(n)..(ai + 1) * n].fill(false);
            }
        }
    };
    let initial: std::cell::RefCell<Vec<Vec<CostReport>>> = std::cell::RefCell::new(Vec::new());
    let initial_realism: std::cell::RefCell<Vec<CostReport>> = std::cell::RefCell::new(Vec::new());
    let mut moved = vec![false; scene.agents.len()];
    for sl in &plan.slots {
        moved[sl.agent] = true;
    }
    let realism_on = cfg.realism.weight > 0.0;
    let realism = |t: &Trajectories, reports: &[CostReport], keep_clear: bool| {
        let exempt = crate::cost::Allowed::from_reports(reports, scene);
        let r = Realism {
            keep_clear,
            ..cfg.realism
        };
        r.evaluate(scene, t, &moved, &exempt)
    };
    // Every sample's guidance cost (scripts, realism, known states) at the coefficients
    // `dv` (each agent's copies equal to its owner's) and its gradient w.r.t. the owners'
    // coefficients, with realism's collision term where `keep_clear`; the first call keeps
    // its reports (the collision term's included) as the samples' initial ones.
    let objective = |dv: &[f32], step: usize, keep_clear: bool| -> CostsAndGradient {
        let mut trajs = plan.trajectories(dv);
        let aligned: Vec<Vec<Aligned>> = trajs
            .iter_mut()
            .map(|t| {
                let a = plan.align_headings(t);
                retire(t);
                a
            })
            .collect();
        let mut g = vec![0f32; rows * n * k];
        let mut totals = Vec::with_capacity(trajs.len());
        let first = initial.borrow().is_empty();
        for (s, t) in trajs.iter().enumerate() {
            let mut world = vec![0.0; t.layout.len()];
            let mut total = 0.0;
            let mut reports = Vec::with_capacity(scripts.len());
            for script in scripts {
                let r = evaluate(script, t)?;
                for (w, v) in world.iter_mut().zip(&r.gradient) {
                    *w += v;
                }
                total += r.total;
                reports.push(r);
            }
            if realism_on {
                let r = realism(t, &reports, keep_clear);
                for (w, v) in world.iter_mut().zip(&r.gradient) {
                    *w += v;
                }
                total += r.total;
                if first {
                    let whole = if keep_clear {
                        r
                    } else {
                        realism(t, &reports, true)
                    };
                    initial_realism.borrow_mut().push(whole);
                }
            }
            if first {
                initial.borrow_mut().push(reports);
            }
            if cfg.task == Task::Conditional {
                for &Slot { agent: ai, .. } in &plan.slots {
                    if let Some((k, ex, ey)) = recorded_end[ai] {
                        let (p, _) = t.state(ai, k);
                        let i = (ai * t.layout.steps + k) * 3;
                        let (dx, dy) = (p[0] - ex, p[1] - ey);
                        world[i] += 2.0 * cfg.known_weight * dx;
                        world[i + 1] += 2.0 * cfg.known_weight * dy;
                        total += cfg.known_weight * (dx * dx + dy * dy);
                    }
                }
            }
            Aligned::chain(&aligned[s], &mut world);
            if world.iter().any(|v| !v.is_finite()) {
                return Err(SampleError::NonFinite {
                    what: "cost gradient",
                    step,
                });
            }
            plan.to_coeffs(&world, t.layout.steps, &mut g, s, dv);
            totals.push(total);
        }
        Ok((totals, g))
    };
    let guiding = cfg.lambda > 0.0 && !(scripts.is_empty() && cfg.task == Task::Unconditional);
    let guided = |x: &Tensor, sigma: f64, step: usize| -> Result<Tensor, SampleError> {
        check_stop(stop)?;
        let sig = vec![sigma; rows];
        let (d, xv) = if cfg.guidance == Guidance::Denoiser && guiding {
            let xv = Var::from_tensor(x)?;
            (
                model.denoise(&batch.ctx, &map, xv.as_tensor(), &sig)?,
                Some(xv),
            )
        } else {
            (model.denoise(&batch.ctx, &map, x, &sig)?, None)
        };
        let raw: Vec<f32> = d.flatten_all()?.to_vec1()?;
        if raw.iter().any(|v| !v.is_finite()) {
            return Err(SampleError::NonFinite {
                what: "denoiser output",
                step,
            });
        }
        let mut dv = raw.clone();
        plan.consensus(&mut dv, None, 0.0, cfg.clamp);
        plan.hold(&mut dv);
        if !guiding {
            return Ok(Tensor::from_vec(dv, (rows, n, k), &dev)?);
        }
        // Without polish there is no later stage to keep clear in.
        let (_, g) = objective(&dv, step, cfg.polish == 0)?;
        let gd = Tensor::from_vec(g, (rows, n, k), &dev)?;
        let grad = match xv {
            Some(xv) => {
                // Pull the output-space gradient back through the denoiser: d(D·g)/dx = Jᵀ g.
                let grads = (d.clone() * &gd)?.sum_all()?.backward()?;
                grads.get(xv.as_tensor()).cloned().unwrap_or(gd)
            }
            None => gd,
        };
        let lambda = cfg.lambda * cfg.schedule.factor(sigma, edm.sigma_data);
        let gv: Vec<f32> = grad.flatten_all()?.to_vec1()?;
        let mut out = raw;
        plan.consensus(&mut out, Some(&gv), lambda, cfg.clamp);
        plan.hold(&mut out);
        Ok(Tensor::from_vec(out, (rows, n, k), &dev)?)
    };
    let x = heun(x0, &sigmas, guided)?;
    let mut xv: Vec<f32> = x.flatten_all()?.to_vec1()?;
    if xv.iter().any(|v| !v.is_finite()) {
        return Err(SampleError::NonFinite {
            what: "sample",
            step: sigmas.len() - 1,
        });
    }
    if guiding && cfg.polish > 0 {
        let variances = &trained.meta.normaliser.pca.variances;
        // Routes first, then clearance: see the realism module.
        let keep_clear = if realism_on {
            &[false, true][..]
        } else {
            &[false]
        };
        for &clear in keep_clear {
            polish(&mut xv, kk, variances, cfg.polish, |c| {
                check_stop(stop)?;
                let mut c = c.to_vec();
                plan.consensus(&mut c, None, 0.0, cfg.clamp);
                let (j, g) = objective(&c, sigmas.len() - 1, clear)?;
                Ok((c, j, g))
            })?;
        }
    }
    let mut trajs = plan.trajectories(&xv);
    for t in &mut trajs {
        plan.align_headings(t);
        retire(t);
    }
    let mut out = Vec::with_capacity(kk);
    for t in trajs {
        let mut sim = scene.clone();
        for (ai, a) in sim.agents.iter_mut().enumerate() {
            // A fixed agent keeping its velocity says so, so that a closed loop's next round,
            // which starts from these states, keeps it going.
            let keeps = cfg.task == Task::Unconditional && plan.fixed.iter().any(|f| f.0 == a.id);
            let (vx, vy) = if keeps {
                (a.states[c].vx, a.states[c].vy)
            } else {
                (0.0, 0.0)
            };
            for j in 0..t.layout.steps {
                let (p, valid) = t.state(ai, j);
                a.states[c + 1 + j] = if valid {
                    AgentState {
                        x: p[0],
                        y: p[1],
                        heading: p[2],
                        vx,
                        vy,
                        valid,
                    }
                } else {
                    AgentState::INVALID
                };
            }
            if !keeps {
                // A sampled state's velocity is what the next closed-loop round, a script's
                // `current_speed` and realism's speed-up bound read as the current one; left
                // at zero, a car driving at 15 m/s would start the next round standing.
                velocities_from_positions(&mut a.states, c + 1, scene.meta.dt);
            }
        }
        let reports = scripts
            .iter()
            .map(|s| evaluate(s, &t))
            .collect::<Result<Vec<_>, _>>()?;
        let fin = realism_on.then(|| realism(&t, &reports, true));
        out.push(Sample {
            scene: sim,
            initial_reports: Vec::new(),
            reports,
            realism: None,
            fixed: plan.fixed.clone(),
        });
        if let (Some(f), Some(o)) = (fin, out.last_mut()) {
            o.realism = Some((f.clone(), f));
        }
    }
    for (o, r) in out.iter_mut().zip(initial.into_inner()) {
        o.initial_reports = r;
    }
    for (o, r) in out.iter_mut().zip(initial_realism.into_inner()) {
        if let Some(pair) = &mut o.realism {
            pair.0 = r;
        }
    }
    Ok(out)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::cost::{Limits, Params};
    use crate::io::{load_scene, LoadOptions};
    use crate::train::train;
    use std::path::Path;
    use std::rc::Rc;

    /// A tiny model trained on the script-test highways, and the first of them prepared.
    pub(crate) fn setup() -> (Trained, Scene) {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes");
        let scenes: Vec<Scene> = [
            "highway.yaml",
            "highway_cut_in.yaml",
            "highway_left.yaml",
            "highway_right.yaml",
        ]
        .iter()
        .map(|f| load_scene(&dir.join(f), 0, &LoadOptions::default()).unwrap())
        .collect();
        let cfg = crate::train::trainer::tiny_config(40, 3, 40);
        let t = train(&scenes, cfg, None, None, |_, _, _| {}).unwrap();
        let s = prepare(&scenes[0], &t).unwrap();
        (t, s)
    }

    /// Two unconditional samples in 8 steps: the guided tests' sampler.
    pub(crate) fn quick() -> SampleConfig {
        SampleConfig {
            steps: 8,
            samples: 2,
            task: Task::Unconditional,
            ..SampleConfig::default()
        }
    }

    fn rightmost(scene: &Scene) -> CostScript {
        let src = std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/rightmost_lane.rhai"),
        )
        .unwrap();
        CostScript::compile(
            &src,
            "rightmost_lane.rhai",
            Rc::new(scene.clone()),
            &Params::parse(&["vehicle=3"]).unwrap(),
            &Limits::default(),
        )
        .unwrap()
    }

    #[test]
    fn a_stop_flag_ends_open_and_closed_loop_sampling_with_stopped() {
        let (t, scene) = setup();
        let stop = AtomicBool::new(true);
        let script = rightmost(&scene);
        let e = sample_until(&t, &scene, &[script], &quick(), &stop).unwrap_err();
        assert!(matches!(e, SampleError::Stopped), "{e}");
        let e = crate::sample::closed_loop_until(&t, &scene, &[], &quick(), 5, &stop).unwrap_err();
        assert!(matches!(e, SampleError::Stopped), "{e}");
        // Unset, the same calls sample.
        let go = AtomicBool::new(false);
        assert_eq!(
            sample_until(&t, &scene, &[rightmost(&scene)], &quick(), &go)
                .unwrap()
                .len(),
            2
        );
    }

    #[test]
    fn aligned_heading_gradients_land_on_the_positions_that_set_them() {
        // A cost of 2·h at step 1, whose heading points from state 0 to state 2, and of 3·h at
        // the last step (2), which points from state 1 to itself.
        let xy = [[0.0, 0.0], [1.0, 0.3], [2.5, 0.2]];
        let heading = |xy: &[[f64; 2]; 3], a: usize, b: usize| {
            (xy[b][1] - xy[a][1]).atan2(xy[b][0] - xy[a][0])
        };
        let cost = |xy: &[[f64; 2]; 3]| 2.0 * heading(xy, 0, 2) + 3.0 * heading(xy, 1, 2);
        let set = [
            Aligned {
                at: 1,
                behind: Some(0),
                ahead: 2,
                dx: 2.5,
                dy: 0.2,
            },
            Aligned {
                at: 2,
                behind: Some(1),
                ahead: 2,
                dx: 1.5,
                dy: -0.1,
            },
        ];
        let mut world = vec![0.0; 9];
        world[1 * 3 + 2] = 2.0;
        world[2 * 3 + 2] = 3.0;
        Aligned::chain(&set, &mut world);
        assert_eq!((world[5], world[8]), (0.0, 0.0), "headings are not free");
        for k in 0..3 {
            for c in 0..2 {
                let (mut lo, mut hi) = (xy, xy);
                lo[k][c] -= 1e-6;
                hi[k][c] += 1e-6;
                let fd = (cost(&hi) - cost(&lo)) / 2e-6;
                assert!(
                    (world[k * 3 + c] - fd).abs() < 1e-6,
                    "state {k} coord {c}: {} vs {fd}",
                    world[k * 3 + c]
                );
            }
        }
    }

    #[test]
    fn unguided_samples_are_finite_and_seeded() {
        let (t, s) = setup();
        let cfg = SampleConfig {
            steps: 8,
            samples: 2,
            lambda: 0.0,
            task: Task::Unconditional,
            ..SampleConfig::default()
        };
        let a = sample(&t, &s, &[], &cfg).unwrap();
        let b = sample(&t, &s, &[], &cfg).unwrap();
        assert_eq!(a.len(), 2);
        assert_eq!(a[0].scene.num_steps(), s.num_steps());
        for ag in &a[0].scene.agents {
            assert!(ag.states[s.meta.current_step + 1..]
                .iter()
                .all(|x| x.valid && x.x.is_finite()));
        }
        assert_eq!(
            a[0].scene, b[0].scene,
            "the same seed gives the same samples"
        );
    }

    #[test]
    fn static_obstacles_stay_where_they_are() {
        // A parked car (CommonRoad's `parkedVehicle` static obstacle) is a vehicle the model
        // has seen, yet it must not drive away, whatever the task and however it was
        // recorded moving.
        let (t, mut s) = setup();
        let c = s.meta.current_step;
        let parked = (0..s.agents.len())
            .find(|&i| s.agents[i].is_valid(c) && s.agents[i].states[c].speed() > 1.0)
            .expect("a moving agent");
        s.agents[parked].is_static = true;
        let now = s.agents[parked].states[c];
        for task in [Task::Unconditional, Task::Conditional] {
            let cfg = SampleConfig {
                steps: 8,
                lambda: 0.0,
                task,
                ..SampleConfig::default()
            };
            let out = sample(&t, &s, &[], &cfg).unwrap().remove(0);
            assert!(out.fixed.is_empty(), "{task:?}: {:?}", out.fixed);
            for k in c + 1..s.num_steps() {
                let got = out.scene.agents[parked].states[k];
                assert!(got.valid, "{task:?} step {k}");
                assert_eq!(
                    (got.x, got.y, got.heading),
                    (now.x, now.y, now.heading),
                    "{task:?} step {k}"
                );
            }
        }
    }

    #[test]
    fn a_car_the_conditional_task_shows_standing_stays_put() {
        // Standing now, and recorded 0.3 m ahead at the end: it rolls there at an even pace
        // with its heading, instead of the model's creep and sideways slide. One 0.6 m ahead
        // at the end is the model's to move.
        let (t, mut s) = setup();
        let c = s.meta.current_step;
        let i = (0..s.agents.len())
            .find(|&i| s.agents[i].is_valid(c))
            .expect("an agent");
        let now = AgentState {
            vx: 0.0,
            vy: 0.0,
            ..s.agents[i].states[c]
        };
        let (hs, hc) = now.heading.sin_cos();
        let n = s.num_steps();
        let set_end = |s: &mut Scene, ahead: f64| {
            for k in c..n {
                let u = if k + 1 == n { ahead } else { 0.0 };
                s.agents[i].states[k] = AgentState {
                    x: now.x + u * hc,
                    y: now.y + u * hs,
                    ..now
                };
            }
        };
        let cfg = SampleConfig {
            steps: 8,
            lambda: 0.0,
            task: Task::Conditional,
            ..SampleConfig::default()
        };
        set_end(&mut s, 0.3);
        let out = sample(&t, &s, &[], &cfg).unwrap().remove(0);
        for k in c + 1..n {
            let got = out.scene.agents[i].states[k];
            let u = 0.3 * (k - c) as f64 / (n - 1 - c) as f64;
            assert!(got.valid, "step {k}");
            assert!(
                (got.x - (now.x + u * hc)).abs() < 1e-9 && (got.y - (now.y + u * hs)).abs() < 1e-9,
                "step {k}: ({}, {}) off the even roll to the end",
                got.x,
                got.y
            );
            assert_eq!(got.heading, now.heading, "step {k}");
        }
        set_end(&mut s, 0.6);
        let free = sample(&t, &s, &[], &cfg).unwrap().remove(0);
        let moved = (c + 1..n - 1).any(|k| {
            let got = free.scene.agents[i].states[k];
            let u = 0.6 * (k - c) as f64 / (n - 1 - c) as f64;
            (got.x - (now.x + u * hc)).hypot(got.y - (now.y + u * hs)) > 1e-3
        });
        assert!(moved, "an end 0.6 m away leaves the agent to the model");
    }

    #[test]
    fn agents_of_types_the_model_never_saw_follow_their_log_or_keep_velocity() {
        let (t, mut s) = setup();
        let c = s.meta.current_step;
        let ped = (0..s.agents.len())
            .find(|&i| s.agents[i].is_valid(c) && s.agents[i].states[c].speed() > 1.0)
            .expect("a moving agent");
        s.agents[ped].agent_type = AgentType::Pedestrian;
        let id = s.agents[ped].id;
        for task in [Task::Unconditional, Task::Conditional] {
            let cfg = SampleConfig {
                steps: 8,
                lambda: 0.0,
                task,
                ..SampleConfig::default()
            };
            let out = sample(&t, &s, &[], &cfg).unwrap().remove(0);
            assert_eq!(out.fixed, vec![(id, AgentType::Pedestrian)], "{task:?}");
            let now = s.agents[ped].states[c];
            for k in c + 1..s.num_steps() {
                let (got, log) = (out.scene.agents[ped].states[k], s.agents[ped].states[k]);
                let want = match task {
                    Task::Conditional => log,
                    Task::Unconditional => {
                        let tau = (k - c) as f64 * s.meta.dt;
                        AgentState {
                            x: now.x + now.vx * tau,
                            y: now.y + now.vy * tau,
                            ..now
                        }
                    }
                };
                assert_eq!(got.valid, want.valid, "{task:?} step {k}");
                if want.valid {
                    assert!(
                        (got.x - want.x).abs() < 1e-9 && (got.y - want.y).abs() < 1e-9,
                        "{task:?} step {k}: {got:?} vs {want:?}"
                    );
                }
            }
            // The vehicles are still sampled: the model moved at least one off its log.
            let moved = (0..s.agents.len()).filter(|&i| i != ped).any(|i| {
                let (a, b) = (&out.scene.agents[i].states, &s.agents[i].states);
                (c + 1..s.num_steps()).any(|k| a[k].valid && (a[k].x - b[k].x).abs() > 1e-6)
            });
            assert!(moved, "{task:?}");
        }
    }

    #[test]
    fn a_script_that_overflows_stops_the_run_with_an_error() {
        let (t, s) = setup();
        // Finite on the recorded future is not required here: compile without validating,
        // as a caller that skips validation would.
        let script = CostScript::compile(
            "let a = agent(3); let big = 1e300 * 1e300; term(\"boom\", a.x.last() * big);",
            "boom.rhai",
            Rc::new(s.clone()),
            &Params::default(),
            &Limits::default(),
        )
        .unwrap();
        for guidance in [Guidance::OutputSpace, Guidance::Denoiser] {
            let err = sample(
                &t,
                &s,
                std::slice::from_ref(&script),
                &SampleConfig {
                    steps: 8,
                    task: Task::Unconditional,
                    guidance,
                    ..SampleConfig::default()
                },
            )
            .err()
            .expect("an overflowing script must not yield samples");
            let msg = err.to_string();
            assert!(
                msg.contains("non-finite") || msg.contains("boom"),
                "{guidance:?}: {msg}"
            );
        }
    }

    #[test]
    fn a_slow_script_stops_the_run_at_its_budget_saying_how_many_evaluations_ran() {
        let (t, s) = setup();
        // Within the per-call wall time, slow over a run: a long loop at every evaluation.
        let slow = || {
            CostScript::compile(
                "let n = 0; for i in 0..40000 { n += 1; }\n\
                 let a = agent(3); term(\"ahead\", relu(100.0 - a.x.last()));",
                "slow.rhai",
                Rc::new(s.clone()),
                &Params::default(),
                &Limits::default(),
            )
            .unwrap()
        };
        let cfg = SampleConfig {
            lambda: 1.0,
            ..quick()
        };
        let whole = slow();
        sample(&t, &s, std::slice::from_ref(&whole), &cfg).unwrap();
        let full = whole.usage();
        let budget = full.time / 4;
        let script = slow();
        let err = sample(
            &t,
            &s,
            std::slice::from_ref(&script),
            &SampleConfig {
                script_budget: budget,
                ..cfg
            },
        )
        .err()
        .expect("a run past its budget must not yield samples");
        let SampleError::ScriptBudget { used, .. } = &err else {
            panic!("{err}");
        };
        // Stopped at the evaluation that crossed the budget, not at the end of the run.
        assert_eq!(*used, script.usage());
        assert!(used.time > budget, "{err}");
        assert!(
            used.evaluations >= 1 && used.evaluations < full.evaluations,
            "{} of {}: {err}",
            used.evaluations,
            full.evaluations
        );
        let msg = err.to_string();
        assert!(
            msg.contains(&format!("over {} evaluations (", used.evaluations))
                && msg.contains("s each)")
                && msg.contains("--script-budget"),
            "{msg}"
        );
        let zero = SampleConfig {
            script_budget: std::time::Duration::ZERO,
            ..cfg
        };
        assert!(zero.validate().unwrap_err().contains("script budget = 0 s"));
    }

    #[test]
    fn windows_tile_every_observed_agent_once() {
        let (t, s) = setup();
        let c = s.meta.current_step;
        let wcfg = crate::train::WindowConfig {
            max_agents: 2,
            ..t.meta.config.window
        };
        let Tiling {
            windows,
            slots,
            copies,
            ..
        } = tile(&s, &wcfg, c, 0, &t.meta, RouteHint::Unknown);
        let observed: Vec<usize> = (0..s.agents.len())
            .filter(|&i| s.agents[i].is_valid(c))
            .collect();
        assert!(observed.len() > 2);
        assert!(windows.len() >= observed.len().div_ceil(2));
        let mut got: Vec<usize> = slots.iter().map(|x| x.agent).collect();
        got.sort();
        assert_eq!(got, observed, "each observed agent exactly once");
        let centre_dist = |w: usize, ai: usize| {
            let (p, q) = (
                s.agents[windows[w].agents[0]].states[c].position(),
                s.agents[ai].states[c].position(),
            );
            (p - q).norm()
        };
        for (sl, cp) in slots.iter().zip(&copies) {
            assert_eq!(cp[0], (sl.window, sl.slot), "the owner comes first");
            let held: Vec<(usize, usize)> = windows
                .iter()
                .enumerate()
                .flat_map(|(w, win)| {
                    win.agents
                        .iter()
                        .enumerate()
                        .filter(|(_, &a)| a == sl.agent)
                        .map(move |(k, _)| (w, k))
                })
                .collect();
            let mut sorted = cp.clone();
            sorted.sort();
            assert_eq!(sorted, held, "every window holding agent {}", sl.agent);
            for &(w, _) in cp {
                assert!(centre_dist(sl.window, sl.agent) <= centre_dist(w, sl.agent));
            }
        }
    }

    #[test]
    fn headings_follow_the_path_forwards_and_backwards_but_never_sideways() {
        let (t, s) = setup();
        let c = s.meta.current_step;
        let Tiling {
            windows,
            slots,
            copies,
            ..
        } = tile(&s, &t.meta.config.window, c, 0, &t.meta, RouteHint::Unknown);
        let sl = slots[0];
        let plan = Plan {
            trained: &t,
            windows,
            slots: vec![sl],
            copies: vec![copies[0].clone()],
            base: Trajectories::filled(&s),
            fixed: Vec::new(),
            held: Vec::new(),
            routes: Vec::new(),
            drawn: Vec::new(),
        };
        let [x0, y0, h0] = sl.pose;
        let drive = |angle: f64| {
            let mut tr = plan.base.clone();
            let n = tr.layout.steps;
            for j in 0..n {
                let r = 0.5 * (j + 1) as f64;
                tr.xyh[sl.agent * n + j] =
                    [x0 + r * (h0 + angle).cos(), y0 + r * (h0 + angle).sin(), h0];
            }
            plan.align_headings(&mut tr);
            tr.xyh[sl.agent * n + n / 2][2] - h0
        };
        assert!(
            (drive(0.1) - 0.1).abs() < 1e-9,
            "forwards, 0.1 rad off: turned"
        );
        assert!(
            (drive(std::f64::consts::PI + 0.1) - 0.1).abs() < 1e-9,
            "reversing"
        );
        assert_eq!(drive(std::f64::consts::FRAC_PI_2), 0.0, "sideways: kept");
    }

    #[test]
    fn a_car_turns_only_as_it_rolls() {
        let (t, s) = setup();
        let c = s.meta.current_step;
        let Tiling {
            windows,
            slots,
            copies,
            ..
        } = tile(&s, &t.meta.config.window, c, 0, &t.meta, RouteHint::Unknown);
        let sl = slots[0];
        assert_eq!(sl.curvature, 0.3, "a car's steering bound");
        let plan = Plan {
            trained: &t,
            windows,
            slots: vec![sl],
            copies: vec![copies[0].clone()],
            base: Trajectories::filled(&s),
            fixed: Vec::new(),
            held: Vec::new(),
            routes: Vec::new(),
            drawn: Vec::new(),
        };
        let [x0, y0, h0] = sl.pose;
        // Steps of `step(j)` metres straight ahead, the model's heading wobbling by ±0.2 rad.
        let drive = |step: &dyn Fn(usize) -> f64| {
            let mut tr = plan.base.clone();
            let n = tr.layout.steps;
            let mut r = 0.0;
            for j in 0..n {
                r += step(j);
                let wobble = if j % 2 == 0 { 0.2 } else { -0.2 };
                tr.xyh[sl.agent * n + j] = [x0 + r * h0.cos(), y0 + r * h0.sin(), h0 + wobble];
            }
            plan.align_headings(&mut tr);
            let mut worst: f64 = 0.0;
            let (mut last, mut last_h) = ([x0, y0], h0);
            for j in 0..n {
                let p = tr.xyh[sl.agent * n + j];
                let ds = (p[0] - last[0]).hypot(p[1] - last[1]);
                let turn = crate::geom::wrap_angle(p[2] - last_h).abs();
                worst = worst.max(turn - 0.3 * ds);
                (last, last_h) = ([p[0], p[1]], p[2]);
            }
            worst
        };
        // Creeping at 0.3 m/s, and near 2 m/s where steps cross the path-heading threshold.
        assert!(drive(&|_| 0.03) <= 1e-12, "creeping");
        assert!(
            drive(&|j| if j % 3 == 0 { 0.17 } else { 0.23 }) <= 1e-12,
            "near 2 m/s"
        );
        // Standing still, the heading stays exactly the current one.
        let mut tr = plan.base.clone();
        let n = tr.layout.steps;
        for j in 0..n {
            tr.xyh[sl.agent * n + j] = [x0, y0, h0 + 0.1 * (j as f64).sin()];
        }
        plan.align_headings(&mut tr);
        assert!((0..n).all(|j| tr.xyh[sl.agent * n + j][2] == h0));

        // Creeping straight ahead at 0.3 m/s, a car keeps its heading whatever the model's
        // heading channel says; a pedestrian (no steering bound) keeps the model's.
        let creep = |plan: &Plan| {
            let mut tr = plan.base.clone();
            for j in 0..n {
                let r = 0.03 * (j + 1) as f64;
                let wobble = if j % 2 == 0 { 0.2 } else { -0.2 };
                tr.xyh[sl.agent * n + j] = [x0 + r * h0.cos(), y0 + r * h0.sin(), h0 + wobble];
            }
            plan.align_headings(&mut tr);
            (0..n)
                .map(|j| tr.xyh[sl.agent * n + j][2] - h0)
                .collect::<Vec<f64>>()
        };
        assert!(creep(&plan).iter().all(|&d| d == 0.0), "a creeping car");
        let walker = Plan {
            slots: vec![Slot {
                curvature: f64::INFINITY,
                ..sl
            }],
            ..plan
        };
        let d = creep(&walker);
        assert!(
            d.iter()
                .enumerate()
                .all(|(j, &d)| (d.abs() - 0.2).abs() < 1e-9 && (d > 0.0) == (j % 2 == 0)),
            "a walker turns with the model: {d:?}"
        );
    }

    #[test]
    fn consensus_writes_the_owner_estimate_less_the_summed_gradient_to_every_copy() {
        let (mut t, s) = setup();
        let c = s.meta.current_step;
        // Windows of 3 agents: the plan's dimensions follow the model's window config.
        t.meta.config.window.max_agents = 3;
        let Tiling {
            windows,
            slots,
            copies,
            ..
        } = tile(&s, &t.meta.config.window, c, 0, &t.meta, RouteHint::Unknown);
        assert!(copies.iter().any(|cp| cp.len() > 1), "windows overlap");
        let plan = Plan {
            trained: &t,
            windows,
            slots,
            copies: copies.clone(),
            base: Trajectories::filled(&s),
            fixed: Vec::new(),
            held: Vec::new(),
            routes: Vec::new(),
            drawn: Vec::new(),
        };
        let (n, k, _, nw) = (3, t.meta.config.model.k, 0, plan.windows.len());
        let len = nw * n * k;
        let mut d: Vec<f32> = (0..len).map(|i| i as f32).collect();
        let g: Vec<f32> = (0..len)
            .map(|i| if i % 2 == 0 { 0.3 } else { -2.0 })
            .collect();
        let before = d.clone();
        plan.consensus(&mut d, Some(&g), 0.5, Clamp::Coordinate);
        for cp in &copies {
            let at = |(w, sl): (usize, usize)| (w * n + sl) * k;
            for j in 0..k {
                let gs: f32 = cp.iter().map(|&x| g[at(x) + j]).sum();
                let want = before[at(cp[0]) + j] - 0.5 * gs.clamp(-1.0, 1.0);
                for &x in cp {
                    assert!((d[at(x) + j] - want).abs() < 1e-5);
                }
            }
        }
    }

    #[test]
    fn a_model_with_small_windows_still_moves_every_agent() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes");
        let scenes: Vec<Scene> = ["highway.yaml", "highway_cut_in.yaml"]
            .iter()
            .map(|f| load_scene(&dir.join(f), 0, &LoadOptions::default()).unwrap())
            .collect();
        let mut cfg = crate::train::trainer::tiny_config(20, 3, 20);
        cfg.window.max_agents = 2;
        let t = train(&scenes, cfg, None, None, |_, _, _| {}).unwrap();
        let s = prepare(&scenes[1], &t).unwrap();
        let out = sample(
            &t,
            &s,
            &[],
            &SampleConfig {
                steps: 8,
                samples: 3,
                lambda: 0.0,
                task: Task::Unconditional,
                ..SampleConfig::default()
            },
        )
        .unwrap();
        assert_eq!(out.len(), 3);
        let c = s.meta.current_step;
        // Constant velocity is what agents outside every window would get.
        let cv = crate::cost::Trajectories::filled(&s);
        for o in &out {
            for (ai, a) in o.scene.agents.iter().enumerate() {
                let last = a.states.len() - 1;
                let (p, _) = cv.state(ai, last - c - 1);
                let st = a.states[last];
                assert!(st.valid && st.x.is_finite());
                assert!(
                    (st.x - p[0]).abs() + (st.y - p[1]).abs() > 1e-6,
                    "agent {ai} was left at constant velocity"
                );
            }
        }
    }

    #[test]
    fn guidance_lowers_the_script_cost_in_both_modes() {
        let (t, s) = setup();
        let script = rightmost(&s);
        let base = quick();
        let unguided = sample(
            &t,
            &s,
            std::slice::from_ref(&script),
            &SampleConfig {
                lambda: 0.0,
                ..base
            },
        )
        .unwrap();
        let cost =
            |v: &[Sample]| v.iter().map(|x| x.reports[0].total).sum::<f64>() / v.len() as f64;
        for mode in [Guidance::OutputSpace, Guidance::Denoiser] {
            let guided = sample(
                &t,
                &s,
                std::slice::from_ref(&script),
                &SampleConfig {
                    // Clamped gradients act like signs: every late step moves by λ whatever
                    // the remaining error, so a large λ overshoots (0.05 doubles this tiny
                    // model's cost; 0.01 halves it).
                    lambda: 0.01,
                    guidance: mode,
                    ..base
                },
            )
            .unwrap();
            assert!(
                cost(&guided) < cost(&unguided),
                "{mode:?}: {} vs unguided {}",
                cost(&guided),
                cost(&unguided)
            );
        }
    }

    #[test]
    fn polish_descends_each_sample_in_the_data_s_common_directions() {
        // Two samples of two agents with three coefficients each, a quadratic cost per sample
        // with its minimum at `target`; the third component has no variance in the data.
        let variances = [4.0, 1.0, 0.0];
        let target = [
            1.5f32, -0.5, 3.0, -1.0, 0.25, 3.0, 0.5, 0.5, 3.0, 2.0, -2.0, 3.0,
        ];
        let mut calls = 0;
        let mut costs: Vec<Vec<f64>> = Vec::new();
        let eval = |x: &[f32]| -> Result<(Vec<f32>, Vec<f64>, Vec<f32>), SampleError> {
            let g: Vec<f32> = x.iter().zip(&target).map(|(a, b)| 2.0 * (a - b)).collect();
            let j = x
                .chunks(6)
                .zip(target.chunks(6))
                .map(|(a, b)| a.iter().zip(b).map(|(a, b)| ((a - b) as f64).powi(2)).sum())
                .collect();
            Ok((x.to_vec(), j, g))
        };
        let mut traced = |x: &[f32]| {
            calls += 1;
            let r = eval(x)?;
            costs.push(r.1.clone());
            Ok(r)
        };
        let mut x = vec![0f32; 12];
        polish(&mut x, 2, &variances, 200, &mut traced).unwrap();
        assert!(
            calls <= 201,
            "one evaluation per iteration, and the start: {calls}"
        );
        for (j, (a, b)) in x.iter().zip(&target).enumerate() {
            if j % 3 == 2 {
                assert_eq!(*a, 0.0, "a direction the data never takes is not taken");
            } else {
                assert!((a - b).abs() < 1e-3, "coefficient {j}: {a} vs {b}");
            }
        }
        // What is kept never costs more than what was kept before.
        let mut best = costs[0].clone();
        for c in &costs[1..] {
            for s in 0..2 {
                best[s] = best[s].min(c[s]);
            }
        }
        assert_eq!(best, eval(&x).unwrap().1);
        // An iteration budget of 0 leaves the sample as it is.
        let mut y = vec![0.3f32; 12];
        polish(&mut y, 2, &variances, 0, eval).unwrap();
        assert_eq!(y, vec![0.3f32; 12]);
    }

    #[test]
    fn polish_lowers_a_guided_sample_s_cost() {
        let (t, s) = setup();
        let script = rightmost(&s);
        let base = SampleConfig {
            lambda: 0.01,
            ..quick()
        };
        let run = |polish| {
            sample(
                &t,
                &s,
                std::slice::from_ref(&script),
                &SampleConfig { polish, ..base },
            )
            .unwrap()
        };
        let (plain, polished) = (run(0), run(50));
        for (a, b) in plain.iter().zip(&polished) {
            assert!(
                b.reports[0].total < 0.5 * a.reports[0].total,
                "{} vs {}",
                b.reports[0].total,
                a.reports[0].total
            );
        }
        // Unguided samples are not polished: nothing guides them.
        let unguided = |polish| {
            sample(
                &t,
                &s,
                std::slice::from_ref(&script),
                &SampleConfig {
                    lambda: 0.0,
                    polish,
                    ..base
                },
            )
            .unwrap()[0]
                .reports[0]
                .total
        };
        assert_eq!(unguided(0), unguided(50));
    }

    #[test]
    fn polish_takes_the_routes_then_keeps_the_cars_clear() {
        // Agent 4 recorded on top of agent 1: the model's samples start where the boxes
        // overlap. Realism's collision term is reported from the start, and polish (its second
        // stage) clears most of it; without polish, denoising alone carries the term.
        let (t, mut s) = setup();
        let c = s.meta.current_step;
        let on_top = s.agents[0].states[..=c].to_vec();
        s.agents[3].states[..=c].clone_from_slice(&on_top);
        let script = rightmost(&s);
        let run = |polish| {
            let out = sample(
                &t,
                &s,
                std::slice::from_ref(&script),
                &SampleConfig {
                    lambda: 0.01,
                    realism: Realism::default(),
                    polish,
                    ..quick()
                },
            )
            .unwrap();
            out.into_iter()
                .map(|o| {
                    let (first, last) = o.realism.unwrap();
                    let v = |r: &CostReport| r.term("realism_collision").unwrap().value;
                    (v(&first), v(&last))
                })
                .collect::<Vec<_>>()
        };
        for (first, last) in run(60) {
            assert!(first > 1.0, "{first}");
            assert!(last < 0.1 * first, "{first} -> {last}");
        }
        for (first, last) in run(0) {
            assert!(first > 1.0 && last > 0.0, "{first} -> {last}");
        }
    }

    #[test]
    fn sampled_states_carry_the_velocity_of_their_positions() {
        let (t, s) = setup();
        let out = sample(
            &t,
            &s,
            &[],
            &SampleConfig {
                steps: 8,
                task: Task::Unconditional,
                ..SampleConfig::default()
            },
        )
        .unwrap();
        let (c, dt) = (s.meta.current_step, s.meta.dt);
        let mut checked = 0;
        for a in &out[0].scene.agents {
            for k in c + 1..a.states.len() - 1 {
                let (p, q, st) = (&a.states[k - 1], &a.states[k + 1], &a.states[k]);
                if p.valid && q.valid && st.valid {
                    assert!(
                        (st.vx - (q.x - p.x) / (2.0 * dt)).abs() < 1e-9,
                        "agent {} step {k}",
                        a.id
                    );
                    assert!(
                        (st.vy - (q.y - p.y) / (2.0 * dt)).abs() < 1e-9,
                        "agent {} step {k}",
                        a.id
                    );
                    checked += 1;
                }
            }
        }
        assert!(checked > 0);
        // A state whose neighbours are invalid takes the one-sided difference, and a lone one
        // stands still.
        let at = |x: f64, valid: bool| AgentState {
            x,
            y: 0.0,
            heading: 0.0,
            vx: 9.0,
            vy: 9.0,
            valid,
        };
        let mut states = vec![
            at(0.0, true),
            at(1.0, true),
            at(3.0, true),
            at(0.0, false),
            at(5.0, true),
        ];
        velocities_from_positions(&mut states, 1, 0.5);
        let vx: Vec<f64> = states.iter().map(|s| s.vx).collect();
        assert_eq!(vx, vec![9.0, 3.0, 4.0, 9.0, 0.0]);
        assert!(states[1..].iter().filter(|s| s.valid).all(|s| s.vy == 0.0));
    }
}
