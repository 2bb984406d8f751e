//! The road map: lanes with their lane graph, road edges, road lines, crosswalks, stop lines,
//! speed bumps and drivable areas, in the world frame.

use std::collections::HashSet;

use serde::{Deserialize, Serialize};

use super::lane_graph::LaneGraph;
use super::SceneError;
use crate::geom::{wrap_angle, FrenetPath, Point, Polygon, Polyline, SegmentGrid};

/// Identifier of a lane, as the source numbers it.
pub type LaneId = i64;

/// What a lane is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LaneType {
    /// Motorways and ramps.
    Freeway,
    /// Urban and rural roads.
    SurfaceStreet,
    /// Bicycle lanes.
    Bike,
    /// Bus lanes.
    Bus,
    /// Lanes not meant for vehicles (sidewalks, shoulders) or of unknown use.
    Other,
}

impl LaneType {
    /// Whether vehicles normally drive in it.
    pub fn is_vehicle_lane(self) -> bool {
        matches!(
            self,
            LaneType::Freeway | LaneType::SurfaceStreet | LaneType::Bus
        )
    }
}

/// A lane: its centre line (direction of travel), boundaries and edges as the source lists them.
#[derive(Debug, Clone, PartialEq)]
pub struct Lane {
    /// Identifier from the source.
    pub id: LaneId,
    /// Centre line in the direction of travel.
    pub centerline: Polyline,
    /// Left boundary, where the source has one.
    pub left_boundary: Option<Polyline>,
    /// Right boundary, where the source has one.
    pub right_boundary: Option<Polyline>,
    /// What the lane is for.
    pub lane_type: LaneType,
    /// Speed limit in m/s, where known.
    pub speed_limit: Option<f64>,
    /// Whether the lane lies inside an intersection.
    pub is_intersection: bool,
    /// Lanes that flow into this one.
    pub predecessors: Vec<LaneId>,
    /// Lanes this one flows into.
    pub successors: Vec<LaneId>,
    /// Same-direction neighbours to the left.
    pub left_neighbors: Vec<LaneId>,
    /// Same-direction neighbours to the right.
    pub right_neighbors: Vec<LaneId>,
}

impl Lane {
    /// A lane with a centre line and nothing else known.
    pub fn new(id: LaneId, centerline: Polyline) -> Self {
        Self {
            id,
            centerline,
            left_boundary: None,
            right_boundary: None,
            lane_type: LaneType::SurfaceStreet,
            speed_limit: None,
            is_intersection: false,
            predecessors: Vec::new(),
            successors: Vec::new(),
            left_neighbors: Vec::new(),
            right_neighbors: Vec::new(),
        }
    }

    /// The lane surface between its boundaries, when both are known.
    pub fn surface(&self) -> Option<Polygon> {
        let (l, r) = (self.left_boundary.as_ref()?, self.right_boundary.as_ref()?);
        Polygon::new(
            r.points()
                .iter()
                .copied()
                .chain(l.points().iter().rev().copied()),
        )
        .ok()
    }
}

/// Kind of road edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RoadEdgeKind {
    /// Curb or barrier with no traffic beyond it.
    Boundary,
    /// Barrier or island separating traffic.
    Median,
    /// Unspecified.
    Unknown,
}

/// A road edge, oriented so that the road is on its left (the WOMD convention).
#[derive(Debug, Clone, PartialEq)]
pub struct RoadEdge {
    /// Kind of edge.
    pub kind: RoadEdgeKind,
    /// The edge's Frenet frame (its polyline is `path.polyline()`).
    pub path: FrenetPath,
}

impl RoadEdge {
    /// An edge from a polyline with the road on its left.
    pub fn new(kind: RoadEdgeKind, line: Polyline) -> Self {
        Self {
            kind,
            path: FrenetPath::new(line),
        }
    }

    /// The edge's polyline.
    pub fn line(&self) -> &Polyline {
        self.path.polyline()
    }
}

/// Painted line kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RoadLineKind {
    /// Broken (dashed) line, may be crossed.
    Broken,
    /// Solid line.
    Solid,
    /// Double solid line.
    DoubleSolid,
    /// Anything else.
    Unknown,
}

/// A painted line on the road.
#[derive(Debug, Clone, PartialEq)]
pub struct RoadLine {
    /// Kind of marking.
    pub kind: RoadLineKind,
    /// Whether it is yellow (separates opposite directions in North America).
    pub yellow: bool,
    /// Its shape.
    pub line: Polyline,
}

/// A stop line or stop sign position and the lanes it controls.
#[derive(Debug, Clone, PartialEq)]
pub struct StopLine {
    /// One point (a sign) or the two ends of a painted line.
    pub points: Vec<Point>,
    /// Lanes it controls.
    pub lanes: Vec<LaneId>,
}

/// The widest gap between two drivable areas that still counts as road. Adjacent lanelets
/// store their shared boundary twice, and the copies need not match: the NGSIM maps leave
/// cracks of a few centimetres between lanes (decimetres in places on Lankershim), where a
/// point inside neither polygon would be metres "off the road", its nearest road edge being
/// the far side of the carriageway. Half a metre is narrower than any kerbed median.
pub const SEAM_GAP: f64 = 0.5;

/// Shortest lane (metres) whose direction of travel is judged, and with it on which side its
/// boundaries lie: real maps hold lanelets of 0.1-0.3 m whose centre lines zigzag, and
/// their boundaries read as swapped at random.
pub const MIN_JUDGED_LENGTH: f64 = 1.0;

/// Mean width (metres) of a lane given by its bounds, and on which side its left bound lies:
/// the mean sine of the angle from the driving direction to the right-to-left vector, near 1
/// where the left bound lies left and near -1 where the bounds are swapped; 0 where the lane
/// is shorter than [`MIN_JUDGED_LENGTH`] for its direction to say.
pub fn signed_width(left: &Polyline, right: &Polyline) -> (f64, f64) {
    let n = left.points().len().max(right.points().len()).max(2);
    let (l, r) = (left.resample_count(n), right.resample_count(n));
    let (mut width, mut side, mut length) = (0.0, 0.0, 0.0);
    for i in 0..n {
        let (a, b) = (l.points()[i], r.points()[i]);
        let (j, k) = if i + 1 < n { (i, i + 1) } else { (i - 1, i) };
        let dir = (l.points()[k] + r.points()[k]) * 0.5 - (l.points()[j] + r.points()[j]) * 0.5;
        let across = a - b;
        width += across.norm();
        side += dir.x * across.y - dir.y * across.x;
        length += dir.norm();
    }
    let width = width / n as f64;
    if length < MIN_JUDGED_LENGTH || width <= 0.0 {
        return (width, 0.0);
    }
    (width, side / (length * width))
}

/// Below this mean width (metres) a lane's bounds coincide: it has no surface.
pub const ZERO_WIDTH: f64 = 0.05;

/// Sharpest turn (degrees) a lane's centre line may take between consecutive half-metre
/// pieces before it counts as turning back on itself. On 66,790 lane centre lines of 1,250
/// CommonRoad towns and the AV2 sample the sharpest is 111° (99.99% under 64°); a line
/// drawn out and back (`g + reversed(g)`) turns by 180°, and its length and every path along
/// it are wrong.
pub const MAX_LANE_TURN: f64 = 150.0;

/// Lanes whose centre lines turn back on themselves (see [`MAX_LANE_TURN`]): each one's id,
/// where (arc length, metres) and by how much (degrees), as a reader's warning names them.
pub fn lanes_turning_back(lanes: &[Lane]) -> Vec<(LaneId, f64, f64)> {
    lanes
        .iter()
        .filter_map(|l| {
            l.centerline
                .sharpest_turn(0.5)
                .filter(|(_, turn)| *turn > MAX_LANE_TURN)
                .map(|(s, turn)| (l.id, s, turn))
        })
        .collect()
}

/// The parts a reader assembles into a [`Map`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MapParts {
    /// Lanes.
    pub lanes: Vec<Lane>,
    /// Road edges, road on their left.
    pub road_edges: Vec<RoadEdge>,
    /// Painted lines.
    pub road_lines: Vec<RoadLine>,
    /// Crosswalk polygons.
    pub crosswalks: Vec<Polygon>,
    /// Stop lines and signs.
    pub stop_lines: Vec<StopLine>,
    /// Speed bump polygons.
    pub speed_bumps: Vec<Polygon>,
    /// Drivable area polygons, where the source has them (a point inside any is on the road).
    pub drivable_areas: Vec<Polygon>,
}

/// A road map with its lane graph.
#[derive(Debug, Clone, PartialEq)]
pub struct Map {
    parts: MapParts,
    graph: LaneGraph,
    edge_bounds: Vec<(Point, Point)>,
    /// Every vehicle lane's centre-line segments, each offset by half its lane's width, for
    /// [`Map::outside_own_way`]; `own_way_segments[i]` is segment `i`'s lane index, segment
    /// index and direction (radians).
    own_way: SegmentGrid,
    own_way_segments: Vec<(usize, usize, f64)>,
    /// Every road edge's segments, for [`Map::nearest_road_edge`]; `edge_segments[i]` is
    /// segment `i`'s edge index and segment index. Each edge scanned in turn (pruned by its
    /// bounds) cost a query the length of the road: `eval --task unconditional` asks once per
    /// agent and step, so a scene twice as long with twice the cars took four times as long.
    edges: SegmentGrid,
    edge_segments: Vec<(usize, usize)>,
    exits: Vec<MapExit>,
}

/// The largest difference (radians) between an agent's heading and a lane's direction for the
/// lane to go the agent's way in [`Map::outside_own_way`]: 60°, wide enough for a car whose
/// heading leads or lags a curved lane, narrow enough that a crossing lane in a junction is not
/// its own.
pub const OWN_WAY: f64 = std::f64::consts::FRAC_PI_3;

/// Cell width (metres) of [`Map::outside_own_way`]'s grid: about two lanes, so that the
/// cells around a car on its lane hold the answer.
const OWN_WAY_CELL: f64 = 8.0;

/// The most centre-line points [`half_width`] measures a lane at: each measure scans both
/// boundaries, so measuring at every point took time in the square of the lane's length (a
/// 100 km YAML road, 100,000 points a lane, took 16 s to read, 74 s wound into a circle).
/// Real lanes have fewer points, and are measured at all of them.
const HALF_WIDTH_SAMPLES: usize = 256;

/// Half a lane's width: the median over its centre-line points (at most
/// [`HALF_WIDTH_SAMPLES`] of them, evenly spaced) of half the distance between its
/// boundaries, 1.75 m where it has none.
fn half_width(l: &Lane) -> f64 {
    let (Some(a), Some(b)) = (&l.left_boundary, &l.right_boundary) else {
        return 1.75;
    };
    let points = l.centerline.points();
    let step = points.len().div_ceil(HALF_WIDTH_SAMPLES).max(1);
    let mut w: Vec<f64> = points
        .iter()
        .step_by(step)
        .map(|q| 0.5 * (a.distance_to(q) + b.distance_to(q)))
        .filter(|w| w.is_finite())
        .collect();
    if w.is_empty() {
        return 1.75;
    }
    w.sort_unstable_by(f64::total_cmp);
    w[w.len() / 2]
}

/// Where the mapped road stops: the open end of a lane with no successor and no mapped lane
/// ahead of it. Recorded traffic leaves the scene there (the recording ends, not the road),
/// so a simulated car that drives through it has left the map rather than the road.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapExit {
    /// The lane's last centre-line point.
    pub point: Point,
    /// Unit direction of travel there.
    pub direction: Point,
    /// Half the lane's width there (1.75 m when the lane has no boundaries).
    pub half_width: f64,
}

/// How far beside a lane's end another lane may continue (metres, lateral) and still make the
/// end a lane drop rather than the edge of the map.
const EXIT_CORRIDOR: f64 = 15.0;

fn find_exits(lanes: &[Lane]) -> Vec<MapExit> {
    let tree = crate::geom::PointTree::new(
        lanes
            .iter()
            .flat_map(|o| o.centerline.points())
            .copied()
            .collect(),
    );
    lanes
        .iter()
        .filter(|l| l.successors.is_empty() && l.lane_type.is_vehicle_lane())
        .filter_map(|l| {
            let n = l.centerline.segment_count();
            let (point, direction) = (l.centerline.last(), l.centerline.segment_direction(n - 1));
            let beyond = tree.any_in_corridor(point, direction, 2.0, EXIT_CORRIDOR);
            if beyond {
                return None;
            }
            let half_width = match (&l.left_boundary, &l.right_boundary) {
                (Some(a), Some(b)) => 0.5 * (a.distance_to(&point) + b.distance_to(&point)),
                _ => 1.75,
            };
            Some(MapExit {
                point,
                direction,
                half_width,
            })
        })
        .collect()
}

impl Map {
    /// Builds the map and its lane graph; lane ids must be unique.
    pub fn new(parts: MapParts) -> Result<Self, SceneError> {
        let mut seen = HashSet::new();
        for lane in &parts.lanes {
            if !seen.insert(lane.id) {
                return Err(SceneError::DuplicateLane(lane.id));
            }
            if let Some(limit) = lane.speed_limit {
                if !super::LANE_SPEED_LIMIT.contains(&limit) {
                    return Err(SceneError::SpeedLimit {
                        lane: lane.id,
                        limit,
                    });
                }
            }
        }
        let graph = LaneGraph::build(&parts.lanes);
        let edge_bounds = parts.road_edges.iter().map(|e| e.line().bounds()).collect();
        let mut own_way_segments = Vec::new();
        let mut segments = Vec::new();
        for (li, l) in parts.lanes.iter().enumerate() {
            if !l.lane_type.is_vehicle_lane() {
                continue;
            }
            let (line, hw) = (&l.centerline, half_width(l));
            for i in 0..line.segment_count() {
                let dir = line.segment_direction(i);
                own_way_segments.push((li, i, dir.y.atan2(dir.x)));
                segments.push((line.points()[i], line.points()[i + 1], hw));
            }
        }
        let own_way = SegmentGrid::new(segments, OWN_WAY_CELL);
        let (mut edge_segments, mut segments) = (Vec::new(), Vec::new());
        for (ei, e) in parts.road_edges.iter().enumerate() {
            let line = e.line();
            for i in 0..line.segment_count() {
                edge_segments.push((ei, i));
                segments.push((line.points()[i], line.points()[i + 1], 0.0));
            }
        }
        let edges = SegmentGrid::new(segments, OWN_WAY_CELL);
        let exits = find_exits(&parts.lanes);
        Ok(Self {
            parts,
            graph,
            edge_bounds,
            own_way,
            own_way_segments,
            edges,
            edge_segments,
            exits,
        })
    }

    /// An empty map.
    pub fn empty() -> Self {
        Self::new(MapParts::default()).expect("an empty map is valid")
    }

    /// The parts the map was built from.
    pub fn parts(&self) -> &MapParts {
        &self.parts
    }

    /// All lanes.
    pub fn lanes(&self) -> &[Lane] {
        &self.parts.lanes
    }

    /// The lane with this id.
    pub fn lane(&self, id: LaneId) -> Option<&Lane> {
        self.parts.lanes.iter().find(|l| l.id == id)
    }

    /// The lane graph.
    pub fn graph(&self) -> &LaneGraph {
        &self.graph
    }

    /// Road edges (road on their left).
    pub fn road_edges(&self) -> &[RoadEdge] {
        &self.parts.road_edges
    }

    /// Painted lines.
    pub fn road_lines(&self) -> &[RoadLine] {
        &self.parts.road_lines
    }

    /// Crosswalks.
    pub fn crosswalks(&self) -> &[Polygon] {
        &self.parts.crosswalks
    }

    /// Stop lines and stop signs.
    pub fn stop_lines(&self) -> &[StopLine] {
        &self.parts.stop_lines
    }

    /// Speed bumps.
    pub fn speed_bumps(&self) -> &[Polygon] {
        &self.parts.speed_bumps
    }

    /// Drivable areas.
    pub fn drivable_areas(&self) -> &[Polygon] {
        &self.parts.drivable_areas
    }

    /// Bounding box of all lanes and edges, `None` for an empty map.
    pub fn bounds(&self) -> Option<(Point, Point)> {
        let lines = self
            .parts
            .lanes
            .iter()
            .map(|l| l.centerline.bounds())
            .chain(self.edge_bounds.iter().copied())
            .chain(self.parts.road_lines.iter().map(|l| l.line.bounds()))
            .chain(self.parts.drivable_areas.iter().map(|p| p.bounds()));
        lines.reduce(|(lo, hi), (a, b)| (lo.inf(&a), hi.sup(&b)))
    }

    /// The map's exits (see [`MapExit`]).
    pub fn exits(&self) -> &[MapExit] {
        &self.exits
    }

    /// Whether `p` is at an exit: from 0.5 m short of an exit lane's end to 10 m beyond it,
    /// within a metre of the lane's width. Meant for a car's front bumper, which reaches the
    /// end first.
    pub fn at_exit(&self, p: Point) -> bool {
        self.exits.iter().any(|e| {
            let r = p - e.point;
            let ahead = r.dot(&e.direction);
            (-0.5..10.0).contains(&ahead) && r.perp(&e.direction).abs() <= e.half_width + 1.0
        })
    }

    /// Whether the front bumper of a car `length` long at `(x, y)` facing `heading` is at an
    /// exit ([`Map::at_exit`]).
    pub fn bumper_at_exit(&self, x: f64, y: f64, heading: f64, length: f64) -> bool {
        let (sn, cs) = heading.sin_cos();
        !self.exits.is_empty()
            && self.at_exit(Point::new(x + 0.5 * length * cs, y + 0.5 * length * sn))
    }

    /// Signed distance from `p` to the nearest road edge: negative on the road, positive off it.
    ///
    /// With drivable areas the side comes from them (inside any area = on the road); otherwise
    /// from the nearest edge's orientation (road on its left). `None` when the map has no edges.
    pub fn signed_distance_to_road_edge(&self, p: Point) -> Option<f64> {
        self.nearest_road_edge(p).map(|(d, _)| d)
    }

    /// The signed distance of [`Map::signed_distance_to_road_edge`] and the nearest point on
    /// the edge (the distance's gradient w.r.t. `p` is `sign · (p - q) / |p - q|`).
    pub fn nearest_road_edge(&self, p: Point) -> Option<(f64, Point)> {
        // Ties go to the lowest index, that is the first edge and its first segment, as in a
        // scan of every edge in turn.
        let hit = self.edges.nearest(&p, |_| true)?;
        let (i, j) = self.edge_segments[hit.index];
        let best = hit.distance;
        let edge = &self.parts.road_edges[i];
        let cum = edge.line().arc_lengths();
        let s = cum[j] + hit.t * (cum[j + 1] - cum[j]);
        let on_road = if self.parts.drivable_areas.is_empty() {
            edge.path.project(p).d >= 0.0
        } else {
            self.parts.drivable_areas.iter().any(|a| a.contains(&p)) || self.in_seam(p)
        };
        let q = edge.line().point_at(s);
        Some((if on_road { -best } else { best }, q))
    }

    /// Whether `p`, outside every drivable area, lies in a seam between two of them: both
    /// within [`SEAM_GAP`]` / 2`, on opposite sides of `p` (beside a single area, or at the
    /// joint of two consecutive ones, both nearest points lie the same way).
    fn in_seam(&self, p: Point) -> bool {
        let half = 0.5 * SEAM_GAP;
        let near: Vec<(f64, Point)> = self
            .parts
            .drivable_areas
            .iter()
            .filter(|a| {
                let (lo, hi) = a.bounds();
                (lo.x - half..=hi.x + half).contains(&p.x)
                    && (lo.y - half..=hi.y + half).contains(&p.y)
            })
            .map(|a| a.nearest_boundary_point(&p))
            .filter(|(d, _)| *d <= half)
            .collect();
        near.iter().any(|(d, _)| *d <= 1e-9)
            || near.iter().enumerate().any(|(i, (_, qa))| {
                near[i + 1..]
                    .iter()
                    .any(|(_, qb)| (qa - p).dot(&(qb - p)) < 0.0)
            })
    }

    /// Width of `lane` at the point of its centre line nearest `p`: the distances from there to
    /// its two boundaries (`None` when the lane or a boundary is unknown).
    pub fn lane_width_at(&self, lane: LaneId, p: Point) -> Option<f64> {
        let l = self.lane(lane)?;
        let (a, b) = (l.left_boundary.as_ref()?, l.right_boundary.as_ref()?);
        let q = l.centerline.point_at(l.centerline.nearest(&p).s);
        let w = a.distance_to(&q) + b.distance_to(&q);
        w.is_finite().then_some(w)
    }

    /// How far `p` lies outside every vehicle lane going the way `heading` points (within
    /// [`OWN_WAY`]): the distance to the nearest such lane's centre line less half the lane's
    /// width, negative inside one. With the nearest centre-line point `q`, so that the value's
    /// gradient w.r.t. `p` is `(p − q) / |p − q|`. `None` when no vehicle lane goes that way.
    ///
    /// A car in the oncoming lanes is on the road, where the road-edge distance cannot see it;
    /// this can.
    pub fn outside_own_way(&self, p: Point, heading: f64) -> Option<(f64, Point)> {
        // The nearest segment going the agent's way, not each lane's nearest segment: a corner
        // of a car in a curve is often nearest to the part of its own lane that has already
        // turned.
        let hit = self.own_way.nearest(&p, |i| {
            wrap_angle(heading - self.own_way_segments[i].2).abs() <= OWN_WAY
        })?;
        let (lane, seg, _) = self.own_way_segments[hit.index];
        let line = self.parts.lanes[lane].centerline.points();
        let (a, b) = (line[seg], line[seg + 1]);
        Some((hit.distance, a + (b - a) * hit.t))
    }

    /// The nearest lane to a pose whose direction agrees with `heading` (within 90°).
    ///
    /// Ranks lanes by distance to the centre line plus 2 m per radian of heading difference,
    /// so that of overlapping lanes in an intersection the one going the agent's way wins.
    pub fn lane_at(&self, p: Point, heading: f64) -> Option<LaneId> {
        let mut best: Option<(f64, LaneId)> = None;
        for lane in &self.parts.lanes {
            let hit = lane.centerline.nearest(&p);
            let dir = lane.centerline.segment_direction(hit.segment);
            let diff = wrap_angle(heading - dir.y.atan2(dir.x)).abs();
            if diff >= std::f64::consts::FRAC_PI_2 {
                continue;
            }
            let score = hit.distance + 2.0 * diff;
            if best.is_none_or(|(b, _)| score < b) {
                best = Some((score, lane.id));
            }
        }
        best.map(|(_, id)| id)
    }
}

#[cfg(test)]
mod tests {
    use crate::geom::Point;
    use crate::io::yaml;
    use std::path::Path;

    fn edge_distance(s: &crate::scene::Scene, x: f64, y: f64) -> f64 {
        s.map
            .signed_distance_to_road_edge(Point::new(x, y))
            .unwrap()
    }

    #[test]
    fn signed_distance_to_road_edge_is_negative_on_the_road() {
        let text = "road: {lanes: 2, lane_width: 3.5, length: 100}\nagents: [{id: 1, lane: 0, s: 5, speed: 1}]\n";
        let s = yaml::parse(Path::new("road.yaml"), text).unwrap();
        let sd = |x, y| edge_distance(&s, x, y);
        assert!(
            (sd(50.0, 1.0) + 1.0).abs() < 1e-9,
            "1 m inside the right edge"
        );
        assert!(
            (sd(50.0, 6.0) + 1.0).abs() < 1e-9,
            "1 m inside the left edge"
        );
        assert!(
            (sd(50.0, -2.0) - 2.0).abs() < 1e-9,
            "2 m beyond the right edge"
        );
        assert!(
            (sd(50.0, 9.0) - 2.0).abs() < 1e-9,
            "2 m beyond the left edge"
        );
    }

    #[test]
    fn the_oncoming_lanes_are_outside_a_car_s_own_way() {
        // Eastbound lane 1 (y = 0, 3.5 m wide), westbound lane 2 beside it (y = 3.5, 3 m), and
        // a footpath (y = -3) that no car drives in.
        let text = r#"
steps: 1
current_step: 0
map:
  lanes:
    - {id: 1, centerline: [[0, 0], [100, 0]], left_boundary: [[0, 1.75], [100, 1.75]], right_boundary: [[0, -1.75], [100, -1.75]]}
    - {id: 2, centerline: [[100, 3.5], [0, 3.5]], left_boundary: [[100, 2], [0, 2]], right_boundary: [[100, 5], [0, 5]]}
    - {id: 3, type: other, centerline: [[0, -3], [100, -3]]}
agents:
  - {id: 1, states: [[10, 0, 0]]}
"#;
        let s = yaml::parse(Path::new("two_way.yaml"), text).unwrap();
        let out = |x: f64, y: f64, h: f64| s.map.outside_own_way(Point::new(x, y), h).unwrap();
        let east = 0.0;
        let west = std::f64::consts::PI;
        // Eastbound: inside its lane up to 1.75 m from the centre, then outside by the rest.
        assert!((out(50.0, 1.0, east).0 + 0.75).abs() < 1e-9);
        assert!(
            (out(50.0, 3.5, east).0 - 1.75).abs() < 1e-9,
            "in the oncoming lane"
        );
        assert_eq!(out(50.0, 3.5, east).1, Point::new(50.0, 0.0));
        // Heading a little off the lane (40°) is still its way; crossing it (80°) is not.
        assert!(out(50.0, 3.5, 0.7).0 > 1.0);
        assert!(s.map.outside_own_way(Point::new(50.0, 0.0), 1.4).is_none());
        // Westbound: lane 2 is 3 m wide, so 1.5 m either side of its centre.
        assert!((out(50.0, 3.5, west).0 + 1.5).abs() < 1e-9);
        assert!((out(50.0, 0.0, west).0 - 2.0).abs() < 1e-9);
        // The footpath goes east too, but no car's way.
        assert!((out(50.0, -3.0, east).0 - 1.25).abs() < 1e-9);

        // A lane that turns north at x = 50: a point nearer its northbound part, heading east,
        // is measured against its eastbound part, not refused with the whole lane.
        let text = r#"
steps: 1
current_step: 0
map:
  lanes:
    - {id: 1, centerline: [[0, 0], [50, 0], [50, 50]]}
agents:
  - {id: 1, states: [[10, 0, 0]]}
"#;
        let s = yaml::parse(Path::new("corner.yaml"), text).unwrap();
        let (d, q) = s.map.outside_own_way(Point::new(48.0, 3.0), east).unwrap();
        assert!(
            (d - 1.25).abs() < 1e-9 && q == Point::new(48.0, 0.0),
            "{d} {q}"
        );
    }

    #[test]
    fn own_way_through_the_grid_is_a_scan_of_every_lane_segment() {
        // Real urban maps (AV2 Miami, Lankershim): the grid's answer is the least of (distance
        // less half width) over every vehicle-lane segment going the way, at points over the
        // whole map and every heading.
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/samples");
        let opts = crate::io::LoadOptions::default();
        for file in [
            "av2/scenario_0a1e6f0a-1817-4a98-b02e-db8c9327d151.parquet",
            "commonroad/USA_Lanker-1_1_T-1.xml",
        ] {
            let s = crate::io::load_scene(&root.join(file), 0, &opts).unwrap();
            let m = &s.map;
            let scan = |p: Point, heading: f64| {
                let mut best: Option<(f64, Point)> = None;
                for l in m.lanes().iter().filter(|l| l.lane_type.is_vehicle_lane()) {
                    let line = &l.centerline;
                    for i in 0..line.segment_count() {
                        let dir = line.segment_direction(i);
                        if crate::geom::wrap_angle(heading - dir.y.atan2(dir.x)).abs()
                            > super::OWN_WAY
                        {
                            continue;
                        }
                        let (a, b) = (line.points()[i], line.points()[i + 1]);
                        let (d, t) = crate::geom::point_segment_distance(&p, &a, &b);
                        let d = d - super::half_width(l);
                        if best.is_none_or(|(bd, _)| d < bd) {
                            best = Some((d, a + (b - a) * t));
                        }
                    }
                }
                best
            };
            let (mut lo, mut hi) = (
                Point::repeat(f64::INFINITY),
                Point::repeat(f64::NEG_INFINITY),
            );
            for l in m.lanes() {
                let (a, b) = l.centerline.bounds();
                (lo, hi) = (lo.inf(&a), hi.sup(&b));
            }
            let mut checked = 0;
            for i in 0..=40 {
                for j in 0..=40 {
                    let p = Point::new(
                        lo.x - 20.0 + (hi.x - lo.x + 40.0) * i as f64 / 40.0,
                        lo.y - 20.0 + (hi.y - lo.y + 40.0) * j as f64 / 40.0,
                    );
                    for k in 0..8 {
                        let h = -3.0 + 0.79 * k as f64;
                        let (got, want) = (m.outside_own_way(p, h), scan(p, h));
                        match (got, want) {
                            (Some((d, q)), Some((e, r))) => {
                                assert!((d - e).abs() < 1e-12, "{file} {p:?} {h}: {d} {e}");
                                // Two segments as near give either point.
                                assert!(((q - p).norm() - (r - p).norm()).abs() < 1e-9);
                            }
                            (None, None) => {}
                            other => panic!("{file} {p:?} {h}: {other:?}"),
                        }
                        checked += 1;
                    }
                }
            }
            assert_eq!(checked, 41 * 41 * 8);
        }
    }

    #[test]
    fn exits_are_lane_ends_with_no_road_ahead() {
        // Lane 1 drops at x = 100 beside lane 2, which runs on to x = 200: only lane 2's end
        // is where the map stops. Lane 3 ends at 150 but flows into lane 4.
        let text = r#"
steps: 1
current_step: 0
map:
  lanes:
    - {id: 1, centerline: [[0, 0], [100, 0]]}
    - {id: 2, centerline: [[0, 3.5], [200, 3.5]]}
    - {id: 3, centerline: [[0, 7], [150, 7]], successors: [4]}
    - {id: 4, centerline: [[150, 7], [200, 7]]}
agents:
  - {id: 1, states: [[1, 1, 0]]}
"#;
        let s = yaml::parse(Path::new("exits.yaml"), text).unwrap();
        let ends: Vec<(f64, f64)> = s
            .map
            .exits()
            .iter()
            .map(|e| (e.point.x, e.point.y))
            .collect();
        assert_eq!(ends, vec![(200.0, 3.5), (200.0, 7.0)]);
        assert!(s.map.at_exit(Point::new(201.0, 3.0)));
        assert!(s.map.at_exit(Point::new(199.6, 7.5)));
        assert!(!s.map.at_exit(Point::new(198.0, 3.5)), "short of the end");
        assert!(!s.map.at_exit(Point::new(101.0, 0.0)), "a lane drop");
        assert!(
            !s.map.at_exit(Point::new(215.0, 3.5)),
            "beyond the 10 m band"
        );
    }

    #[test]
    fn a_crack_between_lanes_is_road_but_a_notch_in_the_edge_is_not() {
        // Two lanes whose shared boundary is stored twice, 2 cm apart (as NGSIM's lanelets do),
        // then a third lane beyond a 1 m kerbed median.
        let text = r#"
steps: 1
current_step: 0
map:
  road_edges:
    - points: [[0, 0], [100, 0]]
    - points: [[100, 7.02], [0, 7.02]]
    - points: [[0, 8.02], [100, 8.02]]
    - points: [[100, 11.52], [0, 11.52]]
  drivable_areas:
    - [[0, 0], [100, 0], [100, 3.5], [0, 3.5]]
    - [[0, 3.52], [100, 3.52], [100, 7.02], [0, 7.02]]
    - [[0, 8.02], [100, 8.02], [100, 11.52], [0, 11.52]]
agents:
  - {id: 1, states: [[1, 1, 0]]}
"#;
        let s = yaml::parse(Path::new("crack.yaml"), text).unwrap();
        let sd = |x, y| edge_distance(&s, x, y);
        assert!(
            (sd(50.0, 3.51) + 3.51).abs() < 1e-9,
            "in the crack: on the road, 3.51 m from the right edge, not off it"
        );
        assert!(sd(50.0, 7.5) > 0.0, "on the median");
        assert!(sd(50.0, -0.1) > 0.0, "beyond the edge");
        // Just beyond the edge where two consecutive areas meet: both nearest points lie
        // the same way, so it is no seam.
        let joint = r#"
steps: 1
current_step: 0
map:
  road_edges:
    - points: [[0, 0], [100, 0]]
    - points: [[100, 3.5], [0, 3.5]]
  drivable_areas:
    - [[0, 0], [50, 0], [50, 3.5], [0, 3.5]]
    - [[50, 0], [100, 0], [100, 3.5], [50, 3.5]]
agents:
  - {id: 1, states: [[1, 1, 0]]}
"#;
        let j = yaml::parse(Path::new("joint.yaml"), joint).unwrap();
        let d = edge_distance(&j, 50.0, -0.1);
        assert!((d - 0.1).abs() < 1e-9, "{d}");
    }

    #[test]
    fn edge_orientation_decides_without_drivable_areas() {
        // Road edges only (as in WOMD): the road is on the edge's left.
        let text = r#"
steps: 1
current_step: 0
map:
  road_edges:
    - points: [[0, 0], [100, 0]]
    - points: [[100, 7], [0, 7]]
agents:
  - {id: 1, states: [[1, 1, 0]]}
"#;
        let s = yaml::parse(Path::new("edges.yaml"), text).unwrap();
        let sd = |x, y| edge_distance(&s, x, y);
        assert!(sd(50.0, 2.0) < 0.0 && sd(50.0, 5.0) < 0.0);
        assert!(sd(50.0, -0.5) > 0.0 && sd(50.0, 7.5) > 0.0);
        let empty = yaml::parse(
            Path::new("e.yaml"),
            "steps: 1\ncurrent_step: 0\nmap: {}\nagents:\n  - {id: 1, states: [[1, 1, 0]]}\n",
        )
        .unwrap();
        assert_eq!(
            empty.map.signed_distance_to_road_edge(Point::new(0.0, 0.0)),
            None
        );
    }
}
