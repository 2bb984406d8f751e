//! Hand-written Rust versions of three scripts (`scripts/cut_in.rhai`,
//! `scripts/rightmost_lane.rhai`, `scripts/no_collisions.rhai`) with analytic gradients.
//!
//! They are the baseline of `drivescript bench cost` (how much the script engine costs over
//! plain Rust) and a cross-check of the engine: tests assert that script and hand-written code
//! agree in value and gradient.

use super::fwd::box_clearance;
use super::trajectory::{Coord, Trajectories};
use crate::geom::{FrenetPath, FrenetPoint, Point};
use crate::scene::{Scene, Turn};

/// Total cost and dense gradient.
pub type CostAndGrad = (f64, Vec<f64>);

/// The path an agent's `lane_path()` gives: its current lane, 50 m behind to 300 m ahead of it.
fn agent_path(scene: &Scene, a: usize) -> Option<FrenetPath> {
    Some(
        scene
            .agent_lane_path(a, 300.0, 50.0, Turn::Straight)?
            .frenet,
    )
}

fn project(path: &FrenetPath, traj: &Trajectories, a: usize) -> Vec<FrenetPoint> {
    (0..traj.layout.steps)
        .map(|k| {
            let (xyh, _) = traj.state(a, k);
            path.project(Point::new(xyh[0], xyh[1]))
        })
        .collect()
}

fn add_xy(g: &mut [f64], traj: &Trajectories, a: usize, k: usize, c: f64, d: [f64; 2]) {
    g[traj.layout.var(a, k, Coord::X) as usize] += c * d[0];
    g[traj.layout.var(a, k, Coord::Y) as usize] += c * d[1];
}

/// `scripts/cut_in.rhai` with `gap` and `tol`.
pub fn cut_in(
    scene: &Scene,
    traj: &Trajectories,
    cutter: usize,
    victim: usize,
    gap: f64,
    tol: f64,
) -> Option<CostAndGrad> {
    let path = agent_path(scene, victim)?;
    let fa = project(&path, traj, cutter);
    let fb = project(&path, traj, victim);
    let n = traj.layout.steps;
    let mut g = vec![0.0; traj.layout.len()];
    let mut total = 0.0;
    // starts_beside = relu(1.5 - |d_0|)
    let v = 1.5 - fa[0].d.abs();
    if v > 0.0 {
        total += v;
        add_xy(&mut g, traj, cutter, 0, -fa[0].d.signum(), fa[0].dd);
    }
    // ends_in_victim_lane = relu(|d_last| - tol)
    let last = n - 1;
    let v = fa[last].d.abs() - tol;
    if v > 0.0 {
        total += v;
        add_xy(&mut g, traj, cutter, last, fa[last].d.signum(), fa[last].dd);
    }
    // ends_ahead = relu(gap - (s_a - s_b - (la + lb) / 2)); the victim is held here and in
    // no_contact, so only the cutter's coordinates get gradient.
    let half = 0.5 * (scene.agents[cutter].length + scene.agents[victim].length);
    let v = gap - (fa[last].s - fb[last].s - half);
    if v > 0.0 {
        total += v;
        add_xy(&mut g, traj, cutter, last, -1.0, fa[last].ds);
    }
    // no_contact = 5 · Σ relu(0.5 - clearance)²
    let (za, zb) = (
        (scene.agents[cutter].length, scene.agents[cutter].width),
        (scene.agents[victim].length, scene.agents[victim].width),
    );
    for k in 0..n {
        let c = box_clearance(traj.state(cutter, k).0, za, traj.state(victim, k).0, zb);
        let short = 0.5 - c.v;
        if short > 0.0 {
            total += 5.0 * short * short;
            for (s, coord) in [Coord::X, Coord::Y, Coord::Heading].into_iter().enumerate() {
                g[traj.layout.var(cutter, k, coord) as usize] += -10.0 * short * c.g[s];
            }
        }
    }
    Some((total, g))
}

/// `scripts/rightmost_lane.rhai` with `tol`.
pub fn rightmost(
    scene: &Scene,
    traj: &Trajectories,
    vehicle: usize,
    tol: f64,
) -> Option<CostAndGrad> {
    let s = scene.agents[vehicle].states[scene.meta.current_step];
    let lane = scene.map.lane_at(Point::new(s.x, s.y), s.heading)?;
    let target = scene.map.graph().rightmost(lane);
    let path = scene
        .map
        .lane_path(target, 500.0, 50.0, Turn::Straight)
        .ok()?
        .frenet;
    let f = project(&path, traj, vehicle);
    let n = traj.layout.steps;
    let dt = scene.meta.dt;
    let mut g = vec![0.0; traj.layout.len()];
    let mut total = 0.0;
    let last = n - 1;
    let v = f[last].d.abs() - tol;
    if v > 0.0 {
        total += v;
        add_xy(&mut g, traj, vehicle, last, f[last].d.signum(), f[last].dd);
    }
    // settled = 0.5 · mean over the last second of relu(|d| - tol)
    let horizon = n as f64 * dt;
    let i0 = ((horizon - 1.0 - dt) / dt).round() as usize;
    let i1 = ((horizon - dt) / dt).round() as usize;
    let m = (i1 - i0 + 1) as f64;
    for (k, fk) in f.iter().enumerate().take(i1 + 1).skip(i0) {
        let v = fk.d.abs() - tol;
        if v > 0.0 {
            total += 0.5 * v / m;
            add_xy(&mut g, traj, vehicle, k, 0.5 * fk.d.signum() / m, fk.dd);
        }
    }
    Some((total, g))
}

/// `scripts/no_collisions.rhai`: Σ over vehicle pairs and steps of relu(margin - clearance)².
pub fn no_collisions(scene: &Scene, traj: &Trajectories, margin: f64) -> CostAndGrad {
    let vehicles: Vec<usize> = (0..scene.agents.len())
        .filter(|&i| scene.agents[i].agent_type == crate::scene::AgentType::Vehicle)
        .collect();
    let mut g = vec![0.0; traj.layout.len()];
    let mut total = 0.0;
    for (ii, &i) in vehicles.iter().enumerate() {
        let ai = &scene.agents[i];
        for &j in &vehicles[ii + 1..] {
            let aj = &scene.agents[j];
            let near = 0.5 * ai.length.hypot(ai.width) + 0.5 * aj.length.hypot(aj.width) + margin;
            for k in 0..traj.layout.steps {
                let ((p, vp), (q, vq)) = (traj.state(i, k), traj.state(j, k));
                if !(vp && vq) || (p[0] - q[0]).hypot(p[1] - q[1]) > near {
                    continue;
                }
                let c = box_clearance(p, (ai.length, ai.width), q, (aj.length, aj.width));
                let short = margin - c.v;
                if short > 0.0 {
                    total += short * short;
                    for (s, coord) in [Coord::X, Coord::Y, Coord::Heading].into_iter().enumerate() {
                        g[traj.layout.var(i, k, coord) as usize] += -2.0 * short * c.g[s];
                        g[traj.layout.var(j, k, coord) as usize] += -2.0 * short * c.g[3 + s];
                    }
                }
            }
        }
    }
    (total, g)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cost::{CostScript, Limits, Params};
    use std::path::Path;
    use std::rc::Rc;

    fn script(name: &str, scene: &Rc<Scene>, params: &[String]) -> CostScript {
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        let src = std::fs::read_to_string(root.join("scripts").join(name)).unwrap();
        CostScript::compile(
            &src,
            name,
            scene.clone(),
            &Params::parse(params).unwrap(),
            &Limits::default(),
        )
        .unwrap()
    }

    fn close(a: &CostAndGrad, report: &crate::cost::CostReport) {
        assert!(
            (a.0 - report.total).abs() < 1e-9 * (1.0 + a.0.abs()),
            "{} vs {}",
            a.0,
            report.total
        );
        for (i, (x, y)) in a.1.iter().zip(&report.gradient).enumerate() {
            assert!(
                (x - y).abs() < 1e-9 * (1.0 + x.abs()),
                "coordinate {i}: {x} vs {y}"
            );
        }
    }

    #[test]
    fn hand_written_costs_match_the_scripts() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        let scene = Rc::new(
            crate::io::load_scene(
                &root.join("scripts/scenes/highway.yaml"),
                0,
                &Default::default(),
            )
            .unwrap(),
        );
        // A candidate where something is violated everywhere: vehicle 2 drifts into vehicle 1.
        let mut traj = Trajectories::recorded(&scene);
        for k in 0..traj.layout.steps {
            let w = k as f64 / traj.layout.steps as f64;
            traj.xyh[traj.layout.steps + k][1] += 3.6 * w;
            traj.xyh[traj.layout.steps + k][0] -= 38.0 * w;
        }
        let r = script(
            "cut_in.rhai",
            &scene,
            &["cutter=2".into(), "victim=1".into()],
        )
        .evaluate(&traj)
        .unwrap();
        close(&cut_in(&scene, &traj, 1, 0, 5.0, 0.5).unwrap(), &r);
        let r = script("rightmost_lane.rhai", &scene, &["vehicle=3".into()])
            .evaluate(&traj)
            .unwrap();
        close(&rightmost(&scene, &traj, 2, 0.5).unwrap(), &r);
        let r = script("no_collisions.rhai", &scene, &["margin=0.5".into()])
            .evaluate(&traj)
            .unwrap();
        assert!(r.total > 0.0);
        close(&no_collisions(&scene, &traj, 0.5), &r);
    }
}
