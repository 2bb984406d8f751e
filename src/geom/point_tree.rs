//! Points in a k-d tree, for corridor queries over every point of a map.

use super::Point;

/// Points in a k-d tree (split at the median, alternately in x and y) with each node's bounds,
/// for whether any point lies in a corridor (the map's exits: beyond a dead-end lane's end,
/// `scene::Map`). Trying every point of the map for every dead end was quadratic: a CommonRoad
/// file of 30,000 short lanelets (7 MB) took 15 s in it.
pub struct PointTree {
    points: Vec<Point>,
    /// Per node: the bounds of its points `points[lo..hi]`, `lo`, `hi`, and its children's
    /// indices (none for a leaf).
    nodes: Vec<TreeNode>,
}

struct TreeNode {
    lo_corner: Point,
    hi_corner: Point,
    lo: usize,
    hi: usize,
    children: Option<(usize, usize)>,
}

/// Points a leaf of [`PointTree`] holds at most.
const TREE_LEAF: usize = 16;

impl PointTree {
    /// The tree of `points`.
    pub fn new(mut points: Vec<Point>) -> Self {
        let mut nodes = Vec::new();
        let n = points.len();
        if n > 0 {
            Self::build(&mut points, 0, n, true, &mut nodes);
        }
        Self { points, nodes }
    }

    /// Adds the node of `all[lo..hi]` (not empty) and its subtree; returns its index.
    fn build(all: &mut [Point], lo: usize, hi: usize, x: bool, nodes: &mut Vec<TreeNode>) -> usize {
        let part = &mut all[lo..hi];
        let first = part[0];
        let (a, b) = part
            .iter()
            .fold((first, first), |(a, c), p| (a.inf(p), c.sup(p)));
        let at = nodes.len();
        nodes.push(TreeNode {
            lo_corner: a,
            hi_corner: b,
            lo,
            hi,
            children: None,
        });
        if part.len() > TREE_LEAF {
            let mid = part.len() / 2;
            let key = |p: &Point| if x { p.x } else { p.y };
            part.select_nth_unstable_by(mid, |a, b| key(a).total_cmp(&key(b)));
            let l = Self::build(all, lo, lo + mid, !x, nodes);
            let r = Self::build(all, lo + mid, hi, !x, nodes);
            nodes[at].children = Some((l, r));
        }
        at
    }

    /// Whether a point `q` lies in the corridor from `point` along the unit `direction`:
    /// `(q - point) . direction > ahead` and `|(q - point) x direction| < half_width`. A node
    /// whose corners are all inside holds only such points (the corridor is convex); one whose
    /// corners all lie beyond one of its three sides holds none.
    pub fn any_in_corridor(
        &self,
        point: Point,
        direction: Point,
        ahead: f64,
        half_width: f64,
    ) -> bool {
        let uv = |q: Point| {
            let r = q - point;
            (r.dot(&direction), r.perp(&direction))
        };
        let inside = |(u, v): (f64, f64)| u > ahead && v.abs() < half_width;
        let mut stack = match self.nodes.is_empty() {
            true => vec![],
            false => vec![0],
        };
        while let Some(k) = stack.pop() {
            let n = &self.nodes[k];
            let (a, b) = (n.lo_corner, n.hi_corner);
            let c = [a, Point::new(a.x, b.y), b, Point::new(b.x, a.y)].map(uv);
            if c.iter().all(|&q| inside(q)) {
                return true;
            }
            if c.iter().all(|q| q.0 <= ahead)
                || c.iter().all(|q| q.1 >= half_width)
                || c.iter().all(|q| q.1 <= -half_width)
            {
                continue;
            }
            match n.children {
                Some((l, r)) => stack.extend([l, r]),
                None => {
                    if self.points[n.lo..n.hi].iter().any(|&p| inside(uv(p))) {
                        return true;
                    }
                }
            }
        }
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corridor_queries_agree_with_trying_every_point() {
        // A fixed pseudo-random cloud, queried from points and directions all around it.
        let mut state = 12345u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let points: Vec<Point> = (0..500)
            .map(|_| Point::new(next() * 200.0 - 100.0, next() * 200.0 - 100.0))
            .collect();
        let tree = PointTree::new(points.clone());
        let mut hits = 0;
        for _ in 0..400 {
            let at = Point::new(next() * 240.0 - 120.0, next() * 240.0 - 120.0);
            let a = next() * std::f64::consts::TAU;
            let dir = Point::new(a.cos(), a.sin());
            let (ahead, half) = (next() * 20.0, next() * 3.0);
            let brute = points.iter().any(|&q| {
                let r = q - at;
                r.dot(&dir) > ahead && r.perp(&dir).abs() < half
            });
            assert_eq!(tree.any_in_corridor(at, dir, ahead, half), brute);
            hits += brute as usize;
        }
        // Both answers occur.
        assert!(hits > 20 && hits < 380, "{hits}");
        assert!(!PointTree::new(vec![]).any_in_corridor(
            Point::zeros(),
            Point::new(1.0, 0.0),
            0.0,
            1.0
        ));
    }
}
