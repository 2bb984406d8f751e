//! Polylines with cumulative arc length: the shape of lanes, boundaries and road edges.

use super::{point_segment_distance, GeomError, Point};

/// Consecutive points closer than this are merged: zero-length segments have no direction.
const MERGE_EPS: f64 = 1e-6;

/// The most points [`Polyline::resample_spacing`] makes (and a reader's resampling should):
/// 50 km at half a metre. Coordinates may lie 1e7 m from the origin, so one lane may run
/// 28,000 km; resampled every half metre, that was 56 million points (900 MB) per lane, and a
/// 220 KB CommonRoad file of such lanelets took more than 6 GB and aborted. Longer lines are
/// resampled more coarsely.
pub const MAX_RESAMPLED_POINTS: usize = 100_000;

/// Segments per bounding box of [`Polyline::nearest`]'s broad phase.
const CHUNK: usize = 16;

/// An open polyline of at least two distinct points, with its cumulative arc length.
#[derive(Debug, Clone, PartialEq)]
pub struct Polyline {
    points: Vec<Point>,
    cum: Vec<f64>,
    /// Bounding boxes of each run of [`CHUNK`] segments, so that `nearest` skips the runs
    /// farther than the best segment so far (a 2 km road edge has 2,000 segments).
    chunks: Vec<(Point, Point)>,
}

/// The closest point of a polyline to a query point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SegmentHit {
    /// Index of the segment (between points `segment` and `segment + 1`).
    pub segment: usize,
    /// Position along that segment in [0, 1].
    pub t: f64,
    /// Arc length of the closest point.
    pub s: f64,
    /// Euclidean distance from the query point.
    pub distance: f64,
}

impl Polyline {
    /// Builds a polyline, merging consecutive duplicate points.
    ///
    /// Fails on a non-finite coordinate or when fewer than two distinct points remain.
    pub fn new(points: impl IntoIterator<Item = Point>) -> Result<Self, GeomError> {
        let out = super::finite_deduped(points, MERGE_EPS)?;
        if out.len() < 2 {
            return Err(GeomError::TooFewPoints {
                needed: 2,
                got: out.len(),
            });
        }
        let mut cum = Vec::with_capacity(out.len());
        let mut s = 0.0;
        cum.push(0.0);
        for w in out.windows(2) {
            s += (w[1] - w[0]).norm();
            cum.push(s);
        }
        let chunks = (0..out.len() - 1)
            .step_by(CHUNK)
            .map(|i| bounds_of(&out[i..(i + CHUNK + 1).min(out.len())]))
            .collect();
        Ok(Self {
            points: out,
            cum,
            chunks,
        })
    }

    /// The points, consecutive duplicates removed.
    pub fn points(&self) -> &[Point] {
        &self.points
    }

    /// Cumulative arc length at each point; starts at 0.
    pub fn arc_lengths(&self) -> &[f64] {
        &self.cum
    }

    /// Total length.
    pub fn length(&self) -> f64 {
        *self.cum.last().expect("a polyline has two points")
    }

    /// Number of segments.
    pub fn segment_count(&self) -> usize {
        self.points.len() - 1
    }

    /// First point.
    pub fn first(&self) -> Point {
        self.points[0]
    }

    /// Last point.
    pub fn last(&self) -> Point {
        self.points[self.points.len() - 1]
    }

    /// Index of the segment that holds arc length `s` (clamped to the ends).
    pub fn segment_at(&self, s: f64) -> usize {
        let n = self.segment_count();
        match self.cum.partition_point(|&c| c <= s) {
            0 => 0,
            i => (i - 1).min(n - 1),
        }
    }

    /// The point at arc length `s`; beyond either end the end segment is extended straight.
    pub fn point_at(&self, s: f64) -> Point {
        let i = self.segment_at(s);
        let a = self.points[i];
        let b = self.points[i + 1];
        let len = self.cum[i + 1] - self.cum[i];
        a + (b - a) * ((s - self.cum[i]) / len)
    }

    /// Unit direction of segment `i`.
    pub fn segment_direction(&self, i: usize) -> Point {
        (self.points[i + 1] - self.points[i]).normalize()
    }

    /// Heading (radians) of the segment holding arc length `s`.
    pub fn heading_at(&self, s: f64) -> f64 {
        let d = self.segment_direction(self.segment_at(s));
        d.y.atan2(d.x)
    }

    /// Resamples to points every `spacing` metres (the last point is always kept), or evenly
    /// at [`MAX_RESAMPLED_POINTS`] where that would make more.
    pub fn resample_spacing(&self, spacing: f64) -> Polyline {
        let n = ((self.length() / spacing.max(1e-3)).ceil() as usize).max(1) + 1;
        self.resample_count(n.min(MAX_RESAMPLED_POINTS))
    }

    /// Resamples to exactly `n >= 2` points evenly spaced in arc length.
    pub fn resample_count(&self, n: usize) -> Polyline {
        let n = n.max(2);
        let len = self.length();
        let pts = (0..n).map(|k| self.point_at(len * k as f64 / (n - 1) as f64));
        Polyline::new(pts).expect("resampling a valid polyline keeps two distinct points")
    }

    /// The sharpest turn along the line, judged between consecutive pieces of `spacing`
    /// metres (so that centimetre jitter between close points does not count): where it is
    /// (arc length) and by how much (degrees, 0 to 180). A line shorter than two pieces has
    /// no turn to judge and gives `None`.
    pub fn sharpest_turn(&self, spacing: f64) -> Option<(f64, f64)> {
        if self.length() < 2.0 * spacing {
            return None;
        }
        let r = self.resample_spacing(spacing);
        let p = r.points();
        let step = self.length() / (p.len() - 1) as f64;
        (1..p.len() - 1)
            .map(|i| {
                let (a, b) = (p[i] - p[i - 1], p[i + 1] - p[i]);
                let turn = (a.x * b.y - a.y * b.x).atan2(a.dot(&b)).abs().to_degrees();
                (i as f64 * step, turn)
            })
            .max_by(|x, y| x.1.total_cmp(&y.1))
    }

    /// The same points in reverse order.
    pub fn reversed(&self) -> Polyline {
        Polyline::new(self.points.iter().rev().copied()).expect("reversal keeps the points")
    }

    /// The part between arc lengths `s0 < s1` (clamped to the polyline).
    pub fn slice(&self, s0: f64, s1: f64) -> Option<Polyline> {
        let s0 = s0.max(0.0);
        let s1 = s1.min(self.length());
        if s1 - s0 <= MERGE_EPS {
            return None;
        }
        let mut pts = vec![self.point_at(s0)];
        for (p, &c) in self.points.iter().zip(&self.cum) {
            if c > s0 && c < s1 {
                pts.push(*p);
            }
        }
        pts.push(self.point_at(s1));
        Polyline::new(pts).ok()
    }

    /// The closest point of the polyline to `p`.
    /// Ties go to the first segment, as in a scan of them all.
    pub fn nearest(&self, p: &Point) -> SegmentHit {
        self.nearest_where(p, |_| true)
            .expect("a polyline's points are finite")
    }

    /// [`Polyline::nearest`] among the segments `keep` accepts (by index), with the same
    /// pruning; `None` when it accepts none.
    pub fn nearest_where(&self, p: &Point, keep: impl Fn(usize) -> bool) -> Option<SegmentHit> {
        let mut best = SegmentHit {
            segment: 0,
            t: 0.0,
            s: 0.0,
            distance: f64::INFINITY,
        };
        // Squared: no square root per box.
        let below = |(lo, hi): &(Point, Point)| {
            let dx = (lo.x - p.x).max(p.x - hi.x).max(0.0);
            let dy = (lo.y - p.y).max(p.y - hi.y).max(0.0);
            dx * dx + dy * dy
        };
        let scan = |c: usize, best: &mut SegmentHit| {
            let end = ((c + 1) * CHUNK).min(self.segment_count());
            for i in (c * CHUNK..end).filter(|&i| keep(i)) {
                let (d, t) = point_segment_distance(p, &self.points[i], &self.points[i + 1]);
                if d < best.distance || (d == best.distance && i < best.segment) {
                    *best = SegmentHit {
                        segment: i,
                        t,
                        s: self.cum[i] + t * (self.cum[i + 1] - self.cum[i]),
                        distance: d,
                    };
                }
            }
        };
        // The run whose box is nearest first, for a good bound; then every run that may hold
        // a segment as near (an equal one with a lower index included).
        let (_, first) = self
            .chunks
            .iter()
            .enumerate()
            .map(|(c, b)| (below(b), c))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .expect("a polyline has a segment");
        scan(first, &mut best);
        for c in 0..self.chunks.len() {
            if c != first && !(below(&self.chunks[c]) > best.distance * best.distance) {
                scan(c, &mut best);
            }
        }
        best.distance.is_finite().then_some(best)
    }

    /// Euclidean distance from `p` to the polyline.
    pub fn distance_to(&self, p: &Point) -> f64 {
        self.nearest(p).distance
    }

    /// Axis-aligned bounding box `(min, max)`.
    pub fn bounds(&self) -> (Point, Point) {
        bounds_of(&self.points)
    }
}

/// Axis-aligned bounding box of a non-empty point set.
pub(crate) fn bounds_of(points: &[Point]) -> (Point, Point) {
    let mut lo = Point::new(f64::INFINITY, f64::INFINITY);
    let mut hi = Point::new(f64::NEG_INFINITY, f64::NEG_INFINITY);
    for p in points {
        lo = lo.inf(p);
        hi = hi.sup(p);
    }
    (lo, hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resampling_a_line_thousands_of_kilometres_long_is_bounded() {
        // Corner to corner of the coordinate range: 56 million points at half a metre.
        let l = Polyline::new([Point::new(-9.9e6, -9.9e6), Point::new(9.9e6, 9.9e6)]).unwrap();
        assert_eq!(l.resample_spacing(0.5).points().len(), MAX_RESAMPLED_POINTS);
        let (_, turn) = l.sharpest_turn(0.5).unwrap();
        assert!(turn < 1e-6, "{turn}");
        // Short lines keep their spacing.
        assert_eq!(l_shape().resample_spacing(0.5).points().len(), 31);
    }

    fn l_shape() -> Polyline {
        Polyline::new([
            Point::new(0.0, 0.0),
            Point::new(10.0, 0.0),
            Point::new(10.0, 0.0),
            Point::new(10.0, 5.0),
        ])
        .unwrap()
    }

    #[test]
    fn the_sharpest_turn_is_found_where_it_is_and_jitter_under_a_piece_is_not_one() {
        let (s, turn) = l_shape().sharpest_turn(0.5).unwrap();
        assert!(
            (s - 10.0).abs() < 0.26 && (turn - 90.0).abs() < 1e-6,
            "{s} {turn}"
        );
        let back = Polyline::new([
            Point::new(0.0, 0.0),
            Point::new(10.0, 0.0),
            Point::new(4.0, 0.0),
        ])
        .unwrap();
        let (s, turn) = back.sharpest_turn(0.5).unwrap();
        assert!((s - 10.0).abs() < 0.26 && turn > 179.0, "{s} {turn}");
        // Centimetre zigzags between points 2 cm apart along a straight line.
        let zig =
            Polyline::new((0..500).map(|k| Point::new(k as f64 * 0.02, 0.01 * (k % 2) as f64)))
                .unwrap();
        assert!(zig.sharpest_turn(0.5).unwrap().1 < 10.0);
        let short = Polyline::new([Point::new(0.0, 0.0), Point::new(0.9, 0.0)]).unwrap();
        assert_eq!(short.sharpest_turn(0.5), None);
    }

    #[test]
    fn duplicates_are_merged_and_length_is_summed() {
        let l = l_shape();
        assert_eq!(l.points().len(), 3);
        assert!((l.length() - 15.0).abs() < 1e-12);
        assert_eq!(l.arc_lengths(), &[0.0, 10.0, 15.0]);
    }

    #[test]
    fn point_at_extends_beyond_ends() {
        let l = l_shape();
        assert!((l.point_at(-2.0) - Point::new(-2.0, 0.0)).norm() < 1e-12);
        assert!((l.point_at(12.0) - Point::new(10.0, 2.0)).norm() < 1e-12);
        assert!((l.point_at(17.0) - Point::new(10.0, 7.0)).norm() < 1e-12);
    }

    #[test]
    fn too_few_or_non_finite_points_fail() {
        assert_eq!(
            Polyline::new([Point::new(1.0, 1.0), Point::new(1.0, 1.0)]),
            Err(GeomError::TooFewPoints { needed: 2, got: 1 })
        );
        assert!(matches!(
            Polyline::new([Point::new(0.0, 0.0), Point::new(f64::NAN, 1.0)]),
            Err(GeomError::NonFinite { index: 1, .. })
        ));
    }

    #[test]
    fn nearest_is_the_first_nearest_segment_of_a_full_scan() {
        // A winding line of 500 segments that doubles back on itself (equal distances to
        // several segments), queried near, on and far from it.
        let pts: Vec<Point> = (0..501)
            .map(|k| {
                let a = k as f64 * 0.05;
                Point::new(
                    a * 10.0 * a.cos(),
                    (k % 50) as f64 * 0.7 - if k % 100 < 50 { 0.0 } else { 35.0 },
                )
            })
            .collect();
        let line = Polyline::new(pts).unwrap();
        for q in 0..400 {
            let p = Point::new((q % 20) as f64 * 12.0 - 100.0, (q / 20) as f64 * 7.0 - 70.0);
            let mut want = (f64::INFINITY, 0);
            for i in 0..line.segment_count() {
                let (d, _) = point_segment_distance(&p, &line.points[i], &line.points[i + 1]);
                if d < want.0 {
                    want = (d, i);
                }
            }
            let got = line.nearest(&p);
            assert_eq!((got.distance, got.segment), want, "query {q}");
        }
    }

    #[test]
    fn resample_keeps_ends_and_spacing() {
        let l = l_shape().resample_spacing(1.0);
        assert_eq!(l.points().len(), 16);
        assert!((l.length() - 15.0).abs() < 1e-9);
        assert!((l.last() - Point::new(10.0, 5.0)).norm() < 1e-12);
    }

    #[test]
    fn nearest_and_slice() {
        let l = l_shape();
        let h = l.nearest(&Point::new(12.0, 3.0));
        assert_eq!(h.segment, 1);
        assert!((h.s - 13.0).abs() < 1e-12 && (h.distance - 2.0).abs() < 1e-12);
        let s = l.slice(5.0, 12.0).unwrap();
        assert!((s.length() - 7.0).abs() < 1e-12);
        assert!((s.first() - Point::new(5.0, 0.0)).norm() < 1e-12);
    }
}
