//! Simple polygons: crosswalks, drivable areas, lane surfaces.

use super::polyline::bounds_of;
use super::{cross, point_segment_distance, GeomError, Point};

/// A closed simple polygon (the last point connects back to the first).
#[derive(Debug, Clone, PartialEq)]
pub struct Polygon {
    points: Vec<Point>,
    lo: Point,
    hi: Point,
    /// A tree over the edges (edge `i` joins points `i - 1` and `i`): `levels[0]` holds per
    /// run of [`CHUNK`] edges its lowest and highest y and its largest x, and each level above
    /// the same per [`CHUNK`] nodes of the level below, so that `contains` skips whole stretches
    /// a ray cannot cross. One level was not enough: a 100 km lane surface has 200,000 edges,
    /// 12,500 runs looked at per point, and scoring 6,000 cars on it spent two thirds of its
    /// time here.
    levels: Vec<Vec<[f64; 3]>>,
}

/// Nodes of `below` merged by [`CHUNK`]: the lowest y, the highest y, the largest x.
fn merged(below: &[[f64; 3]]) -> Vec<[f64; 3]> {
    below
        .chunks(CHUNK)
        .map(|run| {
            run.iter().fold(
                [f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY],
                |c, n| [c[0].min(n[0]), c[1].max(n[1]), c[2].max(n[2])],
            )
        })
        .collect()
}

/// Edges per run of [`Polygon::contains`]'s broad phase.
const CHUNK: usize = 16;

impl Polygon {
    /// Builds a polygon; a repeated closing point is dropped. Needs three distinct points.
    pub fn new(points: impl IntoIterator<Item = Point>) -> Result<Self, GeomError> {
        let mut pts = super::finite_deduped(points, 1e-9)?;
        while pts.len() > 1 && (pts[0] - pts[pts.len() - 1]).norm() <= 1e-9 {
            pts.pop();
        }
        if pts.len() < 3 {
            return Err(GeomError::TooFewPoints {
                needed: 3,
                got: pts.len(),
            });
        }
        let (lo, hi) = bounds_of(&pts);
        let n = pts.len();
        let chunks: Vec<[f64; 3]> = (0..n)
            .step_by(CHUNK)
            .map(|start| {
                let mut c = [f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
                for i in start..(start + CHUNK).min(n) {
                    for q in [pts[i], pts[(i + n - 1) % n]] {
                        c = [c[0].min(q.y), c[1].max(q.y), c[2].max(q.x)];
                    }
                }
                c
            })
            .collect();
        let mut levels = vec![chunks];
        while levels[levels.len() - 1].len() > CHUNK {
            let up = merged(&levels[levels.len() - 1]);
            levels.push(up);
        }
        Ok(Self {
            points: pts,
            lo,
            hi,
            levels,
        })
    }

    /// The ring's points, without the closing repeat.
    pub fn points(&self) -> &[Point] {
        &self.points
    }

    /// Signed area: positive when the points run counter-clockwise.
    pub fn signed_area(&self) -> f64 {
        let n = self.points.len();
        0.5 * (0..n)
            .map(|i| cross(&self.points[i], &self.points[(i + 1) % n]))
            .sum::<f64>()
    }

    /// Axis-aligned bounding box `(min, max)`.
    pub fn bounds(&self) -> (Point, Point) {
        (self.lo, self.hi)
    }

    /// Whether `p` is inside (even-odd rule; points on the boundary may go either way).
    pub fn contains(&self, p: &Point) -> bool {
        if p.x < self.lo.x || p.x > self.hi.x || p.y < self.lo.y || p.y > self.hi.y {
            return false;
        }
        let n = self.points.len();
        let mut inside = false;
        let top = self.levels.len() - 1;
        // (level, node) pairs left to look at, depth first.
        let mut stack: Vec<(usize, usize)> = (0..self.levels[top].len())
            .rev()
            .map(|c| (top, c))
            .collect();
        while let Some((level, c)) = stack.pop() {
            let [ylo, yhi, xhi] = self.levels[level][c];
            // No edge below the node straddles the ray's height, or all lie left of p: none
            // crosses the ray going right from p.
            if p.y < ylo || p.y >= yhi || xhi < p.x {
                continue;
            }
            if level > 0 {
                let below = self.levels[level - 1].len();
                stack.extend(
                    (c * CHUNK..((c + 1) * CHUNK).min(below))
                        .rev()
                        .map(|k| (level - 1, k)),
                );
                continue;
            }
            for i in c * CHUNK..((c + 1) * CHUNK).min(n) {
                let (a, b) = (self.points[i], self.points[(i + n - 1) % n]);
                if (a.y > p.y) != (b.y > p.y) && p.x < (b.x - a.x) * (p.y - a.y) / (b.y - a.y) + a.x
                {
                    inside = !inside;
                }
            }
        }
        inside
    }

    /// Distance from `p` to the polygon's boundary.
    pub fn boundary_distance(&self, p: &Point) -> f64 {
        let n = self.points.len();
        (0..n)
            .map(|i| point_segment_distance(p, &self.points[i], &self.points[(i + 1) % n]).0)
            .fold(f64::INFINITY, f64::min)
    }

    /// The nearest point of the boundary to `p`, and its distance.
    pub fn nearest_boundary_point(&self, p: &Point) -> (f64, Point) {
        let n = self.points.len();
        (0..n)
            .map(|i| {
                let (a, b) = (self.points[i], self.points[(i + 1) % n]);
                let (d, t) = point_segment_distance(p, &a, &b);
                (d, a + (b - a) * t)
            })
            .fold((f64::INFINITY, *p), |m, x| if x.0 < m.0 { x } else { m })
    }

    /// Centroid of the vertices (good enough for label placement).
    pub fn vertex_centroid(&self) -> Point {
        self.points.iter().sum::<Point>() / self.points.len() as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn square_contains_and_area() {
        let sq = Polygon::new([
            Point::new(0.0, 0.0),
            Point::new(2.0, 0.0),
            Point::new(2.0, 2.0),
            Point::new(0.0, 2.0),
            Point::new(0.0, 0.0),
        ])
        .unwrap();
        assert_eq!(sq.points().len(), 4);
        let (d, q) = sq.nearest_boundary_point(&Point::new(1.5, 3.0));
        assert!((d - 1.0).abs() < 1e-12 && (q - Point::new(1.5, 2.0)).norm() < 1e-12);
        assert!((sq.signed_area() - 4.0).abs() < 1e-12);
        assert!(sq.contains(&Point::new(1.0, 1.0)));
        assert!(!sq.contains(&Point::new(3.0, 1.0)));
        assert!((sq.boundary_distance(&Point::new(1.0, 1.5)) - 0.5).abs() < 1e-12);
    }

    #[test]
    fn contains_agrees_with_the_even_odd_rule_over_every_edge() {
        // Combs of 200 and 5,000 teeth (800 and 20,000 points, two and three levels of the
        // tree): many crossings along a ray, runs of every kind.
        for teeth in [200, 5000] {
            comb_agrees(teeth);
        }
    }

    fn comb_agrees(teeth: usize) {
        let mut pts = Vec::new();
        for k in 0..teeth {
            let x = k as f64 * 2.0;
            pts.extend([
                Point::new(x, 0.0),
                Point::new(x, 10.0 + (k % 7) as f64),
                Point::new(x + 1.0, 10.0 + (k % 5) as f64),
                Point::new(x + 1.0, 1.0),
            ]);
        }
        let end = 2.0 * teeth as f64;
        pts.push(Point::new(end, 0.0));
        pts.push(Point::new(end, -5.0));
        pts.push(Point::new(0.0, -5.0));
        let poly = Polygon::new(pts.clone()).unwrap();
        assert_eq!(poly.levels.len(), if teeth == 200 { 2 } else { 3 });
        let n = pts.len();
        for q in 0..2000 {
            let p = Point::new(
                (q % 100) as f64 * (end + 4.0) / 100.0 - 2.0 + 0.07,
                (q / 100) as f64 * 1.13 - 6.0,
            );
            let mut want = false;
            for i in 0..n {
                let (a, b) = (pts[i], pts[(i + n - 1) % n]);
                if (a.y > p.y) != (b.y > p.y) && p.x < (b.x - a.x) * (p.y - a.y) / (b.y - a.y) + a.x
                {
                    want = !want;
                }
            }
            assert_eq!(poly.contains(&p), want, "{p:?}");
        }
    }

    #[test]
    fn degenerate_polygon_fails() {
        assert!(Polygon::new([Point::new(0.0, 0.0), Point::new(1.0, 0.0)]).is_err());
    }
}
