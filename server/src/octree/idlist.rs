//! Primitive id lists that keep the builder within its memory budget.
//!
//! Every list of primitive ids the builder holds (a pending node's, a queued treelet job's) is an
//! [`IdList`]. Lists live in memory only while the shared [`Budget`] has room for them; a list that
//! would exceed it is written to a scratch [`SpillFile`] in chunks as it is produced, and streamed
//! back chunk by chunk when it is partitioned. The root's list of all primitives is a plain range.
//! So the ids held in memory never exceed the budget, plus fixed per-writer buffers
//! ([`WRITE_CHUNK`] ids for each of the 8 children of a node being partitioned, per thread).

use crate::source::scratch_file;
use std::fs::File;
use std::ops::Range;
use std::os::unix::fs::FileExt;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

/// Ids per chunk written to or read from the spill file (256 KiB).
pub const WRITE_CHUNK: usize = 1 << 16;

/// Bytes of id lists that may be held in memory, shared by all threads of a build.
#[derive(Debug)]
pub struct Budget {
    limit: usize,
    used: AtomicUsize,
    peak: AtomicUsize,
}

impl Budget {
    pub fn new(limit: usize) -> Arc<Self> {
        Arc::new(Self {
            limit,
            used: AtomicUsize::new(0),
            peak: AtomicUsize::new(0),
        })
    }

    /// Reserves `bytes` if that stays within the limit.
    pub fn try_reserve(&self, bytes: usize) -> bool {
        let mut cur = self.used.load(Ordering::Relaxed);
        loop {
            if cur + bytes > self.limit {
                return false;
            }
            match self.used.compare_exchange_weak(
                cur,
                cur + bytes,
                Ordering::AcqRel,
                Ordering::Relaxed,
            ) {
                Ok(_) => {
                    self.peak.fetch_max(cur + bytes, Ordering::Relaxed);
                    return true;
                }
                Err(now) => cur = now,
            }
        }
    }

    pub fn release(&self, bytes: usize) {
        self.used.fetch_sub(bytes, Ordering::AcqRel);
    }

    pub fn used(&self) -> usize {
        self.used.load(Ordering::Relaxed)
    }

    /// Highest reservation seen.
    pub fn peak(&self) -> usize {
        self.peak.load(Ordering::Relaxed)
    }

    pub fn limit(&self) -> usize {
        self.limit
    }
}

/// Append-only scratch file of id chunks, shared by all threads.
#[derive(Debug)]
pub struct SpillFile {
    file: File,
    end: AtomicU64,
}

impl SpillFile {
    pub fn create(dir: &Path) -> std::io::Result<Arc<Self>> {
        let file = scratch_file(&dir.join("idlists.spill"))?;
        Ok(Arc::new(Self {
            file,
            end: AtomicU64::new(0),
        }))
    }

    /// Appends a chunk and returns its offset.
    fn append(&self, ids: &[u32]) -> std::io::Result<u64> {
        let bytes: &[u8] = bytemuck::cast_slice(ids);
        let at = self.end.fetch_add(bytes.len() as u64, Ordering::AcqRel);
        self.file.write_all_at(bytes, at)?;
        Ok(at)
    }

    fn read(&self, offset: u64, len: u32, out: &mut Vec<u32>) -> std::io::Result<()> {
        out.clear();
        out.resize(len as usize, 0);
        self.file
            .read_exact_at(bytemuck::cast_slice_mut(out), offset)
    }

    /// Bytes written over the whole build.
    pub fn bytes_written(&self) -> u64 {
        self.end.load(Ordering::Relaxed)
    }
}

/// The budget and spill file of one build.
#[derive(Debug, Clone)]
pub struct Lists {
    pub budget: Arc<Budget>,
    pub spill: Arc<SpillFile>,
}

/// A list of primitive ids. Sixteen bytes: the fill moves eight of them per split and queues
/// one per node, and at 48 bytes (the lists inline) copying them was a tenth of the fill.
#[derive(Debug)]
pub enum IdList {
    /// `start..end`, costing nothing (the root's list).
    Range(Range<u32>),
    /// Held in memory; its bytes are reserved in the budget until it is dropped.
    Memory(Box<InMemory>),
    /// Chunks in the spill file.
    Spilled(Box<InSpill>),
}

/// The ids of an in-memory [`IdList`].
#[derive(Debug)]
pub struct InMemory {
    ids: Vec<u32>,
    budget: Arc<Budget>,
}

/// Where a spilled [`IdList`]'s chunks are.
#[derive(Debug)]
pub struct InSpill {
    spill: Arc<SpillFile>,
    chunks: Vec<(u64, u32)>,
    len: u64,
}

impl Drop for IdList {
    fn drop(&mut self) {
        if let IdList::Memory(m) = self {
            m.budget.release(m.ids.len() * 4);
        }
    }
}

impl IdList {
    pub fn len(&self) -> u64 {
        match self {
            IdList::Range(r) => u64::from(r.end - r.start),
            IdList::Memory(m) => m.ids.len() as u64,
            IdList::Spilled(s) => s.len,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The ids, when they are in memory.
    pub fn as_slice(&self) -> Option<&[u32]> {
        match self {
            IdList::Memory(m) => Some(&m.ids),
            _ => None,
        }
    }

    /// Bytes this list holds in memory.
    pub fn memory_bytes(&self) -> usize {
        self.as_slice().map_or(0, |s| s.len() * 4)
    }

    /// Calls `f` with the ids, one chunk at a time, in order.
    pub fn for_each_chunk(&self, mut f: impl FnMut(&[u32])) -> std::io::Result<()> {
        match self {
            IdList::Range(r) => {
                let mut buf = Vec::with_capacity(WRITE_CHUNK.min((r.end - r.start) as usize));
                let mut at = r.start;
                while at < r.end {
                    let end = at.saturating_add(WRITE_CHUNK as u32).min(r.end);
                    buf.clear();
                    buf.extend(at..end);
                    f(&buf);
                    at = end;
                }
            }
            IdList::Memory(m) => f(&m.ids),
            IdList::Spilled(s) => {
                let mut buf = Vec::new();
                for &(offset, len) in &s.chunks {
                    s.spill.read(offset, len, &mut buf)?;
                    f(&buf);
                }
            }
        }
        Ok(())
    }

    /// Up to `max` ids from the start of the list, in memory (unaccounted: callers use it
    /// briefly and `max` is small).
    pub fn prefix(&self, max: usize) -> std::io::Result<Vec<u32>> {
        if let Some(s) = self.as_slice() {
            return Ok(s[..s.len().min(max)].to_vec());
        }
        let mut out = Vec::new();
        let mut done = false;
        self.for_each_chunk(|c| {
            if !done {
                let take = (max - out.len()).min(c.len());
                out.extend_from_slice(&c[..take]);
                done = out.len() >= max;
            }
        })?;
        Ok(out)
    }

    /// Moves an in-memory list to the spill file (frees its budget).
    pub fn spill(self, lists: &Lists) -> std::io::Result<IdList> {
        if self.as_slice().is_none() {
            return Ok(self);
        }
        let mut w = ListWriter::spilling(lists);
        self.for_each_chunk(|c| {
            for &id in c {
                w.push(id);
            }
        })?;
        drop(self);
        w.finish()
    }

    /// Brings a spilled list back into memory if the budget has room (the fast path for
    /// partitioning); otherwise returns it unchanged.
    pub fn load(self, lists: &Lists) -> std::io::Result<IdList> {
        if !matches!(self, IdList::Spilled(_)) {
            return Ok(self);
        }
        let bytes = self.len() as usize * 4;
        if !lists.budget.try_reserve(bytes) {
            return Ok(self);
        }
        let mut ids = Vec::with_capacity(self.len() as usize);
        if let Err(e) = self.for_each_chunk(|c| ids.extend_from_slice(c)) {
            lists.budget.release(bytes);
            return Err(e);
        }
        Ok(IdList::Memory(Box::new(InMemory {
            ids,
            budget: lists.budget.clone(),
        })))
    }
}

/// Builds an [`IdList`] id by id: in memory while the budget grants room (reserved in growing
/// blocks of at most [`WRITE_CHUNK`] ids), spilling in chunks from the first refusal on.
#[derive(Debug)]
pub struct ListWriter {
    lists: Lists,
    buf: Vec<u32>,
    /// Ids reserved in the budget for `buf` (memory mode only).
    reserved: usize,
    chunks: Vec<(u64, u32)>,
    spilled: u64,
    spilling: bool,
    error: Option<std::io::Error>,
}

impl ListWriter {
    pub fn new(lists: &Lists) -> Self {
        Self {
            lists: lists.clone(),
            buf: Vec::new(),
            reserved: 0,
            chunks: Vec::new(),
            spilled: 0,
            spilling: false,
            error: None,
        }
    }

    fn spilling(lists: &Lists) -> Self {
        let mut w = Self::new(lists);
        w.spilling = true;
        w
    }

    fn flush(&mut self) {
        if self.buf.is_empty() || self.error.is_some() {
            return;
        }
        match self.lists.spill.append(&self.buf) {
            Ok(at) => {
                self.chunks.push((at, self.buf.len() as u32));
                self.spilled += self.buf.len() as u64;
            }
            Err(e) => self.error = Some(e),
        }
        self.buf.clear();
    }

    pub fn push(&mut self, id: u32) {
        if !self.spilling && self.buf.len() == self.reserved {
            // Reservations grow with the list (256 ids, doubling up to a chunk) so that many small
            // lists do not each claim a whole chunk of the budget.
            let block = self.reserved.clamp(256, WRITE_CHUNK);
            if self.lists.budget.try_reserve(block * 4) {
                self.reserved += block;
            } else {
                // Out of budget: everything so far and from now on goes to disk.
                self.lists.budget.release(self.reserved * 4);
                self.reserved = 0;
                self.spilling = true;
                let held = std::mem::take(&mut self.buf);
                for c in held.chunks(WRITE_CHUNK) {
                    self.buf.extend_from_slice(c);
                    self.flush();
                }
            }
        }
        self.buf.push(id);
        if self.spilling && self.buf.len() >= WRITE_CHUNK {
            self.flush();
        }
    }

    pub fn len(&self) -> u64 {
        self.spilled + self.buf.len() as u64
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn finish(mut self) -> std::io::Result<IdList> {
        if !self.spilling {
            // Keep exactly what the list needs reserved.
            let keep = self.buf.len();
            self.lists.budget.release((self.reserved - keep) * 4);
            self.reserved = 0;
            let mut ids = std::mem::take(&mut self.buf);
            ids.shrink_to_fit();
            return Ok(IdList::Memory(Box::new(InMemory {
                ids,
                budget: self.lists.budget.clone(),
            })));
        }
        self.flush();
        if let Some(e) = self.error.take() {
            return Err(e);
        }
        Ok(IdList::Spilled(Box::new(InSpill {
            spill: self.lists.spill.clone(),
            chunks: std::mem::take(&mut self.chunks),
            len: self.spilled,
        })))
    }
}

impl Drop for ListWriter {
    fn drop(&mut self) {
        self.lists.budget.release(self.reserved * 4);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_list_is_two_words() {
        assert_eq!(std::mem::size_of::<IdList>(), 16);
    }

    fn lists(dir: &Path, limit: usize) -> Lists {
        Lists {
            budget: Budget::new(limit),
            spill: SpillFile::create(dir).unwrap(),
        }
    }

    fn collect(l: &IdList) -> Vec<u32> {
        let mut v = Vec::new();
        l.for_each_chunk(|c| v.extend_from_slice(c)).unwrap();
        v
    }

    #[test]
    fn writer_stays_in_memory_within_budget() {
        let dir = tempfile::tempdir().unwrap();
        let l = lists(dir.path(), 1 << 24);
        let mut w = ListWriter::new(&l);
        for i in 0..100_000 {
            w.push(i);
        }
        let list = w.finish().unwrap();
        assert!(list.as_slice().is_some());
        assert_eq!(l.budget.used(), 400_000);
        assert_eq!(collect(&list), (0..100_000).collect::<Vec<_>>());
        drop(list);
        assert_eq!(l.budget.used(), 0);
    }

    #[test]
    fn writer_spills_beyond_budget_and_never_exceeds_it() {
        let dir = tempfile::tempdir().unwrap();
        let l = lists(dir.path(), 3 * WRITE_CHUNK * 4);
        let mut keep = Vec::new();
        for k in 0..5u32 {
            let mut w = ListWriter::new(&l);
            for i in 0..(WRITE_CHUNK as u32 + 7) {
                w.push(k * 1_000_000 + i);
            }
            keep.push(w.finish().unwrap());
            assert!(l.budget.used() <= l.budget.limit());
        }
        assert!(l.budget.peak() <= l.budget.limit());
        assert!(keep.iter().any(|k| matches!(k, IdList::Spilled(_))));
        assert!(l.spill.bytes_written() > 0);
        for (k, list) in keep.iter().enumerate() {
            let want: Vec<u32> = (0..(WRITE_CHUNK as u32 + 7))
                .map(|i| k as u32 * 1_000_000 + i)
                .collect();
            assert_eq!(collect(list), want);
            assert_eq!(list.prefix(10).unwrap(), want[..10].to_vec());
        }
        drop(keep);
        assert_eq!(l.budget.used(), 0);
    }

    #[test]
    fn spill_and_load_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let l = lists(dir.path(), 1 << 20);
        let mut w = ListWriter::new(&l);
        for i in (0..50_000).rev() {
            w.push(i);
        }
        let m = w.finish().unwrap();
        let want = collect(&m);
        let s = m.spill(&l).unwrap();
        assert!(matches!(s, IdList::Spilled(_)));
        assert_eq!(l.budget.used(), 0);
        assert_eq!(collect(&s), want);
        let back = s.load(&l).unwrap();
        assert_eq!(back.as_slice().unwrap(), &want[..]);
        let r = IdList::Range(5..200_000);
        assert_eq!(collect(&r), (5..200_000).collect::<Vec<_>>());
        assert_eq!(r.prefix(3).unwrap(), vec![5, 6, 7]);
    }
}
