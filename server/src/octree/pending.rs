//! The FIFO of treelets still to build. Their primitive lists are [`IdList`](super::idlist::IdList)s under the build's
//! memory budget: a job queued while the budget is more than half used has its list moved to the
//! spill file, and a spilled list is brought back into memory when its job is taken, if the
//! budget has room then. So queued work never crowds out the lists of the treelets being filled.

use std::collections::VecDeque;

use super::idlist::Lists;
use super::treelet_builder::TreeletJob;

/// FIFO of [`TreeletJob`]s whose primitive lists spill to disk under memory pressure.
#[derive(Debug)]
pub struct PendingQueue {
    queue: VecDeque<TreeletJob>,
    lists: Lists,
}

impl PendingQueue {
    pub fn new(lists: &Lists) -> Self {
        Self {
            queue: VecDeque::new(),
            lists: lists.clone(),
        }
    }

    pub fn len(&self) -> usize {
        self.queue.len()
    }

    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }

    pub fn push(&mut self, mut job: TreeletJob) -> std::io::Result<()> {
        let budget = &self.lists.budget;
        if job.prims.memory_bytes() > 0 && budget.used() > budget.limit() / 2 {
            let prims = std::mem::replace(&mut job.prims, super::idlist::IdList::Range(0..0));
            job.prims = prims.spill(&self.lists)?;
        }
        self.queue.push_back(job);
        Ok(())
    }

    /// Takes the next job, its list loaded into memory when the budget allows.
    pub fn pop(&mut self) -> std::io::Result<Option<TreeletJob>> {
        let Some(mut job) = self.queue.pop_front() else {
            return Ok(None);
        };
        let prims = std::mem::replace(&mut job.prims, super::idlist::IdList::Range(0..0));
        job.prims = prims.load(&self.lists)?;
        Ok(Some(job))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree::idlist::{Budget, IdList, ListWriter, SpillFile};
    use arbor_proto::{Cell, TreeletId};

    fn job(lists: &Lists, i: u32, n: u32) -> TreeletJob {
        let mut w = ListWriter::new(lists);
        for p in i..i + n {
            w.push(p);
        }
        TreeletJob {
            id: TreeletId(i),
            parent_id: TreeletId::NONE,
            parent_leaf_index: 0,
            parent_leaf_parent_index: 0,
            child_index_in_parent: 0,
            root: Cell::ROOT,
            prims: w.finish().unwrap(),
        }
    }

    #[test]
    fn spills_under_pressure_and_keeps_order() {
        let dir = tempfile::tempdir().unwrap();
        let lists = Lists {
            budget: Budget::new(1 << 20),
            spill: SpillFile::create(dir.path()).unwrap(),
        };
        let mut q = PendingQueue::new(&lists);
        for i in 0..10 {
            q.push(job(&lists, i * 100_000, 60_000)).unwrap();
            assert!(lists.budget.used() <= lists.budget.limit());
        }
        assert!(lists.spill.bytes_written() > 0, "nothing spilled");
        for i in 0..10 {
            let j = q.pop().unwrap().unwrap();
            assert_eq!(j.id, TreeletId(i * 100_000));
            let mut got = Vec::new();
            j.prims
                .for_each_chunk(|c| got.extend_from_slice(c))
                .unwrap();
            assert_eq!(got, (i * 100_000..i * 100_000 + 60_000).collect::<Vec<_>>());
            assert!(
                matches!(j.prims, IdList::Memory(_)),
                "loaded back when room"
            );
        }
        assert!(q.pop().unwrap().is_none());
        assert_eq!(lists.budget.used(), 0);
    }
}
