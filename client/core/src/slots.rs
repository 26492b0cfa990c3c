//! The incore slot buffer (docs/design.md §5, "Incore update"): which treelet sits in which slot, the
//! patched node records the ray caster walks, and the eviction policy that keeps the buffer
//! within a fixed memory budget.
//!
//! It owns the incore octree: `capacity × N` node records plus one attribute array per held
//! channel, allocated once in [`SlotBuffer::new`] and never reallocated (a buffer made by
//! [`SlotBuffer::new_growing`] writes them slot by slot within that allocation), and all
//! per-slot bookkeeping (resident tree, visibility ages, the records patched leaves replaced, the dirty set). It is a
//! plain data structure in the quinn-proto style: no I/O, no GPU, no clock. The network hands it
//! decoded treelets, the presort pass tells it what is visible, and the upload step takes the
//! dirty slots ([`crate::upload`]); that is what makes every rule here unit-testable and lets
//! the model test in `arbor-tests` drive it with random step sequences.
//!
//! Layout and patching: node `k` of slot `s` has the global index `s·N + k` (see
//! [`IncoreView`]). Inserting a child treelet overwrites the refinable leaf it refines in its
//! parent with the child's root record, its `first_child` made relative to that leaf's own
//! global index and pointing at the child's node 1; the leaf bit in the leaf's parent is cleared.
//! The child's own node 0 is never reached by a traversal: its root lives at the patched leaf.

use std::borrow::Borrow;
use std::fmt;

use arbor_proto::codec::{self, PreparedDictionaries, SceneDictionaries};
use arbor_proto::{Cell, Channel, Node, ProtoError, SceneDescription, Treelet, TreeletId};

use crate::incore::IncoreView;

/// "No slot" in the bookkeeping links.
const NO_SLOT: u32 = u32::MAX;
/// Most changed cells [`SlotBuffer::take_changed_cells`] keeps between two calls (a caller
/// that takes them rarely, or never, holds no more than this).
pub const CHANGED_CELLS_MAX: usize = 4096;
/// Bookkeeping flag: the slot must be uploaded again.
const DIRTY: u8 = 1;
/// Bookkeeping flag, set only during an eviction scan: the slot is the new treelet's parent or
/// one of its ancestors and must not be evicted to make room for it.
const PROTECTED: u8 = 2;
/// Bookkeeping flag: never evicted until [`SlotBuffer::unpin_all`] (see [`SlotBuffer::pin`]).
const PINNED: u8 = 4;

/// How a new buffer makes its node and attribute arrays.
#[derive(Clone, Copy)]
enum Arrays {
    /// Every slot's records written now ([`SlotBuffer::new`]).
    Written,
    /// Reserved for every slot, written as slots are first filled ([`SlotBuffer::new_growing`]).
    Growing,
}

/// What the slot buffer is asked to hold.
#[derive(Clone, Debug, PartialEq)]
pub struct SlotConfig {
    /// Bytes the buffer may allocate for its slots, bookkeeping included (see
    /// [`SlotBuffer::slot_bytes`]).
    pub budget_bytes: u64,
    /// `N`, node records per treelet (the scene's).
    pub treelet_nodes: u32,
    /// Attribute channels held beside the nodes, each at most once.
    pub channels: Vec<Channel>,
    /// Visibility a slot gets when seen (n², the feedback ratio squared): the number of cycles
    /// it stays protected from eviction after it was last seen.
    pub visibility_max: u16,
    /// Treelets inserted per cycle at most (copy and upload cost per frame).
    pub load_limit: u32,
}

/// Errors of decoding treelets for the buffer and of building it.
#[derive(Debug, thiserror::Error)]
pub enum SlotError {
    /// The node or an attribute block failed to decompress, decode or validate.
    #[error("treelet {id}: {source}")]
    Decode {
        /// The treelet.
        id: TreeletId,
        /// What the decoder said.
        #[source]
        source: ProtoError,
    },
    /// The node block's header names another treelet than the message or the caller.
    #[error("treelet {expected}: the node block is treelet {found}")]
    IdMismatch {
        /// The id the message or caller named.
        expected: TreeletId,
        /// The id in the node block.
        found: TreeletId,
    },
    /// The message announced a different number of used node records than the block holds.
    #[error("treelet {id}: message announced {announced} used nodes, the block has {found}")]
    UsedNodesMismatch {
        /// The treelet.
        id: TreeletId,
        /// Used records the message announced.
        announced: u16,
        /// Used records the block holds.
        found: u16,
    },
    /// The treelet's capacity is not the scene's or buffer's `N`.
    #[error("treelet {id}: {found} node records, expected {expected}")]
    WrongNodeCount {
        /// The treelet.
        id: TreeletId,
        /// Its record count.
        found: u32,
        /// The scene's `N`.
        expected: u32,
    },
    /// A channel the client holds is missing from the treelet, or has the wrong length.
    #[error("treelet {id}: channel {channel:?} missing or not {expected} bytes")]
    MissingChannel {
        /// The treelet.
        id: TreeletId,
        /// The channel.
        channel: Channel,
        /// Bytes the block should decode to.
        expected: usize,
    },
    /// The configuration names a channel twice.
    #[error("channel {0:?} listed twice in the slot configuration")]
    DuplicateChannel(Channel),
    /// `N` is too small to hold a root and its children.
    #[error("treelets of {0} node records cannot be held: at least 2 are needed")]
    TreeletTooSmall(u32),
    /// The budget does not hold a single slot.
    #[error(
        "slot budget of {budget} bytes holds no slot: the minimum budget is {slot_bytes} bytes \
         (one slot of {treelet_nodes} nodes with its attributes and bookkeeping)"
    )]
    BudgetTooSmall {
        /// The budget asked for, bytes.
        budget: u64,
        /// What one slot costs, bytes.
        slot_bytes: u64,
        /// `N`.
        treelet_nodes: u32,
    },
    /// Slot 0 must hold the scene's root treelet.
    #[error("the root slot needs treelet 0 with no parent, got treelet {id} (parent {parent})")]
    NotRoot {
        /// The treelet given.
        id: TreeletId,
        /// Its parent.
        parent: TreeletId,
    },
    /// [`SlotBuffer::fully_resident`] was given a different number of treelets than the scene
    /// has.
    #[error("a fully resident buffer needs all {expected} treelets, got {found}")]
    Incomplete {
        /// The scene's treelet count.
        expected: u32,
        /// Treelets given.
        found: u32,
    },
    /// [`SlotBuffer::fully_resident`] could not place a treelet.
    #[error("treelet {id} could not be placed: {outcome:?}")]
    NotPlaced {
        /// The treelet.
        id: TreeletId,
        /// What the insert did.
        outcome: InsertOutcome,
    },
}

/// A treelet decompressed, decoded and validated, with the attribute channels the client holds.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DecodedTreelet {
    /// The node records and header.
    pub treelet: Treelet,
    /// One entry per wanted channel, in the order asked for; each `used_nodes × size` bytes.
    pub attributes: Vec<(Channel, Vec<u8>)>,
}

impl DecodedTreelet {
    /// Decodes a treelet message as a transport delivered it: `id` and `used_nodes` as the
    /// message announced them, the compressed blocks as stored. Decompresses with the scene's
    /// dictionaries (prepared once per scene: a raw one is loaded again on every block),
    /// validates the tree against the scene's depth, and checks that the announced id and
    /// used-node count agree with the block and that every wanted channel is present with the
    /// right length (channels not wanted are ignored).
    pub fn decode_message(
        id: TreeletId,
        used_nodes: u16,
        nodes: &[u8],
        channels: &[(Channel, &[u8])],
        scene: &SceneDescription,
        dictionaries: &PreparedDictionaries,
        wanted: &[Channel],
    ) -> Result<Self, SlotError> {
        let decoded = Self::from_blocks_prepared(id, nodes, channels, scene, dictionaries, wanted)?;
        let found = decoded.treelet.header.used_nodes;
        if found != used_nodes {
            return Err(SlotError::UsedNodesMismatch {
                id,
                announced: used_nodes,
                found,
            });
        }
        Ok(decoded)
    }

    /// Decodes a treelet from its compressed blocks as stored (pool, cache, tests): `nodes` is
    /// the node block, `channels` the attribute blocks on hand, `wanted` the channels to keep.
    /// Uses the scene's raw dictionaries; a reader of many blocks prepares them once
    /// ([`from_blocks_prepared`](Self::from_blocks_prepared)).
    pub fn from_blocks(
        id: TreeletId,
        nodes: &[u8],
        channels: &[(Channel, &[u8])],
        scene: &SceneDescription,
        wanted: &[Channel],
    ) -> Result<Self, SlotError> {
        let raw = SceneDictionaries::Raw(scene);
        Self::decode_blocks(id, nodes, channels, scene, raw, wanted)
    }

    /// [`from_blocks`](Self::from_blocks) with the scene's dictionaries prepared.
    pub fn from_blocks_prepared(
        id: TreeletId,
        nodes: &[u8],
        channels: &[(Channel, &[u8])],
        scene: &SceneDescription,
        dictionaries: &PreparedDictionaries,
        wanted: &[Channel],
    ) -> Result<Self, SlotError> {
        let prepared = SceneDictionaries::Prepared(dictionaries);
        Self::decode_blocks(id, nodes, channels, scene, prepared, wanted)
    }

    fn decode_blocks(
        id: TreeletId,
        nodes: &[u8],
        channels: &[(Channel, &[u8])],
        scene: &SceneDescription,
        dictionaries: SceneDictionaries<'_>,
        wanted: &[Channel],
    ) -> Result<Self, SlotError> {
        let treelet =
            codec::decode_compressed_treelet_using(nodes, scene.max_depth, dictionaries.nodes())
                .map_err(|source| SlotError::Decode { id, source })?;
        if treelet.header.id != id {
            return Err(SlotError::IdMismatch {
                expected: id,
                found: treelet.header.id,
            });
        }
        if treelet.capacity() != scene.treelet_nodes {
            return Err(SlotError::WrongNodeCount {
                id,
                found: treelet.capacity(),
                expected: scene.treelet_nodes,
            });
        }
        let used = treelet.header.used_nodes;
        let mut attributes = Vec::with_capacity(wanted.len());
        for &channel in wanted {
            let expected = usize::from(used) * channel.size();
            let Some((_, block)) = channels.iter().find(|(c, _)| *c == channel) else {
                return Err(SlotError::MissingChannel {
                    id,
                    channel,
                    expected,
                });
            };
            let raw = codec::decode_compressed_attributes_using(
                block,
                channel,
                used,
                dictionaries.channel(channel),
            )
            .map_err(|source| SlotError::Decode { id, source })?;
            attributes.push((channel, raw));
        }
        Ok(Self {
            treelet,
            attributes,
        })
    }

    /// The treelet's id.
    pub fn id(&self) -> TreeletId {
        self.treelet.header.id
    }
}

/// What [`SlotBuffer::insert`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InsertOutcome {
    /// The treelet now sits in `slot`; `evicted` treelets (descendants included) made room.
    Inserted {
        /// Where it went.
        slot: u32,
        /// Treelets evicted for it.
        evicted: u32,
    },
    /// The treelet was resident already; nothing changed.
    AlreadyResident,
    /// The parent is not resident (or, resident, has no refinable leaf for this treelet where
    /// its header says): nothing to attach it to, the treelet is dropped.
    ParentMissing,
    /// No slot was free and none could be evicted.
    NoRoom,
    /// This cycle's load limit is reached; nothing changed.
    LoadLimit,
}

/// Cumulative counters of a [`SlotBuffer`].
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct SlotStats {
    /// Treelets inserted (the root included).
    pub inserted: u64,
    /// Treelets evicted, descendants freed with an evicted treelet included.
    pub evicted: u64,
    /// Treelets dropped because their parent was not resident.
    pub orphans: u64,
    /// Of those, treelets whose resident parent had no matching refinable leaf (a header that
    /// does not fit the parent: another scene's treelet or a corrupt one).
    pub mismatched: u64,
    /// Treelets dropped because no slot was free and none could be evicted.
    pub no_room: u64,
    /// Treelets that were resident already.
    pub duplicates: u64,
    /// Treelets refused because the cycle's load limit was reached.
    pub load_limited: u64,
}

/// Per-slot bookkeeping. Its size is part of [`SlotBuffer::slot_bytes`].
#[derive(Clone, Copy, Debug)]
struct SlotRecord {
    /// [`TreeletId::NONE`] when the slot is free.
    treelet: TreeletId,
    /// Slot of the parent treelet; [`NO_SLOT`] for slot 0 and free slots.
    parent: u32,
    /// Resident children, as an intrusive doubly linked list (bounded: no allocation).
    first_child: u32,
    next_sibling: u32,
    prev_sibling: u32,
    /// The leaf record this treelet's root replaced in its parent, restored on eviction.
    replaced: Node,
    /// Cycle in which the slot was last marked visible.
    last_visible: u64,
    /// Cycles of protection left; 0 = invisible.
    visibility: u16,
    parent_leaf_index: u16,
    parent_leaf_parent_index: u16,
    child_index_in_parent: u8,
    flags: u8,
    /// The cell of the treelet's root voxel: what its eviction restores as one leaf.
    root: Cell,
}

impl SlotRecord {
    const FREE: SlotRecord = SlotRecord {
        treelet: TreeletId::NONE,
        parent: NO_SLOT,
        first_child: NO_SLOT,
        next_sibling: NO_SLOT,
        prev_sibling: NO_SLOT,
        replaced: Node {
            first_child: 0,
            valid_mask: 0,
            leaf_mask: 0,
            spare: 0,
        },
        last_visible: 0,
        visibility: 0,
        parent_leaf_index: 0,
        parent_leaf_parent_index: 0,
        child_index_in_parent: 0,
        flags: 0,
        root: Cell::ROOT,
    };

    fn is_free(&self) -> bool {
        self.treelet.is_none()
    }
}

/// Per slot besides the record: two id-index entries (the index is kept at most half full),
/// one free-list entry and one dirty-list entry, all `u32`.
const INDEX_ENTRIES_PER_SLOT: u64 = 2;
const BOOKKEEPING_BYTES: u64 =
    std::mem::size_of::<SlotRecord>() as u64 + INDEX_ENTRIES_PER_SLOT * 4 + 4 + 4;

/// The incore slot buffer. See the module docs.
pub struct SlotBuffer {
    config: SlotConfig,
    capacity: u32,
    /// `capacity × N` node records, slot-major.
    nodes: Vec<Node>,
    /// Per held channel, `capacity × N × size` bytes, in config order.
    attributes: Vec<(Channel, Vec<u8>)>,
    records: Vec<SlotRecord>,
    /// Open-addressing (linear probing) map treelet id → slot: entries are slots, [`NO_SLOT`]
    /// empty; a fixed `2 × capacity` entries so it never grows and probes stay short.
    index: Vec<u32>,
    /// Free slots, popped from the end (so low slots fill first after `new`).
    free: Vec<u32>,
    /// Dirty slots, unsorted, each once (the record's [`DIRTY`] flag dedupes).
    dirty: Vec<u32>,
    /// Changes to the node and attribute arrays so far ([`SlotBuffer::changes`]).
    changes: u64,
    /// Cells of the treelets inserted and the subtrees evicted since the last
    /// [`SlotBuffer::take_changed_cells`]; `None` once more than [`CHANGED_CELLS_MAX`] piled up.
    changed_cells: Option<Vec<Cell>>,
    cycle: u64,
    loaded_this_cycle: u32,
    stats: SlotStats,
    /// Treelets evicted since the last [`SlotBuffer::take_evicted`].
    evicted_log: Vec<TreeletId>,
    /// Root cells of the subtrees evicted since the last [`SlotBuffer::take_evicted_roots`]:
    /// where a leaf was restored, so only rays through them can see anything change.
    evicted_roots: Vec<Cell>,
}

impl fmt::Debug for SlotBuffer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SlotBuffer")
            .field("config", &self.config)
            .field("capacity", &self.capacity)
            .field("used_slots", &self.used_slots())
            .field("cycle", &self.cycle)
            .field("stats", &self.stats)
            .finish_non_exhaustive()
    }
}

impl SlotBuffer {
    /// Bytes one slot costs: its `N` node records, its attribute records, and the per-slot
    /// bookkeeping (slot record with the saved leaf record, id-index entries, free- and
    /// dirty-list entries). `capacity × slot_bytes` is everything the buffer allocates that
    /// scales with its size.
    pub fn slot_bytes(treelet_nodes: u32, channels: &[Channel]) -> u64 {
        Self::slot_data_bytes(treelet_nodes, channels) + BOOKKEEPING_BYTES
    }

    /// Bytes of one slot that are uploaded: node records and attributes, no bookkeeping.
    pub fn slot_data_bytes(treelet_nodes: u32, channels: &[Channel]) -> u64 {
        let per_node = std::mem::size_of::<Node>() as u64
            + channels.iter().map(|c| c.size() as u64).sum::<u64>();
        u64::from(treelet_nodes) * per_node
    }

    /// A buffer of `budget / slot_bytes` slots (capped so that every global node index fits a
    /// `u32` below [`Node::NONE`]), all allocated now, with `root` in slot 0 for good.
    pub fn new(config: SlotConfig, root: DecodedTreelet) -> Result<Self, SlotError> {
        Self::build(config, root, Arrays::Written)
    }

    /// [`SlotBuffer::new`] for a buffer that is only cast through and dropped, never uploaded
    /// whole: the node and attribute arrays are reserved for every slot but written only as
    /// slots are first filled (lowest first), so [`SlotBuffer::view`]'s arrays end after the
    /// highest slot ever filled. The server's visible cuts build one per cast at the client's
    /// budget (32 MiB by default) and often fill a few percent of it; writing the rest cost
    /// 1.2 ms a cut.
    pub fn new_growing(config: SlotConfig, root: DecodedTreelet) -> Result<Self, SlotError> {
        Self::build(config, root, Arrays::Growing)
    }

    fn build(config: SlotConfig, root: DecodedTreelet, arrays: Arrays) -> Result<Self, SlotError> {
        let n = config.treelet_nodes;
        if n < 2 {
            return Err(SlotError::TreeletTooSmall(n));
        }
        for (i, c) in config.channels.iter().enumerate() {
            if config.channels[..i].contains(c) {
                return Err(SlotError::DuplicateChannel(*c));
            }
        }
        let slot_bytes = Self::slot_bytes(n, &config.channels);
        let addressable = u64::from((Node::NONE - 1) / n);
        let capacity = (config.budget_bytes / slot_bytes).min(addressable) as u32;
        if capacity == 0 {
            return Err(SlotError::BudgetTooSmall {
                budget: config.budget_bytes,
                slot_bytes,
                treelet_nodes: n,
            });
        }
        let h = root.treelet.header;
        if h.id != TreeletId::ROOT || !h.parent_id.is_none() {
            return Err(SlotError::NotRoot {
                id: h.id,
                parent: h.parent_id,
            });
        }
        let records = capacity as usize * n as usize;
        let (nodes, attributes) = match arrays {
            Arrays::Written => (
                vec![Node::default(); records],
                config
                    .channels
                    .iter()
                    .map(|&c| (c, vec![0u8; records * c.size()]))
                    .collect(),
            ),
            Arrays::Growing => (
                Vec::with_capacity(records),
                config
                    .channels
                    .iter()
                    .map(|&c| (c, Vec::with_capacity(records * c.size())))
                    .collect(),
            ),
        };
        let mut buffer = Self {
            capacity,
            nodes,
            attributes,
            records: vec![SlotRecord::FREE; capacity as usize],
            index: vec![NO_SLOT; capacity as usize * INDEX_ENTRIES_PER_SLOT as usize],
            free: (1..capacity).rev().collect(),
            dirty: Vec::with_capacity(capacity as usize),
            changes: 0,
            changed_cells: Some(Vec::new()),
            cycle: 0,
            loaded_this_cycle: 0,
            evicted_log: Vec::new(),
            evicted_roots: Vec::new(),
            stats: SlotStats::default(),
            config,
        };
        buffer.check_fits(&root)?;
        buffer.fill_slot(0, &root);
        buffer.records[0] = SlotRecord {
            treelet: TreeletId::ROOT,
            visibility: buffer.config.visibility_max,
            ..SlotRecord::FREE
        };
        buffer.index_insert(TreeletId::ROOT, 0);
        buffer.mark_dirty(0);
        buffer.stats.inserted = 1;
        Ok(buffer)
    }

    /// A buffer holding a whole scene: one slot per treelet, each inserted in id order (so every
    /// parent is resident before its children), no load limit. Errors if the treelets are not
    /// exactly the scene's or one could not be placed.
    pub fn fully_resident(
        scene: &SceneDescription,
        channels: &[Channel],
        treelets: impl IntoIterator<Item = DecodedTreelet>,
    ) -> Result<Self, SlotError> {
        let mut all: Vec<DecodedTreelet> = treelets.into_iter().collect();
        if all.len() != scene.treelet_count as usize {
            return Err(SlotError::Incomplete {
                expected: scene.treelet_count,
                found: all.len() as u32,
            });
        }
        all.sort_by_key(DecodedTreelet::id);
        let mut rest = all.into_iter();
        let root = rest.next().ok_or(SlotError::Incomplete {
            expected: scene.treelet_count,
            found: 0,
        })?;
        let config = SlotConfig {
            budget_bytes: u64::from(scene.treelet_count)
                * Self::slot_bytes(scene.treelet_nodes, channels),
            treelet_nodes: scene.treelet_nodes,
            channels: channels.to_vec(),
            // Nothing is ever evicted (every treelet has its slot), so visibility is moot.
            visibility_max: 1,
            load_limit: u32::MAX,
        };
        let mut buffer = Self::new(config, root)?;
        for t in rest {
            let id = t.id();
            match buffer.insert(t) {
                InsertOutcome::Inserted { .. } => {}
                outcome => return Err(SlotError::NotPlaced { id, outcome }),
            }
        }
        Ok(buffer)
    }

    /// The incore octree as the ray caster reads it.
    pub fn view(&self) -> IncoreView<'_> {
        let channel = |c: Channel| {
            self.attributes
                .iter()
                .find(|(k, _)| *k == c)
                .map(|(_, v)| v.as_slice())
        };
        IncoreView {
            nodes: &self.nodes,
            treelet_nodes: self.config.treelet_nodes,
            color: channel(Channel::Color),
            normal: channel(Channel::Normal),
            density: channel(Channel::Density),
        }
    }

    /// Slots in the buffer (fixed at creation).
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// Slots holding a treelet (the root's included).
    pub fn used_slots(&self) -> u32 {
        self.capacity - self.free.len() as u32
    }

    /// What the buffer was made with (the visibility span as last set).
    pub fn config(&self) -> &SlotConfig {
        &self.config
    }

    /// Sets how many cycles a slot stays visible after it was last seen (at least 1): about the
    /// cycles a full look at the view takes, which depends on how much a cycle samples.
    pub fn set_visibility_max(&mut self, cycles: u16) {
        self.config.visibility_max = cycles.max(1);
    }

    /// The current cycle (number of [`begin_cycle`](Self::begin_cycle) calls).
    pub fn cycle(&self) -> u64 {
        self.cycle
    }

    /// The treelet in `slot`, if any.
    pub fn treelet_in(&self, slot: u32) -> Option<TreeletId> {
        let r = self.records.get(slot as usize)?;
        (!r.is_free()).then_some(r.treelet)
    }

    /// The slot holding treelet `id`, if resident.
    pub fn slot_of(&self, id: TreeletId) -> Option<u32> {
        if id.is_none() {
            return None;
        }
        let mut at = self.home(id);
        loop {
            let slot = self.index[at];
            if slot == NO_SLOT {
                return None;
            }
            if self.records[slot as usize].treelet == id {
                return Some(slot);
            }
            at = (at + 1) % self.index.len();
        }
    }

    /// The slot of the parent of the treelet in `slot`; `None` for slot 0 and free slots.
    pub fn parent_slot(&self, slot: u32) -> Option<u32> {
        let p = self.records.get(slot as usize)?.parent;
        (p != NO_SLOT).then_some(p)
    }

    /// The treelet sits in a slot.
    pub fn is_resident(&self, id: TreeletId) -> bool {
        self.slot_of(id).is_some()
    }

    /// Visibility left in `slot` (0 = invisible), for diagnostics and tests.
    pub fn visibility(&self, slot: u32) -> u16 {
        self.records[slot as usize].visibility
    }

    /// Insertions the per-cycle load limit still allows this cycle.
    pub fn loads_left(&self) -> u32 {
        self.config
            .load_limit
            .saturating_sub(self.loaded_this_cycle)
    }

    /// Slots holding nothing.
    pub fn free_slots(&self) -> u32 {
        self.free.len() as u32
    }

    /// Slots an insertion could use now: free ones plus those eviction may take (a treelet
    /// and its parent both invisible). The core caps its request list to this, so an
    /// oversubscribed buffer does not ask for treelets it would have to drop.
    pub fn room(&self) -> u32 {
        let evictable = self
            .records
            .iter()
            .skip(1)
            .filter(|r| {
                !r.is_free()
                    && r.flags & PINNED == 0
                    && r.visibility == 0
                    && self.records[r.parent as usize].visibility == 0
            })
            .count() as u32;
        self.free.len() as u32 + evictable
    }

    /// Free slots plus resident ones outside `visible` (sorted): the room the view has when
    /// the core may evict what no pixel reaches ([`SlotBuffer::evict_outside`]).
    pub fn room_outside(&self, visible: &[u32]) -> u32 {
        let seen = |slot: u32| visible.binary_search(&slot).is_ok();
        let unseen = self
            .records
            .iter()
            .enumerate()
            .skip(1)
            .filter(|(s, r)| !r.is_free() && r.flags & PINNED == 0 && !seen(*s as u32))
            .count() as u32;
        self.free.len() as u32 + unseen
    }

    /// Evicts up to `count` treelets outside `visible` (sorted), least recently visible first,
    /// each with its resident descendants (which are outside `visible` too, since `visible`
    /// holds the ancestors of every seen slot); returns the treelets freed.
    ///
    /// Unlike the eviction an insertion makes, this one may take a treelet whose parent is
    /// visible: it is for a caller that knows the *whole* view (every pixel sampled since the
    /// view last changed), so no pixel's hit lies in the treelet. A ray may still have passed
    /// through the gaps of the evicted subtree on its way to its hit, and the restored leaf is
    /// solid, so the caller must sample the view again.
    /// Returns the treelets freed.
    pub fn evict_outside(&mut self, visible: &[u32], count: u32) -> u32 {
        let seen = |slot: u32| visible.binary_search(&slot).is_ok();
        let mut victims: Vec<(u64, u32)> = self
            .records
            .iter()
            .enumerate()
            .skip(1)
            .filter(|(s, r)| !r.is_free() && r.flags & PINNED == 0 && !seen(*s as u32))
            .map(|(s, r)| (r.last_visible, s as u32))
            .collect();
        victims.sort_unstable();
        let mut freed = 0;
        for (_, slot) in victims {
            if freed >= count {
                break;
            }
            // An earlier victim may have freed this one as its descendant.
            if !self.records[slot as usize].is_free() {
                freed += self.evict(slot);
            }
        }
        freed
    }

    /// Keeps treelet `id` (if resident) from eviction until [`SlotBuffer::unpin_all`]: for a
    /// treelet the view needs although no pixel's hit lies in it — rays pass through its gaps
    /// to what lies behind, and its restored coarse leaf would stop them — so visibility alone
    /// would let it go, and the view would ask for it again.
    pub fn pin(&mut self, id: TreeletId) {
        if let Some(slot) = self.slot_of(id) {
            self.records[slot as usize].flags |= PINNED;
        }
    }

    /// Lifts every [`SlotBuffer::pin`] (the view changed).
    pub fn unpin_all(&mut self) {
        for r in &mut self.records {
            r.flags &= !PINNED;
        }
    }

    /// Whether treelet `id` is resident and pinned.
    pub fn is_pinned(&self, id: TreeletId) -> bool {
        self.slot_of(id)
            .is_some_and(|s| self.records[s as usize].flags & PINNED != 0)
    }

    /// The treelets evicted (descendants included) since the last call.
    pub fn take_evicted(&mut self) -> Vec<TreeletId> {
        std::mem::take(&mut self.evicted_log)
    }

    /// The root cells of the subtrees evicted since the last call (by an insertion or by
    /// [`SlotBuffer::evict_outside`]), each once: a restored leaf fills each, so only rays
    /// through them can see anything change.
    pub fn take_evicted_roots(&mut self) -> Vec<Cell> {
        std::mem::take(&mut self.evicted_roots)
    }

    /// Starts a cycle: every slot's visibility ages by one, the load counter resets.
    pub fn begin_cycle(&mut self) {
        for r in &mut self.records {
            r.visibility = r.visibility.saturating_sub(1);
        }
        self.loaded_this_cycle = 0;
        self.cycle += 1;
    }

    /// Marks `slot` seen this cycle. The caller passes the ancestors of every seen slot too
    /// (presort's visible set does). Free slots are ignored: a stale feedback entry may name a
    /// slot evicted since.
    ///
    /// # Panics
    /// If `slot ≥ capacity`.
    pub fn mark_visible(&mut self, slot: u32) {
        assert!(
            slot < self.capacity,
            "slot {slot} ≥ capacity {}",
            self.capacity
        );
        let max = self.config.visibility_max;
        let cycle = self.cycle;
        let r = &mut self.records[slot as usize];
        if !r.is_free() {
            r.visibility = max;
            r.last_visible = cycle;
        }
    }

    /// Inserts a treelet (docs/design.md §5): refused with nothing changed when the cycle's load limit is
    /// reached, the treelet is resident already or its parent is not resident; otherwise copied
    /// into a free slot (evicting if none is free) and patched into its parent.
    ///
    /// # Panics
    /// If the treelet does not fit this buffer (another `N`, a held channel missing or of the
    /// wrong length): [`DecodedTreelet::decode_message`] with the buffer's channels guarantees it.
    ///
    /// The treelet is only read: a caller holding it shared (the server's visible cuts fetch
    /// from a cache of `Arc`s) passes it without a copy.
    pub fn insert(&mut self, t: impl Borrow<DecodedTreelet>) -> InsertOutcome {
        let t: &DecodedTreelet = t.borrow();
        if let Err(e) = self.check_fits(t) {
            panic!("treelet does not fit the slot buffer: {e}");
        }
        if self.loaded_this_cycle >= self.config.load_limit {
            self.stats.load_limited += 1;
            return InsertOutcome::LoadLimit;
        }
        let h = t.treelet.header;
        if self.is_resident(h.id) {
            self.stats.duplicates += 1;
            return InsertOutcome::AlreadyResident;
        }
        let Some(parent) = self.slot_of(h.parent_id) else {
            self.stats.orphans += 1;
            return InsertOutcome::ParentMissing;
        };
        let Some((site, leaf_bit)) = self.checked_site(
            parent,
            h.parent_leaf_index,
            h.parent_leaf_parent_index,
            h.child_index_in_parent,
            h.id,
        ) else {
            self.stats.orphans += 1;
            self.stats.mismatched += 1;
            return InsertOutcome::ParentMissing;
        };
        let mut evicted = 0;
        let slot = match self.free.pop() {
            Some(s) => s,
            None => match self.eviction_candidate(parent) {
                Some(victim) => {
                    evicted = self.evict(victim);
                    self.free.pop().expect("eviction freed a slot")
                }
                None => {
                    self.stats.no_room += 1;
                    return InsertOutcome::NoRoom;
                }
            },
        };
        self.fill_slot(slot, t);
        let n = self.config.treelet_nodes;
        let root = t.treelet.nodes[0];
        let replaced = self.nodes[site as usize];
        // A child root with children becomes an inner node at the leaf's place: point it at the
        // child's node 1 (the root's children always start there, breadth-first) relative to the
        // leaf's own global index, wrapping when the child sits in a lower slot, and clear the
        // leaf bit. A child root without children is itself a leaf: copied verbatim, its
        // `first_child` keeps its leaf meaning (NONE or the subtreelet id) and the leaf bit stays
        // set, so the caster still sees a leaf there, now refined by that subtreelet id.
        self.nodes[site as usize] = if root.valid_mask == 0 {
            root
        } else {
            if let Some((leaf_parent, child)) = leaf_bit {
                self.nodes[leaf_parent as usize].leaf_mask &= !(1 << child);
            }
            Node {
                first_child: (slot * n + 1).wrapping_sub(site),
                ..root
            }
        };
        // A new treelet was just requested for a visible leaf, so it starts fully visible: it is
        // not evicted again before the caster has had a chance to see it.
        self.records[slot as usize] = SlotRecord {
            treelet: h.id,
            parent,
            first_child: NO_SLOT,
            next_sibling: self.records[parent as usize].first_child,
            prev_sibling: NO_SLOT,
            replaced,
            last_visible: self.cycle,
            visibility: self.config.visibility_max,
            parent_leaf_index: h.parent_leaf_index,
            parent_leaf_parent_index: h.parent_leaf_parent_index,
            child_index_in_parent: h.child_index_in_parent,
            flags: 0,
            root: h.root_cell(),
        };
        let old_first = self.records[parent as usize].first_child;
        if old_first != NO_SLOT {
            self.records[old_first as usize].prev_sibling = slot;
        }
        self.records[parent as usize].first_child = slot;
        self.index_insert(h.id, slot);
        self.note_changed_cell(h.root_cell());
        self.mark_dirty(slot);
        self.mark_dirty(site / n);
        if let Some((leaf_parent, _)) = leaf_bit {
            self.mark_dirty(leaf_parent / n);
        }
        self.loaded_this_cycle += 1;
        self.stats.inserted += 1;
        InsertOutcome::Inserted { slot, evicted }
    }

    /// Changes to the node and attribute arrays so far: every change marks a slot dirty (the
    /// GPU copy is kept equal through exactly those), so while the count stands still the
    /// arrays hold the same bytes, and a render of them from the same camera is the same image.
    pub fn changes(&self) -> u64 {
        self.changes
    }

    /// The cells where the arrays changed since the last call: the root cell of every treelet
    /// inserted and of every subtree evicted. A ray that meets none of these cubes meets the
    /// same records as before, so only the pixels whose rays may meet them can look different.
    /// `None` when more than [`CHANGED_CELLS_MAX`] piled up (then assume everything changed).
    pub fn take_changed_cells(&mut self) -> Option<Vec<Cell>> {
        self.changed_cells.replace(Vec::new())
    }

    fn note_changed_cell(&mut self, cell: Cell) {
        if let Some(cells) = &mut self.changed_cells {
            if cells.len() < CHANGED_CELLS_MAX {
                cells.push(cell);
            } else {
                self.changed_cells = None;
            }
        }
    }

    /// The dirty slots, sorted; the dirty set is cleared.
    pub fn take_dirty(&mut self) -> Vec<u32> {
        for &s in &self.dirty {
            self.records[s as usize].flags &= !DIRTY;
        }
        self.dirty.sort_unstable();
        // A slot dirtied, freed (its record reset, flag included) and dirtied again within one
        // cycle is listed twice: report it once.
        self.dirty.dedup();
        let out = self.dirty.clone();
        self.dirty.clear();
        out
    }

    /// Counters since creation.
    pub fn stats(&self) -> &SlotStats {
        &self.stats
    }

    /// Checks `t` has this buffer's `N` and every held channel with the right length.
    fn check_fits(&self, t: &DecodedTreelet) -> Result<(), SlotError> {
        let id = t.id();
        let n = self.config.treelet_nodes;
        if t.treelet.capacity() != n {
            return Err(SlotError::WrongNodeCount {
                id,
                found: t.treelet.capacity(),
                expected: n,
            });
        }
        let used = usize::from(t.treelet.header.used_nodes);
        for &channel in &self.config.channels {
            let expected = used * channel.size();
            let ok = t
                .attributes
                .iter()
                .any(|(c, v)| *c == channel && v.len() == expected);
            if !ok {
                return Err(SlotError::MissingChannel {
                    id,
                    channel,
                    expected,
                });
            }
        }
        Ok(())
    }

    /// Copies all `N` node records and the attributes into `slot`, zeroing the unused attribute
    /// space (so an upload never carries a previous tenant's bytes).
    fn fill_slot(&mut self, slot: u32, t: &DecodedTreelet) {
        let n = self.config.treelet_nodes as usize;
        let s = slot as usize;
        // A growing buffer's arrays end at the highest slot filled so far (see `new_growing`);
        // a written one's never need this.
        if self.nodes.len() < (s + 1) * n {
            self.nodes.resize((s + 1) * n, Node::default());
        }
        self.nodes[s * n..(s + 1) * n].copy_from_slice(&t.treelet.nodes);
        for (channel, dst) in &mut self.attributes {
            let size = channel.size();
            if dst.len() < (s + 1) * n * size {
                dst.resize((s + 1) * n * size, 0);
            }
            let src = &t
                .attributes
                .iter()
                .find(|(c, _)| c == channel)
                .expect("checked by check_fits")
                .1;
            let area = &mut dst[s * n * size..(s + 1) * n * size];
            area[..src.len()].copy_from_slice(src);
            area[src.len()..].fill(0);
        }
    }

    /// Global index where a traversal meets node `local` of the treelet in `slot`. Node `k ≥ 1`
    /// sits at `slot·N + k`, but a treelet's root record is met at the leaf it patched in its
    /// parent, never at its own node 0 (which only keeps a copy) — and if that leaf is itself the
    /// parent's root (a child root without children, copied verbatim), one level further up.
    fn record_at(&self, mut slot: u32, local: u16) -> u32 {
        let n = self.config.treelet_nodes;
        if local != 0 {
            return slot * n + u32::from(local);
        }
        loop {
            if slot == 0 {
                return 0;
            }
            let r = &self.records[slot as usize];
            if r.parent_leaf_index != 0 {
                return r.parent * n + u32::from(r.parent_leaf_index);
            }
            slot = r.parent;
        }
    }

    /// Where a child of the treelet in `slot` refining its leaf `leaf` (child `child` of node
    /// `leaf_parent`) patches: `(global index of the leaf record, Some((global index of the
    /// record holding its leaf bit, child index)))`, the bit `None` when the leaf is the scene
    /// root (whose leafness is its own `valid_mask == 0`). Both records are found where a
    /// traversal meets them ([`record_at`](Self::record_at)): the leaf bit of a leaf whose parent
    /// is the treelet's root lives in the root's patched copy in the grandparent.
    fn site(
        &self,
        mut slot: u32,
        mut leaf: u16,
        mut leaf_parent: u16,
        mut child: u8,
    ) -> (u32, Option<(u32, u8)>) {
        loop {
            if leaf != 0 {
                return (
                    self.record_at(slot, leaf),
                    Some((self.record_at(slot, leaf_parent), child)),
                );
            }
            // The leaf is the treelet's root: it is met, with its leaf bit, where that root
            // patched its own parent.
            if slot == 0 {
                return (0, None);
            }
            let r = &self.records[slot as usize];
            (slot, leaf, leaf_parent, child) = (
                r.parent,
                r.parent_leaf_index,
                r.parent_leaf_parent_index,
                r.child_index_in_parent,
            );
        }
    }

    /// [`site`](Self::site) for a new child `id`, checked against what the parent holds there: a
    /// leaf refined by `id`, marked a leaf in a parent that has it as child `child`. `None` if the
    /// header does not fit the parent (indices out of range or another record there).
    fn checked_site(
        &self,
        parent: u32,
        leaf: u16,
        leaf_parent: u16,
        child: u8,
        id: TreeletId,
    ) -> Option<(u32, Option<(u32, u8)>)> {
        let n = self.config.treelet_nodes;
        if u32::from(leaf) >= n || u32::from(leaf_parent) >= n || child >= 8 {
            return None;
        }
        let (site, bit) = self.site(parent, leaf, leaf_parent, child);
        let record = self.nodes[site as usize];
        if record.valid_mask != 0 || record.first_child != id.0 {
            return None;
        }
        if let Some((lp, ci)) = bit {
            let p = self.nodes[lp as usize];
            let pos = p.child_slot(ci)?;
            if p.leaf_mask & (1 << ci) == 0
                || lp.wrapping_add(p.first_child).wrapping_add(pos) != site
            {
                return None;
            }
        }
        Some((site, bit))
    }

    /// The slot to evict to make room for a child of `parent`: a slot other than 0 whose
    /// treelet and parent are both invisible (a visible parent would show the restored coarse
    /// leaf at silhouettes and flicker), not `parent` or one of its ancestors, least recently
    /// visible first, ties to the lower slot.
    fn eviction_candidate(&mut self, parent: u32) -> Option<u32> {
        let mut s = parent;
        while s != NO_SLOT {
            self.records[s as usize].flags |= PROTECTED;
            s = self.records[s as usize].parent;
        }
        let mut best: Option<(u64, u32)> = None;
        for (slot, r) in self.records.iter().enumerate().skip(1) {
            if r.is_free() || r.visibility != 0 || r.flags & (PROTECTED | PINNED) != 0 {
                continue;
            }
            if self.records[r.parent as usize].visibility != 0 {
                continue;
            }
            let key = (r.last_visible, slot as u32);
            if best.is_none_or(|b| key < b) {
                best = Some(key);
            }
        }
        let mut s = parent;
        while s != NO_SLOT {
            self.records[s as usize].flags &= !PROTECTED;
            s = self.records[s as usize].parent;
        }
        best.map(|(_, slot)| slot)
    }

    /// Evicts the treelet in `victim` with all its resident descendants; restores the leaf its
    /// root replaced in its parent and sets the leaf bit again. Returns the treelets freed.
    fn evict(&mut self, victim: u32) -> u32 {
        let r = self.records[victim as usize];
        let (site, bit) = self.site(
            r.parent,
            r.parent_leaf_index,
            r.parent_leaf_parent_index,
            r.child_index_in_parent,
        );
        self.nodes[site as usize] = r.replaced;
        let n = self.config.treelet_nodes;
        if let Some((leaf_parent, child)) = bit {
            self.nodes[leaf_parent as usize].leaf_mask |= 1 << child;
            self.mark_dirty(leaf_parent / n);
        }
        self.mark_dirty(site / n);
        self.evicted_roots.push(r.root);
        self.note_changed_cell(r.root);
        self.unlink(victim);
        // Free the subtree depth-first through the child links, no stack needed: descend to a
        // slot without children, free it, continue at its parent.
        let mut freed = 0;
        let mut s = victim;
        loop {
            let child = self.records[s as usize].first_child;
            if child != NO_SLOT {
                s = child;
                continue;
            }
            let up = self.records[s as usize].parent;
            if s != victim {
                self.unlink(s);
            }
            self.evicted_log.push(self.records[s as usize].treelet);
            self.free_slot(s);
            freed += 1;
            if s == victim {
                break;
            }
            s = up;
        }
        self.stats.evicted += u64::from(freed);
        freed
    }

    /// Removes `slot` from its parent's child list.
    fn unlink(&mut self, slot: u32) {
        let r = self.records[slot as usize];
        if r.prev_sibling != NO_SLOT {
            self.records[r.prev_sibling as usize].next_sibling = r.next_sibling;
        } else {
            self.records[r.parent as usize].first_child = r.next_sibling;
        }
        if r.next_sibling != NO_SLOT {
            self.records[r.next_sibling as usize].prev_sibling = r.prev_sibling;
        }
    }

    fn free_slot(&mut self, slot: u32) {
        let id = self.records[slot as usize].treelet;
        self.index_remove(id);
        // A freed slot needs no upload: nothing reaches it until a new treelet is copied in,
        // which marks it dirty again. Its DIRTY flag stays consistent with the dirty list.
        let flags = self.records[slot as usize].flags & DIRTY;
        self.records[slot as usize] = SlotRecord {
            flags,
            ..SlotRecord::FREE
        };
        self.free.push(slot);
    }

    fn mark_dirty(&mut self, slot: u32) {
        self.changes += 1;
        let r = &mut self.records[slot as usize];
        if r.flags & DIRTY == 0 {
            r.flags |= DIRTY;
            self.dirty.push(slot);
        }
    }

    /// Home position of `id` in the index (Fibonacci hashing, multiply-shift to the range).
    fn home(&self, id: TreeletId) -> usize {
        let h = id.0.wrapping_mul(0x9E37_79B9);
        ((u64::from(h) * self.index.len() as u64) >> 32) as usize
    }

    fn index_insert(&mut self, id: TreeletId, slot: u32) {
        let mut at = self.home(id);
        while self.index[at] != NO_SLOT {
            at = (at + 1) % self.index.len();
        }
        self.index[at] = slot;
    }

    /// Removes `id` with backward-shift deletion, so no tombstones accumulate and lookups stay
    /// short however many inserts and evictions happen.
    fn index_remove(&mut self, id: TreeletId) {
        let len = self.index.len();
        let mut hole = self.home(id);
        while self.records[self.index[hole] as usize].treelet != id {
            hole = (hole + 1) % len;
        }
        let mut j = hole;
        loop {
            j = (j + 1) % len;
            let slot = self.index[j];
            if slot == NO_SLOT {
                break;
            }
            let home = self.home(self.records[slot as usize].treelet);
            // The entry at j may move into the hole unless its home lies cyclically in
            // (hole, j]: then moving it would put it before its home.
            let stays = if hole <= j {
                hole < home && home <= j
            } else {
                hole < home || home <= j
            };
            if !stays {
                self.index[hole] = slot;
                hole = j;
            }
        }
        self.index[hole] = NO_SLOT;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use arbor_proto::codec::{compress, encode_treelet};
    use arbor_proto::{AttributeLayout, BuildParameters, SceneStats, SourceKind, TreeletHeader};

    const N: u32 = 16;
    const NONE: u32 = Node::NONE;

    fn header(id: u32, parent: Option<(u32, u16, u16, u8)>, used: u16) -> TreeletHeader {
        let (parent_id, leaf, leaf_parent, child) = parent.unwrap_or((NONE, 0, 0, 0));
        TreeletHeader {
            id: TreeletId(id),
            parent_id: TreeletId(parent_id),
            parent_leaf_index: leaf,
            parent_leaf_parent_index: leaf_parent,
            child_index_in_parent: child,
            root_depth: u8::from(parent.is_some()),
            root_cell: [0, 0, 0],
            used_nodes: used,
        }
    }

    fn finish(header: TreeletHeader, nodes: Vec<Node>, n: u32) -> DecodedTreelet {
        let mut all = nodes;
        all.resize(n as usize, Node::default());
        let treelet = Treelet { header, nodes: all };
        treelet.validate(20).expect("test treelet is well formed");
        let used = usize::from(header.used_nodes);
        DecodedTreelet {
            treelet,
            attributes: vec![(Channel::Color, vec![header.id.0 as u8; used * 3])],
        }
    }

    /// Treelet `id` refining leaf `leaf` (child `leaf − 1` of node 0) of treelet `parent`; its
    /// root has one leaf child per entry of `leaves` (child indices 0..), refined by that id.
    fn treelet_n(id: u32, parent: Option<(u32, u16)>, leaves: &[u32], n: u32) -> DecodedTreelet {
        let mut nodes = vec![Node {
            first_child: 1,
            valid_mask: ((1u16 << leaves.len()) - 1) as u8,
            leaf_mask: ((1u16 << leaves.len()) - 1) as u8,
            spare: 0,
        }];
        nodes.extend(leaves.iter().map(|&l| Node::leaf(l)));
        let parent = parent.map(|(p, leaf)| (p, leaf, 0, (leaf - 1) as u8));
        finish(header(id, parent, nodes.len() as u16), nodes, n)
    }

    fn treelet(id: u32, parent: Option<(u32, u16)>, leaves: &[u32]) -> DecodedTreelet {
        treelet_n(id, parent, leaves, N)
    }

    /// Treelet `id` whose root is itself a leaf refined by `sub`, refining `parent`'s leaf
    /// given as (parent, leaf, leaf's parent, child index).
    fn leaf_root(id: u32, parent: Option<(u32, u16, u16, u8)>, sub: u32) -> DecodedTreelet {
        finish(header(id, parent, 1), vec![Node::leaf(sub)], N)
    }

    fn config(slots: u64, load_limit: u32) -> SlotConfig {
        SlotConfig {
            budget_bytes: slots * SlotBuffer::slot_bytes(N, &[Channel::Color]),
            treelet_nodes: N,
            channels: vec![Channel::Color],
            visibility_max: 1,
            load_limit,
        }
    }

    fn buffer(slots: u64, root: DecodedTreelet) -> SlotBuffer {
        SlotBuffer::new(config(slots, u32::MAX), root).unwrap()
    }

    fn inserted(b: &mut SlotBuffer, t: DecodedTreelet) -> (u32, u32) {
        match b.insert(t) {
            InsertOutcome::Inserted { slot, evicted } => (slot, evicted),
            other => panic!("expected an insert, got {other:?}"),
        }
    }

    /// Global indices a traversal from the root reaches.
    fn reached(view: &IncoreView<'_>) -> Vec<u32> {
        let mut out = vec![0];
        let mut stack = vec![(0u32, view.nodes[0].valid_mask == 0)];
        while let Some((i, leaf)) = stack.pop() {
            if leaf {
                continue;
            }
            let n = view.nodes[i as usize];
            let base = i.wrapping_add(n.first_child);
            for (ci, k) in n.children() {
                out.push(base + k);
                stack.push((base + k, n.leaf_mask & (1 << ci) != 0));
            }
        }
        out.sort_unstable();
        out
    }

    #[test]
    fn insert_patches_the_leaf_to_point_at_node_one() {
        let mut b = buffer(4, treelet(0, None, &[1, 2, NONE]));
        assert_eq!(b.take_dirty(), vec![0]);
        assert_eq!(
            b.insert(treelet(1, Some((0, 1)), &[NONE, NONE])),
            InsertOutcome::Inserted {
                slot: 1,
                evicted: 0
            }
        );
        let v = b.view();
        assert_eq!(
            v.nodes[1],
            Node {
                first_child: N,
                valid_mask: 0b11,
                leaf_mask: 0b11,
                spare: 0
            }
        );
        assert_eq!(v.nodes[0].leaf_mask, 0b110, "leaf bit of child 0 cleared");
        assert_eq!(reached(&v), vec![0, 1, 2, 3, N + 1, N + 2]);
        assert_eq!(b.take_dirty(), vec![0, 1]);
        assert!(b.take_dirty().is_empty());
        assert_eq!(b.slot_of(TreeletId(1)), Some(1));
        assert_eq!(b.treelet_in(1), Some(TreeletId(1)));
        assert_eq!(b.parent_slot(1), Some(0));
        assert_eq!(b.parent_slot(0), None);
        assert_eq!(b.used_slots(), 2);
    }

    #[test]
    fn attributes_are_copied_and_the_rest_zeroed() {
        let mut b = buffer(2, treelet(0, None, &[1]));
        inserted(&mut b, treelet(1, Some((0, 1)), &[NONE, NONE, NONE]));
        let v = b.view();
        assert!(v.normal.is_none() && v.density.is_none());
        let color = v.color.unwrap();
        assert_eq!(color.len(), 2 * N as usize * 3);
        assert_eq!(v.attribute(Channel::Color, N + 3), Some(&[1u8, 1, 1][..]));
        assert_eq!(v.attribute(Channel::Color, N + 4), Some(&[0u8, 0, 0][..]));
        assert_eq!(v.attribute(Channel::Color, 1), Some(&[0u8, 0, 0][..]));
    }

    #[test]
    fn child_in_a_lower_slot_gets_a_wrapping_offset() {
        let mut b = buffer(3, treelet(0, None, &[1, 2]));
        inserted(&mut b, treelet(1, Some((0, 1)), &[NONE]));
        assert_eq!(inserted(&mut b, treelet(2, Some((0, 2)), &[3])), (2, 0));
        b.begin_cycle();
        b.take_dirty();
        // Slot 1 (treelet 1) is the only candidate: treelet 2 is the new one's parent.
        assert_eq!(inserted(&mut b, treelet(3, Some((2, 1)), &[NONE])), (1, 1));
        let site = 2 * N + 1;
        let fc = b.view().nodes[site as usize].first_child;
        assert!(fc > u32::MAX / 2, "offset wraps: {fc:#x}");
        assert_eq!(site.wrapping_add(fc), N + 1);
        // Treelet 1's leaf is restored with its leaf bit.
        assert_eq!(b.view().nodes[1], Node::leaf(1));
        assert_eq!(b.view().nodes[0].leaf_mask & 1, 1);
        assert_eq!(b.view().nodes[0].leaf_mask & 2, 0);
        assert_eq!(b.take_dirty(), vec![0, 1, 2]);
        assert_eq!(reached(&b.view()), vec![0, 1, 2, N + 1, 2 * N + 1]);
    }

    #[test]
    fn eviction_restores_the_leaf_and_frees_descendants() {
        let mut b = buffer(4, treelet(0, None, &[1, 2]));
        let original_root = b.view().nodes[0];
        inserted(&mut b, treelet(1, Some((0, 1)), &[3]));
        inserted(&mut b, treelet(3, Some((1, 1)), &[NONE]));
        inserted(&mut b, treelet(2, Some((0, 2)), &[4]));
        assert_eq!(b.used_slots(), 4);
        // Treelet 3 (slot 2) was seen later than treelet 1 (slot 1).
        b.begin_cycle();
        b.mark_visible(2);
        b.begin_cycle();
        assert_eq!(b.visibility(2), 0);
        assert_eq!(
            b.insert(treelet(4, Some((2, 1)), &[NONE])),
            InsertOutcome::Inserted {
                slot: 1,
                evicted: 2
            }
        );
        assert!(!b.is_resident(TreeletId(1)) && !b.is_resident(TreeletId(3)));
        assert_eq!(b.slot_of(TreeletId(4)), Some(1));
        assert_eq!(b.view().nodes[1], Node::leaf(1));
        assert_eq!(
            b.view().nodes[0],
            Node {
                leaf_mask: 0b01,
                ..original_root
            }
        );
        assert_eq!(b.stats().evicted, 2);
        assert_eq!(b.used_slots(), 3);
        assert_eq!(b.treelet_in(2), None);
        assert_eq!(reached(&b.view()), vec![0, 1, 2, N + 1, 3 * N + 1]);
    }

    /// The change count moves with every insert and eviction (the arrays change) and stands
    /// still otherwise: a refused insert, visibility, a new cycle, taking the dirty set.
    #[test]
    fn changes_count_what_alters_the_arrays_only() {
        let mut b = buffer(3, treelet(0, None, &[1]));
        let at_start = b.changes();
        assert!(at_start > 0, "the root's copy is a change");
        inserted(&mut b, treelet(1, Some((0, 1)), &[2]));
        let after_insert = b.changes();
        assert!(after_insert > at_start);
        b.begin_cycle();
        b.mark_visible(0);
        b.take_dirty();
        assert_eq!(
            b.insert(treelet(1, Some((0, 1)), &[2])),
            InsertOutcome::AlreadyResident
        );
        assert_eq!(b.changes(), after_insert, "nothing in the arrays changed");
        inserted(&mut b, treelet(2, Some((1, 1)), &[3]));
        let full = b.changes();
        b.begin_cycle();
        assert_eq!(
            b.insert(treelet(3, Some((2, 1)), &[NONE])),
            InsertOutcome::NoRoom
        );
        assert_eq!(b.changes(), full, "a refused insert changes nothing");
        assert!(b.evict_outside(&[0], 1) > 0);
        assert!(b.changes() > full, "an eviction restores a leaf");
    }

    /// The changed cells are the inserted treelets' root cells and the evicted subtrees' root
    /// cells, each taken once; too many pile up into "everything".
    #[test]
    fn changed_cells_name_inserts_and_evictions_once() {
        let mut b = buffer(3, treelet(0, None, &[1]));
        assert_eq!(
            b.take_changed_cells(),
            Some(vec![]),
            "the root is no change"
        );
        let one = treelet(1, Some((0, 1)), &[2]);
        let one_cell = one.treelet.header.root_cell();
        inserted(&mut b, one);
        assert_eq!(b.take_changed_cells(), Some(vec![one_cell]));
        assert_eq!(b.take_changed_cells(), Some(vec![]), "taken once");
        b.begin_cycle();
        assert!(b.evict_outside(&[0], 1) > 0);
        assert_eq!(b.take_changed_cells(), Some(vec![one_cell]));
        for _ in 0..=CHANGED_CELLS_MAX / 2 {
            inserted(&mut b, treelet(1, Some((0, 1)), &[2]));
            b.begin_cycle();
            assert!(b.evict_outside(&[0], 1) > 0);
        }
        assert_eq!(b.take_changed_cells(), None, "more than the log holds");
        assert_eq!(
            b.take_changed_cells(),
            Some(vec![]),
            "and a fresh log after"
        );
    }

    #[test]
    fn parent_and_ancestors_are_never_evicted_for_their_child() {
        let mut b = buffer(3, treelet(0, None, &[1]));
        inserted(&mut b, treelet(1, Some((0, 1)), &[2]));
        inserted(&mut b, treelet(2, Some((1, 1)), &[3]));
        b.begin_cycle();
        b.take_dirty();
        assert_eq!(
            b.insert(treelet(3, Some((2, 1)), &[NONE])),
            InsertOutcome::NoRoom
        );
        assert_eq!(b.stats().no_room, 1);
        assert!(b.take_dirty().is_empty(), "nothing changed");

        // The least recently visible slot is an ancestor: the next candidate goes instead.
        let mut b = buffer(4, treelet(0, None, &[1, 5]));
        inserted(&mut b, treelet(1, Some((0, 1)), &[2]));
        inserted(&mut b, treelet(2, Some((1, 1)), &[3]));
        inserted(&mut b, treelet(5, Some((0, 2)), &[NONE]));
        b.begin_cycle();
        b.mark_visible(3);
        b.begin_cycle();
        assert_eq!(inserted(&mut b, treelet(3, Some((2, 1)), &[NONE])), (3, 1));
        assert!(!b.is_resident(TreeletId(5)));
        assert!(b.is_resident(TreeletId(1)) && b.is_resident(TreeletId(2)));
    }

    #[test]
    fn visible_treelets_and_children_of_visible_parents_stay() {
        let mut b = buffer(3, treelet(0, None, &[1, 5]));
        inserted(&mut b, treelet(1, Some((0, 1)), &[NONE]));
        inserted(&mut b, treelet(5, Some((0, 2)), &[6]));
        // New treelets start fully visible.
        assert_eq!(b.visibility(1), 1);
        assert_eq!(
            b.insert(treelet(6, Some((5, 1)), &[NONE])),
            InsertOutcome::NoRoom
        );
        b.begin_cycle();
        b.mark_visible(0);
        // Treelet 1 is invisible but its parent (the root) is visible.
        assert_eq!(
            b.insert(treelet(6, Some((5, 1)), &[NONE])),
            InsertOutcome::NoRoom
        );
        b.begin_cycle();
        assert_eq!(inserted(&mut b, treelet(6, Some((5, 1)), &[NONE])), (1, 1));
        assert_eq!(b.stats().no_room, 2);
    }

    #[test]
    fn pinned_treelets_are_never_evicted_until_unpinned() {
        let mut b = buffer(3, treelet(0, None, &[1, 5]));
        inserted(&mut b, treelet(1, Some((0, 1)), &[NONE]));
        inserted(&mut b, treelet(5, Some((0, 2)), &[6]));
        b.pin(TreeletId(1));
        assert!(b.is_pinned(TreeletId(1)) && !b.is_pinned(TreeletId(5)));
        b.begin_cycle();
        b.begin_cycle();
        // Both invisible, 1 the least recently seen: without its pin it would go. Only 5 counts
        // as room, and 5 is the new one's parent, so nothing may go for it.
        assert_eq!(b.room(), 1);
        assert_eq!(b.room_outside(&[]), 1);
        assert_eq!(
            b.insert(treelet(6, Some((5, 1)), &[NONE])),
            InsertOutcome::NoRoom
        );
        assert!(b.take_evicted().is_empty());
        b.unpin_all();
        assert!(!b.is_pinned(TreeletId(1)));
        assert_eq!(inserted(&mut b, treelet(6, Some((5, 1)), &[NONE])), (1, 1));
        assert_eq!(b.take_evicted(), vec![TreeletId(1)]);
        assert!(b.take_evicted().is_empty(), "taken once");
        assert_eq!(
            b.take_evicted_roots(),
            vec![treelet(1, Some((0, 1)), &[NONE]).treelet.header.root_cell()],
            "an insertion's eviction restores a leaf too"
        );
        // A pinned treelet freed as the descendant of an evicted one leaves its slot unpinned.
        b.pin(TreeletId(6));
        b.begin_cycle();
        b.begin_cycle();
        assert_eq!(b.evict_outside(&[], 1), 2, "5, and 6 below it");
        assert_eq!(
            b.take_evicted_roots(),
            vec![treelet(5, Some((0, 2)), &[6]).treelet.header.root_cell()],
            "one subtree (6 below 5), one restored leaf"
        );
        assert!(b.take_evicted_roots().is_empty(), "taken once");
        let mut gone = b.take_evicted();
        gone.sort_unstable();
        assert_eq!(gone, vec![TreeletId(5), TreeletId(6)]);
        inserted(&mut b, treelet(5, Some((0, 2)), &[6]));
        inserted(&mut b, treelet(6, Some((5, 1)), &[NONE]));
        assert!(!b.is_pinned(TreeletId(5)) && !b.is_pinned(TreeletId(6)));
    }

    #[test]
    fn load_limit_refuses_until_the_next_cycle() {
        let mut b = SlotBuffer::new(config(4, 1), treelet(0, None, &[1, 2])).unwrap();
        inserted(&mut b, treelet(1, Some((0, 1)), &[NONE]));
        assert_eq!(
            b.insert(treelet(2, Some((0, 2)), &[NONE])),
            InsertOutcome::LoadLimit
        );
        assert!(!b.is_resident(TreeletId(2)));
        assert_eq!(b.stats().load_limited, 1);
        b.begin_cycle();
        inserted(&mut b, treelet(2, Some((0, 2)), &[NONE]));
    }

    #[test]
    fn orphans_duplicates_and_mismatched_headers_are_dropped() {
        let mut b = buffer(4, treelet(0, None, &[1, 2]));
        b.take_dirty();
        assert_eq!(
            b.insert(treelet(3, Some((1, 1)), &[NONE])),
            InsertOutcome::ParentMissing
        );
        assert_eq!(b.stats().orphans, 1);
        assert!(b.take_dirty().is_empty());
        inserted(&mut b, treelet(1, Some((0, 1)), &[3]));
        assert_eq!(
            b.insert(treelet(1, Some((0, 1)), &[3])),
            InsertOutcome::AlreadyResident
        );
        assert_eq!(
            b.insert(treelet(0, None, &[1, 2])),
            InsertOutcome::AlreadyResident
        );
        assert_eq!(b.stats().duplicates, 2);
        // Treelet 7 claims leaf 2 of the root, which is refined by treelet 2.
        assert_eq!(
            b.insert(treelet(7, Some((0, 2)), &[NONE])),
            InsertOutcome::ParentMissing
        );
        // Leaf index beyond N.
        let mut bad = treelet(8, Some((0, 1)), &[NONE]);
        bad.treelet.header.parent_leaf_index = N as u16;
        assert_eq!(b.insert(bad), InsertOutcome::ParentMissing);
        assert_eq!(b.stats().mismatched, 2);
        assert_eq!(b.stats().orphans, 3);
        assert_eq!(b.stats().inserted, 2);
    }

    #[test]
    fn budget_too_small_and_bad_roots_are_errors() {
        let one = SlotBuffer::slot_bytes(N, &[Channel::Color]);
        let mut cfg = config(1, 1);
        cfg.budget_bytes = one - 1;
        let e = SlotBuffer::new(cfg.clone(), treelet(0, None, &[NONE])).unwrap_err();
        assert!(matches!(e, SlotError::BudgetTooSmall { .. }));
        let msg = e.to_string();
        assert!(
            msg.contains(&format!("minimum budget is {one} bytes")),
            "{msg}"
        );

        cfg.budget_bytes = one;
        let mut b = SlotBuffer::new(cfg.clone(), treelet(0, None, &[1])).unwrap();
        assert_eq!(b.capacity(), 1);
        assert_eq!(
            b.insert(treelet(1, Some((0, 1)), &[NONE])),
            InsertOutcome::NoRoom
        );

        let e = SlotBuffer::new(cfg.clone(), treelet(1, Some((0, 1)), &[NONE])).unwrap_err();
        assert!(matches!(e, SlotError::NotRoot { .. }), "{e}");
        let mut twice = cfg.clone();
        twice.channels = vec![Channel::Color, Channel::Color];
        twice.budget_bytes = 10 * one;
        let e = SlotBuffer::new(twice, treelet(0, None, &[NONE])).unwrap_err();
        assert!(
            matches!(e, SlotError::DuplicateChannel(Channel::Color)),
            "{e}"
        );
        let mut normal = cfg;
        normal.channels = vec![Channel::Normal];
        normal.budget_bytes = 10 * one;
        let e = SlotBuffer::new(normal, treelet(0, None, &[NONE])).unwrap_err();
        assert!(matches!(e, SlotError::MissingChannel { .. }), "{e}");
    }

    #[test]
    fn capacity_times_slot_bytes_stays_within_the_budget() {
        let one = SlotBuffer::slot_bytes(N, &[Channel::Color]);
        let mut cfg = config(1, 1);
        cfg.budget_bytes = 10 * one + one / 2;
        let b = SlotBuffer::new(cfg.clone(), treelet(0, None, &[NONE])).unwrap();
        assert_eq!(b.capacity(), 10);
        assert!(u64::from(b.capacity()) * one <= cfg.budget_bytes);
        // What the buffer allocates per slot is what slot_bytes counts.
        let allocated = b.nodes.capacity() * 8
            + b.attributes
                .iter()
                .map(|(_, v)| v.capacity())
                .sum::<usize>()
            + b.records.capacity() * std::mem::size_of::<SlotRecord>()
            + (b.index.capacity() + b.dirty.capacity() + b.capacity as usize) * 4;
        assert!(allocated as u64 <= u64::from(b.capacity()) * one);
        let big = SlotBuffer::slot_bytes(512, &[Channel::Color, Channel::Normal]);
        println!(
            "slot bytes, N = 512, colour + normal: {big} ({} data + {BOOKKEEPING_BYTES} bookkeeping)",
            SlotBuffer::slot_data_bytes(512, &[Channel::Color, Channel::Normal])
        );
        assert_eq!(big, 512 * (8 + 3 + 4) + BOOKKEEPING_BYTES);
    }

    #[test]
    fn root_leaf_refined_by_an_inner_child_becomes_inner() {
        let mut b = buffer(2, leaf_root(0, None, 1));
        assert_eq!(reached(&b.view()), vec![0]);
        inserted(
            &mut b,
            treelet(1, Some((0, 1)), &[NONE, NONE]).with_site(0, 0, 0),
        );
        let v = b.view();
        assert_eq!(v.nodes[0].first_child, N + 1);
        assert_eq!(v.nodes[0].valid_mask, 0b11);
        assert_eq!(reached(&v), vec![0, N + 1, N + 2]);
    }

    #[test]
    fn child_root_without_children_stays_a_leaf() {
        let mut b = buffer(4, treelet(0, None, &[1, 2]));
        // Treelet 1's root is a leaf refined by treelet 3: copied verbatim, leaf bit kept.
        inserted(&mut b, leaf_root(1, Some((0, 1, 0, 0)), 3));
        assert_eq!(b.view().nodes[1], Node::leaf(3));
        assert_eq!(b.view().nodes[0].leaf_mask, 0b11);
        assert_eq!(reached(&b.view()), vec![0, 1, 2]);
        b.take_dirty();
        // Treelet 3 refines treelet 1's root, which a traversal meets at the root's leaf 1.
        let (slot3, _) = inserted(&mut b, treelet(3, Some((1, 1)), &[NONE]).with_site(0, 0, 0));
        assert_eq!(slot3, 2);
        let v = b.view();
        assert_eq!(1u32.wrapping_add(v.nodes[1].first_child), 2 * N + 1);
        assert_eq!(v.nodes[0].leaf_mask, 0b10);
        assert_eq!(reached(&v), vec![0, 1, 2, 2 * N + 1]);
        assert_eq!(b.take_dirty(), vec![0, 2]);
        inserted(&mut b, treelet(2, Some((0, 2)), &[4]));
        // Evict treelet 3 alone (treelet 1 was seen later): the verbatim leaf comes back.
        b.begin_cycle();
        b.mark_visible(1);
        b.begin_cycle();
        assert_eq!(inserted(&mut b, treelet(4, Some((2, 1)), &[9])), (2, 1));
        assert_eq!(b.view().nodes[1], Node::leaf(3));
        assert_eq!(b.view().nodes[0].leaf_mask & 1, 1);
        // Then treelet 1 itself: the root's original leaf comes back.
        b.begin_cycle();
        b.mark_visible(2);
        b.begin_cycle();
        assert_eq!(
            b.insert(treelet(9, Some((4, 1)), &[NONE])),
            InsertOutcome::Inserted {
                slot: 1,
                evicted: 1
            }
        );
        assert_eq!(b.view().nodes[1], Node::leaf(1));
        assert_eq!(b.view().nodes[0].leaf_mask & 1, 1);
    }

    impl DecodedTreelet {
        /// Re-aims the header at (leaf, leaf's parent, child index) in the same parent.
        fn with_site(mut self, leaf: u16, leaf_parent: u16, child: u8) -> Self {
            let h = &mut self.treelet.header;
            h.parent_leaf_index = leaf;
            h.parent_leaf_parent_index = leaf_parent;
            h.child_index_in_parent = child;
            self
        }
    }

    #[test]
    fn take_dirty_is_sorted_and_clears() {
        let mut b = buffer(5, treelet(0, None, &[1, 2, 3]));
        inserted(&mut b, treelet(3, Some((0, 3)), &[NONE]));
        inserted(&mut b, treelet(2, Some((0, 2)), &[NONE]));
        inserted(&mut b, treelet(1, Some((0, 1)), &[NONE]));
        assert_eq!(b.take_dirty(), vec![0, 1, 2, 3]);
        assert!(b.take_dirty().is_empty());
    }

    #[test]
    fn a_slot_dirtied_freed_and_refilled_in_one_cycle_is_reported_once() {
        let mut b = buffer(2, treelet(0, None, &[1, 2]));
        let _ = b.take_dirty();
        inserted(&mut b, treelet(1, Some((0, 1)), &[NONE]));
        // Treelet 1 and the root age out unseen; treelet 2 then takes slot 1 in the same cycle.
        for _ in 0..=u32::from(b.config().visibility_max) {
            b.begin_cycle();
        }
        assert_eq!(
            b.insert(treelet(2, Some((0, 2)), &[NONE])),
            InsertOutcome::Inserted {
                slot: 1,
                evicted: 1
            }
        );
        assert_eq!(b.take_dirty(), vec![0, 1]);
    }

    #[test]
    fn fully_resident_holds_every_treelet() {
        let scene = scene(N, 4);
        let ts = vec![
            treelet(3, Some((1, 1)), &[NONE]),
            treelet(2, Some((0, 2)), &[NONE, NONE]),
            treelet(0, None, &[1, 2]),
            treelet(1, Some((0, 1)), &[3]),
        ];
        let used: u32 = ts
            .iter()
            .map(|t| u32::from(t.treelet.header.used_nodes))
            .sum();
        let b = SlotBuffer::fully_resident(&scene, &[Channel::Color], ts.clone()).unwrap();
        assert_eq!(b.capacity(), 4);
        assert_eq!(b.used_slots(), 4);
        assert_eq!(reached(&b.view()).len() as u32, used - 3);
        let e =
            SlotBuffer::fully_resident(&scene, &[Channel::Color], ts[..3].to_vec()).unwrap_err();
        assert!(matches!(e, SlotError::Incomplete { .. }), "{e}");
        let mut orphan = ts.clone();
        orphan[0] = treelet(3, Some((2, 1)), &[NONE]);
        let e = SlotBuffer::fully_resident(&scene, &[Channel::Color], orphan).unwrap_err();
        assert!(matches!(e, SlotError::NotPlaced { .. }), "{e}");
    }

    fn scene(n: u32, count: u32) -> SceneDescription {
        SceneDescription {
            name: "unit".into(),
            origin: [0.0; 3],
            edge: 1.0,
            treelet_nodes: n,
            max_depth: 12,
            layout: AttributeLayout::new([Channel::Color, Channel::Normal]),
            treelet_count: count,
            root_treelet: TreeletId::ROOT,
            source_kind: SourceKind::Points,
            source: "synthetic".into(),
            primitives: 1,
            build: BuildParameters {
                requested_depth: None,
                data_resolution: 0.01,
                treelet_bytes: n * 8,
                iso: None,
                zstd_level: 3,
                dictionary: false,
            },
            stats: SceneStats::default(),
            node_dictionary: None,
            channel_dictionaries: vec![None, None],
        }
    }

    fn blocks(t: &Treelet, color_len: usize) -> (Vec<u8>, Vec<u8>, Vec<u8>) {
        let nodes = compress(&encode_treelet(t), 3, None).unwrap();
        let color = compress(&vec![7u8; color_len], 3, None).unwrap();
        let normal = compress(&vec![9u8; usize::from(t.header.used_nodes) * 4], 3, None).unwrap();
        (nodes, color, normal)
    }

    #[test]
    fn decode_checks_blocks_against_message_and_scene() {
        const M: u32 = 128;
        let scene = scene(M, 2);
        let t = treelet_n(1, Some((0, 1)), &[NONE, NONE], M).treelet;
        let used = usize::from(t.header.used_nodes);
        let (nodes, color, normal) = blocks(&t, used * 3);
        let blocks_of = [
            (Channel::Color, color.as_slice()),
            (Channel::Normal, normal.as_slice()),
        ];
        let decode = |id: u32, used_nodes: u16, wanted: &[Channel]| {
            DecodedTreelet::decode_message(
                TreeletId(id),
                used_nodes,
                &nodes,
                &blocks_of,
                &scene,
                &PreparedDictionaries::of(&scene),
                wanted,
            )
        };
        let used_nodes = t.header.used_nodes;
        // Extra channels are ignored.
        let d = decode(1, used_nodes, &[Channel::Color]).unwrap();
        assert_eq!(d.treelet, t);
        assert_eq!(d.attributes, vec![(Channel::Color, vec![7u8; used * 3])]);

        let e = decode(1, used_nodes + 1, &[Channel::Color]).unwrap_err();
        assert!(matches!(e, SlotError::UsedNodesMismatch { .. }), "{e}");

        let e = decode(2, used_nodes, &[Channel::Color]).unwrap_err();
        assert!(matches!(e, SlotError::IdMismatch { .. }), "{e}");

        let e = decode(1, used_nodes, &[Channel::Density]).unwrap_err();
        assert!(matches!(e, SlotError::MissingChannel { .. }), "{e}");

        let garbage = [1u8, 2, 3, 4];
        let e = DecodedTreelet::from_blocks(TreeletId(1), &garbage, &[], &scene, &[]).unwrap_err();
        assert!(matches!(e, SlotError::Decode { .. }), "{e}");

        // A tree whose leaf mask names a child that does not exist.
        let mut bad = t.clone();
        bad.nodes[0].leaf_mask |= 0b1000_0000;
        let (bad_nodes, _, _) = blocks(&bad, 0);
        let e =
            DecodedTreelet::from_blocks(TreeletId(1), &bad_nodes, &[], &scene, &[]).unwrap_err();
        assert!(
            matches!(
                e,
                SlotError::Decode {
                    source: ProtoError::MalformedTreelet { .. },
                    ..
                }
            ),
            "{e}"
        );

        // An attribute block of the wrong length.
        let (_, short, _) = blocks(&t, used * 3 - 1);
        let e = DecodedTreelet::from_blocks(
            TreeletId(1),
            &nodes,
            &[(Channel::Color, &short)],
            &scene,
            &[Channel::Color],
        )
        .unwrap_err();
        assert!(matches!(e, SlotError::Decode { .. }), "{e}");

        // A treelet of another size than the scene's.
        let other = scene_with_nodes(256);
        let e = DecodedTreelet::from_blocks(TreeletId(1), &nodes, &[], &other, &[]).unwrap_err();
        assert!(matches!(e, SlotError::WrongNodeCount { .. }), "{e}");
    }

    fn scene_with_nodes(n: u32) -> SceneDescription {
        scene(n, 2)
    }
}
