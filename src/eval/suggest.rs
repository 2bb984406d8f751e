//! Choosing the agents of a behaviour request from a scene's geometry ([`suggest`]), so that
//! success rates over many scenes need no hand-picked ids; each choice asks only for what a
//! driver there could plausibly do within the horizon.

use super::behaviors::{driven_route, lane_of, merges, Behavior, Routes};
use crate::cost::{ParamValue, Params};
use crate::eval::kinematic::KinematicLimits;
use crate::geom::Point;
use crate::scene::{Agent, AgentType, LanePath, Scene, Turn};

/// A vehicle `suggest` may name, with its lane at the current step and that lane's path.
type Candidate<'a> = (&'a Agent, i64, std::rc::Rc<LanePath>);

/// Speed (m/s) above which `suggest` counts a car as moving.
const MOVING: f64 = 2.0;
/// Seconds a cutter needs, once its rear is past the victim's front bumper, to move across
/// into the victim's lane (`suggest` for `cut_in`).
const CUT_IN_MERGE: f64 = 1.0;
/// The bumper-to-bumper gap (metres) `suggest` asks a follower to keep.
const FOLLOW_GAP: f64 = 10.0;

/// Farthest a neighbouring lane's centre may lie from the recorded end (m) for `target_point`:
/// a lane beside it, not one that stops short of it.
const TARGET_BESIDE: f64 = 5.0;

/// How far inside the road edge (m, centre to edge) `suggest` looks for a car to drive off
/// it: the outer lane.
const OFF_ROAD_REACH: f64 = 4.0;

/// Farthest (m) a car may stand across its route for `suggest` to ask it to turn along it:
/// half a lane. Farther, it is off the lane (SUMO's cars cross junctions off the map's
/// lanes) and the turn asks it to move across first.
const TURN_ON_ROUTE: f64 = 1.75;
/// Lateral acceleration (m/s², below the judge's 5) and braking (m/s², as `yield`'s) within
/// which a car asked to turn must be able to take the corner: at 14 m/s, 3 m before a
/// corner of 8 m radius, it could only turn by braking at 9-12 m/s² or leaving its route.
const TURN_LATERAL: f64 = 4.0;
/// See [`TURN_LATERAL`].
const TURN_BRAKE: f64 = 3.0;
/// Metres over which [`can_take_turn`] averages the corner's curvature (a lane's vertices are
/// metres apart; the path's curvature between them is not the car's).
const TURN_CURVE_SPAN: f64 = 4.0;

/// Whether a car at arc length `s0` on `route` doing `v` m/s can be at a speed it can corner
/// at ([`TURN_LATERAL`]) everywhere from here to the end of its turn, braking at
/// [`TURN_BRAKE`] at most.
fn can_take_turn(route: &LanePath, s0: f64, v: f64, end: f64) -> bool {
    let f = &route.frenet;
    let half = 0.5 * TURN_CURVE_SPAN;
    let steps = ((end - s0) / 0.5).ceil().max(0.0) as usize;
    (0..=steps).all(|i| {
        let s = s0 + (end - s0) * i as f64 / steps.max(1) as f64;
        let bend = crate::geom::wrap_angle(f.heading_at(s + half) - f.heading_at(s - half));
        let kappa = bend.abs() / TURN_CURVE_SPAN;
        v * v - 2.0 * TURN_BRAKE * (s - s0) <= TURN_LATERAL / kappa.max(1e-9)
    })
}

/// Braking and backing up as [`suggest`] times a `reverse` request: to a stop at
/// [`REVERSE_BRAKE`], then backwards at [`REVERSE_ACCEL`] up to [`REVERSE_SPEED`] (the script's
/// default speed), until [`REVERSE_MARGIN`] beyond the checker's metre behind the start.
const REVERSE_BRAKE: f64 = 4.0;
/// See [`REVERSE_BRAKE`].
const REVERSE_ACCEL: f64 = 2.0;
/// See [`REVERSE_BRAKE`].
const REVERSE_SPEED: f64 = 2.0;
/// See [`REVERSE_BRAKE`].
const REVERSE_MARGIN: f64 = 0.5;

/// Whether `a` can stop and back up 1 m behind where it is now (plus [`REVERSE_MARGIN`])
/// within `horizon` seconds less 0.5 s, and the nearest vehicle behind it in its lane (a box
/// overlapping its corridor) can stop at [`REVERSE_BRAKE`] short of where it backs to, 1 m
/// clear.
fn can_back_up(scene: &Scene, a: &Agent, horizon: f64) -> bool {
    let c = scene.meta.current_step;
    let s = a.states[c];
    let v = s.speed();
    // Forward while braking, then back past the start.
    let ahead = v * v / (2.0 * REVERSE_BRAKE);
    let back = ahead + 1.0 + REVERSE_MARGIN;
    let ramp = REVERSE_SPEED * REVERSE_SPEED / (2.0 * REVERSE_ACCEL);
    let backing = if back <= ramp {
        (2.0 * back / REVERSE_ACCEL).sqrt()
    } else {
        REVERSE_SPEED / REVERSE_ACCEL + (back - ramp) / REVERSE_SPEED
    };
    if v / REVERSE_BRAKE + backing > horizon - 0.5 {
        return false;
    }
    let dir = Point::new(s.heading.cos(), s.heading.sin());
    let room = 1.0 + REVERSE_MARGIN + 1.0;
    scene
        .agents
        .iter()
        .filter(|o| o.id != a.id && o.agent_type == AgentType::Vehicle && o.is_valid(c))
        .all(|o| {
            let r = o.states[c].position() - s.position();
            let (lon, lat) = (r.dot(&dir), dir.x * r.y - dir.y * r.x);
            let behind = lon < 0.0 && lat.abs() < 0.5 * (a.width + o.width);
            let gap = -lon - 0.5 * (a.length + o.length);
            let vo = o.states[c].speed();
            !behind || gap >= room + vo * vo / (2.0 * REVERSE_BRAKE)
        })
}

/// Agents for which a behaviour is a meaningful request in `scene`, chosen by geometry alone,
/// so that success rates over many scenes need no hand-picked ids (`None` when the scene has
/// no suitable agent). Candidates are vehicles observed at the current step and through the
/// recorded future, on a lane; ties go to the one nearest the scene's ego (or first vehicle).
/// `horizon` is the number of future steps the methods simulate, which may exceed the
/// recording's (`eval --horizon`, a model's horizon): requests are timed by it.
///
/// - one-vehicle behaviours: the nearest candidate; lane changes and `rightmost_lane` need a
///   lane on that side (for `rightmost_lane`, not already the rightmost); `speed_limit` asks for
///   80 % of its current speed from the time braking to it at 2.5 m/s² takes; `target_point`
///   for the point level with its recorded end on the centre line of the lane beside it (left
///   where there is one, else right; within 5 m of the end); `stop` within 60 % of the horizon or the
///   time braking at 4 m/s² takes, if longer, for the nearest vehicle that can then stand
///   still for the last 0.5 s; `reverse` for the nearest one that can brake to a stop at 4 m/s²
///   and back up 1.5 m behind its start (at 2 m/s² up to 2 m/s) within the horizon less 0.5 s,
///   with room for the vehicle behind it in its lane to stop at 4 m/s² 1 m short of that;
/// - `cut_in`: a victim and a cutter moving at 2 m/s or more in an adjacent lane within 15 m
///   along the victim's path that can end 5 m (bumper to bumper) ahead of the victim holding its speed, accelerating at
///   2.5 m/s² and no faster than 0.75 of the sprint bound allows (the kinematic checker's and
///   realism's bounds), and get its rear past the victim's front bumper a second before the
///   horizon ends, to move across: a slower car far behind cannot cut in plausibly;
/// - `follow`: a leader ahead in the follower's lane within 60 m, asking for a 10 m gap that
///   the follower can bring within the checker's 5–20 m by half the horizon with the leader
///   holding its speed, braking at up to 3 m/s² (never backing up) or speeding up at 2 m/s²;
/// - `off_road`: the nearest car moving at 2 m/s or more with its centre within 4 m of the
///   road edge (a car queued at a light, or boxed in mid-road, has no way off it);
/// - `yield`: two vehicles whose routes (the lane paths, straight on, left or right at forks,
///   that their recorded ends lie nearest) meet ahead of both, within 1.2 times the distance
///   the yielder covers over the horizon at its current speed plus 20 m, and that the other,
///   moving at 2 m/s or more, passes by 2 m within the horizon at its current speed, while the
///   yielder, moving too, would get there first at its own but can hold back 2 m before the
///   point until then braking at 3 m/s² at most (yielding to a car that waits at a light, is
///   too far away to arrive or passes first anyway asks for nothing; yielding from the
///   junction's edge asks for an emergency stop);
/// - `accident`: the nearest pair; `no_collisions`: no agents;
/// - `turn_left` / `turn_right`: the nearest car whose route (that way at forks) has such a
///   turn ahead, whose middle it can reach within the horizon less a second; it stands
///   within half a lane of the route, and can slow to a speed it can corner at
///   (4 m/s² across) braking at 3 m/s² at most.
pub fn suggest(b: Behavior, scene: &Scene, horizon: usize) -> Option<Params> {
    let c = scene.meta.current_step;
    let n = scene.num_steps();
    let horizon = horizon as f64 * scene.meta.dt;
    // Recorded over the whole horizon without reaching a map exit: a car that leaves the
    // scene within it (every method's car leaves there too) cannot show a behaviour.
    let kept = scene.retire_exited();
    let routes = Routes::default();
    let mut cands: Vec<Candidate> = scene
        .agents
        .iter()
        .zip(&kept.agents)
        .filter(|(a, k)| a.agent_type == AgentType::Vehicle && (c..n).all(|t| k.is_valid(t)))
        .map(|(a, _)| a)
        // The recording must end on a mapped lane: where the map stops short of the agent's
        // future (NGSIM maps cover a few hundred metres), no lane-based behaviour can be
        // judged at the end of the horizon, whatever the simulator does.
        .filter(|a| lane_of(scene, a, n - 1).is_some())
        .filter_map(|a| {
            Some((
                a,
                lane_of(scene, a, c)?,
                routes.route(scene, a, Turn::Straight)?,
            ))
        })
        .collect();
    let centre = scene
        .meta
        .ego
        .and_then(|e| scene.agent(e))
        .or_else(|| cands.first().map(|x| x.0))?
        .states[c]
        .position();
    cands.sort_by(|x, y| {
        let d = |a: &Agent| (a.states[c].position() - centre).norm();
        d(x.0).total_cmp(&d(y.0)).then(x.0.id.cmp(&y.0.id))
    });
    let g = scene.map.graph();
    let p = |kv: &[(&str, f64)]| Some(Params::numbers(kv));
    match b {
        Behavior::NoCollisions => p(&[]),
        // The limit is below the current speed; braking to it at a moderate 2.5 m/s² takes
        // time (a 14 m/s car needs 1.2 s), which the request allows.
        Behavior::SpeedLimit => {
            let (a, _, _) = cands.first()?;
            let v = a.states[c].speed();
            p(&[
                ("vehicle", a.id as f64),
                ("limit", 0.8 * v),
                ("from", (0.2 * v / 2.5 * 10.0).ceil() / 10.0),
            ])
        }
        // The point level with the recorded end in the lane beside it (the left one where
        // there is one): a lane change, ended where the recorded car ended. The request 20 m
        // to the left it replaces crossed five lanes, or the road's edge, within 4 s.
        Behavior::TargetPoint => cands.iter().find_map(|(a, _, _)| {
            let end = a.states[n - 1].position();
            let lane = lane_of(scene, a, n - 1)?;
            let centre = &scene
                .map
                .lane(g.left(lane).or_else(|| g.right(lane))?)?
                .centerline;
            let hit = centre.nearest(&end);
            // Beside the end, not where a neighbour that stops short of it ends.
            (hit.distance <= TARGET_BESIDE).then_some(())?;
            let at = centre.point_at(hit.s);
            p(&[("vehicle", a.id as f64), ("x", at.x), ("y", at.y)])
        }),
        Behavior::LaneChangeLeft => cands
            .iter()
            .find(|x| g.left(x.1).is_some())
            .and_then(|x| p(&[("vehicle", x.0.id as f64)])),
        Behavior::LaneChangeRight => cands
            .iter()
            .find(|x| g.right(x.1).is_some())
            .and_then(|x| p(&[("vehicle", x.0.id as f64)])),
        // A lane change takes about 2 s, so the nearest vehicle with at most one lane per 2 s
        // of horizon to go (at least one): five lanes across a US-101 in 4 s is no behaviour
        // a driver shows.
        Behavior::RightmostLane => {
            let reach = ((horizon / 2.0).floor() as usize).max(1);
            let lanes_to_right = |mut l: i64| {
                let mut k = 0;
                while let Some(r) = g.right(l).filter(|_| k <= reach) {
                    (l, k) = (r, k + 1);
                }
                k
            };
            cands
                .iter()
                .find(|x| (1..=reach).contains(&lanes_to_right(x.1)))
                .and_then(|x| p(&[("vehicle", x.0.id as f64)]))
        }
        Behavior::Weave => cands.first().and_then(|x| p(&[("vehicle", x.0.id as f64)])),
        // A car that can stop, then back up past the checker's metre within the horizon, with
        // room behind it for the car that follows to stop: a 15 m/s car cannot do it in
        // 4 s, and one with a car on its bumper can only back into it.
        Behavior::Reverse => cands
            .iter()
            .find(|x| can_back_up(scene, x.0, horizon))
            .and_then(|x| p(&[("vehicle", x.0.id as f64)])),
        // A moving car within a lane of the road's edge. A car at rest in a queue, or one in
        // a middle lane with traffic on both sides, has no way off the road a driver could
        // take in a few seconds (held-out NGSIM: most failed requests were such cars).
        Behavior::OffRoad => cands
            .iter()
            .find(|x| {
                let s = x.0.states[c];
                s.speed() >= MOVING
                    && scene
                        .map
                        .signed_distance_to_road_edge(s.position())
                        .is_some_and(|d| d >= -OFF_ROAD_REACH)
            })
            .and_then(|x| p(&[("vehicle", x.0.id as f64)])),
        // The 4 s default assumes WOMD's 8 s future; a car at 18 m/s cannot stop within
        // 2.4 s, nor without braking harder than the script allows.
        Behavior::Stop => cands.iter().find_map(|x| {
            let braking = x.0.states[c].speed() / 4.0;
            let within = ((0.6 * horizon).max(braking) * 10.0).ceil() / 10.0;
            (within <= horizon - 0.5)
                .then(|| p(&[("vehicle", x.0.id as f64), ("within", within)]))?
        }),
        Behavior::CutIn => cut_in(scene, &cands, horizon),
        Behavior::Follow => follow(scene, &cands, horizon),
        Behavior::Yield => yield_to(scene, &cands, &routes, horizon),
        // The nearest car whose route has the turn ahead, with the middle of the corner within
        // what it covers over the horizon less a second, speeding up at 1.5 m/s² at most, and
        // not yet reached: a car already round the corner has nothing left to do.
        Behavior::TurnLeft | Behavior::TurnRight => {
            let way = b.turn().expect("a turning behaviour");
            cands.iter().find_map(|(a, _, _)| {
                let route = routes.route(scene, a, way)?;
                let span = route.next_turn(&scene.map, way)?;
                let here = route.frenet.project(a.states[c].position());
                let to_go = span.middle - here.s;
                let t = (horizon - 1.0).max(0.0);
                let v = a.states[c].speed();
                let reach = v * t + 0.75 * t * t;
                (to_go > 0.0
                    && to_go + 1.0 <= reach
                    && here.d.abs() <= TURN_ON_ROUTE
                    && can_take_turn(&route, here.s, v, span.end))
                .then(|| p(&[("vehicle", a.id as f64)]))?
            })
        }
        Behavior::Accident => {
            let (a, _, _) = cands.first()?;
            let (b, _, _) = cands.get(1)?;
            p(&[("attacker", a.id as f64), ("target", b.id as f64)])
        }
    }
}

/// `cut_in`: see [`suggest`].
fn cut_in(scene: &Scene, cands: &[Candidate], horizon: f64) -> Option<Params> {
    let c = scene.meta.current_step;
    let g = scene.map.graph();
    let p = |kv: &[(&str, f64)]| Some(Params::numbers(kv));
    let lim = KinematicLimits::default();
    let along = Along::default();
    for (victim, lv, path) in cands {
        let sv = along.of(path, victim, c);
        for (cutter, lc, _) in cands {
            let adjacent =
                g.left_neighbors(*lv).contains(lc) || g.right_neighbors(*lv).contains(lc);
            let sc = along.of(path, cutter, c);
            let speed = |a: &Agent| a.states[c].vx.hypot(a.states[c].vy);
            let (vc, vv) = (speed(cutter), speed(victim));
            // Speed gain at 2.5 m/s² up to the cap, as a ramp over the horizon.
            let cap = vc + 0.75 * (lim.sprint_bound(vc, 0.0) - vc).max(0.0);
            // The bumper-to-bumper gap the cutter can open ahead of the victim in `t`
            // seconds, the victim holding its speed.
            let ahead_by = |t: f64| {
                let gain = (2.5 * t).min(cap - vc);
                sc - sv - 0.5 * (cutter.length + victim.length) + (vc - vv) * t + 0.5 * gain * t
            };
            // A cutter at rest (a queue at a light) does not cut in. It must also clear the
            // victim's front bumper CUT_IN_MERGE before the horizon ends: one only level at
            // the end has no time left to move across, and guidance merges it behind the
            // victim instead, where contact holds it back (held-out NGSIM: the cutters that
            // ended 9-11 m short started 10 m behind).
            if cutter.id != victim.id
                && adjacent
                && vc >= MOVING
                && (sc - sv).abs() <= 15.0
                && ahead_by(horizon) >= 5.0
                && ahead_by((horizon - CUT_IN_MERGE).max(0.0)) >= 0.0
            {
                return p(&[("cutter", cutter.id as f64), ("victim", victim.id as f64)]);
            }
        }
    }
    None
}

/// Agents' arc lengths along routes, each projected once: candidates on one lane share one
/// route ([`Routes`]), and projecting every other candidate onto it once per pair made
/// `follow` on a 100 km road take 32 s for 300 cars (each projection walks the whole path).
#[derive(Default)]
struct Along(std::cell::RefCell<std::collections::HashMap<(*const LanePath, i64), f64>>);

impl Along {
    /// `a`'s arc length along `path` at step `c`.
    fn of(&self, path: &std::rc::Rc<LanePath>, a: &Agent, c: usize) -> f64 {
        let key = (std::rc::Rc::as_ptr(path), a.id);
        if let Some(&s) = self.0.borrow().get(&key) {
            return s;
        }
        let s = path.frenet.project(a.states[c].position()).s;
        self.0.borrow_mut().insert(key, s);
        s
    }
}

/// `follow`: see [`suggest`].
fn follow(scene: &Scene, cands: &[Candidate], horizon: f64) -> Option<Params> {
    let c = scene.meta.current_step;
    let p = |kv: &[(&str, f64)]| Some(Params::numbers(kv));
    let want = FOLLOW_GAP;
    // The checker wants the bumper gap within gap/2 .. 2·gap over the last half of
    // the horizon. With the leader holding its speed, the follower can open the gap
    // at most by braking to a standstill at 3 m/s² and close it at most by speeding
    // up at 2 m/s², never backing up: a car queued 3 m behind a standing one cannot
    // drop back to 5 m.
    let reachable = |f: &Agent, l: &Agent, ahead: f64| {
        let half = horizon / 2.0;
        let gap0 = ahead - 0.5 * (f.length + l.length);
        let (vf, vl) = (f.states[c].speed(), l.states[c].speed());
        let stop = (vf / 3.0).min(half);
        let widest = gap0 + vl * half - (vf * stop - 1.5 * stop * stop);
        let closest = gap0 + vl * half - (vf * half + half * half);
        widest >= want / 2.0 && closest <= 2.0 * want
    };
    let along = Along::default();
    for (f, lf, path) in cands {
        let sf = along.of(path, f, c);
        for (l, ll, _) in cands {
            let ahead = along.of(path, l, c) - sf;
            if l.id != f.id && ll == lf && ahead > 0.0 && ahead <= 60.0 && reachable(f, l, ahead) {
                return p(&[
                    ("follower", f.id as f64),
                    ("leader", l.id as f64),
                    ("gap", want),
                ]);
            }
        }
    }
    None
}

/// `yield`: see [`suggest`].
fn yield_to(scene: &Scene, cands: &[Candidate], routes: &Routes, horizon: f64) -> Option<Params> {
    let c = scene.meta.current_step;
    // How far the yielder could get over the horizon: its current speed with some
    // slack (2.5 m/s² of acceleration).
    let reach = |a: &Agent| 1.2 * a.states[c].speed() * horizon + 20.0;
    // The other must be coming: moving, and past the meeting point (by the checker's
    // 2 m) within the horizon at its current speed. Yielding to a car that is waiting
    // at a light, or that is too far to arrive, asks for nothing a driver can show.
    let coming = |o: &Agent, to_go: f64| {
        let v = o.states[c].speed();
        v >= MOVING && to_go + 2.0 <= v * horizon
    };
    // And the yielder, holding its speed, would get there first (otherwise the other
    // passes first by itself and "yield" asks for nothing either), yet can hold back,
    // braking at most 3 m/s², where the yield script stops it (front bumper 2 m short
    // of the meeting point, 10 m more where the lanes merge) until the other's rear
    // bumper is 2 m past: a car already at the junction cannot yield without an
    // emergency stop, and a request the script can only meet that way is not offered.
    let first = |a: &Agent, a_to_go: f64, o: &Agent, o_to_go: f64, merge: bool| {
        let (va, vo) = (a.states[c].speed(), o.states[c].speed());
        let stop_short = a.length / 2.0 + 2.0 + if merge { 10.0 } else { 0.0 };
        let (room, other_past) = (a_to_go - stop_short, (o_to_go + o.length / 2.0 + 2.0) / vo);
        let brake = 3.0;
        let holds = room > 0.0
            && (va * va / (2.0 * brake) <= room
                || (va - (va * va - 2.0 * brake * room).sqrt()) / brake >= other_past);
        va >= MOVING && a_to_go / va <= o_to_go / vo && holds
    };
    // Each car's route as recorded: a car that turned left at the junction meets the
    // oncoming traffic there, which its path straight on never does.
    let driven: Vec<(&Agent, Turn, std::rc::Rc<LanePath>)> = cands
        .iter()
        .filter_map(|(a, _, _)| driven_route(scene, a, routes).map(|(t, p)| (*a, t, p)))
        .collect();
    for (a, ta, pa) in &driven {
        let sa0 = pa.frenet.project(a.states[c].position()).s;
        for (o, to, po) in &driven {
            if o.id == a.id {
                continue;
            }
            let so0 = po.frenet.project(o.states[c].position()).s;
            if let Some((sa, so, _)) = pa.first_meeting(po) {
                if sa > sa0
                    && so > so0
                    && sa - sa0 <= reach(a)
                    && coming(o, so - so0)
                    && first(a, sa - sa0, o, so - so0, merges(pa, po))
                {
                    let mut p =
                        Params::numbers(&[("yielder", a.id as f64), ("other", o.id as f64)]);
                    p.set("yielder_turn", ParamValue::Str(ta.word().into()));
                    p.set("other_turn", ParamValue::Str(to.word().into()));
                    return Some(p);
                }
            }
        }
    }
    None
}
