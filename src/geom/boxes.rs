//! Oriented boxes: agents' footprints, their overlap, distance and IoU.

use super::{cross, segment_segment_distance, Point};

/// An agent's footprint: a rectangle centred at `center`, long side along `heading`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OrientedBox {
    /// Centre of the box.
    pub center: Point,
    /// Heading of the long axis, radians.
    pub heading: f64,
    /// Extent along the heading.
    pub length: f64,
    /// Extent across the heading.
    pub width: f64,
}

impl OrientedBox {
    /// A box from its pose and size.
    pub fn new(x: f64, y: f64, heading: f64, length: f64, width: f64) -> Self {
        Self {
            center: Point::new(x, y),
            heading,
            length,
            width,
        }
    }

    /// Unit vectors along and across the heading.
    pub fn axes(&self) -> (Point, Point) {
        let (s, c) = self.heading.sin_cos();
        (Point::new(c, s), Point::new(-s, c))
    }

    /// Corners counter-clockwise: rear-right, front-right, front-left, rear-left.
    pub fn corners(&self) -> [Point; 4] {
        let (u, v) = self.axes();
        let hl = u * (0.5 * self.length);
        let hw = v * (0.5 * self.width);
        let c = self.center;
        [c - hl - hw, c + hl - hw, c + hl + hw, c - hl + hw]
    }

    /// Area.
    pub fn area(&self) -> f64 {
        self.length * self.width
    }

    /// Whether the boxes share any point (separating-axis test).
    pub fn overlaps(&self, other: &OrientedBox) -> bool {
        let a = self.corners();
        let b = other.corners();
        let (u1, v1) = self.axes();
        let (u2, v2) = other.axes();
        [u1, v1, u2, v2].iter().all(|axis| {
            let pa = project(&a, axis);
            let pb = project(&b, axis);
            pa.0 <= pb.1 && pb.0 <= pa.1
        })
    }

    /// Shortest distance between the two boxes; zero when they overlap.
    pub fn distance(&self, other: &OrientedBox) -> f64 {
        if self.overlaps(other) {
            return 0.0;
        }
        let a = self.corners();
        let b = other.corners();
        let mut best = f64::INFINITY;
        for i in 0..4 {
            for j in 0..4 {
                best = best.min(segment_segment_distance(
                    &a[i],
                    &a[(i + 1) % 4],
                    &b[j],
                    &b[(j + 1) % 4],
                ));
            }
        }
        best
    }

    /// Area of the intersection of the two boxes.
    pub fn intersection_area(&self, other: &OrientedBox) -> f64 {
        if !self.overlaps(other) {
            return 0.0;
        }
        let mut poly: Vec<Point> = self.corners().to_vec();
        let clip = other.corners();
        for i in 0..4 {
            let (a, b) = (clip[i], clip[(i + 1) % 4]);
            let inside = |p: &Point| cross(&(b - a), &(p - a)) >= 0.0;
            let input = std::mem::take(&mut poly);
            for k in 0..input.len() {
                let cur = input[k];
                let prev = input[(k + input.len() - 1) % input.len()];
                let (ci, pi) = (inside(&cur), inside(&prev));
                if ci != pi {
                    let d1 = cross(&(b - a), &(prev - a));
                    let d2 = cross(&(b - a), &(cur - a));
                    poly.push(prev + (cur - prev) * (d1 / (d1 - d2)));
                }
                if ci {
                    poly.push(cur);
                }
            }
            if poly.is_empty() {
                return 0.0;
            }
        }
        let n = poly.len();
        0.5 * (0..n)
            .map(|i| cross(&poly[i], &poly[(i + 1) % n]))
            .sum::<f64>()
            .abs()
    }

    /// Intersection over union of the two boxes.
    pub fn iou(&self, other: &OrientedBox) -> f64 {
        let inter = self.intersection_area(other);
        let union = self.area() + other.area() - inter;
        if union > 0.0 {
            inter / union
        } else {
            0.0
        }
    }
}

fn project(corners: &[Point; 4], axis: &Point) -> (f64, f64) {
    corners
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), c| {
            let p = c.dot(axis);
            (lo.min(p), hi.max(p))
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_4;

    #[test]
    fn separated_boxes_have_the_gap_as_distance() {
        let a = OrientedBox::new(0.0, 0.0, 0.0, 4.0, 2.0);
        let b = OrientedBox::new(7.0, 0.0, 0.0, 4.0, 2.0);
        assert!(!a.overlaps(&b));
        assert!((a.distance(&b) - 3.0).abs() < 1e-12);
        assert_eq!(a.iou(&b), 0.0);
    }

    #[test]
    fn rotated_corner_touching_a_box_overlaps() {
        let a = OrientedBox::new(0.0, 0.0, 0.0, 2.0, 2.0);
        // A diamond whose corner reaches x = 1 - 0.1 inside the square.
        let r = 2f64.sqrt();
        let b = OrientedBox::new(1.0 + r - 0.1, 0.0, FRAC_PI_4, 2.0, 2.0);
        assert!(a.overlaps(&b));
        assert_eq!(a.distance(&b), 0.0);
        let c = OrientedBox::new(1.0 + r + 0.1, 0.0, FRAC_PI_4, 2.0, 2.0);
        assert!(!c.overlaps(&a));
        assert!((a.distance(&c) - 0.1).abs() < 1e-9);
    }

    #[test]
    fn iou_of_shifted_boxes() {
        let a = OrientedBox::new(0.0, 0.0, 0.3, 4.0, 2.0);
        assert!((a.iou(&a) - 1.0).abs() < 1e-9);
        let b = OrientedBox::new(0.0, 0.0, 0.0, 4.0, 2.0);
        let c = OrientedBox::new(2.0, 0.0, 0.0, 4.0, 2.0);
        // Overlap 2x2 = 4, union 8 + 8 - 4 = 12.
        assert!((b.iou(&c) - 4.0 / 12.0).abs() < 1e-9);
    }
}
