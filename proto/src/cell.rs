//! Exact integer cell coordinates of octree voxels.

use serde::{Deserialize, Serialize};

use crate::limits::MAX_DEPTH;

/// A voxel of the octree: depth and integer coordinates in `0..2^depth` per axis. Positions are
/// kept as integers so that no float drift accumulates with depth (docs/design.md §2, §9).
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize,
)]
pub struct Cell {
    /// Depth below the root (0 = the root cube), at most 31.
    pub depth: u8,
    /// Integer x of the cell at its depth, in `0..2^depth`.
    pub x: u32,
    /// Integer y of the cell at its depth.
    pub y: u32,
    /// Integer z of the cell at its depth.
    pub z: u32,
}

impl Cell {
    /// The root voxel.
    pub const ROOT: Cell = Cell {
        depth: 0,
        x: 0,
        y: 0,
        z: 0,
    };

    /// Whether depth and coordinates are in range.
    pub fn is_valid(&self) -> bool {
        if self.depth > MAX_DEPTH {
            return false;
        }
        let side = 1u64 << self.depth;
        (self.x as u64) < side && (self.y as u64) < side && (self.z as u64) < side
    }

    /// Child `i` with `i = 4·x_bit + 2·y_bit + z_bit` (docs/design.md §2).
    pub fn child(&self, i: u8) -> Cell {
        debug_assert!(i < 8 && self.depth < MAX_DEPTH);
        Cell {
            depth: self.depth + 1,
            x: self.x * 2 + u32::from((i >> 2) & 1),
            y: self.y * 2 + u32::from((i >> 1) & 1),
            z: self.z * 2 + u32::from(i & 1),
        }
    }

    /// The parent voxel and this voxel's child index in it; `None` for the root.
    pub fn parent(&self) -> Option<(Cell, u8)> {
        if self.depth == 0 {
            return None;
        }
        let i = ((self.x & 1) << 2 | (self.y & 1) << 1 | (self.z & 1)) as u8;
        Some((
            Cell {
                depth: self.depth - 1,
                x: self.x >> 1,
                y: self.y >> 1,
                z: self.z >> 1,
            },
            i,
        ))
    }

    /// The ancestor at `depth` (≤ own depth).
    pub fn ancestor(&self, depth: u8) -> Cell {
        debug_assert!(depth <= self.depth);
        let s = self.depth - depth;
        Cell {
            depth,
            x: self.x >> s,
            y: self.y >> s,
            z: self.z >> s,
        }
    }

    /// Whether `other` is this voxel or lies inside it.
    pub fn contains(&self, other: &Cell) -> bool {
        other.depth >= self.depth && other.ancestor(self.depth) == *self
    }

    /// The voxel's box in units of cells at `target_depth` (≥ own depth): `[min, max]` per axis.
    /// Exact in `f64` for every depth up to [`MAX_DEPTH`].
    pub fn box_at(&self, target_depth: u8) -> ([f64; 3], [f64; 3]) {
        debug_assert!(target_depth >= self.depth);
        let s = (1u64 << (target_depth - self.depth)) as f64;
        let min = [self.x as f64 * s, self.y as f64 * s, self.z as f64 * s];
        (min, [min[0] + s, min[1] + s, min[2] + s])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn child_and_parent_invert() {
        let c = Cell {
            depth: 3,
            x: 5,
            y: 2,
            z: 7,
        };
        for i in 0..8 {
            let ch = c.child(i);
            assert_eq!(ch.parent(), Some((c, i)));
            assert!(c.contains(&ch));
            assert!(ch.is_valid());
        }
        assert_eq!(Cell::ROOT.parent(), None);
    }

    #[test]
    fn child_index_bits_are_x4_y2_z1() {
        let c = Cell::ROOT.child(4);
        assert_eq!((c.x, c.y, c.z), (1, 0, 0));
        let c = Cell::ROOT.child(2);
        assert_eq!((c.x, c.y, c.z), (0, 1, 0));
        let c = Cell::ROOT.child(1);
        assert_eq!((c.x, c.y, c.z), (0, 0, 1));
    }

    #[test]
    fn deepest_cells_are_exact() {
        let side = (1u64 << MAX_DEPTH) as u32;
        let c = Cell {
            depth: MAX_DEPTH,
            x: side - 1,
            y: 0,
            z: side / 2,
        };
        assert!(c.is_valid());
        let (min, max) = c.box_at(MAX_DEPTH);
        assert_eq!(max[0] - min[0], 1.0);
        assert_eq!(min[0], (side - 1) as f64);
        assert!(!Cell { x: side, ..c }.is_valid());
        assert_eq!(c.ancestor(0), Cell::ROOT);
    }
}
