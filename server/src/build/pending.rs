//! The FIFO of treelets still to build, with their primitive lists. Lists are kept in memory up
//! to a byte budget; beyond it they are spilled to a scratch file and read back when their turn
//! comes, so the builder's working set stays bounded however large the input.

use std::collections::VecDeque;
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use super::treelet_builder::TreeletJob;

enum Prims {
    Memory(Vec<u32>),
    Spilled { offset: u64, len: u32 },
}

struct Queued {
    job: TreeletJob,
    prims: Prims,
}

/// FIFO of [`TreeletJob`]s whose primitive lists spill to disk beyond `budget` bytes.
pub struct PendingQueue {
    queue: VecDeque<Queued>,
    in_memory: usize,
    budget: usize,
    spill_path: PathBuf,
    spill: Option<BufWriter<File>>,
    spill_reader: Option<File>,
    spill_len: u64,
    /// Bytes written to the spill file over the whole build.
    pub spilled_bytes: u64,
}

impl std::fmt::Debug for PendingQueue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PendingQueue")
            .field("len", &self.queue.len())
            .field("in_memory", &self.in_memory)
            .field("spilled_bytes", &self.spilled_bytes)
            .finish()
    }
}

impl PendingQueue {
    pub fn new(scratch: &Path, budget: usize) -> Self {
        Self {
            queue: VecDeque::new(),
            in_memory: 0,
            budget,
            spill_path: scratch.join("pending.spill"),
            spill: None,
            spill_reader: None,
            spill_len: 0,
            spilled_bytes: 0,
        }
    }

    pub fn len(&self) -> usize {
        self.queue.len()
    }

    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }

    /// Bytes of primitive lists currently held in memory.
    pub fn bytes_in_memory(&self) -> usize {
        self.in_memory
    }

    pub fn push(&mut self, mut job: TreeletJob) -> std::io::Result<()> {
        let list = std::mem::take(&mut job.prims);
        let bytes = list.len() * 4;
        let prims = if self.in_memory + bytes <= self.budget {
            self.in_memory += bytes;
            Prims::Memory(list)
        } else {
            if self.spill.is_none() {
                let f = File::options()
                    .create(true)
                    .truncate(true)
                    .read(true)
                    .write(true)
                    .open(&self.spill_path)?;
                self.spill_reader = Some(f.try_clone()?);
                self.spill = Some(BufWriter::with_capacity(1 << 20, f));
            }
            let w = self.spill.as_mut().expect("opened above");
            let offset = self.spill_len;
            w.write_all(bytemuck::cast_slice(&list))?;
            self.spill_len += bytes as u64;
            self.spilled_bytes += bytes as u64;
            Prims::Spilled {
                offset,
                len: list.len() as u32,
            }
        };
        self.queue.push_back(Queued { job, prims });
        Ok(())
    }

    /// Takes the next job with its primitive list loaded.
    pub fn pop(&mut self) -> std::io::Result<Option<TreeletJob>> {
        let Some(q) = self.queue.pop_front() else {
            return Ok(None);
        };
        let mut job = q.job;
        job.prims = match q.prims {
            Prims::Memory(v) => {
                self.in_memory -= v.len() * 4;
                v
            }
            Prims::Spilled { offset, len } => {
                if let Some(w) = self.spill.as_mut() {
                    w.flush()?;
                }
                let mut v = vec![0u32; len as usize];
                let reader = self.spill_reader.as_ref().expect("spill file open");
                reader.read_exact_at(bytemuck::cast_slice_mut(&mut v), offset)?;
                v
            }
        };
        if self.queue.is_empty() {
            // Everything spilled has been read back: start the file over.
            if let Some(w) = self.spill.as_mut() {
                w.flush()?;
                w.get_mut().set_len(0)?;
                w.get_mut().seek(SeekFrom::Start(0))?;
            }
            self.spill_len = 0;
        }
        Ok(Some(job))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use arbor_proto::{Cell, TreeletId};

    fn job(i: u32, n: u32) -> TreeletJob {
        TreeletJob {
            id: TreeletId(i),
            parent_id: TreeletId::NONE,
            parent_leaf_index: 0,
            parent_leaf_parent_index: 0,
            child_index_in_parent: 0,
            root: Cell::ROOT,
            prims: (i..i + n).collect(),
        }
    }

    #[test]
    fn spills_beyond_budget_and_keeps_order() {
        let dir = tempfile::tempdir().unwrap();
        let mut q = PendingQueue::new(dir.path(), 4 * 100);
        for i in 0..10 {
            q.push(job(i, 60)).unwrap();
            assert!(q.bytes_in_memory() <= 400);
        }
        assert!(q.spilled_bytes > 0);
        for i in 0..10 {
            let j = q.pop().unwrap().unwrap();
            assert_eq!(j.id, TreeletId(i));
            assert_eq!(j.prims, (i..i + 60).collect::<Vec<_>>());
        }
        assert!(q.pop().unwrap().is_none());
        // Reusable after draining.
        q.push(job(50, 200)).unwrap();
        assert_eq!(q.pop().unwrap().unwrap().prims.len(), 200);
    }
}
