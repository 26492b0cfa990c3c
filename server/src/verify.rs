//! `verify`: checks every invariant of a stored scene, treelet by treelet in id order, keeping
//! only the links still to be matched in memory (bounded by the width of the treelet tree).
//!
//! Checked: the description; every node well formed (masks consistent, offsets in range,
//! children contiguous in child-index and breadth-first order — [`Treelet::validate`]); every
//! voxel inside its parent and no deeper than the target depth; treelet links both ways (parent
//! id, parent leaf, leaf's parent, child index; a refinable leaf's subtreelet exists, has a higher
//! id, and its root cell equals the leaf's cell); each refinable leaf has exactly one subtreelet
//! and every treelet but the root is reached; attribute blocks decode to the right length; inner
//! attributes equal the mean of their children within one quantization step and a refinable
//! leaf's attributes equal its subtreelet root's; stored counts match the description.

use std::collections::HashMap;

use arbor_proto::codec::{self, PreparedDictionaries};
use arbor_proto::treelet::NodePlace;
use arbor_proto::{Cell, Channel, Node, Treelet, TreeletId};

use crate::pool::{PoolError, StoredScene};

/// Result of a verification.
#[derive(Debug, Default)]
pub struct VerifyReport {
    pub treelets: u64,
    pub node_records: u64,
    pub voxels: u64,
    pub leaf_voxels: u64,
    /// Every broken invariant found (at most [`MAX_PROBLEMS`] are kept, `problem_count` counts all).
    pub problems: Vec<String>,
    pub problem_count: u64,
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

/// What a refinable leaf promises its subtreelet.
struct Link {
    parent: TreeletId,
    leaf: u16,
    leaf_parent: u16,
    child_index: u8,
    cell: Cell,
    attributes: Vec<Vec<u8>>,
}

/// Verifies a stored scene. `Err` only for pool I/O failures; broken invariants are in the report.
pub fn verify_scene(scene: &StoredScene) -> Result<VerifyReport, PoolError> {
    let d = &scene.description;
    let mut v = Verifier {
        scene,
        channels: d.layout.channels().to_vec(),
        dictionaries: PreparedDictionaries::of(d),
        links: HashMap::new(),
        r: VerifyReport::default(),
    };
    if let Err(e) = d.validate() {
        v.r.problem(format!("description: {e}"));
        return Ok(v.r);
    }
    let mut expected_next = 0u32;
    for id in scene.stored_ids() {
        let id = id?;
        if id.0 != expected_next {
            v.r.problem(format!(
                "treelet ids not contiguous: expected {expected_next}, found {id}"
            ));
        }
        expected_next = id.0.wrapping_add(1);
        v.r.treelets += 1;
        v.treelet(id)?;
    }
    v.totals();
    Ok(v.r)
}

/// The state of one verification: the report so far and the links refinable leaves promised.
struct Verifier<'a> {
    scene: &'a StoredScene,
    channels: Vec<Channel>,
    /// The scene's dictionaries, loaded once for its many blocks.
    dictionaries: PreparedDictionaries,
    /// Subtreelet id → what its leaf promised, until the subtreelet is checked.
    links: HashMap<u32, Link>,
    r: VerifyReport,
}

impl Verifier<'_> {
    /// One stored treelet: decodes, checks the header, its attribute blocks, its link to the
    /// parent, and every node.
    fn treelet(&mut self, id: TreeletId) -> Result<(), PoolError> {
        let d = &self.scene.description;
        let Some(bytes) = self.scene.nodes(id)? else {
            return Ok(());
        };
        let (t, places) = match codec::decode_compressed_treelet_with_places_using(
            &bytes,
            d.max_depth,
            self.dictionaries.nodes(),
        ) {
            Ok(decoded) => decoded,
            Err(e) => {
                self.r.problem(format!("treelet {id}: {e}"));
                return Ok(());
            }
        };
        if t.header.id != id {
            self.r.problem(format!(
                "treelet stored under {id} says it is {}",
                t.header.id
            ));
        }
        if t.capacity() != d.treelet_nodes {
            self.r.problem(format!(
                "treelet {id}: capacity {} != scene's {}",
                t.capacity(),
                d.treelet_nodes
            ));
        }
        self.r.node_records += t.used().len() as u64;
        let attrs = self.attributes(id, &t)?;
        let attrs = (attrs.len() == self.channels.len()).then_some(attrs);
        check_link(
            &mut self.r,
            &mut self.links,
            &t,
            attrs.as_deref().unwrap_or(&[]),
            &self.channels,
        );
        for (i, place) in places.iter().enumerate() {
            self.node(id, &t, &places, i, place, attrs.as_deref());
        }
        Ok(())
    }

    /// The treelet's attribute blocks, decoded, one per channel; a missing or bad block is a
    /// problem and is left out.
    fn attributes(&mut self, id: TreeletId, t: &Treelet) -> Result<Vec<Vec<u8>>, PoolError> {
        let mut attrs = Vec::new();
        for &c in &self.channels {
            let Some(b) = self.scene.channel(c, id)? else {
                self.r
                    .problem(format!("treelet {id}: {} block missing", c.name()));
                continue;
            };
            match codec::decode_compressed_attributes_using(
                &b,
                c,
                t.header.used_nodes,
                self.dictionaries.channel(c),
            ) {
                Ok(b) => attrs.push(b),
                Err(e) => self
                    .r
                    .problem(format!("treelet {id}: {} block: {e}", c.name())),
            }
        }
        Ok(attrs)
    }

    /// One node: inside its parent; a leaf is final (counted) or names a later subtreelet
    /// (remembered as a link); an inner node's attributes are its children's mean.
    fn node(
        &mut self,
        id: TreeletId,
        t: &Treelet,
        places: &[NodePlace],
        i: usize,
        place: &NodePlace,
        attrs: Option<&[Vec<u8>]>,
    ) {
        let d = &self.scene.description;
        let n = t.nodes[i];
        if place.parent != u32::MAX {
            let pc = places[place.parent as usize].cell;
            if !pc.contains(&place.cell) || place.cell.depth != pc.depth + 1 {
                self.r.problem(format!(
                    "treelet {id} node {i}: voxel {:?} not inside parent {pc:?}",
                    place.cell
                ));
            }
        }
        if !place.is_leaf {
            if let Some(attrs) = attrs {
                self.inner_means(id, i, n, attrs);
            }
            return;
        }
        if n.first_child == Node::NONE {
            if place.cell.depth == d.max_depth {
                self.r.leaf_voxels += 1;
            }
            return;
        }
        let child = n.first_child;
        if child <= id.0 || child >= d.treelet_count {
            self.r.problem(format!(
                "treelet {id} leaf {i}: subtreelet {child} out of range"
            ));
        }
        let link = Link {
            parent: id,
            leaf: i as u16,
            leaf_parent: if place.parent == u32::MAX {
                0
            } else {
                place.parent as u16
            },
            child_index: place.child_index,
            cell: place.cell,
            attributes: attrs.map_or_else(Vec::new, |attrs| {
                self.channels
                    .iter()
                    .enumerate()
                    .map(|(k, c)| record(&attrs[k], *c, i).to_vec())
                    .collect()
            }),
        };
        if self.links.insert(child, link).is_some() {
            self.r
                .problem(format!("subtreelet {child} is claimed by two leaves"));
        }
    }

    /// An inner node's attributes must be the mean of its children's (within one step).
    fn inner_means(&mut self, id: TreeletId, i: usize, n: Node, attrs: &[Vec<u8>]) {
        let first = i + n.first_child as usize;
        let kids = n.child_count() as usize;
        for (k, &c) in self.channels.iter().enumerate() {
            let mut mean = vec![0u8; c.size()];
            c.mean(
                (first..first + kids).map(|j| record(&attrs[k], c, j)),
                &mut mean,
            );
            if !c.within_one_step(&mean, record(&attrs[k], c, i)) {
                self.r.problem(format!(
                    "treelet {id} node {i}: {} {:?} is not the mean {:?} of its children",
                    c.name(),
                    record(&attrs[k], c, i),
                    mean
                ));
            }
        }
    }

    /// Whole-scene checks: counts against the description, links left unresolved.
    fn totals(&mut self) {
        let d = &self.scene.description;
        let r = &mut self.r;
        r.voxels = r.node_records.saturating_sub(r.treelets.saturating_sub(1));
        if r.treelets != u64::from(d.treelet_count) {
            r.problem(format!(
                "{} treelets stored, description says {}",
                r.treelets, d.treelet_count
            ));
        }
        for (child, link) in std::mem::take(&mut self.links) {
            r.problem(format!(
                "treelet {} leaf {}: subtreelet {child} does not exist",
                link.parent, link.leaf
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
    }
}

fn record(block: &[u8], c: Channel, i: usize) -> &[u8] {
    &block[i * c.size()..(i + 1) * c.size()]
}

/// Checks a treelet against the leaf that refers to it (or, for 0, that it is a proper root).
fn check_link(
    r: &mut VerifyReport,
    links: &mut HashMap<u32, Link>,
    t: &Treelet,
    attrs: &[Vec<u8>],
    channels: &[Channel],
) {
    let h = &t.header;
    let id = h.id;
    if id == TreeletId::ROOT {
        if !h.parent_id.is_none() || h.root_cell() != Cell::ROOT {
            r.problem(format!(
                "root treelet has parent {} and root cell {:?}",
                h.parent_id,
                h.root_cell()
            ));
        }
        return;
    }
    let Some(link) = links.remove(&id.0) else {
        r.problem(format!(
            "treelet {id} is not reachable: no leaf refers to it"
        ));
        return;
    };
    if h.parent_id != link.parent
        || h.parent_leaf_index != link.leaf
        || h.parent_leaf_parent_index != link.leaf_parent
        || h.child_index_in_parent != link.child_index
    {
        r.problem(format!(
            "treelet {id}: header says parent {} leaf {} leaf parent {} child {}, but leaf {} of treelet {} (parent node {}, child {}) refers to it",
            h.parent_id, h.parent_leaf_index, h.parent_leaf_parent_index, h.child_index_in_parent,
            link.leaf, link.parent, link.leaf_parent, link.child_index
        ));
    }
    if h.root_cell() != link.cell {
        r.problem(format!(
            "treelet {id}: root cell {:?} != refined leaf's cell {:?}",
            h.root_cell(),
            link.cell
        ));
    }
    if attrs.len() == channels.len() && link.attributes.len() == channels.len() {
        for (k, &c) in channels.iter().enumerate() {
            if record(&attrs[k], c, 0) != link.attributes[k].as_slice() {
                r.problem(format!(
                    "treelet {id}: root {} differs from the refined leaf's",
                    c.name()
                ));
            }
        }
    }
}
