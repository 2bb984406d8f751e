//! The lane graph: successor, predecessor and same-direction left/right neighbour edges.

use std::collections::{HashMap, HashSet};

use serde::Serialize;

use super::map::{Lane, LaneId};

/// Topology of the lanes of a map, by lane id.
///
/// Edges are made symmetric (a successor edge implies the predecessor edge back, a left
/// neighbour implies the right neighbour back) because sources often list only one side.
/// References to lanes that are not in the map are dropped from the graph and counted in
/// [`LaneGraph::dangling`] (WOMD maps are cropped, so their lanes name lanes outside the crop).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LaneGraph {
    index: HashMap<LaneId, usize>,
    ids: Vec<LaneId>,
    succ: Vec<Vec<LaneId>>,
    pred: Vec<Vec<LaneId>>,
    left: Vec<Vec<LaneId>>,
    right: Vec<Vec<LaneId>>,
    dangling: usize,
}

/// Number of directed edges of each kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
pub struct EdgeCounts {
    /// lane → successor edges.
    pub successor: usize,
    /// lane → predecessor edges.
    pub predecessor: usize,
    /// lane → left neighbour edges.
    pub left: usize,
    /// lane → right neighbour edges.
    pub right: usize,
}

/// Appends `id` to list `which` (0 successors, 1 predecessors, 2 left, 3 right) of lane `at`
/// unless it is there: `seen` holds every entry, since `contains` on the list made a lane that
/// thousands of lanes name cost the square of their number, and a file of such lanes the cube.
fn push_unique(
    seen: &mut HashSet<(u8, usize, LaneId)>,
    lists: &mut [Vec<LaneId>],
    which: u8,
    at: usize,
    id: LaneId,
) {
    if seen.insert((which, at, id)) {
        lists[at].push(id);
    }
}

impl LaneGraph {
    /// Builds the graph from the lanes' own edge lists. Lane ids must be unique (checked by
    /// the map).
    pub fn build(lanes: &[Lane]) -> Self {
        let n = lanes.len();
        let index: HashMap<LaneId, usize> =
            lanes.iter().enumerate().map(|(i, l)| (l.id, i)).collect();
        let mut g = LaneGraph {
            ids: lanes.iter().map(|l| l.id).collect(),
            succ: vec![Vec::new(); n],
            pred: vec![Vec::new(); n],
            left: vec![Vec::new(); n],
            right: vec![Vec::new(); n],
            dangling: 0,
            index,
        };
        let mut seen = HashSet::new();
        for (i, lane) in lanes.iter().enumerate() {
            let lists = [
                (&lane.successors, 0),
                (&lane.predecessors, 1),
                (&lane.left_neighbors, 2),
                (&lane.right_neighbors, 3),
            ];
            for (list, kind) in lists {
                for &other in list {
                    let Some(&j) = g.index.get(&other) else {
                        g.dangling += 1;
                        continue;
                    };
                    if j == i {
                        continue;
                    }
                    let (fwd, back) = match kind {
                        0 => ((&mut g.succ, 0), (&mut g.pred, 1)),
                        1 => ((&mut g.pred, 1), (&mut g.succ, 0)),
                        2 => ((&mut g.left, 2), (&mut g.right, 3)),
                        _ => ((&mut g.right, 3), (&mut g.left, 2)),
                    };
                    push_unique(&mut seen, fwd.0, fwd.1, i, other);
                    push_unique(&mut seen, back.0, back.1, j, lane.id);
                }
            }
        }
        g
    }

    fn at(&self, id: LaneId) -> Option<usize> {
        self.index.get(&id).copied()
    }

    /// Whether the lane is in the graph.
    pub fn contains(&self, id: LaneId) -> bool {
        self.index.contains_key(&id)
    }

    /// Lanes this lane flows into.
    pub fn successors(&self, id: LaneId) -> &[LaneId] {
        self.at(id).map_or(&[], |i| &self.succ[i])
    }

    /// Lanes that flow into this lane.
    pub fn predecessors(&self, id: LaneId) -> &[LaneId] {
        self.at(id).map_or(&[], |i| &self.pred[i])
    }

    /// All left neighbours (same direction).
    pub fn left_neighbors(&self, id: LaneId) -> &[LaneId] {
        self.at(id).map_or(&[], |i| &self.left[i])
    }

    /// All right neighbours (same direction).
    pub fn right_neighbors(&self, id: LaneId) -> &[LaneId] {
        self.at(id).map_or(&[], |i| &self.right[i])
    }

    /// The left neighbour (the first listed, when a source lists several).
    pub fn left(&self, id: LaneId) -> Option<LaneId> {
        self.left_neighbors(id).first().copied()
    }

    /// The right neighbour (the first listed).
    pub fn right(&self, id: LaneId) -> Option<LaneId> {
        self.right_neighbors(id).first().copied()
    }

    /// Follows left neighbours as far as they go.
    pub fn leftmost(&self, id: LaneId) -> LaneId {
        self.walk(id, |g, l| g.left(l))
    }

    /// Follows right neighbours as far as they go.
    pub fn rightmost(&self, id: LaneId) -> LaneId {
        self.walk(id, |g, l| g.right(l))
    }

    /// Whether no lane lies to the right in the same direction.
    pub fn is_rightmost(&self, id: LaneId) -> bool {
        self.right(id).is_none()
    }

    /// Number of same-direction lanes side by side with this one (itself included).
    pub fn lane_count(&self, id: LaneId) -> usize {
        let mut n = 1;
        let mut cur = self.leftmost(id);
        let mut seen = vec![cur];
        while let Some(r) = self.right(cur) {
            if seen.contains(&r) {
                break;
            }
            seen.push(r);
            cur = r;
            n += 1;
        }
        n
    }

    fn walk(&self, id: LaneId, step: impl Fn(&Self, LaneId) -> Option<LaneId>) -> LaneId {
        let mut cur = id;
        // Maps with inconsistent neighbour lists can form cycles.
        for _ in 0..self.ids.len() {
            match step(self, cur) {
                Some(next) if next != id => cur = next,
                _ => break,
            }
        }
        cur
    }

    /// References to lanes missing from the map.
    pub fn dangling(&self) -> usize {
        self.dangling
    }

    /// Number of directed edges of each kind.
    pub fn edge_counts(&self) -> EdgeCounts {
        let count = |v: &Vec<Vec<LaneId>>| v.iter().map(Vec::len).sum();
        EdgeCounts {
            successor: count(&self.succ),
            predecessor: count(&self.pred),
            left: count(&self.left),
            right: count(&self.right),
        }
    }
}

/// Largest gap (metres) between a lane's end and the start of a lane it names as successor,
/// or between a predecessor's end and its start, before the link counts as far. On 14,539
/// links of 260 real maps (CommonRoad samples, SUMO and scenario-factory towns) the largest
/// is 0.26 m; a path along a far link jumps by the gap, which no car drives.
pub const LINK_GAP: f64 = 2.0;

/// A successor or predecessor link whose lanes do not meet (see [`LINK_GAP`]).
#[derive(Debug, Clone, PartialEq)]
pub struct FarLink {
    /// The lane that names the other.
    pub lane: LaneId,
    /// The lane named.
    pub other: LaneId,
    /// Whether `other` is named as a successor (else as a predecessor).
    pub successor: bool,
    /// Distance in metres from the earlier lane's end to the later lane's start.
    pub gap: f64,
}

/// Successor and predecessor links of `lanes` whose ends lie more than [`LINK_GAP`] apart,
/// in the order the lanes and their lists give them. Links to lanes not among `lanes` are
/// not judged (a cropped map names lanes outside it).
pub fn far_links(lanes: &[Lane]) -> Vec<FarLink> {
    let by_id: HashMap<LaneId, &Lane> = lanes.iter().map(|l| (l.id, l)).collect();
    let mut out = Vec::new();
    // A link given from both ends (a successor, and the predecessor back) is one link.
    let mut seen = HashSet::new();
    for l in lanes {
        for (successor, ids) in [(true, &l.successors), (false, &l.predecessors)] {
            for id in ids {
                let Some(o) = by_id.get(id) else { continue };
                let pair = if successor { (l.id, *id) } else { (*id, l.id) };
                if !seen.insert(pair) {
                    continue;
                }
                let gap = if successor {
                    (o.centerline.first() - l.centerline.last()).norm()
                } else {
                    (l.centerline.first() - o.centerline.last()).norm()
                };
                // NaN never reaches here (polylines are finite), so `>` is the whole test.
                if gap > LINK_GAP {
                    out.push(FarLink {
                        lane: l.id,
                        other: *id,
                        successor,
                        gap,
                    });
                }
            }
        }
    }
    out
}
