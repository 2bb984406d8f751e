//! Lane paths: a lane extended through its successors (and back through its predecessors) into
//! one reference path for Frenet coordinates.

use serde::{Deserialize, Serialize};

use super::map::{LaneId, Map};
use super::SceneError;
use crate::geom::{wrap_angle, FrenetPath, Polyline};

/// Which way to go where a lane forks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Turn {
    /// The successor whose heading changes least.
    #[default]
    Straight,
    /// The successor turning most to the left.
    Left,
    /// The successor turning most to the right.
    Right,
}

impl Turn {
    /// The word for this turn in scripts and behaviour parameters.
    pub fn word(self) -> &'static str {
        match self {
            Turn::Straight => "straight",
            Turn::Left => "left",
            Turn::Right => "right",
        }
    }

    /// The turn a word names (`"straight"`, `"left"` or `"right"`).
    pub fn from_word(w: &str) -> Option<Self> {
        [Turn::Straight, Turn::Left, Turn::Right]
            .into_iter()
            .find(|t| t.word() == w)
    }
}

/// Heading change (radians) beyond which a lane counts as a turn.
pub const TURN_THRESHOLD: f64 = 30.0 * std::f64::consts::PI / 180.0;

/// Where a path turns ([`LanePath::next_turn`]), in arc length along it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TurnSpan {
    /// The turning lane.
    pub lane: LaneId,
    /// Where the lane starts.
    pub start: f64,
    /// Where the path's heading has turned half the lane's turn.
    pub middle: f64,
    /// Where the lane ends.
    pub end: f64,
    /// The lane's heading change, radians (positive to the left).
    pub angle: f64,
}

/// A reference path made of consecutive lanes.
#[derive(Debug, Clone, PartialEq)]
pub struct LanePath {
    /// The lanes in driving order.
    pub lanes: Vec<LaneId>,
    /// Arc length on the path at which each lane starts.
    pub lane_starts: Vec<f64>,
    /// The lane the path was requested for.
    pub origin: LaneId,
    /// The path's Frenet frame.
    pub frenet: FrenetPath,
}

impl LanePath {
    /// Arc length at which the requested lane starts (the path may begin earlier).
    pub fn origin_s(&self) -> f64 {
        let k = self
            .lanes
            .iter()
            .position(|&l| l == self.origin)
            .expect("the origin lane is on its path");
        self.lane_starts[k]
    }

    /// The first point along this path where it touches `other` (a crossing, or the start of a
    /// merge where both continue on the same lane), with the arc length on each path there.
    pub fn first_meeting(&self, other: &LanePath) -> Option<(f64, f64, crate::geom::Point)> {
        use crate::geom::{cross, point_segment_distance, segments_intersect};
        let (la, lb) = (self.frenet.polyline(), other.frenet.polyline());
        let (pa, pb) = (la.points(), lb.points());
        let (lo, hi) = lb.bounds();
        for i in 0..pa.len() - 1 {
            let (p0, p1) = (pa[i], pa[i + 1]);
            if p0.x.max(p1.x) < lo.x
                || p0.x.min(p1.x) > hi.x
                || p0.y.max(p1.y) < lo.y
                || p0.y.min(p1.y) > hi.y
            {
                continue;
            }
            let mut best: Option<f64> = None;
            for j in 0..pb.len() - 1 {
                if segments_intersect(&p0, &p1, &pb[j], &pb[j + 1]) {
                    let (e, f) = (p1 - p0, pb[j + 1] - pb[j]);
                    let den = cross(&e, &f);
                    // Where the segments cross, or (parallel, touching) the nearer touching end.
                    let t = if den.abs() > 1e-12 {
                        (cross(&(pb[j] - p0), &f) / den).clamp(0.0, 1.0)
                    } else {
                        point_segment_distance(&pb[j], &p0, &p1)
                            .1
                            .min(point_segment_distance(&pb[j + 1], &p0, &p1).1)
                    };
                    best = Some(best.map_or(t, |b: f64| b.min(t)));
                }
            }
            if let Some(t) = best {
                let p = p0 + (p1 - p0) * t;
                let arc = la.arc_lengths();
                let sa = arc[i] + t * (arc[i + 1] - arc[i]);
                return Some((sa, other.frenet.project(p).s, p));
            }
        }
        None
    }

    /// The first lane from the requested one on that turns `turn` ([`Map::turn_of`]): where it
    /// starts and ends on this path, and the middle of the turn, where the path's heading has
    /// changed by half the lane's turn. `None` for [`Turn::Straight`], or where no lane on the
    /// path turns that way. The middle is what a car must pass to have turned: a turning lane
    /// often runs on straight well past the corner, so its end is too far, and its start is
    /// still on the approach.
    pub fn next_turn(&self, map: &Map, turn: Turn) -> Option<TurnSpan> {
        if turn == Turn::Straight {
            return None;
        }
        let from = self.lanes.iter().position(|&l| l == self.origin)?;
        let k = (from..self.lanes.len()).find(|&k| map.turn_of(self.lanes[k]) == Some(turn))?;
        let lane = self.lanes[k];
        let start = self.lane_starts[k];
        let end = start + map.lane(lane)?.centerline.length();
        let change = map.heading_change(lane)?;
        let h0 = self.frenet.heading_at(start + 1e-6);
        // Sampled every 0.25 m: lanes' vertices are metres apart, so this finds the segment.
        let steps = ((end - start) / 0.25).ceil().max(1.0) as usize;
        let middle = (0..=steps)
            .map(|i| start + (end - start) * i as f64 / steps as f64)
            .find(|&s| {
                wrap_angle(self.frenet.heading_at(s) - h0) * change.signum() >= 0.5 * change.abs()
            })
            .unwrap_or(end);
        Some(TurnSpan {
            lane,
            start,
            middle,
            end,
            angle: change,
        })
    }

    /// The lane holding arc length `s`.
    pub fn lane_at_s(&self, s: f64) -> LaneId {
        let k = self.lane_starts.partition_point(|&x| x <= s);
        self.lanes[k.saturating_sub(1)]
    }
}

impl Map {
    /// Total heading change along a lane, radians (positive = turning left).
    pub fn heading_change(&self, id: LaneId) -> Option<f64> {
        let c = &self.lane(id)?.centerline;
        let a = c.segment_direction(0);
        let b = c.segment_direction(c.segment_count() - 1);
        Some(wrap_angle(b.y.atan2(b.x) - a.y.atan2(a.x)))
    }

    /// Classifies a lane as a left turn, right turn or straight by its heading change.
    pub fn turn_of(&self, id: LaneId) -> Option<Turn> {
        let h = self.heading_change(id)?;
        Some(if h > TURN_THRESHOLD {
            Turn::Left
        } else if h < -TURN_THRESHOLD {
            Turn::Right
        } else {
            Turn::Straight
        })
    }

    fn pick_successor(&self, options: &[LaneId], turn: Turn) -> Option<LaneId> {
        let scored = options
            .iter()
            .filter_map(|&id| Some((self.heading_change(id)?, id)));
        let key = |h: f64| match turn {
            Turn::Straight => h.abs(),
            Turn::Left => -h,
            Turn::Right => h,
        };
        scored
            .min_by(|a, b| key(a.0).total_cmp(&key(b.0)).then(a.1.cmp(&b.1)))
            .map(|(_, id)| id)
    }

    /// The predecessor whose end lines up best with the start of `id`.
    fn pick_predecessor(&self, id: LaneId) -> Option<LaneId> {
        let start = self.lane(id)?.centerline.segment_direction(0);
        self.graph()
            .predecessors(id)
            .iter()
            .filter_map(|&p| {
                let c = &self.lane(p)?.centerline;
                let end = c.segment_direction(c.segment_count() - 1);
                Some((end.dot(&start), p))
            })
            .max_by(|a, b| a.0.total_cmp(&b.0).then(b.1.cmp(&a.1)))
            .map(|(_, p)| p)
    }

    /// The path through `lane`: at least `ahead` metres from the lane's start onwards (through
    /// successors, taking `turn` at forks) and up to `behind` metres before it (through the best
    /// aligned predecessors). Stops early where the graph ends or would loop.
    pub fn lane_path(
        &self,
        lane: LaneId,
        ahead: f64,
        behind: f64,
        turn: Turn,
    ) -> Result<LanePath, SceneError> {
        let lanes = self.lane_sequence(lane, ahead, behind, turn)?;
        self.path_through(lanes, lane)
    }

    /// The lanes of [`Map::lane_path`], first to last, without building the path: cheap, where
    /// the path copies every lane's centre line.
    pub(crate) fn lane_sequence(
        &self,
        lane: LaneId,
        ahead: f64,
        behind: f64,
        turn: Turn,
    ) -> Result<Vec<LaneId>, SceneError> {
        let first = self.lane(lane).ok_or(SceneError::UnknownLane(lane))?;
        // A set for the loop check and the lanes behind gathered apart: linear in the path's
        // length (a 100 km path over 10^5 lanes took minutes with `contains` and `insert(0)`).
        let mut seen = std::collections::HashSet::from([lane]);
        let mut ahead_lanes = vec![lane];
        let mut forward = first.centerline.length();
        while forward < ahead {
            let last = *ahead_lanes.last().expect("non-empty");
            let Some(next) = self.pick_successor(self.graph().successors(last), turn) else {
                break;
            };
            if !seen.insert(next) {
                break;
            }
            forward += self
                .lane(next)
                .expect("graph lanes exist")
                .centerline
                .length();
            ahead_lanes.push(next);
        }
        let mut behind_lanes = Vec::new();
        let mut back = 0.0;
        while back < behind {
            let earliest = behind_lanes.last().copied().unwrap_or(lane);
            let Some(prev) = self.pick_predecessor(earliest) else {
                break;
            };
            if !seen.insert(prev) {
                break;
            }
            back += self
                .lane(prev)
                .expect("graph lanes exist")
                .centerline
                .length();
            behind_lanes.push(prev);
        }
        behind_lanes.reverse();
        let mut lanes = behind_lanes;
        lanes.extend(ahead_lanes);
        Ok(lanes)
    }

    /// The path along `lanes` (consecutive lanes of this map, as [`Map::lane_sequence`] gives
    /// them), its Frenet origin in `origin`.
    pub(crate) fn path_through(
        &self,
        lanes: Vec<LaneId>,
        origin: LaneId,
    ) -> Result<LanePath, SceneError> {
        let mut points: Vec<crate::geom::Point> = Vec::new();
        let mut lane_starts = Vec::with_capacity(lanes.len());
        let mut s = 0.0;
        for id in &lanes {
            let c = &self
                .lane(*id)
                .ok_or(SceneError::UnknownLane(*id))?
                .centerline;
            if let Some(prev_end) = points.last().copied() {
                s += (c.first() - prev_end).norm();
            }
            lane_starts.push(s);
            s += c.length();
            points.extend_from_slice(c.points());
        }
        let line = Polyline::new(points).map_err(|e| SceneError::Geometry {
            what: format!("lane path from lane {origin}"),
            source: e,
        })?;
        Ok(LanePath {
            lanes,
            lane_starts,
            origin,
            frenet: FrenetPath::new(line),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::Point;
    use crate::io::yaml;
    use std::path::Path;

    /// Lane 1 runs east into a fork: 2 goes straight on, 3 turns left, 4 turns right; 0 leads
    /// into 1, and 5 runs beside 1 on its left.
    fn fork() -> crate::scene::Scene {
        let text = r#"
steps: 2
current_step: 0
map:
  lanes:
    - {id: 0, centerline: [[-50, 0], [0, 0]], successors: [1]}
    - {id: 1, centerline: [[0, 0], [50, 0]], successors: [2, 3, 4], left: [5]}
    - {id: 2, centerline: [[50, 0], [100, 0]]}
    - {id: 3, centerline: [[50, 0], [60, 2], [68, 10], [70, 20]]}
    - {id: 4, centerline: [[50, 0], [60, -2], [68, -10], [70, -20]]}
    - {id: 5, centerline: [[0, 3.5], [50, 3.5]]}
agents:
  - {id: 1, states: [[10, 0, 0], [11, 0, 0]]}
"#;
        yaml::parse(Path::new("fork.yaml"), text).unwrap()
    }

    #[test]
    fn straight_on_at_forks_unless_told() {
        let s = fork();
        let p = s.map.lane_path(1, 200.0, 100.0, Turn::Straight).unwrap();
        assert_eq!(p.lanes, vec![0, 1, 2]);
        assert!((p.origin_s() - 50.0).abs() < 1e-9);
        assert!((p.frenet.length() - 150.0).abs() < 1e-9);
        assert_eq!(p.lane_at_s(75.0), 1);
        let left = s.map.lane_path(1, 200.0, 0.0, Turn::Left).unwrap();
        assert_eq!(left.lanes, vec![1, 3]);
        let right = s.map.lane_path(1, 200.0, 0.0, Turn::Right).unwrap();
        assert_eq!(right.lanes, vec![1, 4]);
        // Short requests stop as soon as the length is covered.
        assert_eq!(
            s.map.lane_path(1, 30.0, 0.0, Turn::Straight).unwrap().lanes,
            vec![1]
        );
        assert!(matches!(
            s.map.lane_path(42, 10.0, 0.0, Turn::Straight),
            Err(SceneError::UnknownLane(42))
        ));
    }

    #[test]
    fn a_long_chain_gives_its_lanes_in_order_behind_and_ahead() {
        // A 1 km chain of 10 m lanes, with a loop back from its last lane to its first.
        let n = 100;
        use crate::scene::{Lane, MapParts};
        let lanes: Vec<Lane> = (0..n)
            .map(|k| {
                let x = 10.0 * k as f64;
                let line =
                    Polyline::new(vec![Point::new(x, 0.0), Point::new(x + 10.0, 0.0)]).unwrap();
                let mut l = Lane::new(k, line);
                l.successors = vec![(k + 1) % n];
                l
            })
            .collect();
        let map = Map::new(MapParts {
            lanes,
            ..MapParts::default()
        })
        .unwrap();
        let p = map.lane_path(50, 300.0, 200.0, Turn::Straight).unwrap();
        assert_eq!(p.lanes, (30..80).collect::<Vec<_>>());
        // Asked for more than the loop holds, it stops before a lane repeats.
        let p = map.lane_path(50, 5000.0, 5000.0, Turn::Straight).unwrap();
        let expected: Vec<LaneId> = (50..100).chain(0..50).collect();
        assert_eq!(p.lanes, expected);
    }

    #[test]
    fn the_next_turn_is_found_with_the_middle_of_its_corner() {
        let s = fork();
        let left = s.map.lane_path(1, 200.0, 50.0, Turn::Left).unwrap();
        let t = left.next_turn(&s.map, Turn::Left).unwrap();
        assert_eq!(t.lane, 3);
        // Lane 0 (50 m) and lane 1 (50 m) come first.
        assert!((t.start - 100.0).abs() < 1e-9, "{t:?}");
        // The heading goes 11.3 -> 45 -> 78.7 degrees: half of the 67.4 degree turn is
        // reached on the 45 degree segment (10.2 to 21.5 m into the lane); the Frenet frame
        // turns smoothly across vertices, so 4 m into it.
        assert!((t.middle - 114.23).abs() <= 0.25, "{t:?}");
        assert!((t.angle.to_degrees() - 67.38).abs() < 0.01, "{t:?}");
        let right = s.map.lane_path(1, 200.0, 50.0, Turn::Right).unwrap();
        let t = right.next_turn(&s.map, Turn::Right).unwrap();
        assert_eq!(t.lane, 4);
        assert!(t.angle < 0.0);
        // Straight on there is no turn, and a path has no turn the other way.
        let straight = s.map.lane_path(1, 200.0, 50.0, Turn::Straight).unwrap();
        assert_eq!(straight.next_turn(&s.map, Turn::Left), None);
        assert_eq!(left.next_turn(&s.map, Turn::Right), None);
        assert_eq!(left.next_turn(&s.map, Turn::Straight), None);
    }

    #[test]
    fn turns_are_classified_by_heading_change() {
        let s = fork();
        assert_eq!(s.map.turn_of(2), Some(Turn::Straight));
        assert_eq!(s.map.turn_of(3), Some(Turn::Left));
        assert_eq!(s.map.turn_of(4), Some(Turn::Right));
    }

    #[test]
    fn frenet_on_a_lane_path_measures_from_its_start() {
        let s = fork();
        let p = s.map.lane_path(1, 100.0, 50.0, Turn::Straight).unwrap();
        let f = p.frenet.project(Point::new(20.0, 1.5));
        assert!((f.s - 70.0).abs() < 1e-9 && (f.d - 1.5).abs() < 1e-9);
    }

    #[test]
    fn lane_graph_queries() {
        let s = fork();
        let g = s.map.graph();
        assert_eq!(g.left(1), Some(5));
        assert_eq!(g.right(5), Some(1), "neighbour edges are made symmetric");
        assert_eq!(g.leftmost(1), 5);
        assert_eq!(g.rightmost(5), 1);
        assert!(g.is_rightmost(1) && !g.is_rightmost(5));
        assert_eq!(g.lane_count(1), 2);
        assert_eq!(g.predecessors(3), &[1]);
        assert_eq!(g.successors(0), &[1]);
        let c = g.edge_counts();
        assert_eq!((c.successor, c.predecessor, c.left, c.right), (4, 4, 1, 1));
    }

    #[test]
    fn lane_at_prefers_the_lane_going_the_agents_way() {
        let s = fork();
        // At the fork all three successors start at the same point; heading decides.
        let at = |x: f64, y: f64, h: f64| s.map.lane_at(Point::new(x, y), h);
        assert_eq!(at(52.0, 0.3, 0.2), Some(3));
        assert_eq!(at(52.0, -0.3, -0.2), Some(4));
        assert_eq!(at(20.0, 3.0, 0.0), Some(5));
        assert_eq!(at(20.0, 0.5, 0.0), Some(1));
        // Facing backwards matches no lane.
        assert_eq!(at(20.0, 0.5, std::f64::consts::PI), None);
    }
}
