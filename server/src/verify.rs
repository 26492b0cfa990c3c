//! `verify`: checks every invariant of a stored scene, in batches of consecutive ids, holding
//! nothing that grows with the scene.
//!
//! How: the treelets are read in batches of [`BATCH_TREELETS`] consecutive ids (one sled read
//! per pack and tree); each treelet's own checks — decoding, nodes, attribute means — run on
//! every core (rayon), each returning only its findings, its header and its root's records.
//! Then the parents the batch's headers name are read and decoded again, once each and in
//! parallel, and each treelet is matched, in id order, with the leaf its header names: that
//! leaf must name it back, with its cell, place and records. Counting the matched pairs against
//! the refinable leaves makes the matching a bijection without remembering any leaf from one
//! batch to the next (a breadth-first pass would otherwise hold one link for every treelet of
//! the next level: 1.1 million on the 10⁸-point city, gigabytes on a scan a hundred times
//! larger). The report is the same whatever the cores and the batch size. On the city the
//! checks, not the reads, are the time (decoding, means, normals' encoding); reading the
//! parents again costs about a tenth more CPU. The next batch is read while this one is checked
//! (the reads are one `get` after another): 1.5 → 1.75 cores busy on two, the city's check
//! 32–40 → 29.5–32 s.
//!
//! Memory: sled keeps part of every page a pass over whole trees reads, whatever its cache
//! (docs/measurements.md, stop 70: 435 MB verifying the city in one opening). So
//! [`verify_pool_scene`] closes the pool and opens it again after every [`REOPEN_AFTER_BYTES`]
//! of blocks read, resuming after the last treelet checked, and names a scene replaced in between.
//!
//! Checked: the description; every node well formed (masks consistent, offsets in range,
//! children contiguous in child-index and breadth-first order — [`Treelet::validate`]); every
//! voxel inside its parent and no deeper than the target depth; treelet links both ways (parent
//! id, parent leaf, leaf's parent, child index; a refinable leaf's subtreelet exists, has a higher
//! id, and its root cell equals the leaf's cell); each refinable leaf has exactly one subtreelet
//! naming it back and every treelet but the root is reached; attribute blocks decode to the right length; inner
//! attributes equal the mean of their children within one quantization step and a refinable
//! leaf's attributes equal its subtreelet root's; stored counts match the description.

use std::collections::HashMap;
use std::ops::ControlFlow;
use std::path::Path;

use arbor_proto::codec::{self, PreparedDictionaries};
use arbor_proto::treelet::{NodePlace, TreeletHeader};
use arbor_proto::{Cell, Channel, Node, SceneDescription, Treelet, TreeletId};
use rayon::prelude::*;

use crate::pool::{Pool, PoolError, StoredScene};

pub use crate::pool::copy::REOPEN_AFTER_BYTES;

/// Consecutive treelets read, then checked on every core, at a time: enough for a pack of
/// every tree and work for every thread, little memory (only compressed blocks are held).
pub const BATCH_TREELETS: usize = 1024;

/// Result of a verification.
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct VerifyReport {
    pub treelets: u64,
    pub node_records: u64,
    pub voxels: u64,
    pub leaf_voxels: u64,
    /// Every broken invariant found (at most [`MAX_PROBLEMS`] are kept, `problem_count` counts all).
    pub problems: Vec<String>,
    pub problem_count: u64,
    /// Bytes of blocks read.
    pub bytes_read: u64,
    /// Times the pool was closed and opened again ([`verify_pool_scene`]).
    pub reopens: u32,
}

/// Problems kept verbatim in a report.
pub const MAX_PROBLEMS: usize = 100;

impl VerifyReport {
    pub fn is_ok(&self) -> bool {
        self.problem_count == 0
    }

    fn problem(&mut self, p: String) {
        self.problem_count += 1;
        if self.problems.len() < MAX_PROBLEMS {
            self.problems.push(p);
        }
    }
}

/// Bytes of one record of every channel side by side (a layout names a channel at most once).
const RECORDS_BYTES: usize = {
    let mut n = 0;
    let mut i = 0;
    while i < Channel::ALL.len() {
        n += Channel::ALL[i].size();
        i += 1;
    }
    n
};

/// One node's records of the scene's channels, in layout order, side by side.
type Records = [u8; RECORDS_BYTES];

/// What a refinable leaf promises its subtreelet: read from the parent when the subtreelet is
/// checked (module docs: nothing is held from one batch to the next).
struct Link {
    /// The subtreelet the leaf names.
    child: u32,
    cell: Cell,
    leaf_parent: u16,
    child_index: u8,
    /// The leaf's records, if its parent's attribute blocks decoded.
    attributes: Option<Records>,
}

/// Node `i`'s records of every channel (`attrs` in layout order) side by side.
fn records(channels: &[Channel], attrs: &[Vec<u8>], i: usize) -> Records {
    let mut out = [0u8; RECORDS_BYTES];
    let mut at = 0;
    for (&c, block) in channels.iter().zip(attrs) {
        out[at..at + c.size()].copy_from_slice(record(block, c, i));
        at += c.size();
    }
    out
}

/// Verifies a stored scene. `Err` only for pool I/O failures; broken invariants are in the report.
pub fn verify_scene(scene: &StoredScene) -> Result<VerifyReport, PoolError> {
    let mut v = Verifier::new(&scene.description, BATCH_TREELETS);
    if !v.r.is_ok() {
        return Ok(v.r);
    }
    v.check_from(scene, TreeletId(0), u64::MAX, &mut |_| {
        ControlFlow::Continue(())
    })?;
    Ok(v.finish())
}

/// [`verify_scene`] on a scene of a pool that stays open (the daemon's: `POST
/// /v1/scenes/{name}/verify`), `batch_treelets` at a time, telling `progress` before the first
/// batch and after each. The pass stops, `Ok(None)`, as soon as `progress` answers
/// [`ControlFlow::Break`]: that is how a running check is cancelled. The report is
/// [`verify_scene`]'s, whatever the batch size.
pub fn verify_scene_observed(
    scene: &StoredScene,
    batch_treelets: usize,
    progress: &mut dyn FnMut(VerifyProgress) -> ControlFlow<()>,
) -> Result<Option<VerifyReport>, PoolError> {
    let mut v = Verifier::new(&scene.description, batch_treelets);
    let planned = VerifyProgress::Planned {
        treelets: u64::from(scene.description.treelet_count),
    };
    if progress(planned).is_break() {
        return Ok(None);
    }
    if !v.r.is_ok() {
        return Ok(Some(v.r));
    }
    let pass = v.check_from(scene, TreeletId(0), u64::MAX, &mut |n| {
        progress(VerifyProgress::Checked(n))
    })?;
    Ok(match pass {
        Pass::Stopped => None,
        Pass::Ended | Pass::ResumeAt(_) => Some(v.finish()),
    })
}

/// What [`verify_pool_scene`] reports while it runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VerifyProgress {
    /// Once, before any treelet is checked: the treelets the description counts.
    Planned { treelets: u64 },
    /// Treelets checked since the last report.
    Checked(u64),
}

/// How [`verify_pool_scene`] reads.
#[derive(Clone, Copy, Debug)]
pub struct VerifyOptions {
    /// Bytes of blocks read between two openings of the pool ([`REOPEN_AFTER_BYTES`]).
    pub reopen_after_bytes: u64,
    /// Treelets read and checked at a time ([`BATCH_TREELETS`]; tests take fewer to cross
    /// batches and openings within a small scene).
    pub batch_treelets: usize,
}

impl Default for VerifyOptions {
    fn default() -> Self {
        VerifyOptions {
            reopen_after_bytes: REOPEN_AFTER_BYTES,
            batch_treelets: BATCH_TREELETS,
        }
    }
}

/// Verifies the scene `name` of the pool in `dir` ([`Pool::open_for_scan`]: nothing is
/// changed), closing the pool and opening it again after every `reopen_after_bytes` of blocks
/// read so that sled's memory stays bounded whatever the scene's size (module docs). The report
/// is [`verify_scene`]'s, whatever the options. A directory without a pool is
/// [`PoolError::NoPool`] (none is made); a scene replaced or removed between two openings is
/// [`PoolError::ChangedWhileRead`]. `progress` is told after the pool is closed.
pub fn verify_pool_scene(
    dir: &Path,
    name: &str,
    options: &VerifyOptions,
    progress: &dyn Fn(VerifyProgress),
) -> Result<VerifyReport, PoolError> {
    if !crate::pool::is_pool(dir) {
        return Err(PoolError::NoPool(dir.to_owned()));
    }
    let scene = Pool::open_for_scan(dir)?.scene(name)?;
    let generation = scene.generation;
    progress(VerifyProgress::Planned {
        treelets: u64::from(scene.description.treelet_count),
    });
    let mut v = Verifier::new(&scene.description, options.batch_treelets);
    if !v.r.is_ok() {
        return Ok(v.r);
    }
    let mut scene = Some(scene);
    let mut next = TreeletId(0);
    loop {
        let current = match scene.take() {
            Some(s) => s,
            None => {
                v.r.reopens += 1;
                Pool::open_for_scan(dir)?.scene_of_generation(name, generation)?
            }
        };
        let before = v.r.treelets;
        let pass = v.check_from(&current, next, options.reopen_after_bytes, &mut |_| {
            ControlFlow::Continue(())
        })?;
        // Dropping the scene's trees and the pool closes the database: its memory goes.
        drop(current);
        progress(VerifyProgress::Checked(v.r.treelets - before));
        match pass {
            Pass::ResumeAt(id) => next = id,
            Pass::Ended | Pass::Stopped => return Ok(v.finish()),
        }
    }
}

/// Where a pass over stored treelets ([`Verifier::check_from`]) stopped.
enum Pass {
    /// The scene's end.
    Ended,
    /// The byte budget: the next id to check.
    ResumeAt(TreeletId),
    /// Told to stop.
    Stopped,
}

/// Consecutive treelets' blocks, read for checking.
struct Batch {
    ids: Vec<TreeletId>,
    nodes: Vec<Option<sled::IVec>>,
    /// Per channel of the layout, in its order.
    channels: Vec<Vec<Option<sled::IVec>>>,
    /// Bytes of all those blocks.
    bytes: u64,
}

impl Batch {
    /// The blocks of `ids` (ascending): one sled read per pack and tree while consecutive ids
    /// stay in a pack.
    fn read(
        scene: &StoredScene,
        channels: &[Channel],
        ids: Vec<TreeletId>,
    ) -> Result<Batch, PoolError> {
        let nodes = scene.nodes_of(&ids)?;
        let channels = channels
            .iter()
            .map(|&c| scene.channel_of(c, &ids))
            .collect::<Result<Vec<_>, _>>()?;
        let bytes = nodes
            .iter()
            .chain(channels.iter().flatten())
            .flatten()
            .map(|b| b.len() as u64)
            .sum::<u64>();
        Ok(Batch {
            ids,
            nodes,
            channels,
            bytes,
        })
    }
}

/// A scene's settings every treelet's checks share (read-only, so that they run in parallel).
struct Context {
    description: SceneDescription,
    channels: Vec<Channel>,
    /// The scene's dictionaries, loaded once for its many blocks.
    dictionaries: PreparedDictionaries,
}

/// What one treelet's own checks found, for the in-order pass that matches it with its parent.
#[derive(Default)]
struct Checked {
    /// The header, if the node block decoded.
    header: Option<TreeletHeader>,
    /// The root node's records, if every attribute block decoded.
    root_attributes: Option<Records>,
    node_records: u64,
    leaf_voxels: u64,
    /// Leaves naming a subtreelet.
    refinable_leaves: u64,
    /// Findings before the link check (header, blocks) and after it (nodes), in the order a
    /// one-by-one pass reports them.
    problems: Vec<String>,
    node_problems: Vec<String>,
}

/// A parent treelet as its subtreelets in one batch need it: the refinable leaves they name.
enum Parent {
    /// Leaf index → what it promises (only the leaves the batch's subtreelets name).
    Read(HashMap<u16, Option<Link>>),
    /// Its node block is missing or does not decode (reported when it was checked itself).
    Unreadable,
}

/// The state of one verification: the report so far and two counts. Nothing grows with the
/// scene: a subtreelet is matched with the leaf its header names by reading the parent again
/// (its batch's parents, once each), and the counts make the matching a bijection — every
/// matched pair is a leaf naming the subtreelet and the subtreelet naming that leaf back, a
/// leaf names one subtreelet, so as many pairs as refinable leaves means none is left over.
struct Verifier {
    context: Context,
    /// Leaves naming a subtreelet, over the treelets checked.
    refinable_leaves: u64,
    /// Subtreelets whose header names a leaf that names them.
    matched: u64,
    /// The id the next stored treelet should have (ids are contiguous).
    expected_next: u32,
    batch_treelets: usize,
    r: VerifyReport,
}

impl Verifier {
    /// A verifier of a scene with this description; an invalid description is the report's
    /// only problem.
    fn new(d: &SceneDescription, batch_treelets: usize) -> Verifier {
        let mut v = Verifier {
            context: Context {
                description: d.clone(),
                channels: d.layout.channels().to_vec(),
                dictionaries: PreparedDictionaries::of(d),
            },
            refinable_leaves: 0,
            matched: 0,
            expected_next: 0,
            batch_treelets: batch_treelets.max(1),
            r: VerifyReport::default(),
        };
        if let Err(e) = d.validate() {
            v.r.problem(format!("description: {e}"));
        } else if v.context.channels.iter().map(|c| c.size()).sum::<usize>() > RECORDS_BYTES {
            v.r.problem("description: a channel is named twice in the layout".into());
        }
        v
    }

    /// Checks the stored treelets from `start` on, batch by batch, telling `after_batch` how
    /// many each batch held, until the scene ends, at least `byte_budget` bytes of blocks were
    /// read (the id to resume at), or `after_batch` answers [`ControlFlow::Break`]. The next
    /// batch is read while this one is checked: the reads are one sled `get` after another, the
    /// checks use every core.
    fn check_from(
        &mut self,
        scene: &StoredScene,
        start: TreeletId,
        byte_budget: u64,
        after_batch: &mut dyn FnMut(u64) -> ControlFlow<()>,
    ) -> Result<Pass, PoolError> {
        let mut ids = scene.stored_ids_from(start);
        let size = self.batch_treelets;
        let channels = self.context.channels.clone();
        let next_batch = |ids: &mut dyn Iterator<Item = Result<TreeletId, PoolError>>| {
            let ids = ids.take(size).collect::<Result<Vec<_>, _>>()?;
            Batch::read(scene, &channels, ids)
        };
        let mut batch = next_batch(&mut ids)?;
        let mut read = 0u64;
        loop {
            let Some(&last) = batch.ids.last() else {
                return Ok(Pass::Ended);
            };
            read += batch.bytes;
            let more = read < byte_budget;
            let treelets = batch.ids.len() as u64;
            let (following, checked) = rayon::join(
                || more.then(|| next_batch(&mut ids)).transpose(),
                || self.check_batch(scene, batch),
            );
            checked?;
            if after_batch(treelets).is_break() {
                return Ok(Pass::Stopped);
            }
            match following? {
                Some(b) => batch = b,
                None if last.0 < u32::MAX => return Ok(Pass::ResumeAt(TreeletId(last.0 + 1))),
                None => return Ok(Pass::Ended),
            }
        }
    }

    /// Checks a batch read: each treelet on its own in parallel, then links matched and counts
    /// made in id order.
    fn check_batch(&mut self, scene: &StoredScene, batch: Batch) -> Result<(), PoolError> {
        let Batch {
            ids,
            nodes,
            channels,
            bytes,
        } = batch;
        let context = &self.context;
        let checked: Vec<Option<Checked>> = ids
            .par_iter()
            .enumerate()
            .map(|(k, &id)| {
                let blocks: Vec<Option<&[u8]>> = channels.iter().map(|c| c[k].as_deref()).collect();
                nodes[k]
                    .as_deref()
                    .map(|bytes| context.check_treelet(id, bytes, &blocks))
            })
            .collect();
        let parents = self.parents(scene, &checked)?;
        for (&id, checked) in ids.iter().zip(checked) {
            if id.0 != self.expected_next {
                self.r.problem(format!(
                    "treelet ids not contiguous: expected {}, found {id}",
                    self.expected_next
                ));
            }
            self.expected_next = id.0.wrapping_add(1);
            self.r.treelets += 1;
            if let Some(c) = checked {
                self.merge(id, c, &parents);
            }
        }
        self.r.bytes_read += bytes;
        Ok(())
    }

    /// The parents the batch's treelets name (each read and decoded once, in parallel), with
    /// the leaves they name.
    fn parents(
        &self,
        scene: &StoredScene,
        checked: &[Option<Checked>],
    ) -> Result<HashMap<u32, Parent>, PoolError> {
        let mut wanted: std::collections::BTreeMap<u32, Vec<u16>> = Default::default();
        for h in checked.iter().flatten().filter_map(|c| c.header.as_ref()) {
            if !h.parent_id.is_none() && h.parent_id.0 < h.id.0 {
                wanted
                    .entry(h.parent_id.0)
                    .or_default()
                    .push(h.parent_leaf_index);
            }
        }
        let ids: Vec<TreeletId> = wanted.keys().map(|&p| TreeletId(p)).collect();
        let Batch {
            ids,
            nodes,
            channels,
            ..
        } = Batch::read(scene, &self.context.channels, ids)?;
        let context = &self.context;
        let wanted: Vec<Vec<u16>> = wanted.into_values().collect();
        Ok(ids
            .par_iter()
            .enumerate()
            .map(|(k, id)| {
                let blocks: Vec<Option<&[u8]>> = channels.iter().map(|c| c[k].as_deref()).collect();
                let parent = match nodes[k].as_deref() {
                    Some(bytes) => context.parent(bytes, &blocks, &wanted[k]),
                    None => Parent::Unreadable,
                };
                (id.0, parent)
            })
            .collect())
    }

    /// One treelet's findings, in id order: its own, then its match with its parent's leaf.
    fn merge(&mut self, id: TreeletId, c: Checked, parents: &HashMap<u32, Parent>) {
        for p in c.problems {
            self.r.problem(p);
        }
        self.r.node_records += c.node_records;
        self.r.leaf_voxels += c.leaf_voxels;
        self.refinable_leaves += c.refinable_leaves;
        // A treelet stored under another id than its own is reported as such, not matched.
        if let Some(header) = c.header.as_ref().filter(|h| h.id == id)
            && check_link(
                &mut self.r,
                parents,
                header,
                c.root_attributes.as_ref(),
                &self.context.channels,
            )
        {
            self.matched += 1;
        }
        for p in c.node_problems {
            self.r.problem(p);
        }
    }

    /// Whole-scene checks: counts against the description, refinable leaves left unmatched.
    fn finish(mut self) -> VerifyReport {
        let d = &self.context.description;
        let r = &mut self.r;
        r.voxels = r.node_records.saturating_sub(r.treelets.saturating_sub(1));
        if r.treelets != u64::from(d.treelet_count) {
            r.problem(format!(
                "{} treelets stored, description says {}",
                r.treelets, d.treelet_count
            ));
        }
        // A treelet is matched only under the id it is stored at, and only with a leaf naming
        // it: never more pairs than leaves.
        if self.matched < self.refinable_leaves {
            r.problem(format!(
                "{} of {} refinable leaves name a subtreelet that does not exist or does not name \
                 them back",
                self.refinable_leaves - self.matched,
                self.refinable_leaves
            ));
        }
        if d.stats.voxels != 0 && d.stats.voxels != r.voxels {
            r.problem(format!(
                "{} voxels found, description says {}",
                r.voxels, d.stats.voxels
            ));
        }
        if d.stats.leaf_voxels != 0 && d.stats.leaf_voxels != r.leaf_voxels {
            r.problem(format!(
                "{} leaf voxels found, description says {}",
                r.leaf_voxels, d.stats.leaf_voxels
            ));
        }
        self.r
    }
}

impl Context {
    /// One stored treelet's own checks: decodes it, checks the header, its attribute blocks
    /// and every node; collects the links it promises.
    fn check_treelet(&self, id: TreeletId, bytes: &[u8], blocks: &[Option<&[u8]>]) -> Checked {
        let d = &self.description;
        let mut c = Checked::default();
        let (t, places) = match codec::decode_compressed_treelet_with_places_using(
            bytes,
            d.max_depth,
            self.dictionaries.nodes(),
        ) {
            Ok(decoded) => decoded,
            Err(e) => {
                c.problems.push(format!("treelet {id}: {e}"));
                return c;
            }
        };
        if t.header.id != id {
            c.problems.push(format!(
                "treelet stored under {id} says it is {}",
                t.header.id
            ));
        }
        if t.capacity() != d.treelet_nodes {
            c.problems.push(format!(
                "treelet {id}: capacity {} != scene's {}",
                t.capacity(),
                d.treelet_nodes
            ));
        }
        c.node_records = t.used().len() as u64;
        let attrs = self.attributes(id, &t, blocks, &mut c.problems);
        let attrs = (attrs.len() == self.channels.len()).then_some(attrs);
        c.root_attributes = attrs
            .as_ref()
            .map(|attrs| records(&self.channels, attrs, 0));
        c.header = Some(t.header);
        for (i, place) in places.iter().enumerate() {
            self.node(id, &t, &places, i, place, attrs.as_deref(), &mut c);
        }
        c
    }

    /// The treelet's attribute blocks, decoded, one per channel; a missing or bad block is a
    /// problem and is left out.
    fn attributes(
        &self,
        id: TreeletId,
        t: &Treelet,
        blocks: &[Option<&[u8]>],
        problems: &mut Vec<String>,
    ) -> Vec<Vec<u8>> {
        let mut attrs = Vec::new();
        for (&c, block) in self.channels.iter().zip(blocks) {
            let Some(b) = block else {
                problems.push(format!("treelet {id}: {} block missing", c.name()));
                continue;
            };
            match codec::decode_compressed_attributes_using(
                b,
                c,
                t.header.used_nodes,
                self.dictionaries.channel(c),
            ) {
                Ok(b) => attrs.push(b),
                Err(e) => problems.push(format!("treelet {id}: {} block: {e}", c.name())),
            }
        }
        attrs
    }

    /// One node: inside its parent; a leaf is final (counted) or names a later subtreelet
    /// (a link); an inner node's attributes are its children's mean.
    #[allow(clippy::too_many_arguments)]
    fn node(
        &self,
        id: TreeletId,
        t: &Treelet,
        places: &[NodePlace],
        i: usize,
        place: &NodePlace,
        attrs: Option<&[Vec<u8>]>,
        c: &mut Checked,
    ) {
        let d = &self.description;
        let n = t.nodes[i];
        if place.parent != u32::MAX {
            let pc = places[place.parent as usize].cell;
            if !pc.contains(&place.cell) || place.cell.depth != pc.depth + 1 {
                c.node_problems.push(format!(
                    "treelet {id} node {i}: voxel {:?} not inside parent {pc:?}",
                    place.cell
                ));
            }
        }
        if !place.is_leaf {
            if let Some(attrs) = attrs {
                self.inner_means(id, i, n, attrs, &mut c.node_problems);
            }
            return;
        }
        if n.first_child == Node::NONE {
            if place.cell.depth == d.max_depth {
                c.leaf_voxels += 1;
            }
            return;
        }
        let child = n.first_child;
        if child <= id.0 || child >= d.treelet_count {
            c.node_problems.push(format!(
                "treelet {id} leaf {i}: subtreelet {child} out of range"
            ));
        }
        c.refinable_leaves += 1;
    }

    /// A parent treelet, decoded again for the subtreelets of a batch that name it: what each
    /// of the `leaves` they name promises (`None`: no such refinable leaf).
    fn parent(&self, bytes: &[u8], blocks: &[Option<&[u8]>], leaves: &[u16]) -> Parent {
        let Ok((t, places)) = codec::decode_compressed_treelet_with_places_using(
            bytes,
            self.description.max_depth,
            self.dictionaries.nodes(),
        ) else {
            return Parent::Unreadable;
        };
        // Its problems were reported when it was checked itself.
        let attrs = self.attributes(t.header.id, &t, blocks, &mut Vec::new());
        let attrs = (attrs.len() == self.channels.len()).then_some(attrs);
        let link = |leaf: u16| {
            let i = usize::from(leaf);
            let place = places.get(i)?;
            let child = t.nodes[i].first_child;
            (place.is_leaf && child != Node::NONE).then(|| Link {
                child,
                cell: place.cell,
                leaf_parent: if place.parent == u32::MAX {
                    0
                } else {
                    place.parent as u16
                },
                child_index: place.child_index,
                attributes: attrs
                    .as_ref()
                    .map(|attrs| records(&self.channels, attrs, i)),
            })
        };
        Parent::Read(leaves.iter().map(|&leaf| (leaf, link(leaf))).collect())
    }

    /// An inner node's attributes must be the mean of its children's (within one step).
    fn inner_means(
        &self,
        id: TreeletId,
        i: usize,
        n: Node,
        attrs: &[Vec<u8>],
        problems: &mut Vec<String>,
    ) {
        let first = i + n.first_child as usize;
        let kids = n.child_count() as usize;
        for (k, &c) in self.channels.iter().enumerate() {
            let mut mean = vec![0u8; c.size()];
            c.mean(
                (first..first + kids).map(|j| record(&attrs[k], c, j)),
                &mut mean,
            );
            if !c.within_one_step(&mean, record(&attrs[k], c, i)) {
                problems.push(format!(
                    "treelet {id} node {i}: {} {:?} is not the mean {:?} of its children",
                    c.name(),
                    record(&attrs[k], c, i),
                    mean
                ));
            }
        }
    }
}

fn record(block: &[u8], c: Channel, i: usize) -> &[u8] {
    &block[i * c.size()..(i + 1) * c.size()]
}

/// Matches a treelet with the leaf its header names (or, for 0, checks that it is a proper
/// root); `root_attributes`: the root node's records, when they all decoded. True when that leaf
/// names this treelet: a matched pair, whatever else differs.
fn check_link(
    r: &mut VerifyReport,
    parents: &HashMap<u32, Parent>,
    h: &TreeletHeader,
    root_attributes: Option<&Records>,
    channels: &[Channel],
) -> bool {
    let id = h.id;
    if id == TreeletId::ROOT {
        if !h.parent_id.is_none() || h.root_cell() != Cell::ROOT {
            r.problem(format!(
                "root treelet has parent {} and root cell {:?}",
                h.parent_id,
                h.root_cell()
            ));
        }
        return false;
    }
    let (parent, leaf) = (h.parent_id, h.parent_leaf_index);
    if parent.is_none() || parent.0 >= id.0 {
        r.problem(format!(
            "treelet {id} is not reachable: its header names parent {parent}, not an earlier treelet"
        ));
        return false;
    }
    let link = match parents.get(&parent.0) {
        Some(Parent::Read(leaves)) => leaves.get(&leaf).and_then(Option::as_ref),
        Some(Parent::Unreadable) | None => {
            r.problem(format!("treelet {id}: its parent {parent} cannot be read"));
            return false;
        }
    };
    let Some(link) = link.filter(|l| l.child == id.0) else {
        r.problem(format!(
            "treelet {id}: header says parent {parent} leaf {leaf}, but that leaf does not refer to it"
        ));
        return false;
    };
    if h.parent_leaf_parent_index != link.leaf_parent || h.child_index_in_parent != link.child_index
    {
        r.problem(format!(
            "treelet {id}: header says parent {parent} leaf {leaf} leaf parent {} child {}, but that leaf's parent node is {} and it is child {}",
            h.parent_leaf_parent_index, h.child_index_in_parent, link.leaf_parent, link.child_index
        ));
    }
    if h.root_cell() != link.cell {
        r.problem(format!(
            "treelet {id}: root cell {:?} != refined leaf's cell {:?}",
            h.root_cell(),
            link.cell
        ));
    }
    if let (Some(root), Some(leaf)) = (root_attributes, &link.attributes) {
        let mut at = 0;
        for &c in channels {
            let range = at..at + c.size();
            if root[range.clone()] != leaf[range] {
                r.problem(format!(
                    "treelet {id}: root {} differs from the refined leaf's",
                    c.name()
                ));
            }
            at += c.size();
        }
    }
    true
}
