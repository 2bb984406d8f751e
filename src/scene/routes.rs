//! Routes: the lane paths a vehicle can take from where it stands, and how closely a future
//! follows the nearest of them.
//!
//! A future told as "this route, so far along it, so far across it" is on its lane by
//! construction; a future told in the plane has to learn the lanes to a few decimetres, which
//! the cities model did not (data/cities-wip/README.md, "The network does not learn even one
//! scene's futures").

use super::lane_path::{LanePath, Turn};
use super::map::{LaneId, Map};
use crate::geom::{wrap_angle, FrenetPath, Point};

/// How far from a lane's centre line (metres) a vehicle may stand for a route to start on it:
/// beyond half a lane, as a car mid-way through a lane change stands.
pub const ORIGIN_RADIUS: f64 = 2.5;

/// How far a lane's direction may differ from the vehicle's heading (radians, 45°) for a
/// route to start on it: of the lanes that overlap in a junction, those going its way.
pub const ORIGIN_HEADING: f64 = std::f64::consts::FRAC_PI_4;

/// Routes kept at most: three turns from each of four origin lanes.
pub const MAX_ROUTES: usize = 12;

/// Metres each route reaches behind the vehicle, so that the first step measures from a point
/// on the path, not from its extension.
const BEHIND: f64 = 30.0;

/// The routes from the pose `(p, heading)`, each reaching at least `ahead` metres past `p`
/// where the lane graph goes that far: straight on, left and right at the forks, from every
/// lane whose centre line passes within [`ORIGIN_RADIUS`] of `p` going within
/// [`ORIGIN_HEADING`] of `heading`, nearest lane first. Where no lane qualifies, the routes
/// start on [`Map::lane_at`]'s lane; a map with no lane going the vehicle's way gives none.
/// Routes with the same lanes are kept once.
pub fn candidate_routes(map: &Map, p: Point, heading: f64, ahead: f64) -> Vec<LanePath> {
    let mut origins: Vec<(f64, LaneId, f64)> = map
        .lanes()
        .iter()
        .filter_map(|lane| {
            let hit = lane.centerline.nearest(&p);
            let dir = lane.centerline.segment_direction(hit.segment);
            let diff = wrap_angle(heading - dir.y.atan2(dir.x)).abs();
            (hit.distance <= ORIGIN_RADIUS && diff <= ORIGIN_HEADING).then_some((
                hit.distance,
                lane.id,
                hit.s,
            ))
        })
        .collect();
    origins.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    if origins.is_empty() {
        if let Some(id) = map.lane_at(p, heading) {
            let lane = map.lane(id).expect("lane_at names a lane of the map");
            origins.push((0.0, id, lane.centerline.nearest(&p).s));
        }
    }
    let mut routes: Vec<LanePath> = Vec::new();
    for (_, lane, along) in origins {
        for turn in [Turn::Straight, Turn::Left, Turn::Right] {
            if routes.len() == MAX_ROUTES {
                return routes;
            }
            // The origin is a lane of this map, so only a malformed graph could refuse it.
            let Ok(path) = map.lane_path(lane, along + ahead, BEHIND, turn) else {
                continue;
            };
            if !routes.iter().any(|r| r.lanes == path.lanes) {
                routes.push(path);
            }
        }
    }
    routes
}

/// Points measured against one route ([`fit_route`]).
#[derive(Debug, Clone, PartialEq)]
pub struct RouteFit {
    /// Which of the routes, by index.
    pub route: usize,
    /// Arc length along the route of each point.
    pub s: Vec<f64>,
    /// Signed offset across the route of each point, positive to the left.
    pub d: Vec<f64>,
    /// The largest `|d|`.
    pub max_offset: f64,
}

/// The route the points stray from least: the smallest largest offset across it, the first
/// route on a tie. `None` with no routes or no points.
pub fn fit_route(routes: &[LanePath], points: &[Point]) -> Option<RouteFit> {
    if points.is_empty() {
        return None;
    }
    let mut best: Option<RouteFit> = None;
    for (i, r) in routes.iter().enumerate() {
        let (mut s, mut d) = (Vec::with_capacity(points.len()), Vec::new());
        let mut max_offset: f64 = 0.0;
        for q in points {
            let f = r.frenet.project(*q);
            max_offset = max_offset.max(f.d.abs());
            // Worse than the best already: its offsets are not needed.
            if best.as_ref().is_some_and(|b| max_offset >= b.max_offset) {
                break;
            }
            s.push(f.s);
            d.push(f.d);
        }
        if best.as_ref().is_none_or(|b| max_offset < b.max_offset) {
            best = Some(RouteFit {
                route: i,
                s,
                d,
                max_offset,
            });
        }
    }
    best
}

/// Metres a stored route reaches behind the vehicle ([`route_line`]).
pub const LINE_BEHIND: f64 = 10.0;

/// The line a vehicle's future is told against, in the world: the route of [`candidate_routes`]
/// that the `observed` future points stray from least (with none observed, the first route:
/// straight on from the nearest lane), from [`LINE_BEHIND`] metres behind `(p, heading)` to
/// `reach` metres ahead (less where the lane graph ends), with the lanes' own vertices. Where
/// no lane goes its way, the line of its heading: told against that, a future is what the
/// heading-frame model generates.
pub fn route_line(map: &Map, p: Point, heading: f64, observed: &[Point], reach: f64) -> Vec<Point> {
    let routes = candidate_routes(map, p, heading, reach + LINE_BEHIND);
    let chosen = if observed.is_empty() {
        routes.first()
    } else {
        fit_route(&routes, observed).map(|f| &routes[f.route])
    };
    chosen
        .and_then(|route| cut(route, p, reach))
        .unwrap_or_else(|| heading_line(p, heading, reach))
}

/// Every route of [`candidate_routes`] as [`route_line`] cuts it, in the same order; the line
/// of the heading alone where no lane goes the vehicle's way.
pub fn route_lines(map: &Map, p: Point, heading: f64, reach: f64) -> Vec<Vec<Point>> {
    let lines: Vec<Vec<Point>> = candidate_routes(map, p, heading, reach + LINE_BEHIND)
        .iter()
        .filter_map(|route| cut(route, p, reach))
        .collect();
    if lines.is_empty() {
        vec![heading_line(p, heading, reach)]
    } else {
        lines
    }
}

/// How near (metres) a route may come back to where the vehicle stands before it is cut there
/// ([`cut`]).
const LOOP_GAP: f64 = 5.0;

/// `route` from [`LINE_BEHIND`] metres behind where `p` projects onto it to `reach` ahead,
/// ended before it comes back within [`LOOP_GAP`] of its part behind the vehicle: a route
/// round a loop of lanes (a roundabout's ring) returns to where it started, and a point there
/// would project onto either end, its distance along the route off by the loop's length.
fn cut(route: &LanePath, p: Point, reach: f64) -> Option<Vec<Point>> {
    let s0 = route.frenet.project(p).s;
    let line = route.frenet.polyline();
    let behind = line.slice(s0 - LINE_BEHIND, s0)?;
    let part = line.slice(s0 - LINE_BEHIND, s0 + reach)?;
    let (points, arc) = (part.points(), part.arc_lengths());
    let here = s0 - (s0 - LINE_BEHIND).max(0.0);
    let end = (0..points.len())
        .find(|&i| arc[i] > here + 2.0 * LOOP_GAP && behind.distance_to(&points[i]) < LOOP_GAP)
        .unwrap_or(points.len());
    Some(points[..end].to_vec())
}

fn heading_line(p: Point, heading: f64, reach: f64) -> Vec<Point> {
    let dir = Point::new(heading.cos(), heading.sin());
    vec![p - dir * LINE_BEHIND, p + dir * reach]
}

/// Points of a route the network reads ([`route_ahead`]).
pub const AHEAD_POINTS: usize = 16;

/// Metres between the points of [`route_ahead`]: with [`AHEAD_POINTS`], 75 m ahead, what a
/// car at 10 m/s covers in 8 s.
pub const AHEAD_SPACING: f64 = 5.0;

/// [`AHEAD_POINTS`] points of `path` [`AHEAD_SPACING`] apart, on its centre line from where
/// `p` projects onto it: the route as the network reads it. Past the path's end they continue
/// straight, as the future told against it does.
pub fn route_ahead(path: &FrenetPath, p: Point) -> Vec<Point> {
    let s0 = path.project(p).s;
    (0..AHEAD_POINTS)
        .map(|i| path.to_cartesian(s0 + AHEAD_SPACING * i as f64, 0.0))
        .collect()
}

/// A future told against its route, per future step `[along, across, heading]`: the
/// distance along the route beyond `advance` metres a step from the current pose, the offset
/// across it beyond the current one, and the heading beyond the route's there (unwrapped, so
/// continuous through ±π). `None` where the step is unobserved. The form the route-frame
/// model generates; [`from_route_residual`] inverts it.
pub fn route_residual(
    path: &FrenetPath,
    current: [f64; 3],
    future: &[Option<[f64; 3]>],
    advance: f64,
) -> Vec<Option<[f64; 3]>> {
    let start = path.project(Point::new(current[0], current[1]));
    let mut prev = 0.0;
    future
        .iter()
        .enumerate()
        .map(|(t, st)| {
            let st = (*st)?;
            let f = path.project(Point::new(st[0], st[1]));
            let h = prev + wrap_angle(st[2] - path.heading_at(f.s) - prev);
            prev = h;
            Some([f.s - start.s - advance * (t + 1) as f64, f.d - start.d, h])
        })
        .collect()
}

/// World poses `(x, y, heading)` of a future told against its route ([`route_residual`]).
pub fn from_route_residual(
    path: &FrenetPath,
    current: [f64; 3],
    residual: &[[f64; 3]],
    advance: f64,
) -> Vec<[f64; 3]> {
    let start = path.project(Point::new(current[0], current[1]));
    residual
        .iter()
        .enumerate()
        .map(|(t, r)| {
            let s = start.s + advance * (t + 1) as f64 + r[0];
            let p = path.to_cartesian(s, start.d + r[1]);
            [p.x, p.y, wrap_angle(path.heading_at(s) + r[2])]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::yaml;
    use std::path::Path;

    /// Lane 1 runs east into a fork (2 straight on, 3 left, 4 right), 0 leads into it, 5 runs
    /// beside 1 on its left and 6 runs west beside it on its right.
    fn fork() -> crate::scene::Scene {
        let text = r#"
steps: 2
current_step: 0
map:
  lanes:
    - {id: 0, centerline: [[-50, 0], [0, 0]], successors: [1]}
    - {id: 1, centerline: [[0, 0], [50, 0]], successors: [2, 3, 4], left: [5]}
    - {id: 2, centerline: [[50, 0], [100, 0]]}
    - {id: 3, centerline: [[50, 0], [60, 2], [68, 10], [70, 20], [70, 60]]}
    - {id: 4, centerline: [[50, 0], [60, -2], [68, -10], [70, -20], [70, -60]]}
    - {id: 5, centerline: [[0, 3.5], [50, 3.5]]}
    - {id: 6, centerline: [[50, -3.5], [0, -3.5]]}
agents:
  - {id: 1, states: [[10, 0, 0], [11, 0, 0]]}
"#;
        yaml::parse(Path::new("fork.yaml"), text).unwrap()
    }

    #[test]
    fn a_car_before_a_fork_has_a_route_for_each_turn_and_one_from_the_lane_beside() {
        let s = fork();
        let routes = candidate_routes(&s.map, Point::new(10.0, 0.5), 0.0, 80.0);
        let lanes: Vec<Vec<LaneId>> = routes.iter().map(|r| r.lanes.clone()).collect();
        // Lane 1 is nearest (0.5 m), then 5 (3.0 m is beyond the radius), so only lane 1's
        // three turns; lane 6 goes the other way.
        assert_eq!(lanes, vec![vec![0, 1, 2], vec![0, 1, 3], vec![0, 1, 4]]);
        // Half-way to lane 5, both lanes start routes, lane 1's first; lane 5 has no fork.
        let routes = candidate_routes(&s.map, Point::new(10.0, 1.7), 0.0, 80.0);
        let lanes: Vec<Vec<LaneId>> = routes.iter().map(|r| r.lanes.clone()).collect();
        assert_eq!(
            lanes,
            vec![vec![0, 1, 2], vec![0, 1, 3], vec![0, 1, 4], vec![5]]
        );
        // Facing west, only lane 6 goes its way.
        let routes = candidate_routes(&s.map, Point::new(10.0, -3.0), std::f64::consts::PI, 80.0);
        assert_eq!(routes.len(), 1);
        assert_eq!(routes[0].lanes, vec![6]);
    }

    #[test]
    fn a_turning_future_fits_the_turning_route() {
        let s = fork();
        let routes = candidate_routes(&s.map, Point::new(10.0, 0.0), 0.0, 80.0);
        // Along lane 1, then up lane 3's last leg 0.3 m to its right.
        let mut pts: Vec<Point> = (0..5)
            .map(|i| Point::new(10.0 + 10.0 * i as f64, 0.0))
            .collect();
        pts.extend((0..4).map(|i| Point::new(70.3, 25.0 + 10.0 * i as f64)));
        let fit = fit_route(&routes, &pts).unwrap();
        assert_eq!(routes[fit.route].lanes, vec![0, 1, 3]);
        // The frame turns smoothly across the corner's vertices: 0.3 m to within 2 mm.
        assert!((fit.max_offset - 0.3).abs() < 2e-3, "{fit:?}");
        assert!(
            (fit.d.last().unwrap() + 0.3).abs() < 2e-3,
            "right of the route is negative"
        );
        assert_eq!(fit.s.len(), pts.len());
        // Straight on, the straight route fits exactly.
        let pts: Vec<Point> = (0..9)
            .map(|i| Point::new(10.0 + 10.0 * i as f64, 0.0))
            .collect();
        let fit = fit_route(&routes, &pts).unwrap();
        assert_eq!(
            (routes[fit.route].lanes.clone(), fit.max_offset),
            (vec![0, 1, 2], 0.0)
        );
        // Arc length counts from the route's start: lane 0, the whole lane behind lane 1.
        assert!((fit.s[0] - 60.0).abs() < 1e-9, "{:?}", fit.s);
        assert!(fit_route(&routes, &[]).is_none() && fit_route(&[], &pts).is_none());
    }

    #[test]
    fn a_route_round_a_loop_of_lanes_ends_before_it_comes_back() {
        // A square ring of four 20 m lanes, each leading into the next; the car stands 1 m
        // into lane 0 and its route reaches 100 m, more than the 80 m ring.
        let text = r#"
steps: 2
current_step: 0
map:
  lanes:
    - {id: 0, centerline: [[0, 0], [20, 0]], successors: [1]}
    - {id: 1, centerline: [[20, 0], [20, 20]], successors: [2]}
    - {id: 2, centerline: [[20, 20], [0, 20]], successors: [3]}
    - {id: 3, centerline: [[0, 20], [0, 0]], successors: [0]}
agents:
  - {id: 1, states: [[1, 0, 0], [2, 0, 0]]}
"#;
        let s = yaml::parse(Path::new("ring.yaml"), text).unwrap();
        let p = Point::new(1.0, 0.0);
        let line = route_line(&s.map, p, 0.0, &[], 100.0);
        let path = FrenetPath::new(crate::geom::Polyline::new(line.clone()).unwrap());
        // It goes round, and stops more than LOOP_GAP short of where the car stands.
        let last = *line.last().unwrap();
        assert!(last.x.abs() < 1e-9 && last.y >= LOOP_GAP - 1e-9, "{line:?}");
        // A car driving round the ring is told against it without a jump in its distance
        // along: every step 1 m further.
        let current = [1.0, 0.0, 0.0];
        let future: Vec<Option<[f64; 3]>> = (1..=60)
            .map(|t| {
                let q = path.to_cartesian(path.project(p).s + t as f64, 0.0);
                Some([q.x, q.y, 0.0])
            })
            .collect();
        let r = route_residual(&path, current, &future, 1.0);
        for (t, v) in r.iter().enumerate() {
            assert!(v.unwrap()[0].abs() < 1e-6, "step {t}: {v:?}");
        }
        assert_eq!(route_lines(&s.map, p, 0.0, 100.0), vec![line]);
    }

    #[test]
    fn a_car_away_from_every_lane_starts_on_the_lane_going_its_way() {
        let s = fork();
        let routes = candidate_routes(&s.map, Point::new(20.0, 12.0), 0.0, 80.0);
        // 8.5 m from lane 5, 12 m from lane 1: lane 5, which has no fork.
        let lanes: Vec<Vec<LaneId>> = routes.iter().map(|r| r.lanes.clone()).collect();
        assert_eq!(lanes, vec![vec![5]]);
    }

    #[test]
    fn a_future_told_against_its_route_comes_back_to_the_plane() {
        let s = fork();
        let routes = candidate_routes(&s.map, Point::new(10.0, 0.0), 0.0, 80.0);
        let left = routes.iter().find(|r| r.lanes == vec![0, 1, 3]).unwrap();
        let path = &left.frenet;
        // 0.2 m left of lane 1 at 12 m/s, drifting 0.1 m right a second and slowing 1 m/s²,
        // heading 0.05 rad left of the lane, for 8 s: round the corner onto lane 3.
        // (The frame's normals lean towards the corner all along lane 1, so the pose is set in
        // the frame, not in the plane.)
        let start = 60.0;
        let p0 = path.to_cartesian(start, 0.2);
        let current = [p0.x, p0.y, path.heading_at(start)];
        let future: Vec<[f64; 3]> = (1..=80)
            .map(|t| {
                let tau = 0.1 * t as f64;
                let along = start + 12.0 * tau - 0.5 * tau * tau;
                let p = path.to_cartesian(along, 0.2 - 0.1 * tau);
                [p.x, p.y, path.heading_at(along) + 0.05]
            })
            .collect();
        assert!(future[79][2] > 1.2, "it ends heading nearly north");
        let observed: Vec<Option<[f64; 3]>> = future.iter().map(|f| Some(*f)).collect();
        let r: Vec<[f64; 3]> = route_residual(path, current, &observed, 1.2)
            .into_iter()
            .map(Option::unwrap)
            .collect();
        for (t, v) in r.iter().enumerate() {
            let tau = 0.1 * (t + 1) as f64;
            assert!(
                (v[0] + 0.5 * tau * tau).abs() < 1e-9,
                "step {t}: along {}",
                v[0]
            );
            assert!((v[1] + 0.1 * tau).abs() < 1e-9, "step {t}: across {}", v[1]);
            assert!((v[2] - 0.05).abs() < 1e-9, "step {t}: heading {}", v[2]);
        }
        let back = from_route_residual(path, current, &r, 1.2);
        for (got, want) in back.iter().zip(&future) {
            let ok = (got[0] - want[0]).abs() < 1e-9
                && (got[1] - want[1]).abs() < 1e-9
                && wrap_angle(got[2] - want[2]).abs() < 1e-9;
            assert!(ok, "{got:?} {want:?}");
        }
        // Unobserved steps stay unobserved, and the heading stays unwrapped past them.
        let mut gaps = observed.clone();
        gaps[3] = None;
        gaps[4] = None;
        let g = route_residual(path, current, &gaps, 1.2);
        assert_eq!((g[3], g[4]), (None, None));
        assert_eq!(g[5], Some(r[5]));
    }
}
