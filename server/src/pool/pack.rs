//! Packs: the blocks of [`PACK_TREELETS`] consecutive treelets of one stream (nodes, or one
//! channel) in one sled value, keyed by the first treelet's id divided by the pack size.
//!
//! Why: sled's cost is per insert (a descent, a page delta, and every few deltas the whole leaf
//! page rewritten and logged). With one value per block, a 10⁸-point import made 3.8 M inserts
//! and sled took a third of its store phase; packs of 16 make 16× fewer, and a read still costs
//! one `get` (the block is a [`sled::IVec::subslice`] of the pack, no copy).
//!
//! Value layout (integers little-endian):
//!
//! ```text
//! u16 n | n × u32 end offset of slot i's block, from the start of the blocks | blocks
//! ```
//!
//! Slot `i` holds treelet `key × PACK_TREELETS + i`; an empty block is an absent treelet (a
//! compressed block is never empty). A pack lists at most `PACK_TREELETS` slots and ends at its
//! last present one.

use std::collections::BTreeMap;

use arbor_proto::{ProtoError, TreeletId};

/// Treelets per pack.
pub const PACK_TREELETS: u32 = 16;

/// Bytes of a pack's count.
const COUNT_BYTES: usize = 2;
/// Bytes of one end offset.
const OFFSET_BYTES: usize = 4;

/// The index of the pack holding `id`, and the slot within it.
fn split(id: TreeletId) -> (u32, usize) {
    (id.0 / PACK_TREELETS, (id.0 % PACK_TREELETS) as usize)
}

/// The sled key of the pack holding `id`, and the slot within it.
pub fn locate(id: TreeletId) -> ([u8; 4], usize) {
    let (pack, slot) = split(id);
    (pack.to_be_bytes(), slot)
}

/// The first treelet id of the pack stored under `key`; `None` for a key that is not 4 bytes or
/// whose ids would pass `u32::MAX`.
pub fn first_id(key: &[u8]) -> Option<u32> {
    let pack = u32::from_be_bytes(key.try_into().ok()?);
    pack.checked_mul(PACK_TREELETS)
}

/// Encodes the blocks of slots `0..blocks.len()` (empty = absent).
pub fn encode(blocks: &[Vec<u8>]) -> Vec<u8> {
    debug_assert!(blocks.len() <= PACK_TREELETS as usize);
    let data: usize = blocks.iter().map(Vec::len).sum();
    let mut out = Vec::with_capacity(COUNT_BYTES + blocks.len() * OFFSET_BYTES + data);
    out.extend_from_slice(&(blocks.len() as u16).to_le_bytes());
    let mut end = 0u32;
    for b in blocks {
        end += b.len() as u32;
        out.extend_from_slice(&end.to_le_bytes());
    }
    for b in blocks {
        out.extend_from_slice(b);
    }
    out
}

/// A pack's slot table, checked against the value's length.
struct Table<'a> {
    ends: &'a [u8],
    data_start: usize,
}

impl<'a> Table<'a> {
    fn read(pack: &'a [u8]) -> Result<Self, ProtoError> {
        let head = pack.get(..COUNT_BYTES).ok_or(ProtoError::Truncated {
            what: "pack count",
            need: COUNT_BYTES,
            have: pack.len(),
        })?;
        let n = usize::from(u16::from_le_bytes([head[0], head[1]]));
        if n > PACK_TREELETS as usize {
            return Err(ProtoError::OutOfRange {
                what: "pack count",
                detail: format!("{n} slots, at most {PACK_TREELETS}"),
            });
        }
        let data_start = COUNT_BYTES + n * OFFSET_BYTES;
        let ends = pack
            .get(COUNT_BYTES..data_start)
            .ok_or(ProtoError::Truncated {
                what: "pack offsets",
                need: data_start,
                have: pack.len(),
            })?;
        let table = Table { ends, data_start };
        let mut previous = 0;
        for slot in 0..n {
            let end = table.end(slot);
            if end < previous {
                return Err(ProtoError::OutOfRange {
                    what: "pack offsets",
                    detail: format!("slot {slot} ends at {end}, before {previous}"),
                });
            }
            previous = end;
        }
        if data_start + previous != pack.len() {
            return Err(ProtoError::OutOfRange {
                what: "pack length",
                detail: format!(
                    "{} bytes, the table says {}",
                    pack.len(),
                    data_start + previous
                ),
            });
        }
        Ok(table)
    }

    fn slots(&self) -> usize {
        self.ends.len() / OFFSET_BYTES
    }

    fn end(&self, slot: usize) -> usize {
        let at = slot * OFFSET_BYTES;
        u32::from_le_bytes(
            self.ends[at..at + OFFSET_BYTES]
                .try_into()
                .expect("4 bytes"),
        ) as usize
    }

    /// The byte range of `slot`'s block within the pack; `None` when absent.
    fn range(&self, slot: usize) -> Option<(usize, usize)> {
        if slot >= self.slots() {
            return None;
        }
        let start = if slot == 0 { 0 } else { self.end(slot - 1) };
        let end = self.end(slot);
        (end > start).then_some((self.data_start + start, end - start))
    }
}

/// The block of `slot` in `pack`, sharing the pack's bytes; `None` when the slot is absent.
pub fn block(pack: &sled::IVec, slot: usize) -> Result<Option<sled::IVec>, ProtoError> {
    let table = Table::read(pack)?;
    Ok(table
        .range(slot)
        .map(|(offset, len)| pack.subslice(offset, len)))
}

/// The slots of `pack` that hold a block, ascending.
pub fn present(pack: &[u8]) -> Result<Vec<usize>, ProtoError> {
    let table = Table::read(pack)?;
    Ok((0..table.slots())
        .filter(|&s| table.range(s).is_some())
        .collect())
}

/// The bytes of `pack`'s blocks together (its length less its slot table), once the table is
/// checked against the length.
pub fn block_bytes(pack: &[u8]) -> Result<usize, ProtoError> {
    Ok(pack.len() - Table::read(pack)?.data_start)
}

/// Every slot's block of `pack` (empty = absent), for tools that rewrite a pack.
pub fn blocks(pack: &[u8]) -> Result<Vec<Vec<u8>>, ProtoError> {
    let table = Table::read(pack)?;
    Ok((0..table.slots())
        .map(|s| {
            table
                .range(s)
                .map_or_else(Vec::new, |(at, len)| pack[at..at + len].to_vec())
        })
        .collect())
}

/// Collects one stream's blocks into packs and inserts each pack when its last slot arrives.
/// Blocks may come in any order (the attribute stream goes level by level, deepest first, so a
/// pack across a level boundary is completed one level later); what never completes is
/// written by [`PackWriter::finish`].
#[derive(Debug)]
pub struct PackWriter {
    tree: sled::Tree,
    /// Packs with some slots still missing: their blocks (empty = not yet) and how many are in.
    open: BTreeMap<u32, (Vec<Vec<u8>>, u32)>,
}

impl PackWriter {
    pub fn new(tree: sled::Tree) -> Self {
        PackWriter {
            tree,
            open: BTreeMap::new(),
        }
    }

    /// Adds the block of `id`; a block given twice replaces the first.
    pub fn put(&mut self, id: TreeletId, block: Vec<u8>) -> Result<(), sled::Error> {
        let (pack, slot) = split(id);
        let (blocks, filled) = self
            .open
            .entry(pack)
            .or_insert_with(|| (vec![Vec::new(); PACK_TREELETS as usize], 0));
        if blocks[slot].is_empty() && !block.is_empty() {
            *filled += 1;
        }
        blocks[slot] = block;
        if *filled == PACK_TREELETS {
            let (blocks, _) = self.open.remove(&pack).expect("open above");
            self.tree.insert(pack.to_be_bytes(), encode(&blocks))?;
        }
        Ok(())
    }

    /// Writes the packs still open (the stream's last, and any with absent treelets), each
    /// ending at its last present slot.
    pub fn finish(&mut self) -> Result<(), sled::Error> {
        for (pack, (mut blocks, _)) in std::mem::take(&mut self.open) {
            while blocks.last().is_some_and(Vec::is_empty) {
                blocks.pop();
            }
            if !blocks.is_empty() {
                self.tree.insert(pack.to_be_bytes(), encode(&blocks))?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_tree() -> (sled::Db, sled::Tree) {
        let db = sled::Config::new().temporary(true).open().unwrap();
        let tree = db.open_tree("t").unwrap();
        (db, tree)
    }

    #[test]
    fn blocks_come_back_from_their_slots_and_absent_slots_are_none() {
        let blocks = vec![b"abc".to_vec(), Vec::new(), b"d".to_vec(), b"efgh".to_vec()];
        let pack = sled::IVec::from(encode(&blocks));
        for (slot, b) in blocks.iter().enumerate() {
            let got = block(&pack, slot).unwrap();
            assert_eq!(
                got.as_deref(),
                (!b.is_empty()).then_some(&b[..]),
                "slot {slot}"
            );
        }
        assert_eq!(block(&pack, 4).unwrap(), None, "past the last slot");
        assert_eq!(present(&pack).unwrap(), vec![0, 2, 3]);
        assert_eq!(super::blocks(&pack).unwrap(), blocks);
    }

    #[test]
    fn a_damaged_pack_is_an_error_naming_the_part() {
        let good = encode(&[b"abc".to_vec(), b"de".to_vec()]);
        let cases: Vec<(&str, Vec<u8>)> = vec![
            ("pack count", vec![1]),
            ("pack count", {
                let mut v = good.clone();
                v[..2].copy_from_slice(&17u16.to_le_bytes());
                v
            }),
            ("pack offsets", good[..5].to_vec()),
            ("pack length", good[..good.len() - 1].to_vec()),
            ("pack offsets", {
                let mut v = good.clone();
                v[2..6].copy_from_slice(&9u32.to_le_bytes());
                v
            }),
        ];
        for (what, bytes) in cases {
            let e = block(&sled::IVec::from(bytes), 0).unwrap_err();
            assert!(e.to_string().contains(what), "{what}: {e}");
        }
    }

    #[test]
    fn the_writer_completes_packs_in_any_order_and_finishes_the_rest() {
        let (_db, tree) = temp_tree();
        let mut w = PackWriter::new(tree.clone());
        let n = 2 * PACK_TREELETS + 5;
        let block_of = |id: u32| format!("block {id}").into_bytes();
        // The second half first, as the attribute stream does across a level boundary.
        for id in (n / 2..n).chain(0..n / 2) {
            w.put(TreeletId(id), block_of(id)).unwrap();
        }
        assert_eq!(tree.len(), 2, "two full packs written as they completed");
        w.finish().unwrap();
        assert_eq!(tree.len(), 3);
        for id in 0..n {
            let (key, slot) = locate(TreeletId(id));
            let pack = tree.get(key).unwrap().unwrap();
            assert_eq!(block(&pack, slot).unwrap().unwrap(), block_of(id)[..]);
        }
        let last = tree.get(locate(TreeletId(n - 1)).0).unwrap().unwrap();
        assert_eq!(
            present(&last).unwrap().len(),
            5,
            "the last pack ends at its last treelet"
        );
    }

    #[test]
    fn ids_near_the_top_of_the_range_keep_their_packs() {
        let id = TreeletId(u32::MAX);
        let (key, slot) = locate(id);
        assert_eq!(first_id(&key).unwrap() + slot as u32, u32::MAX);
        assert_eq!(first_id(&[0, 0, 1]), None);
    }
}
