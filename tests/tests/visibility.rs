//! The server's visible cuts (`server/src/service/visibility.rs`) on a real scan, against casts
//! over the fully resident tree: with the root and the cut's treelets resident, every ray of the
//! grid stops exactly where it stops in the whole tree (same voxel, same distance), and a
//! treelet at the bottom of the cut, taken away, changes some ray — for the seeded views and the
//! stiff ones (axis-parallel view, camera inside the data, far and near cameras). A buffer too
//! small or a treelet that cannot be read makes an incomplete cut that never names a treelet the
//! complete cut does not.

use std::collections::BTreeSet;

use arbor_client_core::camera::{Camera, CameraPath};
use arbor_client_core::cycle::view_hint;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::slots::{DecodedTreelet, InsertOutcome, SlotBuffer, SlotConfig};
use arbor_client_core::traverse::{Lod, trace};
use arbor_proto::wire::ViewHint;
use arbor_proto::{Cell, TreeletId};
use arbor_server::service::visibility::{
    CutCaster, FIRST_WORTH_CHECK, VisibleCut, frame_rays, grid_camera, same_view,
};
use arbor_tests::support::{decoded_treelets, small_lion};
use glam::DVec3;

const GRID: u32 = 96;

/// The hint a client sends for `camera` at LOD bias 1 (as `cycle.rs` builds it).
fn hint(camera: &Camera) -> ViewHint {
    view_hint(camera, 1.0, 1000).expect("a valid hint")
}

fn nodes_only(t: &DecodedTreelet) -> DecodedTreelet {
    DecodedTreelet {
        treelet: t.treelet.clone(),
        attributes: Vec::new(),
    }
}

/// Where every ray of `view`'s grid stops in `tree`: the voxel and the distance.
fn stops(tree: &SlotBuffer, frame: &SceneFrame, view: &ViewHint) -> Vec<Option<(Cell, u64)>> {
    let camera = grid_camera(view, GRID);
    let lod = Lod {
        pixel_angle: f64::from(view.footprint),
        lod_bias: 1.0,
        max_depth: frame.max_depth,
    };
    let mut out = Vec::new();
    for y in 0..camera.height {
        for x in 0..camera.width {
            let ray = camera.ray(f64::from(x) + 0.5, f64::from(y) + 0.5);
            out.push(trace(&tree.view(), frame, &ray, &lod).map(|h| (h.cell, h.t.to_bits())));
        }
    }
    out
}

fn ids(cut: &VisibleCut) -> BTreeSet<TreeletId> {
    cut.treelets.iter().map(|&(_, id)| id).collect()
}

struct Lion {
    treelets: Vec<DecodedTreelet>,
    scene: arbor_proto::SceneDescription,
    full: SlotBuffer,
    frame: SceneFrame,
}

fn lion() -> Lion {
    let built = small_lion();
    let treelets = decoded_treelets(&built.scene);
    let scene = built.scene.description.clone();
    let full = SlotBuffer::fully_resident(&scene, &[], treelets.iter().map(nodes_only)).unwrap();
    Lion {
        frame: SceneFrame::of(&scene),
        treelets,
        scene,
        full,
    }
}

impl Lion {
    fn caster(&self, budget_bytes: u64) -> CutCaster {
        CutCaster::new(&self.scene, budget_bytes, nodes_only(&self.treelets[0])).unwrap()
    }

    fn fetch(&self) -> impl FnMut(TreeletId) -> Option<DecodedTreelet> + '_ {
        |id| self.treelets.get(id.0 as usize).map(nodes_only)
    }

    /// The root and `treelets` (parents first) resident, nodes only.
    fn partial(&self, treelets: impl IntoIterator<Item = TreeletId>) -> SlotBuffer {
        let config = SlotConfig {
            budget_bytes: self.whole_scene_bytes() * 2,
            treelet_nodes: self.scene.treelet_nodes,
            channels: Vec::new(),
            visibility_max: 1,
            load_limit: u32::MAX,
        };
        let mut tree = SlotBuffer::new(config, nodes_only(&self.treelets[0])).unwrap();
        for id in treelets {
            let outcome = tree.insert(nodes_only(&self.treelets[id.0 as usize]));
            assert!(
                matches!(outcome, InsertOutcome::Inserted { .. }),
                "{id}: {outcome:?}"
            );
        }
        tree
    }

    fn whole_scene_bytes(&self) -> u64 {
        u64::from(self.scene.treelet_count) * SlotBuffer::slot_bytes(self.scene.treelet_nodes, &[])
    }

    fn views(&self) -> Vec<(&'static str, Camera)> {
        let f = &self.frame;
        let c = DVec3::from_array(f.centre());
        let e = f.edge;
        let at = |what, eye: DVec3, target: DVec3, fov: f64| {
            (
                what,
                Camera::look_at(eye, target, DVec3::Z, fov, 160, 120).unwrap(),
            )
        };
        vec![
            ("static", CameraPath::Static.camera(0, f, 7, 160, 120)),
            (
                "jump",
                CameraPath::Jump { every: 1 }.camera(1, f, 7, 160, 120),
            ),
            (
                "fly-in end",
                CameraPath::FlyIn { cycles: 1 }.camera(5, f, 7, 160, 120),
            ),
            (
                "axis-parallel",
                Camera::look_at(c - DVec3::X * 2.0 * e, c, DVec3::Z, 0.8, 128, 128).unwrap(),
            ),
            at("inside the data", c, c + DVec3::new(1.0, 0.3, 0.1), 1.2),
            at("far", c + DVec3::new(1.0, 1.0, 0.5) * 300.0 * e, c, 0.05),
            at("near", c + DVec3::new(0.2, -0.7, 0.1) * e, c, 1.0),
        ]
    }
}

#[test]
fn with_the_cut_resident_every_ray_stops_where_the_whole_tree_stops_it() {
    let lion = lion();
    let caster = lion.caster(lion.whole_scene_bytes() * 2);
    for (what, camera) in lion.views() {
        let view = hint(&camera);
        let cut = caster.cut(&view, GRID, lion.fetch());
        assert!(cut.complete, "{what}: complete");
        assert!(cut.answers(&view), "{what}");
        assert_eq!(
            ids(&cut).len(),
            cut.treelets.len(),
            "{what}: each treelet once"
        );
        let whole = stops(&lion.full, &lion.frame, &view);
        let resident = lion.partial(cut.treelets.iter().map(|&(_, id)| id));
        assert_eq!(
            stops(&resident, &lion.frame, &view),
            whole,
            "{what}: enough"
        );
        // Parents before children, levels counted from the root.
        let position = |id: TreeletId| cut.treelets.iter().position(|&(_, t)| t == id);
        for &(level, id) in &cut.treelets {
            let parent = lion.treelets[id.0 as usize].treelet.header.parent_id;
            if parent == TreeletId::ROOT {
                assert_eq!(level, 1, "{what}: a child of the root is level 1");
            } else {
                let p = position(parent).unwrap_or_else(|| panic!("{what}: {id}'s parent"));
                assert!(p < position(id).unwrap(), "{what}: {parent} before {id}");
                assert_eq!(cut.treelets[p].0 + 1, level, "{what}: levels");
            }
        }
        // Nothing superfluous: a treelet at the bottom of the cut, taken away, changes a ray.
        let parents: BTreeSet<TreeletId> = cut
            .treelets
            .iter()
            .map(|&(_, id)| lion.treelets[id.0 as usize].treelet.header.parent_id)
            .collect();
        let bottom: Vec<TreeletId> = ids(&cut).difference(&parents).copied().take(8).collect();
        for gone in bottom {
            let fewer = lion.partial(
                cut.treelets
                    .iter()
                    .map(|&(_, id)| id)
                    .filter(|&id| id != gone),
            );
            assert_ne!(
                stops(&fewer, &lion.frame, &view),
                whole,
                "{what}: {gone} is needed"
            );
        }
        // Deterministic: the same view again gives the same cut.
        assert_eq!(
            caster.cut(&view, GRID, lion.fetch()).treelets,
            cut.treelets,
            "{what}"
        );
        // From inside the data every ray starts in the same chain of nested treelets: one ray
        // per treelet follows the chain down before the next round, so the rays are cast a
        // few times, not once per treelet level (12 rounds before, on lion-4k).
        if what == "inside the data" {
            let rays = u64::from(grid_camera(&view, GRID).width * grid_camera(&view, GRID).height);
            assert!(
                cut.rays_cast <= 4 * rays,
                "{what}: {} rays for a grid of {rays}",
                cut.rays_cast
            );
        }
    }
}

#[test]
fn a_fine_cut_cast_from_a_coarse_one_is_the_coarse_cut_and_the_fine_one_together() {
    let lion = lion();
    let caster = lion.caster(lion.whole_scene_bytes() * 2);
    for (what, camera) in lion.views() {
        let view = hint(&camera);
        let coarse = caster.cut(&view, GRID / 4, lion.fetch());
        let fine = caster.cut(&view, GRID, lion.fetch());
        let from = caster.cut_from(&view, GRID, &coarse.treelets, lion.fetch(), |_| true);
        assert!(coarse.complete && fine.complete && from.complete, "{what}");
        let union: BTreeSet<TreeletId> = ids(&coarse).union(&ids(&fine)).copied().collect();
        assert_eq!(ids(&from), union, "{what}");
        assert_eq!(
            ids(&from).len(),
            from.treelets.len(),
            "{what}: each treelet once"
        );
        // Parents first still, and fewer rays: the rounds up to the coarse cut are not cast again.
        let position = |id: TreeletId| from.treelets.iter().position(|&(_, t)| t == id);
        for &(_, id) in &from.treelets {
            let parent = lion.treelets[id.0 as usize].treelet.header.parent_id;
            if parent != TreeletId::ROOT {
                assert!(
                    position(parent) < position(id),
                    "{what}: {parent} before {id}"
                );
            }
        }
        assert!(
            from.rays_cast <= fine.rays_cast,
            "{what}: {} rays",
            from.rays_cast
        );
        assert_eq!(from.grid, GRID);
    }
    // A seed that cannot be read makes the cut incomplete.
    let view = hint(&lion.views()[0].1);
    let coarse = caster.cut(&view, GRID / 4, lion.fetch());
    let unreadable = coarse.treelets[0].1;
    let cut = caster.cut_from(
        &view,
        GRID,
        &coarse.treelets,
        |id: TreeletId| (id != unreadable).then(|| nodes_only(&lion.treelets[id.0 as usize])),
        |_| true,
    );
    assert!(!cut.complete);
}

#[test]
fn a_cut_is_abandoned_where_it_grows_past_what_is_worth_casting() {
    let lion = lion();
    let caster = lion.caster(lion.whole_scene_bytes() * 2);
    let mut asked_at_all = 0;
    for (what, camera) in lion.views() {
        let view = hint(&camera);
        let whole = caster.cut(&view, GRID, lion.fetch());
        // Asked each time the cut has doubled, from FIRST_WORTH_CHECK on; a yes changes nothing.
        let mut asked = Vec::new();
        let cut = caster.cut_from(&view, GRID, &[], lion.fetch(), |n| {
            asked.push(n);
            true
        });
        assert_eq!(cut.treelets, whole.treelets, "{what}");
        assert!(cut.complete && !cut.abandoned, "{what}");
        let mut last = FIRST_WORTH_CHECK / 2;
        for &n in &asked {
            assert!(
                n >= 2 * last && n <= whole.treelets.len(),
                "{what}: {asked:?}"
            );
            last = n;
        }
        assert_eq!(
            asked.is_empty(),
            whole.treelets.len() < FIRST_WORTH_CHECK,
            "{what}: {} treelets, asked at {asked:?}",
            whole.treelets.len()
        );
        let Some(&first) = asked.first() else {
            continue;
        };
        asked_at_all += 1;
        // A no stops the cast there: what it holds is needed, but not all of it.
        let mut again = Vec::new();
        let cut = caster.cut_from(&view, GRID, &[], lion.fetch(), |n| {
            again.push(n);
            false
        });
        assert!(cut.abandoned && !cut.complete, "{what}");
        assert_eq!(again, [first], "{what}");
        assert_eq!(cut.treelets.len(), first, "{what}");
        assert!(ids(&cut).is_subset(&ids(&whole)), "{what}");
        assert!(cut.treelets.len() < whole.treelets.len(), "{what}");
        // A seeded cast is asked first at twice its seed.
        let seed = &whole.treelets[..first];
        let mut seeded = Vec::new();
        caster.cut_from(&view, GRID, seed, lion.fetch(), |n| {
            seeded.push(n);
            true
        });
        assert!(
            seeded.first().is_none_or(|&n| n >= 2 * first),
            "{what}: {seeded:?}"
        );
    }
    assert!(
        asked_at_all > 0,
        "no lion view's cut reached {FIRST_WORTH_CHECK} treelets: the test checks nothing"
    );
}

/// The calling thread's nice value, from `/proc/thread-self/stat` (field 19).
fn thread_nice() -> i32 {
    let stat = std::fs::read_to_string("/proc/thread-self/stat").unwrap();
    let (_, after_name) = stat.rsplit_once(')').unwrap();
    after_name
        .split_whitespace()
        .nth(16)
        .unwrap()
        .parse()
        .unwrap()
}

#[test]
fn a_cut_reads_decodes_and_casts_on_the_cut_threads_which_yield_to_streaming() {
    use arbor_server::service::visibility::CUT_NICE;
    use std::sync::Mutex;
    // The pool is built by this test's first cut, from this thread (one test per process).
    let base = thread_nice();
    let lion = lion();
    let caster = lion.caster(lion.whole_scene_bytes() * 2);
    let (_, camera) = &lion.views()[0];
    let seen = Mutex::new(Vec::new());
    let note = || {
        let name = std::thread::current().name().unwrap_or("").to_owned();
        seen.lock().unwrap().push((name, thread_nice()));
    };
    let mut fetch = lion.fetch();
    let cut = caster.cut_from(
        &hint(camera),
        GRID,
        &[],
        |id| {
            note();
            fetch(id)
        },
        |_| {
            note();
            true
        },
    );
    assert!(cut.complete && cut.treelets.len() >= FIRST_WORTH_CHECK);
    let seen = seen.into_inner().unwrap();
    assert!(
        seen.len() > cut.treelets.len(),
        "every read and check noted"
    );
    for (name, nice) in &seen {
        assert!(name.starts_with("arbor-cut-"), "ran on {name:?}");
        assert_eq!(*nice, (base + CUT_NICE).min(19), "{name}");
    }
    assert_eq!(
        thread_nice(),
        base,
        "the caller's own priority is left alone"
    );
}

#[test]
fn too_small_a_buffer_or_an_unreadable_treelet_gives_an_incomplete_cut_of_needed_treelets() {
    let lion = lion();
    let view = hint(&lion.views()[0].1);
    let whole = lion.caster(lion.whole_scene_bytes() * 2);
    let expected = ids(&whole.cut(&view, GRID, lion.fetch()));
    assert!(expected.len() > 8, "the view needs several treelets");

    let slot = SlotBuffer::slot_bytes(lion.scene.treelet_nodes, &[]);
    let small = lion.caster(slot * 4);
    let cut = small.cut(&view, GRID, lion.fetch());
    assert!(!cut.complete, "four slots cannot hold the view");
    assert!(!ids(&cut).is_empty());
    assert!(ids(&cut).is_subset(&expected), "only needed treelets");

    // Every treelet below the first level unreadable.
    let cut = whole.cut(&view, GRID, |id: TreeletId| {
        let t = lion.treelets.get(id.0 as usize)?;
        (t.treelet.header.parent_id == TreeletId::ROOT).then(|| nodes_only(t))
    });
    assert!(!cut.complete);
    assert!(!ids(&cut).is_empty());
    assert!(ids(&cut).is_subset(&expected));
    assert!(cut.treelets.iter().all(|&(level, _)| level == 1));
}

#[test]
fn a_hint_tells_the_rays_of_its_frame() {
    let lion = lion();
    for (what, camera) in lion.views() {
        let view = hint(&camera);
        assert_eq!(frame_rays(&view), camera.width.max(camera.height), "{what}");
        // At LOD bias 2 the client's pixels count as half as many.
        let coarser = ViewHint {
            footprint: view.footprint * 2.0,
            ..view
        };
        assert_eq!(
            frame_rays(&coarser),
            camera.width.max(camera.height) / 2,
            "{what}"
        );
    }
    let portrait = Camera {
        width: 90,
        height: 300,
        ..lion.views()[0].1
    };
    assert_eq!(frame_rays(&hint(&portrait)), 300);
}

#[test]
fn hints_of_the_same_view_match_and_others_do_not() {
    let lion = lion();
    let views = lion.views();
    let a = hint(&views[0].1);
    let mut noisy = a;
    noisy.eye[0] += a.eye[0].abs().max(1.0) * 1e-9;
    noisy.free_slots = 3;
    assert!(
        same_view(&a, &noisy),
        "float noise and free slots do not matter"
    );
    for (what, camera) in &views[1..] {
        assert!(!same_view(&a, &hint(camera)), "{what}");
    }
    let mut wider = a;
    wider.footprint *= 2.0;
    assert!(!same_view(&a, &wider), "another LOD bias is another view");
}
