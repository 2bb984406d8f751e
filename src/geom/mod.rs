//! Planar geometry: polylines, the Frenet frame of a path, oriented boxes, polygons,
//! neighbour queries and a grid of segments.
//!
//! Everything is in a right-handed world frame in metres; angles are radians counter-clockwise
//! from +x. "Left" is the side a driver going along a polyline sees on the left (positive `d`).

mod boxes;
mod cell_index;
mod frenet;
mod neighbours;
mod point_tree;
mod polygon;
mod polyline;
mod segment_grid;

pub use boxes::OrientedBox;
pub use cell_index::CellIndex;
pub use frenet::{FramePoint, FrenetPath, FrenetPoint};
pub use neighbours::{nearest_distances, pairs_within};
pub use point_tree::PointTree;
pub use polygon::Polygon;
pub use polyline::{Polyline, SegmentHit, MAX_RESAMPLED_POINTS};
pub use segment_grid::{GridHit, SegmentGrid};

/// A point or a vector in the plane.
pub type Point = nalgebra::Vector2<f64>;

/// Errors from building geometry out of input data.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeomError {
    /// A polyline needs two distinct points, a polygon three.
    #[error("needs at least {needed} distinct points, got {got}")]
    TooFewPoints {
        /// The minimum number of distinct points.
        needed: usize,
        /// How many distinct points there were.
        got: usize,
    },
    /// A coordinate farther from the origin than [`MAX_COORD`].
    #[error("point {index} ({}, {}) lies more than {MAX_COORD:e} m from the origin: not a plausible map coordinate", num(*.x), num(*.y))]
    OutOfRange {
        /// Index of the offending point in the input.
        index: usize,
        /// Its x coordinate.
        x: f64,
        /// Its y coordinate.
        y: f64,
    },
    /// A coordinate was NaN or infinite.
    #[error("point {index} is not finite: ({x}, {y})")]
    NonFinite {
        /// Index of the offending point in the input.
        index: usize,
        /// Its x coordinate.
        x: f64,
        /// Its y coordinate.
        y: f64,
    },
}

/// A number for a message: plain, or in exponent form when huge or tiny (a value of 1e300
/// printed plainly is 301 digits, a denormal such as 5e-324 over 300).
pub fn num(v: f64) -> String {
    if v.abs() >= 1e7 || (v != 0.0 && v.abs() < 1e-6) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// A computed value in four significant figures (a measured 237.87322893087398 m/s reads
/// 237.9), in scientific notation outside 0.001 to 10 million: for numbers nobody typed, which
/// [`num`] would print to the last of their 17 digits.
pub fn approx(v: f64) -> String {
    if !v.is_finite() || v == 0.0 {
        return format!("{v}");
    }
    if v.abs() >= 1e7 || v.abs() < 1e-3 {
        return format!("{v:.3e}");
    }
    let decimals = (3 - v.abs().log10().floor() as i32).max(0) as usize;
    let s = format!("{v:.decimals$}");
    // 500.0 reads 500, 0.3000 reads 0.3.
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// Whether `text`, which Rust's parser read as `v`, is a number written beyond the largest
/// float (`1e400` reads as infinity): said as written ("1e400 is beyond ..."), not as "inf",
/// a value nobody typed. `inf` typed as such is not.
pub fn written_beyond_f64(text: &str, v: f64) -> bool {
    v.is_infinite() && text.bytes().any(|b| b.is_ascii_digit())
}

/// What [`written_beyond_f64`]'s messages say after the number as written.
pub const BEYOND_F64: &str = "is beyond the largest number (about 1.8e308)";

/// The largest |x| or |y| accepted, metres. Real maps use local or UTM coordinates (at most a
/// few million metres); beyond this, f64 keeps too few digits below the metre for resampling
/// and projections, which then fail where they cannot (1e200 panicked in resampling).
pub const MAX_COORD: f64 = 1.0e7;

/// Checks that every point is finite and within [`MAX_COORD`], and drops each point closer than
/// `eps` to the one kept before it.
pub(crate) fn finite_deduped(
    points: impl IntoIterator<Item = Point>,
    eps: f64,
) -> Result<Vec<Point>, GeomError> {
    let mut out: Vec<Point> = Vec::new();
    for (index, p) in points.into_iter().enumerate() {
        if !p.x.is_finite() || !p.y.is_finite() {
            return Err(GeomError::NonFinite {
                index,
                x: p.x,
                y: p.y,
            });
        }
        if p.x.abs() > MAX_COORD || p.y.abs() > MAX_COORD {
            return Err(GeomError::OutOfRange {
                index,
                x: p.x,
                y: p.y,
            });
        }
        if out.last().is_none_or(|q| (p - q).norm() > eps) {
            out.push(p);
        }
    }
    Ok(out)
}

/// The 2-D cross product `a × b` (z component).
#[inline]
pub fn cross(a: &Point, b: &Point) -> f64 {
    a.x * b.y - a.y * b.x
}

/// `v` rotated by +90° (to the left).
#[inline]
pub fn left_normal(v: &Point) -> Point {
    Point::new(-v.y, v.x)
}

/// An angle wrapped to (-π, π].
#[inline]
pub fn wrap_angle(a: f64) -> f64 {
    let two_pi = std::f64::consts::TAU;
    let mut r = a % two_pi;
    if r <= -std::f64::consts::PI {
        r += two_pi;
    } else if r > std::f64::consts::PI {
        r -= two_pi;
    }
    r
}

/// Distance from `p` to the segment `a`–`b`, and the clamped parameter of the closest point.
#[inline]
pub fn point_segment_distance(p: &Point, a: &Point, b: &Point) -> (f64, f64) {
    let e = b - a;
    let len2 = e.norm_squared();
    let t = if len2 > 0.0 {
        ((p - a).dot(&e) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    ((p - (a + e * t)).norm(), t)
}

/// Shortest distance between segments `a0`–`a1` and `b0`–`b1` (zero when they cross).
pub fn segment_segment_distance(a0: &Point, a1: &Point, b0: &Point, b1: &Point) -> f64 {
    if segments_intersect(a0, a1, b0, b1) {
        return 0.0;
    }
    point_segment_distance(a0, b0, b1)
        .0
        .min(point_segment_distance(a1, b0, b1).0)
        .min(point_segment_distance(b0, a0, a1).0)
        .min(point_segment_distance(b1, a0, a1).0)
}

/// Whether the closed segments `a0`–`a1` and `b0`–`b1` share a point.
pub fn segments_intersect(a0: &Point, a1: &Point, b0: &Point, b1: &Point) -> bool {
    let d1 = cross(&(b1 - b0), &(a0 - b0));
    let d2 = cross(&(b1 - b0), &(a1 - b0));
    let d3 = cross(&(a1 - a0), &(b0 - a0));
    let d4 = cross(&(a1 - a0), &(b1 - a0));
    if ((d1 > 0.0 && d2 < 0.0) || (d1 < 0.0 && d2 > 0.0))
        && ((d3 > 0.0 && d4 < 0.0) || (d3 < 0.0 && d4 > 0.0))
    {
        return true;
    }
    let on = |p: &Point, q: &Point, r: &Point, d: f64| {
        d == 0.0
            && r.x >= p.x.min(q.x)
            && r.x <= p.x.max(q.x)
            && r.y >= p.y.min(q.y)
            && r.y <= p.y.max(q.y)
    };
    on(b0, b1, a0, d1) || on(b0, b1, a1, d2) || on(a0, a1, b0, d3) || on(a0, a1, b1, d4)
}

#[cfg(test)]
mod tests {
    #[test]
    fn approx_says_a_computed_value_in_four_figures() {
        use super::approx;
        assert_eq!(approx(237.87322893087398), "237.9");
        assert_eq!(approx(500.00000000000006), "500");
        assert_eq!(approx(0.30000000000000004), "0.3");
        assert_eq!(approx(-12.345678), "-12.35");
        assert_eq!(approx(0.0012345), "0.001234");
        assert_eq!(approx(1.5e300), "1.500e300");
        assert_eq!(approx(5e-324), "4.941e-324");
        assert_eq!(approx(0.0), "0");
        assert_eq!(approx(f64::INFINITY), "inf");
    }

    #[test]
    fn numbers_in_messages_are_short_however_large_or_small() {
        assert_eq!(super::num(5e-324), "5e-324");
        assert_eq!(super::num(-1e300), "-1e300");
        assert_eq!(super::num(0.0), "0");
        assert_eq!(super::num(0.25), "0.25");
    }

    use super::*;

    #[test]
    fn wrap_angle_stays_in_range() {
        for k in -20..20 {
            let a = k as f64 * 0.77;
            let w = wrap_angle(a);
            assert!(w > -std::f64::consts::PI - 1e-12 && w <= std::f64::consts::PI + 1e-12);
            assert!(
                ((a - w) / std::f64::consts::TAU).fract().abs() < 1e-9
                    || (1.0 - ((a - w) / std::f64::consts::TAU).fract().abs()) < 1e-9
            );
        }
    }

    #[test]
    fn crossing_segments_have_zero_distance() {
        let d = segment_segment_distance(
            &Point::new(0.0, 0.0),
            &Point::new(2.0, 2.0),
            &Point::new(0.0, 2.0),
            &Point::new(2.0, 0.0),
        );
        assert_eq!(d, 0.0);
        let d = segment_segment_distance(
            &Point::new(0.0, 0.0),
            &Point::new(1.0, 0.0),
            &Point::new(0.0, 1.0),
            &Point::new(1.0, 1.0),
        );
        assert!((d - 1.0).abs() < 1e-12);
    }
}
