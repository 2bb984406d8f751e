//! Simple polygons: crosswalks, drivable areas, lane surfaces.

use super::polyline::bounds_of;
use super::{cross, point_segment_distance, GeomError, Point};

/// A closed simple polygon (the last point connects back to the first).
#[derive(Debug, Clone, PartialEq)]
pub struct Polygon {
    points: Vec<Point>,
    lo: Point,
    hi: Point,
}

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
        Ok(Self {
            points: pts,
            lo,
            hi,
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
        let mut j = n - 1;
        for i in 0..n {
            let (a, b) = (self.points[i], self.points[j]);
            if (a.y > p.y) != (b.y > p.y) && p.x < (b.x - a.x) * (p.y - a.y) / (b.y - a.y) + a.x {
                inside = !inside;
            }
            j = i;
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
    fn degenerate_polygon_fails() {
        assert!(Polygon::new([Point::new(0.0, 0.0), Point::new(1.0, 0.0)]).is_err());
    }
}
