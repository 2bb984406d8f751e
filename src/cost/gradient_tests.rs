//! Every stdlib function's gradient against central finite differences, on real scenes.

use std::path::Path;
use std::rc::Rc;

use super::{CostScript, Limits, Params, Trajectories};
use crate::io::{load_scene, LoadOptions};
use crate::scene::Scene;

fn scene(rel: &str) -> Rc<Scene> {
    Rc::new(sample(rel))
}

/// Scene 0 of `rel` under data/samples, for the cost module's tests.
pub(super) fn sample(rel: &str) -> Scene {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("data/samples")
        .join(rel);
    load_scene(&p, 0, &LoadOptions::default()).unwrap()
}

/// The US-101 sample: 22 agents of NGSIM traffic.
pub(super) const US101: &str = "commonroad/USA_US101-4_1_T-1.xml";

/// Two agents observed over the whole future, the second the nearest to the first.
fn pair(s: &Scene) -> (i64, i64) {
    let c = s.meta.current_step;
    let full: Vec<_> = s
        .agents
        .iter()
        .filter(|a| a.states[c..].iter().all(|x| x.valid))
        .collect();
    let a = full[0];
    let b = full[1..]
        .iter()
        .min_by(|x, y| {
            let d =
                |z: &crate::scene::Agent| (z.states[c].position() - a.states[c].position()).norm();
            d(x).total_cmp(&d(y))
        })
        .unwrap();
    (a.id, b.id)
}

/// Checks the gradient of `term("t", expr)` on the filled recorded future, perturbed a little
/// so that no quantity sits exactly on a kink.
fn check(scene: &Rc<Scene>, body: &str) {
    let (a, b) = pair(scene);
    let params = Params::parse(&[format!("A={a}"), format!("B={b}")]).unwrap();
    let src = format!("let a = agent(A); let b = agent(B);\n{body}");
    let script = CostScript::compile(
        &src,
        "grad-test",
        scene.clone(),
        &params,
        &Limits::default(),
    )
    .unwrap_or_else(|e| panic!("{body}: {e}"));
    let mut traj = Trajectories::filled(scene);
    for (i, v) in traj.xyh.iter_mut().enumerate() {
        v[0] += 0.013 * ((i * 7919) % 13) as f64 / 13.0;
        v[1] -= 0.011 * ((i * 104729) % 11) as f64 / 11.0;
    }
    let report = script
        .evaluate(&traj)
        .unwrap_or_else(|e| panic!("{body}: {e}"));
    let t = &report.terms[0];
    assert!(
        !t.grad.is_empty(),
        "{body}: no dependence on the trajectory"
    );
    // The largest partials, plus coordinates outside the gradient (which must be flat).
    let mut coords: Vec<(u32, f64)> = t.grad.clone();
    coords.sort_by(|x, y| y.1.abs().total_cmp(&x.1.abs()));
    coords.truncate(8);
    let inside: Vec<u32> = t.grad.iter().map(|e| e.0).collect();
    let n = traj.layout.len() as u32;
    let mut k = 17u32;
    for _ in 0..1000 {
        if coords.len() >= 11 {
            break;
        }
        k = k.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        let var = k % n;
        if !inside.contains(&var) && !coords.iter().any(|c| c.0 == var) {
            coords.push((var, 0.0));
        }
    }
    let value = |tr: &Trajectories| {
        script
            .evaluate(tr)
            .unwrap_or_else(|e| panic!("{body}: {e}"))
            .terms[0]
            .value
    };
    for (var, analytic) in coords {
        let h = 1e-5;
        let (i, c) = (var as usize / 3, var as usize % 3);
        let mut plus = traj.clone();
        plus.xyh[i][c] += h;
        let mut minus = traj.clone();
        minus.xyh[i][c] -= h;
        let (fp, fm, f0) = (value(&plus), value(&minus), value(&traj));
        let fd = (fp - fm) / (2.0 * h);
        let tol = 1e-4 * (1.0 + analytic.abs().max(fd.abs()));
        // At a kink (two boxes parallel, two corners equally near) the central difference
        // averages two branches; the analytic gradient must then match one of the sides.
        let one_sided = [(fp - f0) / h, (f0 - fm) / h];
        assert!(
            (fd - analytic).abs() < tol || one_sided.iter().any(|d| (d - analytic).abs() < 10.0 * tol),
            "{body}: d/d{:?} analytic {analytic} vs finite differences {fd} (central), {one_sided:?} (one-sided)",
            traj.layout.decode(var)
        );
    }
}

const AGENT_EXPRS: &[&str] = &[
    "term(\"t\", a.x.sum() + a.y.mean());",
    "term(\"t\", a.heading.sum());",
    "term(\"t\", a.vx.sum() - a.vy.max());",
    "term(\"t\", a.speed.sum());",
    "term(\"t\", a.long_speed.sum());",
    "term(\"t\", a.accel.norm());",
    "term(\"t\", a.jerk.mean());",
    "term(\"t\", a.yaw_rate.sum());",
];

const FRENET_EXPRS: &[&str] = &[
    "let f = a.frenet(a.lane_path()); term(\"t\", f.s.sum() + f.d.sum());",
    "let f = b.frenet(a.lane_path(150)); term(\"t\", f.d.norm());",
    "let f = a.frenet(lane_path(a.lane, 200.0)); term(\"t\", f.to_left.sum() + 2.0 * f.to_right.sum());",
    "let p = lane_path(a.lane, 120, \"straight\"); term(\"t\", a.frenet(p).s.last());",
];

const INTERACT_EXPRS: &[&str] = &[
    "term(\"t\", gap(a, b, a.lane_path()).sum());",
    "term(\"t\", distance(a, b).mean());",
    "term(\"t\", clearance(a, b).sum());",
    "term(\"t\", ttc(a, b, 30.0).sum() + ttc(b, a).sum());",
    "term(\"t\", collision_penalty(a, b, 40.0).sum());",
    "term(\"t\", no_collision_cost(vehicles(), 30.0));",
];

const EDGE_EXPRS: &[&str] = &[
    "term(\"t\", a.edge_distance.sum());",
    "term(\"t\", a.box_edge_distance.sum());",
    "term(\"t\", a.on_road(0.5).sum());",
    "term(\"t\", a.corner_edge_distance(0).sum() + 2.0 * a.corner_edge_distance(2).sum());",
    "term(\"t\", a.wrong_way_distance.sum() + 2.0 * relu(b.wrong_way_distance + 1.0).sum());",
    "term(\"t\", a.corner_wrong_way_distance(1).sum() + 2.0 * a.corner_wrong_way_distance(3).sum());",
];

const MATH_EXPRS: &[&str] = &[
    "term(\"t\", relu(a.x - a.x.mean()).sum());",
    "term(\"t\", abs(a.y - a.y.mean()).sum());",
    "term(\"t\", sqrt(square(a.x - a.x.first()) + 1.0).sum());",
    "term(\"t\", exp((a.x - a.x.mean()) * 0.01).sum() + log(a.speed + 1.0).sum());",
    "term(\"t\", (sin(a.heading) + cos(a.heading) + tanh(a.vx * 0.1)).sum());",
    "term(\"t\", neg(a.x).sum() + (-a.y).sum() + (-(a.x.first())));",
    "term(\"t\", softplus(a.vx).sum() + softplus(a.vy, 2.0).sum());",
    "term(\"t\", sigmoid(a.vx).sum() + sigmoid(a.vy, 0.5).sum());",
    "term(\"t\", smooth_abs(a.vy).sum() + smooth_abs(a.vx, 0.5).sum());",
    "term(\"t\", pow(a.speed, 1.5).sum() + pow(a.speed.first(), a.speed.last() * 0.1));",
    "term(\"t\", clamp(a.vx, -3, 3).sum() + hinge(a.speed, 12.0).sum());",
    "term(\"t\", min(a.x, b.x).sum() + max(a.y, b.y).sum() + min(a.x.first(), b.x.last()));",
    "term(\"t\", smooth_max(a.vx, b.vx, 2.0).sum() + smooth_min(a.vy, b.vy, 2.0).sum());",
    "term(\"t\", norm(a.x - b.x, a.y - b.y).sum() + atan2(a.vy, a.vx).sum());",
    "term(\"t\", (a.x * b.y - a.y / (b.x * 0.001 + 1000.0)).sum());",
    "term(\"t\", (a.x.first() * b.y.last()) / (a.speed.mean() + 1.0) - 2 * a.x.last() + 1);",
    "term(\"t\", (a.x - b.x.first()).sum() + (b.y.last() * a.y).sum() + (3 - a.x).sum() + (a.y / 2).sum());",
];

const SERIES_EXPRS: &[&str] = &[
    "term(\"t\", a.x.first() + a.x.last() + a.y.at(3) + a.y.at(-2) + a.x.at_time(1.0));",
    "term(\"t\", a.x.slice(2, 7).sum() + a.y.window(0.5, 1.2).mean() + a.vx.slice(1, 4).deriv().sum());",
    "term(\"t\", a.x.max() - a.y.min() + a.vx.smooth_max(3.0) + a.vy.smooth_min(3.0));",
    "term(\"t\", a.x.norm() + a.x.deriv().sum());",
];

#[test]
fn agent_series_gradients() {
    let s = scene(US101);
    for e in AGENT_EXPRS {
        check(&s, e);
    }
}

#[test]
fn frenet_gradients() {
    for rel in [US101, "commonroad/USA_Lanker-1_1_T-1.xml"] {
        let s = scene(rel);
        for e in FRENET_EXPRS {
            check(&s, e);
        }
    }
    let s = scene("commonroad/USA_Lanker-1_1_T-1.xml");
    // A turning path through an intersection.
    check(
        &s,
        "let l = a.lane; let p = lane_path(l, 200, \"left\"); term(\"t\", a.frenet(p).d.sum());",
    );
}

#[test]
fn interaction_gradients() {
    for rel in [US101, "commonroad/USA_Lanker-1_1_T-1.xml"] {
        let s = scene(rel);
        for e in INTERACT_EXPRS {
            check(&s, e);
        }
    }
}

#[test]
fn road_edge_gradients() {
    // AV2 decides the side by drivable areas, CommonRoad by lanelet surfaces.
    for rel in ["av2", US101] {
        let s = scene(rel);
        for e in EDGE_EXPRS {
            check(&s, e);
        }
    }
}

#[test]
fn math_and_series_gradients() {
    let s = scene(US101);
    for e in MATH_EXPRS.iter().chain(SERIES_EXPRS) {
        check(&s, e);
    }
}

/// `hold(b)` keeps every value and removes b's coordinates from the gradient, in every kind
/// of term that reads two agents; the same terms without it do move b.
#[test]
fn held_agents_get_no_gradient() {
    let s = scene(US101);
    let (a, b) = pair(&s);
    let bi = s.agents.iter().position(|x| x.id == b).unwrap();
    let params = Params::parse(&[format!("A={a}"), format!("B={b}")]).unwrap();
    let traj = Trajectories::filled(&s);
    let b_vars: Vec<u32> = (0..traj.layout.steps)
        .flat_map(|t| {
            [
                crate::cost::trajectory::Coord::X,
                crate::cost::trajectory::Coord::Y,
                crate::cost::trajectory::Coord::Heading,
            ]
            .map(|c| traj.layout.var(bi, t, c))
        })
        .collect();
    let eval = |body: &str| {
        let src = format!("let a = agent(A); let b = agent(B);\n{body}");
        let script = CostScript::compile(&src, "hold", s.clone(), &params, &Limits::default())
            .unwrap_or_else(|e| panic!("{body}: {e}"));
        let r = script.evaluate(&traj).unwrap();
        let t = r.terms[0].clone();
        let on_b = t
            .grad
            .iter()
            .filter(|(v, g)| b_vars.contains(v) && *g != 0.0)
            .count();
        (
            t.value,
            on_b,
            t.grad.iter().any(|(v, g)| !b_vars.contains(v) && *g != 0.0),
        )
    };
    for body in [
        "let p = a.lane_path(); term(\"t\", square(gap(a, B_, p) - 5.0).sum());",
        "term(\"t\", square(distance(a, B_) - 3.0).sum());",
        "term(\"t\", relu(4.0 - clearance(a, B_)).sum());",
        "term(\"t\", no_collision_cost([a, B_], 30.0));",
        "let p = a.lane_path(); term(\"t\", square(B_.frenet(p).d).sum() + square(a.frenet(p).d).sum());",
        "term(\"t\", square(B_.speed - a.speed).sum());",
    ] {
        let (v_free, on_b_free, _) = eval(&body.replace("B_", "b"));
        let (v_held, on_b_held, on_a) = eval(&body.replace("B_", "hold(b)"));
        assert_eq!(v_free, v_held, "{body}: holding changed the value");
        assert!(on_b_free > 0, "{body}: the free term does not move b (the test cannot fail)");
        assert_eq!(on_b_held, 0, "{body}: the held agent still gets gradient");
        assert!(on_a, "{body}: the other agent lost its gradient");
    }
}
