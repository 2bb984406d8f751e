//! Lane-graph queries and the road edge.

use rhai::{Array, Dynamic, Engine};

use super::agents::{coord_series, AgentRef};
use super::frenet::agent_lane;
use super::{doc, err, number, turn, DocEntry, RResult, Shared};
use crate::cost::series::{Builder, Series};
use crate::cost::trajectory::Coord;
use crate::geom::Point;
use crate::scene::Map;

fn check(map: &Map, lane: i64) -> RResult<()> {
    if map.graph().contains(lane) {
        Ok(())
    } else {
        err(format!("unknown lane {lane}"))
    }
}

fn opt(v: Option<i64>) -> Dynamic {
    v.map_or(Dynamic::UNIT, Dynamic::from)
}

fn ids(v: &[i64]) -> Array {
    v.iter().map(|l| Dynamic::from(*l)).collect()
}

/// Which point of an agent's box [`box_series`] measures.
#[derive(Clone, Copy)]
enum BoxPoint {
    Centre,
    /// The corner farthest off the road (or nearest to leaving it).
    Farthest,
    /// One corner: 0 rear right, 1 front right, 2 front left, 3 rear left.
    Corner(usize),
}

/// Corner `i` of the box (0 rear right, 1 front right, 2 front left, 3 rear left), as `what`
/// takes it.
fn corner(what: &str, i: i64) -> RResult<BoxPoint> {
    match usize::try_from(i).ok().filter(|&i| i < 4) {
        Some(i) => Ok(BoxPoint::Corner(i)),
        None => err(format!("{what}: corner {i} is not 0, 1, 2 or 3")),
    }
}

/// The box corners in the agent's frame, in units of half length and half width.
const CORNERS: [(f64, f64); 4] = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)];

/// Signed road-edge distance of one point of the agent's box, per step.
fn edge_series(shared: &Shared, a: AgentRef, point: BoxPoint) -> RResult<Series> {
    if shared.borrow().scene.map.road_edges().is_empty() {
        return err("the map has no road edges");
    }
    box_series(shared, a, point, |map, p, _| {
        map.nearest_road_edge(p).map(|(d, q)| (d, q, d.signum()))
    })
}

/// How far one point of the agent's box (its centre, or a corner) lies outside every lane
/// going the agent's way ([`Map::outside_own_way`]), per step; unobserved where no lane goes
/// its way. The heading's choice of lanes adds no gradient: the value does not change with it
/// except where the choice does.
fn own_way_series(shared: &Shared, a: AgentRef, point: BoxPoint) -> RResult<Series> {
    let lanes = shared
        .borrow()
        .scene
        .map
        .lanes()
        .iter()
        .any(|l| l.lane_type.is_vehicle_lane());
    if !lanes {
        return err("wrong_way_distance: the map has no vehicle lanes");
    }
    box_series(shared, a, point, |map, p, heading| {
        map.outside_own_way(p, heading).map(|(d, q)| (d, q, 1.0))
    })
}

/// A distance from one point of the agent's box to a map feature, per step, with its gradient
/// w.r.t. the agent's pose. `measure(map, p, heading)` gives the distance, the feature's point
/// nearest `p` and the sign with which the distance grows away from it (the gradient w.r.t. `p`
/// is `sign · (p − q) / |p − q|`), or `None` where there is nothing to measure (unobserved).
fn box_series(
    shared: &Shared,
    a: AgentRef,
    point: BoxPoint,
    measure: impl Fn(&Map, Point, f64) -> Option<(f64, Point, f64)>,
) -> RResult<Series> {
    let xs = coord_series(shared, a, Coord::X);
    let ys = coord_series(shared, a, Coord::Y);
    let hs = coord_series(shared, a, Coord::Heading);
    let ctx = shared.borrow();
    let map = &ctx.scene.map;
    let agent = &ctx.scene.agents[a.idx];
    let (hl, hw) = (0.5 * agent.length, 0.5 * agent.width);
    let offsets: &[(f64, f64)] = match point {
        BoxPoint::Centre => &[(0.0, 0.0)],
        BoxPoint::Farthest => &CORNERS,
        BoxPoint::Corner(i) => &CORNERS[i..=i],
    };
    let (x, y, h) = (&xs.0, &ys.0, &hs.0);
    let mut b = Builder::new(x.val.len(), x.head, x.dt, x.time0);
    for k in 0..x.val.len() {
        if !(x.valid[k] && y.valid[k] && h.valid[k]) {
            b.push_row(0.0, false, std::iter::empty());
            continue;
        }
        let (cx, cy, th) = (x.val[k], y.val[k], h.val[k]);
        let (sn, cs) = th.sin_cos();
        let mut best: Option<(f64, [f64; 3])> = None;
        for &(u, v) in offsets {
            let (lx, ly) = (u * hl, v * hw);
            let p = Point::new(cx + cs * lx - sn * ly, cy + sn * lx + cs * ly);
            let Some((d, q, sign)) = measure(map, p, th) else {
                continue;
            };
            let r = p - q;
            let n = r.norm();
            let g = if n > 1e-12 {
                r / n * sign
            } else {
                Point::zeros()
            };
            let dp_dh = Point::new(-sn * lx - cs * ly, cs * lx - sn * ly);
            let grad = [g.x, g.y, g.dot(&dp_dh)];
            if best.is_none_or(|(bd, _)| d > bd) {
                best = Some((d, grad));
            }
        }
        let Some((d, g)) = best else {
            b.push_row(0.0, false, std::iter::empty());
            continue;
        };
        let row: Vec<(u32, f64)> = match (xs.row(k).first(), ys.row(k).first(), hs.row(k).first()) {
            (Some(&(vx, _)), Some(&(vy, _)), Some(&(vh, _))) => {
                let mut r = vec![(vx, g[0]), (vy, g[1])];
                if !matches!(point, BoxPoint::Centre) {
                    r.push((vh, g[2]));
                }
                r
            }
            _ => vec![],
        };
        b.push_row(d, true, row);
    }
    Ok(b.build())
}

/// The point `(x, y)` a lane function measures at, refused where no map reaches: a NaN or
/// 1e300 made the projection onto the lane panic.
fn map_point(what: &str, x: &Dynamic, y: &Dynamic) -> RResult<Point> {
    let (x, y) = (number(x, what)?, number(y, what)?);
    let far = crate::geom::MAX_COORD;
    if !(x.abs() <= far && y.abs() <= far) {
        return err(format!(
            "{what}: the point ({}, {}) lies on no map: coordinates are numbers within {far:e} m \
             of the origin",
            crate::geom::num(x),
            crate::geom::num(y)
        ));
    }
    Ok(Point::new(x, y))
}

pub(super) fn register(e: &mut Engine, shared: &Shared, docs: &mut Vec<DocEntry>) {
    const S: &str = "Lane graph";
    macro_rules! lanefn {
        ($name:literal, $sig:literal, $doc:literal, |$map:ident, $l:ident| $body:expr) => {{
            doc(docs, S, $sig, $doc);
            let sh = shared.clone();
            e.register_fn($name, move |$l: i64| -> RResult<Dynamic> {
                let ctx = sh.borrow();
                let $map = &ctx.scene.map;
                check($map, $l)?;
                Ok($body)
            });
        }};
    }
    doc(
        docs,
        S,
        "lane_ahead(lane, xpos, ypos) -> float",
        "Metres of mapped lane ahead of the point (xpos, ypos) projected onto the lane, following successors straight on at forks (up to 2 km): where a lane ends (an on-ramp, an exit, the edge of the map) within that distance, a vehicle cannot end in it.",
    );
    let sh = shared.clone();
    e.register_fn(
        "lane_ahead",
        move |l: i64, x: Dynamic, y: Dynamic| -> RResult<f64> {
            let p = map_point("lane_ahead", &x, &y)?;
            let ctx = sh.borrow();
            let m = &ctx.scene.map;
            check(m, l)?;
            let path = m
                .lane_path(l, 2000.0, 0.0, crate::scene::Turn::Straight)
                .map_err(|e| format!("lane_ahead({l}): {e}"))?;
            let s = path.frenet.project(p).s;
            Ok((path.frenet.length() - s).max(0.0))
        },
    );
    doc(
        docs,
        S,
        "lane_width(lane, xpos, ypos) -> float",
        "Width of the lane (between its boundaries) where the point (xpos, ypos) projects onto it, metres; 3.6 where the map gives no boundaries.",
    );
    let sh = shared.clone();
    e.register_fn(
        "lane_width",
        move |l: i64, x: Dynamic, y: Dynamic| -> RResult<f64> {
            let p = map_point("lane_width", &x, &y)?;
            let ctx = sh.borrow();
            if ctx.scene.map.lane(l).is_none() {
                return err(format!("lane_width: no lane {l} in the map"));
            }
            Ok(ctx
                .scene
                .map
                .lane_width_at(l, p)
                .unwrap_or(2.0 * super::frenet::DEFAULT_HALF_WIDTH))
        },
    );
    doc(
        docs,
        S,
        "lane_exists(lane) -> bool",
        "Whether the map has this lane id.",
    );
    let sh = shared.clone();
    e.register_fn("lane_exists", move |l: i64| {
        sh.borrow().scene.map.graph().contains(l)
    });
    lanefn!(
        "left",
        "left(lane) -> int or ()",
        "The same-direction lane to the left, or () if there is none.",
        |m, l| opt(m.graph().left(l))
    );
    lanefn!(
        "right",
        "right(lane) -> int or ()",
        "The same-direction lane to the right, or ().",
        |m, l| opt(m.graph().right(l))
    );
    lanefn!(
        "has_left",
        "has_left(lane) -> bool",
        "Whether a same-direction lane lies to the left.",
        |m, l| Dynamic::from(m.graph().left(l).is_some())
    );
    lanefn!(
        "has_right",
        "has_right(lane) -> bool",
        "Whether a same-direction lane lies to the right.",
        |m, l| Dynamic::from(m.graph().right(l).is_some())
    );
    lanefn!(
        "leftmost",
        "leftmost(lane) -> int",
        "The leftmost same-direction lane beside this one (itself if none is further left).",
        |m, l| Dynamic::from(m.graph().leftmost(l))
    );
    lanefn!(
        "rightmost",
        "rightmost(lane) -> int",
        "The rightmost same-direction lane beside this one.",
        |m, l| Dynamic::from(m.graph().rightmost(l))
    );
    lanefn!(
        "is_rightmost",
        "is_rightmost(lane) -> bool",
        "Whether no same-direction lane lies to the right.",
        |m, l| Dynamic::from(m.graph().is_rightmost(l))
    );
    lanefn!(
        "lane_count",
        "lane_count(lane) -> int",
        "Number of same-direction lanes side by side with this one, itself included.",
        |m, l| Dynamic::from(m.graph().lane_count(l) as i64)
    );
    lanefn!(
        "successors",
        "successors(lane) -> array of int",
        "Lanes this lane flows into.",
        |m, l| Dynamic::from(ids(m.graph().successors(l)))
    );
    lanefn!(
        "predecessors",
        "predecessors(lane) -> array of int",
        "Lanes flowing into this lane.",
        |m, l| Dynamic::from(ids(m.graph().predecessors(l)))
    );
    lanefn!("turn_of", "turn_of(lane) -> string", "\"left\", \"right\" or \"straight\" by the lane's heading change (more than 30 degrees is a turn).", |m, l| Dynamic::from(m.turn_of(l).expect("checked").word().to_string()));
    doc(docs, S, "successor(lane, turn) -> int or ()", "The successor that turns \"left\" / \"right\" (by more than 30 degrees) or goes \"straight\", or () if none does.");
    let sh = shared.clone();
    e.register_fn("successor", move |l: i64, t: &str| -> RResult<Dynamic> {
        let want = turn(t)?;
        let ctx = sh.borrow();
        let m = &ctx.scene.map;
        check(m, l)?;
        Ok(opt(m
            .graph()
            .successors(l)
            .iter()
            .copied()
            .find(|s| m.turn_of(*s) == Some(want))))
    });
    doc(
        docs,
        S,
        "a.lane -> int",
        "The agent's lane at the current step (the nearest lane going its way).",
    );
    let sh = shared.clone();
    e.register_get("lane", move |a: &mut AgentRef| agent_lane(&sh, a));
    doc(docs, S, "lane_of(a, step) -> int or ()", "The agent's lane at a recorded step (0 = first step of the scene), or () where it is not observed or near no lane.");
    let sh = shared.clone();
    e.register_fn(
        "lane_of",
        move |a: AgentRef, step: i64| -> RResult<Dynamic> {
            let ctx = sh.borrow();
            let states = &ctx.scene.agents[a.idx].states;
            let Some(s) = usize::try_from(step).ok().and_then(|k| states.get(k)) else {
                return err(format!(
                    "lane_of: step {step} is outside the scene's {} steps",
                    states.len()
                ));
            };
            if !s.valid {
                return Ok(Dynamic::UNIT);
            }
            Ok(opt(ctx.scene.map.lane_at(Point::new(s.x, s.y), s.heading)))
        },
    );

    const R: &str = "Road edge";
    doc(docs, R, "a.edge_distance -> Series", "Signed distance from the agent's centre to the nearest road edge, metres: negative on the road.");
    let sh = shared.clone();
    e.register_get("edge_distance", move |a: &mut AgentRef| {
        edge_series(&sh, *a, BoxPoint::Centre)
    });
    doc(docs, R, "a.wrong_way_distance -> Series", "How far the agent's centre lies outside every vehicle lane going its way (lane direction within 60° of its heading), metres: the distance to the nearest such lane's centre line less half its width, negative inside one. Positive in the oncoming lanes, which are on the road: `edge_distance` cannot tell them from the agent's own. Unobserved at steps where no lane goes the agent's way; an error on a map without vehicle lanes.");
    let sh = shared.clone();
    e.register_get("wrong_way_distance", move |a: &mut AgentRef| {
        own_way_series(&sh, *a, BoxPoint::Centre)
    });
    doc(docs, R, "a.corner_wrong_way_distance(i) -> Series", "The same for one corner of the box (0 rear right, 1 front right, 2 front left, 3 rear left), each corner measured against the lanes going the agent's way: a car changing between two lanes going its way has every corner inside one of them; one straddling the line to the oncoming lanes has two corners outside.");
    let sh = shared.clone();
    e.register_fn(
        "corner_wrong_way_distance",
        move |a: &mut AgentRef, i: i64| -> RResult<Series> {
            own_way_series(&sh, *a, corner("corner_wrong_way_distance", i)?)
        },
    );
    doc(docs, R, "a.box_edge_distance -> Series", "The same for the agent's box corner farthest off the road (positive as soon as any corner is off).");
    let sh = shared.clone();
    e.register_get("box_edge_distance", move |a: &mut AgentRef| {
        edge_series(&sh, *a, BoxPoint::Farthest)
    });
    doc(docs, R, "a.corner_edge_distance(i) -> Series", "The same for one corner of the box: 0 rear right, 1 front right, 2 front left, 3 rear left. Summing a penalty over the four corners is smooth where two corners are equally far off (a car parallel to the edge), which the farthest corner is not: there its gradient turns the car, pushing the other corner out.");
    let sh = shared.clone();
    e.register_fn(
        "corner_edge_distance",
        move |a: &mut AgentRef, i: i64| -> RResult<Series> {
            edge_series(&sh, *a, corner("corner_edge_distance", i)?)
        },
    );
    doc(docs, R, "a.on_road(k) -> Series", "Soft indicator of the whole box being on the road: sigmoid(-k · box_edge_distance), near 1 on the road, near 0 off it.");
    let sh = shared.clone();
    e.register_fn(
        "on_road",
        move |a: &mut AgentRef, k: Dynamic| -> RResult<Series> {
            // A k of 0 or below turns the indicator over (near 0 on the road) or flat, and a
            // term built on it is 0 on the road, silently: the same k must be positive as
            // softplus's beta and ttc's cap.
            let k = super::real(&k, "on_road k")?;
            if !(k.is_finite() && k > 0.0) {
                return err(format!(
                    "on_road: k must be positive (the sharpness of the step; 1 to 10 is usual), got {}",
                    crate::geom::num(k)
                ));
            }
            let d = edge_series(&sh, *a, BoxPoint::Farthest)?;
            d.map("on_road", |v| {
                let s = 1.0 / (1.0 + (k * v).exp());
                Some((s, -k * s * (1.0 - s)))
            })
            .or_else(err)
        },
    );
}
