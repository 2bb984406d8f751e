//! The nearest of many segments to a point, through a uniform grid: a query looks at the cells
//! around the point, ring by ring, and stops once no farther ring can hold a nearer segment.
//!
//! Why: `own_way.rhai` asks, for every corner of every moved car at every step, for the nearest
//! lane segment going the car's way: about 4,400 queries an evaluation on a US-101 window.
//! Scanning every lane (each pruned by its bounds) took 39 ms an evaluation there, and made
//! `simulate` five times slower with the script than without it.

use super::{point_segment_distance, Point};

/// A segment's distance to the query point, less its offset, and where on it the nearest point
/// lies.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridHit {
    /// The segment's index, in the order given to [`SegmentGrid::new`].
    pub index: usize,
    /// Euclidean distance to the segment, less the segment's offset.
    pub distance: f64,
    /// Parameter (0 at the segment's start, 1 at its end) of the nearest point.
    pub t: f64,
}

/// The most cells a grid has along either axis, and in all: a map whose lanes lie far apart
/// gets coarser cells rather than millions of empty ones.
const MAX_CELLS_PER_AXIS: f64 = 2048.0;
const MAX_CELLS: f64 = 1.0e6;

/// Segments, each with an offset subtracted from its distance (a lane's half width), hashed
/// into square cells.
#[derive(Debug, Clone, PartialEq)]
pub struct SegmentGrid {
    segments: Vec<(Point, Point, f64)>,
    origin: Point,
    cell: f64,
    cols: i64,
    rows: i64,
    /// Cell `k`'s segments are `members[starts[k]..starts[k + 1]]`, in increasing index.
    starts: Vec<u32>,
    members: Vec<u32>,
    /// The largest offset: how much nearer than its distance a segment can rank.
    widest: f64,
}

impl SegmentGrid {
    /// Hashes `segments` (start, end, offset) into cells about `cell` metres wide (wider where
    /// the segments span more than [`MAX_CELLS_PER_AXIS`] of them). Every coordinate must be
    /// finite, as a map's are.
    pub fn new(segments: Vec<(Point, Point, f64)>, cell: f64) -> Self {
        let mut lo = Point::new(f64::INFINITY, f64::INFINITY);
        let mut hi = Point::new(f64::NEG_INFINITY, f64::NEG_INFINITY);
        for (a, b, _) in &segments {
            lo = lo.inf(a).inf(b);
            hi = hi.sup(a).sup(b);
        }
        if segments.is_empty() {
            (lo, hi) = (Point::zeros(), Point::zeros());
        }
        let (w, h) = (hi.x - lo.x, hi.y - lo.y);
        let cell = cell
            .max(w / MAX_CELLS_PER_AXIS)
            .max(h / MAX_CELLS_PER_AXIS)
            .max((w * h / MAX_CELLS).sqrt());
        let cols = ((w / cell).floor() as i64 + 1).max(1);
        let rows = ((h / cell).floor() as i64 + 1).max(1);
        let mut cells: Vec<Vec<u32>> = vec![Vec::new(); (cols * rows) as usize];
        let at = |v: f64, lo: f64, n: i64| (((v - lo) / cell).floor() as i64).clamp(0, n - 1);
        for (i, (a, b, _)) in segments.iter().enumerate() {
            // In pieces no longer than a cell, so that a long diagonal segment lands in the
            // cells it crosses, not in every cell of its bounding box.
            let pieces = ((b - a).norm() / cell).ceil().max(1.0) as usize;
            for k in 0..pieces {
                let p = a + (b - a) * (k as f64 / pieces as f64);
                let q = a + (b - a) * ((k + 1) as f64 / pieces as f64);
                let (x0, x1) = (at(p.x.min(q.x), lo.x, cols), at(p.x.max(q.x), lo.x, cols));
                let (y0, y1) = (at(p.y.min(q.y), lo.y, rows), at(p.y.max(q.y), lo.y, rows));
                for y in y0..=y1 {
                    for x in x0..=x1 {
                        let c = &mut cells[(y * cols + x) as usize];
                        if c.last() != Some(&(i as u32)) {
                            c.push(i as u32);
                        }
                    }
                }
            }
        }
        let mut starts = Vec::with_capacity(cells.len() + 1);
        let mut members = Vec::new();
        starts.push(0);
        for c in cells {
            members.extend(c);
            starts.push(members.len() as u32);
        }
        let widest = segments.iter().fold(0f64, |m, s| m.max(s.2));
        Self {
            segments,
            origin: lo,
            cell,
            cols,
            rows,
            starts,
            members,
            widest,
        }
    }

    /// The segment that `keep` accepts (by index) with the least distance less offset, the
    /// lowest index among equals; `None` when it accepts none.
    pub fn nearest(&self, p: &Point, keep: impl Fn(usize) -> bool) -> Option<GridHit> {
        if self.segments.is_empty() || !p.x.is_finite() || !p.y.is_finite() {
            return None;
        }
        let cx = ((p.x - self.origin.x) / self.cell).floor();
        let cy = ((p.y - self.origin.y) / self.cell).floor();
        // Far outside the grid (or beyond i64): start beside its nearest side, from where the
        // rings reach it at once.
        let clamp = |v: f64, n: i64| v.clamp(-1.0, n as f64) as i64;
        let (cx, cy) = (clamp(cx, self.cols), clamp(cy, self.rows));
        let mut best: Option<GridHit> = None;
        let consider = |i: usize, best: &mut Option<GridHit>| {
            let (a, b, off) = &self.segments[i];
            let (d, t) = point_segment_distance(p, a, b);
            let d = d - off;
            if best.is_none_or(|h| d < h.distance || (d == h.distance && i < h.index)) && keep(i) {
                *best = Some(GridHit {
                    index: i,
                    distance: d,
                    t,
                });
            }
        };
        for r in 0i64.. {
            // Every cell of this ring that lies in the grid.
            for y in (cy - r).max(0)..=(cy + r).min(self.rows - 1) {
                let edge = y == cy - r || y == cy + r;
                let step = if edge { 1 } else { (2 * r).max(1) as usize };
                let xs = (cx - r..=cx + r).step_by(step);
                for x in xs.filter(|&x| (0..self.cols).contains(&x)) {
                    let k = (y * self.cols + x) as usize;
                    for &i in &self.members[self.starts[k] as usize..self.starts[k + 1] as usize] {
                        consider(i as usize, &mut best);
                    }
                }
            }
            let covered =
                cx - r <= 0 && cy - r <= 0 && cx + r >= self.cols - 1 && cy + r >= self.rows - 1;
            if covered {
                break;
            }
            if let Some(h) = best {
                // Anything not yet seen lies in the grid beyond a side of the box of rings
                // 0..=r: in one of four slabs, each a rectangle, at least as far as the nearest
                // of them; ties go to the lower index, hence strict. Measured to the slabs, not
                // to the box's sides: for a point off the map, a side between it and the grid
                // bounded nothing, and every cell of the grid was looked at (a million for a
                // 10 km map) for each point.
                let x0 = self.origin.x + (cx - r) as f64 * self.cell;
                let y0 = self.origin.y + (cy - r) as f64 * self.cell;
                let x1 = self.origin.x + (cx + r + 1) as f64 * self.cell;
                let y1 = self.origin.y + (cy + r + 1) as f64 * self.cell;
                let (gx0, gy0) = (self.origin.x, self.origin.y);
                let gx1 = gx0 + self.cols as f64 * self.cell;
                let gy1 = gy0 + self.rows as f64 * self.cell;
                let slab = |ax: f64, bx: f64, ay: f64, by: f64| {
                    if ax >= bx || ay >= by {
                        return f64::INFINITY;
                    }
                    let dx = (ax - p.x).max(p.x - bx).max(0.0);
                    let dy = (ay - p.y).max(p.y - by).max(0.0);
                    dx.hypot(dy)
                };
                let outside = slab(gx0, x0.min(gx1), gy0, gy1)
                    .min(slab(x1.max(gx0), gx1, gy0, gy1))
                    .min(slab(gx0, gx1, gy0, y0.min(gy1)))
                    .min(slab(gx0, gx1, y1.max(gy0), gy1));
                if h.distance < outside - self.widest {
                    break;
                }
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The same answer as looking at every segment.
    fn brute(
        segs: &[(Point, Point, f64)],
        p: &Point,
        keep: impl Fn(usize) -> bool,
    ) -> Option<GridHit> {
        let mut best: Option<GridHit> = None;
        for (i, (a, b, off)) in segs.iter().enumerate() {
            let (d, t) = point_segment_distance(p, a, b);
            let d = d - off;
            if keep(i) && best.is_none_or(|h| d < h.distance) {
                best = Some(GridHit {
                    index: i,
                    distance: d,
                    t,
                });
            }
        }
        best
    }

    #[test]
    fn the_grid_finds_what_a_scan_of_every_segment_finds() {
        // A deterministic scatter of short and long segments with offsets, queried inside,
        // beside and far outside their extent, with a filter that drops a third of them.
        let mut seed = 7u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut segs = Vec::new();
        for k in 0..300 {
            let a = Point::new(rnd() * 400.0 - 200.0, rnd() * 100.0);
            let len = if k % 10 == 0 {
                300.0
            } else {
                1.0 + rnd() * 15.0
            };
            let ang = rnd() * std::f64::consts::TAU;
            segs.push((a, a + Point::new(ang.cos(), ang.sin()) * len, rnd() * 2.0));
        }
        // A zero-length segment and two segments that tie.
        segs.push((Point::new(5.0, 5.0), Point::new(5.0, 5.0), 0.5));
        segs.push((Point::new(0.0, 200.0), Point::new(10.0, 200.0), 1.0));
        segs.push((Point::new(0.0, 200.0), Point::new(10.0, 200.0), 1.0));
        for cell in [1.0, 8.0, 50.0] {
            let g = SegmentGrid::new(segs.clone(), cell);
            for _ in 0..2000 {
                let p = Point::new(rnd() * 1200.0 - 600.0, rnd() * 600.0 - 200.0);
                let keep = |i: usize| i % 3 != 1;
                assert_eq!(
                    g.nearest(&p, keep),
                    brute(&segs, &p, keep),
                    "{p:?}, cell {cell}"
                );
                assert_eq!(g.nearest(&p, |_| true), brute(&segs, &p, |_| true));
            }
            let p = Point::new(5.0, 198.0);
            assert_eq!(
                g.nearest(&p, |i| i > 300).unwrap().index,
                301,
                "ties: lower index"
            );
            assert_eq!(g.nearest(&p, |_| false), None);
            assert_eq!(
                g.nearest(&Point::new(1e9, -1e9), |_| true),
                brute(&segs, &Point::new(1e9, -1e9), |_| true)
            );
        }
        assert_eq!(
            SegmentGrid::new(Vec::new(), 8.0).nearest(&Point::zeros(), |_| true),
            None
        );
    }

    #[test]
    fn a_point_far_off_the_grid_looks_at_a_few_rings_not_every_cell() {
        // The outline of a 10 km square in 10 m segments: a million 10 m cells. A point
        // beyond the grid's side kept the stopping bound negative, so every query from off
        // the map looked at every cell (2,000 such queries took many seconds).
        let mut segs = Vec::new();
        for k in 0..1000 {
            let (a, b) = (k as f64 * 10.0, (k + 1) as f64 * 10.0);
            segs.push((Point::new(a, 0.0), Point::new(b, 0.0), 0.0));
            segs.push((Point::new(a, 1e4), Point::new(b, 1e4), 0.0));
            segs.push((Point::new(0.0, a), Point::new(0.0, b), 0.0));
            segs.push((Point::new(1e4, a), Point::new(1e4, b), 0.0));
        }
        let g = SegmentGrid::new(segs.clone(), 10.0);
        let t0 = std::time::Instant::now();
        for k in 0..2000 {
            let ang = k as f64 * 0.0031;
            let p = Point::new(5e3 + 3e4 * ang.cos(), 5e3 + 3e4 * ang.sin());
            let hit = g.nearest(&p, |_| true);
            if k % 100 == 0 {
                assert_eq!(hit, brute(&segs, &p, |_| true), "{p:?}");
            }
        }
        let took = t0.elapsed().as_secs_f64();
        assert!(took < 1.0, "{took:.2} s");
    }

    #[test]
    fn segments_far_apart_get_coarser_cells_not_millions() {
        let segs = vec![
            (Point::new(-9e6, -9e6), Point::new(-9e6 + 5.0, -9e6), 0.0),
            (Point::new(9e6, 9e6), Point::new(9e6, 9e6 + 5.0), 0.0),
        ];
        let g = SegmentGrid::new(segs.clone(), 8.0);
        assert!(g.starts.len() < 1_010_000, "{}", g.starts.len());
        let p = Point::new(9e6 - 1.0, 9e6 + 1.0);
        assert_eq!(g.nearest(&p, |_| true), brute(&segs, &p, |_| true));
    }
}
