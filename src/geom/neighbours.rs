//! Which points are near each other, without looking at every pair: a uniform grid for
//! "every pair within reach" and a 2-d tree for "the nearest other point". Collision costs and
//! metrics over thousands of agents would otherwise grow with the square of their number.

use std::collections::HashMap;

use super::Point;

/// Up to this many points every pair is looked at directly: hashing each point into the grid
/// and looking up nine cells around it costs more than the pairs themselves (`drivescript
/// bench cost`'s no_collisions, 24 cars over 80 steps, took twice as long through the grid),
/// and collision costs call this at every step of every evaluation. The grid pays only once
/// the pairs outnumber the cell lookups by far: 96 points are 4,560 pairs, each one
/// subtraction and a square root, against 864 hashed lookups.
const SCAN_UP_TO: usize = 96;

/// Every pair `(a, b)`, `a < b`, of points whose centres are at most `reach[a] + reach[b] +
/// extra` apart, in the order of a scan over all pairs (so that sums over them do not depend
/// on the grid). Points with a non-finite coordinate are in no pair.
pub fn pairs_within(centres: &[Point], reach: &[f64], extra: f64) -> Vec<(usize, usize)> {
    debug_assert_eq!(centres.len(), reach.len());
    if centres.len() <= SCAN_UP_TO {
        scan(centres, reach, extra)
    } else {
        grid(centres, reach, extra)
    }
}

/// [`pairs_within`] by looking at every pair: cheapest for the few agents of a scene.
fn scan(centres: &[Point], reach: &[f64], extra: f64) -> Vec<(usize, usize)> {
    let finite = |p: &Point| p.x.is_finite() && p.y.is_finite();
    let mut pairs = Vec::new();
    for (a, pa) in centres.iter().enumerate() {
        if !finite(pa) {
            continue;
        }
        for (b, pb) in centres.iter().enumerate().skip(a + 1) {
            // The same test as the grid's, so that both find the same pairs.
            if finite(pb) && (pa - pb).norm() <= reach[a] + reach[b] + extra {
                pairs.push((a, b));
            }
        }
    }
    pairs
}

/// [`pairs_within`] through a uniform grid: grows with the points, not their pairs.
fn grid(centres: &[Point], reach: &[f64], extra: f64) -> Vec<(usize, usize)> {
    let farthest = reach.iter().cloned().fold(0.0, f64::max);
    // As wide as the farthest reach of any pair: only points in neighbouring cells can be near.
    let cell = 2.0 * farthest + extra.max(0.0) + 1e-9;
    let mut grid: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
    for (i, p) in centres.iter().enumerate() {
        if p.x.is_finite() && p.y.is_finite() {
            let key = ((p.x / cell).floor() as i64, (p.y / cell).floor() as i64);
            grid.entry(key).or_default().push(i);
        }
    }
    let mut pairs = Vec::new();
    for (&(cx, cy), members) in &grid {
        for dx in -1..=1 {
            for dy in -1..=1 {
                let Some(other) = grid.get(&(cx + dx, cy + dy)) else {
                    continue;
                };
                for &a in members {
                    for &b in other.iter().filter(|&&b| b > a) {
                        let near = reach[a] + reach[b] + extra;
                        if (centres[a] - centres[b]).norm() <= near {
                            pairs.push((a, b));
                        }
                    }
                }
            }
        }
    }
    pairs.sort_unstable();
    pairs
}

/// For each point, the distance to the nearest other point (`None` when it is alone), from a
/// 2-d tree: O(n log n) for points spread over a road.
pub fn nearest_distances(points: &[Point]) -> Vec<Option<f64>> {
    let mut order: Vec<usize> = (0..points.len()).collect();
    build(points, &mut order, 0);
    points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let mut best = f64::INFINITY;
            nearest(points, &order, 0, p, i, &mut best);
            best.is_finite().then_some(best)
        })
        .collect()
}

/// Arranges `idx` as an implicit 2-d tree: the median (by x at even depths, y at odd ones) in
/// the middle, the halves on either side, recursively.
fn build(points: &[Point], idx: &mut [usize], depth: usize) {
    if idx.len() <= 1 {
        return;
    }
    let mid = idx.len() / 2;
    let axis = depth % 2;
    idx.select_nth_unstable_by(mid, |&a, &b| points[a][axis].total_cmp(&points[b][axis]));
    let (lo, hi) = idx.split_at_mut(mid);
    build(points, lo, depth + 1);
    build(points, &mut hi[1..], depth + 1);
}

fn nearest(points: &[Point], idx: &[usize], depth: usize, p: &Point, skip: usize, best: &mut f64) {
    if idx.is_empty() {
        return;
    }
    let mid = idx.len() / 2;
    let here = idx[mid];
    if here != skip {
        let d = (points[here] - p).norm();
        if d < *best {
            *best = d;
        }
    }
    let axis = depth % 2;
    let diff = p[axis] - points[here][axis];
    let (near, far) = if diff < 0.0 {
        (&idx[..mid], &idx[mid + 1..])
    } else {
        (&idx[mid + 1..], &idx[..mid])
    };
    nearest(points, near, depth + 1, p, skip, best);
    // NaN differences fall through to a full search, never to a wrong answer.
    if !(diff.abs() >= *best) {
        nearest(points, far, depth + 1, p, skip, best);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Seeded points: clusters, a line, duplicates and a far outlier.
    fn cloud(n: usize, seed: u64) -> Vec<Point> {
        let mut s = seed;
        let mut r = move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut pts: Vec<Point> = (0..n)
            .map(|k| match k % 4 {
                0 => Point::new(r() * 500.0, r() * 20.0),
                1 => Point::new(100.0 + r() * 3.0, 5.0 + r() * 3.0),
                2 => Point::new(7.0, r() * 300.0),
                _ => Point::new(r() * 1000.0, -r() * 1000.0),
            })
            .collect();
        pts.push(pts[3]);
        pts.push(Point::new(1e6, -1e6));
        pts
    }

    #[test]
    fn pairs_within_reach_are_the_pairs_a_full_scan_finds() {
        let full = |pts: &[Point], reach: &[f64]| {
            let mut all = Vec::new();
            for a in 0..pts.len() {
                for b in a + 1..pts.len() {
                    if (pts[a] - pts[b]).norm() <= reach[a] + reach[b] + 0.5 {
                        all.push((a, b));
                    }
                }
            }
            all
        };
        // Sizes on either side of where the scan hands over to the grid (a cloud of n has
        // n + 2 points), each with points that are in no pair (not finite).
        for n in [4, 20, SCAN_UP_TO - 2, SCAN_UP_TO + 1, 400] {
            for seed in 1..6 {
                let mut pts = cloud(n, seed);
                let k = pts.len();
                pts[k / 2] = Point::new(f64::NAN, 1.0);
                pts[k / 3] = Point::new(2.0, f64::INFINITY);
                let reach: Vec<f64> = (0..k).map(|i| 0.5 + (i % 7) as f64).collect();
                let want = full(&pts, &reach);
                assert!(n < 20 || !want.is_empty(), "{n} points: no pair to compare");
                assert_eq!(pairs_within(&pts, &reach, 0.5), want, "{n} points");
                assert_eq!(scan(&pts, &reach, 0.5), want, "scan, {n} points");
                assert_eq!(grid(&pts, &reach, 0.5), want, "grid, {n} points");
            }
        }
        let one = [Point::new(1.0, 1.0)];
        assert!(pairs_within(&[], &[], 0.5).is_empty());
        assert!(pairs_within(&one, &[1.0], 0.5).is_empty());
        assert_eq!(pairs_within(&[one[0], one[0]], &[1.0, 1.0], 0.0), [(0, 1)]);
    }

    #[test]
    fn nearest_distances_are_those_of_a_full_scan() {
        for seed in 1..6 {
            let pts = cloud(500, seed);
            let got = nearest_distances(&pts);
            for (i, p) in pts.iter().enumerate() {
                let want = pts
                    .iter()
                    .enumerate()
                    .filter(|(j, _)| *j != i)
                    .map(|(_, q)| (p - q).norm())
                    .fold(f64::INFINITY, f64::min);
                assert_eq!(got[i], Some(want), "point {i}");
            }
        }
        assert_eq!(nearest_distances(&[Point::new(1.0, 2.0)]), vec![None]);
        assert!(nearest_distances(&[]).is_empty());
    }
}
