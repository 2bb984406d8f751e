//! Items listed by the square cells their bounding boxes cover, for readers that ask "which
//! items lie near this point?" once per item: without an index each such question tries every
//! item, and a map of tens of thousands of lanelets, lines or lanes took minutes to read.

use std::collections::HashMap;

use super::Point;

/// Indices of items (points, or axis-aligned boxes) by the cells of side `cell` they cover.
/// An item over more than `max_cells` cells is not listed by cell but returned by every query,
/// so that one huge item costs one entry instead of millions.
#[derive(Debug, Clone)]
pub struct CellIndex {
    cell: f64,
    max_cells: i64,
    cells: HashMap<(i64, i64), Vec<usize>>,
    large: Vec<usize>,
}

impl CellIndex {
    /// An empty index of cells `cell` metres wide (finite, above 0).
    pub fn new(cell: f64, max_cells: i64) -> Self {
        Self {
            cell,
            max_cells,
            cells: HashMap::new(),
            large: Vec::new(),
        }
    }

    fn cell_of(&self, p: Point) -> (i64, i64) {
        // `as` saturates: a coordinate beyond i64's cells lands in the outermost one.
        (
            (p.x / self.cell).floor() as i64,
            (p.y / self.cell).floor() as i64,
        )
    }

    /// Lists `item` in every cell that the box from `lo` to `hi` touches (a point: `lo == hi`).
    pub fn insert(&mut self, item: usize, lo: Point, hi: Point) {
        let ((x0, y0), (x1, y1)) = (self.cell_of(lo), self.cell_of(hi));
        let w = x1.saturating_sub(x0).saturating_add(1);
        let h = y1.saturating_sub(y0).saturating_add(1);
        if w.saturating_mul(h) > self.max_cells {
            self.large.push(item);
            return;
        }
        for x in x0..=x1 {
            for y in y0..=y1 {
                let list = self.cells.entry((x, y)).or_default();
                if list.last() != Some(&item) {
                    list.push(item);
                }
            }
        }
    }

    /// The items listed in `p`'s cell, then the large ones: every item whose box holds `p`,
    /// and some that do not.
    pub fn at(&self, p: Point) -> impl Iterator<Item = usize> + '_ {
        let c = self.cell_of(p);
        self.cells
            .get(&c)
            .into_iter()
            .flatten()
            .chain(&self.large)
            .copied()
    }

    /// The items listed in the 3 x 3 cells around `p`'s, then the large ones: every item within
    /// one cell width of `p`, and some farther. An item may come more than once.
    pub fn around(&self, p: Point) -> impl Iterator<Item = usize> + '_ {
        let (x, y) = self.cell_of(p);
        (-1..=1)
            .flat_map(move |dx| {
                (-1..=1).map(move |dy| (x.saturating_add(dx), y.saturating_add(dy)))
            })
            .filter_map(|c| self.cells.get(&c))
            .flatten()
            .chain(&self.large)
            .copied()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sorted(v: impl Iterator<Item = usize>) -> Vec<usize> {
        let mut v: Vec<usize> = v.collect();
        v.sort_unstable();
        v.dedup();
        v
    }

    #[test]
    fn queries_find_every_item_near_and_large_ones_everywhere() {
        let mut ix = CellIndex::new(1.0, 4);
        ix.insert(0, Point::new(0.5, 0.5), Point::new(0.5, 0.5));
        ix.insert(1, Point::new(1.5, 0.5), Point::new(2.5, 1.5));
        ix.insert(2, Point::new(-100.0, -100.0), Point::new(100.0, 100.0));
        ix.insert(3, Point::new(5.5, 5.5), Point::new(5.5, 5.5));
        assert_eq!(sorted(ix.at(Point::new(0.2, 0.9))), vec![0, 2]);
        assert_eq!(sorted(ix.at(Point::new(2.2, 1.2))), vec![1, 2]);
        assert_eq!(sorted(ix.around(Point::new(0.9, 0.9))), vec![0, 1, 2]);
        assert_eq!(sorted(ix.around(Point::new(7.4, 7.4))), vec![2]);
        assert_eq!(sorted(ix.around(Point::new(6.9, 6.9))), vec![2, 3]);
        // Far outside i64's cells: saturated, not a panic or a wrap-around.
        ix.insert(4, Point::new(1e300, -1e300), Point::new(1e300, -1e300));
        assert_eq!(sorted(ix.around(Point::new(1e300, -1e300))), vec![2, 4]);
    }
}
