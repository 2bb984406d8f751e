//! Lane paths and agents' Frenet coordinates on them.

use std::rc::Rc;

use rhai::{Array, Dynamic, Engine};

use super::agents::AgentRef;
use super::{doc, err, number, turn, DocEntry, RResult, Shared};
use crate::cost::series::{Builder, Series};
use crate::cost::trajectory::Coord;
use crate::geom::Point;
use crate::scene::{LanePath, Turn};

/// Half lane width assumed where a lane has no boundaries (WOMD), metres.
pub const DEFAULT_HALF_WIDTH: f64 = 1.8;

/// Metres of path kept behind the requested lane, so that agents approaching it project onto
/// the path rather than its straight extension.
const BEHIND: f64 = 50.0;

/// Metres of path ahead of an agent for `a.lane_path()`.
const AGENT_AHEAD: f64 = 300.0;

/// A script's handle on a lane path, with the lane's half width along it.
#[derive(Debug, Clone)]
pub struct PathRef {
    pub(crate) path: Rc<LanePath>,
    /// `(s, half width)` at every vertex of the path.
    pub(crate) half_width: Rc<Vec<(f64, f64)>>,
}

impl PathRef {
    /// Half width and its derivative w.r.t. s at `s` (held constant beyond the ends).
    fn half_width_at(&self, s: f64) -> (f64, f64) {
        let hw = &self.half_width;
        let k = hw.partition_point(|(x, _)| *x <= s);
        if k == 0 {
            return (hw[0].1, 0.0);
        }
        if k >= hw.len() {
            return (hw[hw.len() - 1].1, 0.0);
        }
        let ((s0, w0), (s1, w1)) = (hw[k - 1], hw[k]);
        let slope = if s1 > s0 { (w1 - w0) / (s1 - s0) } else { 0.0 };
        (w0 + slope * (s - s0), slope)
    }
}

/// An agent's Frenet coordinates on a path.
#[derive(Debug, Clone)]
pub struct FrenetRef {
    pub(crate) s: Series,
    pub(crate) d: Series,
    pub(crate) to_left: Series,
    pub(crate) to_right: Series,
}

/// Refuses a path length outside (0, 100000] metres, as the script gave it.
fn check_length(ahead: f64) -> RResult<()> {
    if !(ahead.is_finite() && ahead > 0.0 && ahead <= 100_000.0) {
        return err(format!(
            "lane_path: length {} must be in (0, 100000] metres",
            crate::geom::num(ahead)
        ));
    }
    Ok(())
}

fn make_path(shared: &Shared, lane: i64, ahead: f64, behind: f64, t: Turn) -> RResult<PathRef> {
    check_length(ahead)?;
    build_path(shared, lane, ahead, behind, t)
}

fn build_path(shared: &Shared, lane: i64, ahead: f64, behind: f64, t: Turn) -> RResult<PathRef> {
    let key = (lane, ahead.to_bits(), behind.to_bits(), t);
    let mut ctx = shared.borrow_mut();
    let path = match ctx.paths.get(&key) {
        Some(p) => p.clone(),
        None => {
            let p = match ctx.scene.map.lane_path(lane, ahead, behind, t) {
                Ok(p) => Rc::new(p),
                Err(e) => return err(format!("lane_path: {e}")),
            };
            ctx.paths.insert(key, p.clone());
            p
        }
    };
    let ptr = Rc::as_ptr(&path) as usize;
    let half_width = match ctx.widths.get(&ptr) {
        Some(w) => w.clone(),
        None => {
            let w = Rc::new(half_widths(&ctx.scene.map, &path));
            ctx.widths.insert(ptr, w.clone());
            w
        }
    };
    Ok(PathRef { path, half_width })
}

fn half_widths(map: &crate::scene::Map, path: &LanePath) -> Vec<(f64, f64)> {
    let line = path.frenet.polyline();
    line.points()
        .iter()
        .zip(line.arc_lengths())
        .map(|(p, &s)| {
            let lane = map.lane(path.lane_at_s(s)).expect("path lanes exist");
            let w = match (&lane.left_boundary, &lane.right_boundary) {
                (Some(l), Some(r)) => 0.5 * (l.distance_to(p) + r.distance_to(p)),
                _ => DEFAULT_HALF_WIDTH,
            };
            (s, w)
        })
        .collect()
}

/// The lane an agent is in at the current step (nearest lane going its way).
pub(crate) fn agent_lane(shared: &Shared, a: &AgentRef) -> RResult<i64> {
    let ctx = shared.borrow();
    let s = ctx.scene.agents[a.idx].states[ctx.scene.meta.current_step];
    if !s.valid {
        return err(format!(
            "agent {} is not observed at the current step, so it has no lane",
            a.id
        ));
    }
    match ctx.scene.map.lane_at(Point::new(s.x, s.y), s.heading) {
        Some(l) => Ok(l),
        None => err(format!(
            "agent {} is near no lane going its way at the current step",
            a.id
        )),
    }
}

fn agent_path(shared: &Shared, a: &AgentRef, ahead: f64, turn: Turn) -> RResult<PathRef> {
    // The length the script gave, not with the agent's place on its lane added: 100000 was
    // refused as "length 100002".
    check_length(ahead)?;
    let lane = agent_lane(shared, a)?;
    let along = {
        let ctx = shared.borrow();
        let s = ctx.scene.agents[a.idx].states[ctx.scene.meta.current_step];
        ctx.scene
            .map
            .lane(lane)
            .expect("lane_at returns map lanes")
            .centerline
            .nearest(&Point::new(s.x, s.y))
            .s
    };
    build_path(shared, lane, along + ahead, BEHIND, turn)
}

/// Frenet series of agent `a` on `p`.
pub(crate) fn frenet(shared: &Shared, a: AgentRef, p: &PathRef) -> FrenetRef {
    let xs = super::agents::coord_series(shared, a, Coord::X);
    let ys = super::agents::coord_series(shared, a, Coord::Y);
    let (x, y) = (&xs.0, &ys.0);
    let n = x.val.len();
    let mk = || Builder::new(n, x.head, x.dt, x.time0);
    let (mut bs, mut bd, mut bl, mut br) = (mk(), mk(), mk(), mk());
    for k in 0..n {
        let valid = x.valid[k] && y.valid[k];
        if !valid {
            for b in [&mut bs, &mut bd, &mut bl, &mut br] {
                b.push_row(0.0, false, std::iter::empty());
            }
            continue;
        }
        let f = p.path.frenet.project(Point::new(x.val[k], y.val[k]));
        let (hw, slope) = p.half_width_at(f.s);
        // Agent series rows are [(x var, 1)] and [(y var, 1)] (or empty for history).
        let (rx, ry) = (xs.row(k), ys.row(k));
        let row = |gx: f64, gy: f64| {
            let mut r: Vec<(u32, f64)> = Vec::with_capacity(2);
            if let (Some(&(vx, _)), Some(&(vy, _))) = (rx.first(), ry.first()) {
                r.push((vx, gx));
                r.push((vy, gy));
            }
            r
        };
        bs.push_row(f.s, true, row(f.ds[0], f.ds[1]));
        bd.push_row(f.d, true, row(f.dd[0], f.dd[1]));
        bl.push_row(
            hw - f.d,
            true,
            row(slope * f.ds[0] - f.dd[0], slope * f.ds[1] - f.dd[1]),
        );
        br.push_row(
            hw + f.d,
            true,
            row(slope * f.ds[0] + f.dd[0], slope * f.ds[1] + f.dd[1]),
        );
    }
    FrenetRef {
        s: bs.build(),
        d: bd.build(),
        to_left: bl.build(),
        to_right: br.build(),
    }
}

/// The first point along `a` where it touches `b`, with both arc lengths.
fn conflict(a: &PathRef, b: &PathRef) -> Option<(f64, f64, Point)> {
    a.path.first_meeting(&b.path)
}

pub(super) fn register(e: &mut Engine, shared: &Shared, docs: &mut Vec<DocEntry>) {
    const S: &str = "Frenet frame";
    doc(docs, S, "lane_path(lane, length) -> Path", "The lane extended through successors (straight on at forks) to `length` metres from its start, and 50 m back through predecessors.");
    let sh = shared.clone();
    e.register_fn("lane_path", move |lane: i64, len: Dynamic| {
        make_path(
            &sh,
            lane,
            number(&len, "lane_path length")?,
            BEHIND,
            Turn::Straight,
        )
    });
    doc(
        docs,
        S,
        "lane_path(lane, length, turn) -> Path",
        "The same, taking \"left\", \"right\" or \"straight\" at forks.",
    );
    let sh = shared.clone();
    e.register_fn("lane_path", move |lane: i64, len: Dynamic, t: &str| {
        make_path(
            &sh,
            lane,
            number(&len, "lane_path length")?,
            BEHIND,
            turn(t)?,
        )
    });
    doc(
        docs,
        S,
        "a.lane_path() -> Path",
        "The path of the agent's current lane, from 50 m behind it to 300 m ahead of the agent.",
    );
    let sh = shared.clone();
    e.register_fn("lane_path", move |a: &mut AgentRef| {
        agent_path(&sh, a, AGENT_AHEAD, Turn::Straight)
    });
    doc(
        docs,
        S,
        "a.lane_path(length) -> Path",
        "The same with `length` metres ahead of the agent.",
    );
    let sh = shared.clone();
    e.register_fn("lane_path", move |a: &mut AgentRef, len: Dynamic| {
        agent_path(&sh, a, number(&len, "lane_path length")?, Turn::Straight)
    });
    doc(
        docs,
        S,
        "a.lane_path(length, turn) -> Path",
        "The same, taking \"left\", \"right\" or \"straight\" at forks (a turning agent's route).",
    );
    let sh = shared.clone();
    e.register_fn(
        "lane_path",
        move |a: &mut AgentRef, len: Dynamic, t: &str| {
            agent_path(&sh, a, number(&len, "lane_path length")?, turn(t)?)
        },
    );
    doc(docs, S, "p.lanes -> array of int, p.length -> float, p.origin_s -> float", "The path's lanes in driving order, its length, and the s at which the requested lane starts.");
    e.register_get("lanes", |p: &mut PathRef| {
        p.path
            .lanes
            .iter()
            .map(|l| Dynamic::from(*l))
            .collect::<Array>()
    });
    e.register_get("length", |p: &mut PathRef| p.path.frenet.length());
    e.register_get("origin_s", |p: &mut PathRef| p.path.origin_s());
    doc(
        docs,
        S,
        "a.frenet(path) -> Frenet",
        "The agent's Frenet coordinates on the path over the future steps (any agent on any path).",
    );
    let sh = shared.clone();
    e.register_fn("frenet", move |a: &mut AgentRef, p: PathRef| {
        frenet(&sh, *a, &p)
    });
    doc(docs, S, "f.s -> Series, f.d -> Series", "Arc length along the path and lateral offset from its centre line (left positive), metres.");
    e.register_get("s", |f: &mut FrenetRef| f.s.clone());
    e.register_get("d", |f: &mut FrenetRef| f.d.clone());
    doc(docs, S, "f.to_left -> Series, f.to_right -> Series", "Distance from the agent's centre to the lane's left / right boundary (positive inside the lane; half width 1.8 m where the map has no boundaries).");
    e.register_get("to_left", |f: &mut FrenetRef| f.to_left.clone());
    e.register_get("to_right", |f: &mut FrenetRef| f.to_right.clone());
    doc(docs, S, "conflict(path_a, path_b) -> map or ()", "Where path_a first meets path_b (a crossing or a merge): #{s_a, s_b, x, y} with each path's arc length there, or () if they never meet.");
    e.register_fn("conflict", |a: PathRef, b: PathRef| -> Dynamic {
        match conflict(&a, &b) {
            Some((sa, sb, p)) => {
                let mut m = rhai::Map::new();
                m.insert("s_a".into(), Dynamic::from(sa));
                m.insert("s_b".into(), Dynamic::from(sb));
                m.insert("x".into(), Dynamic::from(p.x));
                m.insert("y".into(), Dynamic::from(p.y));
                Dynamic::from(m)
            }
            None => Dynamic::UNIT,
        }
    });
    doc(docs, S, "p.next_turn(turn) -> map or ()", "The first lane on the path (from its requested lane on) that turns \"left\" or \"right\": #{lane, start, middle, end, angle}, with the arc lengths where it starts, where the path has turned half its angle (what a car must pass to have turned) and where it ends, and its heading change in radians (left positive); () if no lane on the path turns that way.");
    let sh = shared.clone();
    e.register_fn(
        "next_turn",
        move |p: &mut PathRef, t: &str| -> RResult<Dynamic> {
            let way = turn(t)?;
            if way == Turn::Straight {
                return err("next_turn: the turn must be \"left\" or \"right\"".to_string());
            }
            let ctx = sh.borrow();
            Ok(match p.path.next_turn(&ctx.scene.map, way) {
                Some(span) => {
                    let mut m = rhai::Map::new();
                    m.insert("lane".into(), Dynamic::from(span.lane));
                    m.insert("start".into(), Dynamic::from(span.start));
                    m.insert("middle".into(), Dynamic::from(span.middle));
                    m.insert("end".into(), Dynamic::from(span.end));
                    m.insert("angle".into(), Dynamic::from(span.angle));
                    Dynamic::from(m)
                }
                None => Dynamic::UNIT,
            })
        },
    );
    e.register_fn("to_string", |p: &mut PathRef| {
        format!("path over lanes {:?}", p.path.lanes)
    });
    e.register_fn("to_debug", |p: &mut PathRef| {
        format!("Path({:?}, {:.1} m)", p.path.lanes, p.path.frenet.length())
    });
}
