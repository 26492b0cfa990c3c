//! The sled pool: atomic imports, cleanup of leftovers, replace/remove, channel isolation, and
//! `verify` catching every kind of damage done to a stored scene.

use std::path::Path;

use arbor_proto::{Channel, TreeletId, codec};
use arbor_server::import::{ImportOptions, import_file};
use arbor_server::octree::{BuildOptions, DepthChoice, build_scene};
use arbor_server::pool::{Pool, PoolError, pack};
use arbor_server::source::Source;
use arbor_server::verify::{
    VerifyOptions, VerifyProgress, VerifyReport, verify_pool_scene, verify_scene,
    verify_scene_observed,
};
use std::ops::ControlFlow;

/// A real scan of `../shared/data`, read for an import (its columns in `scratch`).
fn real_scan(relative: &str, scratch: &Path) -> Source {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data")
        .join(relative);
    assert!(
        path.exists(),
        "the real scans in ../shared/data are required ({} is missing)",
        path.display()
    );
    import_file(&path, &ImportOptions::default(), scratch).unwrap()
}

fn bunny(scratch: &Path) -> Source {
    real_scan("meshes/stanford-bunny.obj", scratch)
}

fn opts() -> BuildOptions {
    BuildOptions {
        depth: DepthChoice::Fixed(6),
        treelet_bytes: 1024,
        ..BuildOptions::default()
    }
}

/// Opens a pool, waiting for sled's flusher thread of a just-dropped handle to let go of the lock.
/// Opens a pool, waiting while the process's previous handle still holds sled's lock.
fn open_when_unlocked(dir: &Path) -> Result<Pool, PoolError> {
    for _ in 0..100 {
        match Pool::open(dir) {
            Err(PoolError::InUse(_)) => std::thread::sleep(std::time::Duration::from_millis(50)),
            opened => return opened,
        }
    }
    Pool::open(dir)
}

fn reopen(dir: &Path) -> Pool {
    open_when_unlocked(dir).unwrap()
}

fn import(pool: &Pool, source: &Source, scratch: &Path, name: &str, replace: bool) {
    let mut txn = pool.begin_import(name, replace).unwrap();
    let desc = build_scene(source, name, "bunny", &opts(), scratch, &mut txn).unwrap();
    txn.commit(&desc).unwrap();
}

#[test]
fn abandoned_and_crashed_imports_leave_nothing() {
    let scratch = tempfile::tempdir().unwrap();
    let source = bunny(scratch.path());
    let dir = tempfile::tempdir().unwrap();
    {
        let pool = Pool::open(dir.path()).unwrap();
        import(&pool, &source, scratch.path(), "kept", false);
        // Abandoned: built but dropped without commit.
        let mut txn = pool.begin_import("abandoned", false).unwrap();
        build_scene(
            &source,
            "abandoned",
            "bunny",
            &opts(),
            scratch.path(),
            &mut txn,
        )
        .unwrap();
        drop(txn);
        assert_eq!(pool.stored_generations().len(), 1);
        // Crashed: built, flushed, never committed nor cleaned (as after SIGKILL).
        let mut txn = pool.begin_import("crashed", false).unwrap();
        build_scene(
            &source,
            "crashed",
            "bunny",
            &opts(),
            scratch.path(),
            &mut txn,
        )
        .unwrap();
        txn.abandon_as_if_crashed().unwrap();
        assert_eq!(pool.stored_generations().len(), 2);
    }
    let pool = reopen(dir.path());
    let names: Vec<_> = pool.scenes().unwrap().into_iter().map(|d| d.name).collect();
    assert_eq!(names, vec!["kept".to_string()]);
    assert_eq!(
        pool.stored_generations(),
        vec![pool.scene("kept").unwrap().generation]
    );
    assert!(verify_scene(&pool.scene("kept").unwrap()).unwrap().is_ok());
}

#[test]
fn names_replace_and_remove() {
    let scratch = tempfile::tempdir().unwrap();
    let source = bunny(scratch.path());
    let dir = tempfile::tempdir().unwrap();
    let pool = Pool::open(dir.path()).unwrap();
    import(&pool, &source, scratch.path(), "a", false);
    let first = pool.scene("a").unwrap().generation;
    assert!(matches!(
        pool.begin_import("a", false),
        Err(PoolError::SceneExists(_))
    ));
    for bad in ["", "../x", ".hidden", "a b", &"x".repeat(200)] {
        assert!(
            matches!(pool.begin_import(bad, false), Err(PoolError::BadName(_))),
            "{bad:?}"
        );
    }
    import(&pool, &source, scratch.path(), "a", true);
    let second = pool.scene("a").unwrap().generation;
    assert_ne!(first, second);
    assert_eq!(
        pool.stored_generations(),
        vec![second],
        "replaced generation not dropped"
    );
    pool.remove("a").unwrap();
    assert!(matches!(pool.scene("a"), Err(PoolError::NoSuchScene(_))));
    assert!(matches!(pool.remove("a"), Err(PoolError::NoSuchScene(_))));
    assert!(pool.stored_generations().is_empty());
}

#[test]
fn channels_are_stored_apart() {
    let scratch = tempfile::tempdir().unwrap();
    let source = bunny(scratch.path());
    let dir = tempfile::tempdir().unwrap();
    let pool = Pool::open(dir.path()).unwrap();
    import(&pool, &source, scratch.path(), "b", false);
    let s = pool.scene("b").unwrap();
    // The bunny has no colour: no colour channel is stored, normals are.
    assert_eq!(s.description.layout.channels(), &[Channel::Normal]);
    assert!(
        s.channel(Channel::Color, TreeletId::ROOT)
            .unwrap()
            .is_none()
    );
    let n = s
        .channel(Channel::Normal, TreeletId::ROOT)
        .unwrap()
        .unwrap();
    let d = &s.description;
    let root = s.nodes(TreeletId::ROOT).unwrap().unwrap();
    let t = codec::decode_compressed_treelet(&root, 6, d.node_dictionary.as_deref()).unwrap();
    let block = codec::decode_compressed_attributes(
        &n,
        Channel::Normal,
        t.header.used_nodes,
        d.channel_dictionary(Channel::Normal),
    )
    .unwrap();
    assert_eq!(block.len(), usize::from(t.header.used_nodes) * 4);
}

/// Blocks read for many ids at once, each pack read once while consecutive ids stay in it, are
/// the blocks read one id at a time: ascending and descending runs, repeats, ids crossing pack
/// boundaries back and forth, ids past the scene's end, and a channel the scene does not store.
#[test]
fn blocks_read_together_are_the_blocks_read_one_by_one() {
    let scratch = tempfile::tempdir().unwrap();
    let source = bunny(scratch.path());
    let dir = tempfile::tempdir().unwrap();
    let pool = Pool::open(dir.path()).unwrap();
    import(&pool, &source, scratch.path(), "b", false);
    let s = pool.scene("b").unwrap();
    let count = s.description.treelet_count;
    assert!(
        count > 2 * pack::PACK_TREELETS,
        "{count} treelets span a few packs"
    );
    let mut ids: Vec<TreeletId> = (0..count).map(TreeletId).collect();
    ids.extend((0..count).rev().map(TreeletId));
    ids.extend(
        [
            5,
            5,
            17,
            3,
            40,
            16,
            15,
            16,
            count,
            count + 1,
            2,
            u32::MAX - 1,
        ]
        .map(TreeletId),
    );
    let nodes = s.nodes_of(&ids).unwrap();
    let normals = s.channel_of(Channel::Normal, &ids).unwrap();
    let colours = s.channel_of(Channel::Color, &ids).unwrap();
    assert_eq!(
        (nodes.len(), normals.len(), colours.len()),
        (ids.len(), ids.len(), ids.len())
    );
    for (i, &id) in ids.iter().enumerate() {
        assert_eq!(nodes[i], s.nodes(id).unwrap(), "nodes of {id}");
        assert_eq!(
            normals[i],
            s.channel(Channel::Normal, id).unwrap(),
            "normals of {id}"
        );
        assert!(colours[i].is_none(), "colour of {id}");
        assert_eq!(nodes[i].is_some(), id.0 < count, "{id}");
    }
}

/// Builds a scene, closes the pool, lets `damage` write into sled directly, reopens and verifies.
fn damaged(damage: impl FnOnce(&sled::Db, u64, &arbor_proto::SceneDescription)) -> Vec<String> {
    let scratch = tempfile::tempdir().unwrap();
    let source = bunny(scratch.path());
    let dir = tempfile::tempdir().unwrap();
    let (generation, desc) = {
        let pool = Pool::open(dir.path()).unwrap();
        import(&pool, &source, scratch.path(), "d", false);
        let s = pool.scene("d").unwrap();
        assert!(verify_scene(&s).unwrap().is_ok());
        (s.generation, s.description.clone())
    };
    {
        let db = raw_sled(dir.path());
        damage(&db, generation, &desc);
        db.flush().unwrap();
    }
    let pool = reopen(dir.path());
    let r = verify_scene(&pool.scene("d").unwrap()).unwrap();
    assert!(!r.is_ok(), "verify missed the damage");
    let observed = verify_scene_observed(&pool.scene("d").unwrap(), 7, &mut |_| {
        ControlFlow::Continue(())
    })
    .unwrap()
    .unwrap();
    assert_same_report(&observed, &r);
    drop(pool);
    let stretches = verify_in_stretches(dir.path(), "d", 7);
    assert_same_report(&stretches, &r);
    assert!(stretches.reopens > 0);
    r.problems
}

/// `verify_pool_scene` in batches of `batch` treelets, the pool closed and opened again after
/// every batch; checks that the progress adds up.
fn verify_in_stretches(dir: &Path, name: &str, batch: usize) -> VerifyReport {
    let planned = std::cell::Cell::new(None);
    let checked = std::cell::Cell::new(0u64);
    let options = VerifyOptions {
        reopen_after_bytes: 1,
        batch_treelets: batch,
    };
    let r = verify_pool_scene(dir, name, &options, &|p| match p {
        VerifyProgress::Planned { treelets } => planned.set(Some(treelets)),
        VerifyProgress::Checked(n) => {
            assert!(planned.get().is_some(), "planned before checked");
            checked.set(checked.get() + n);
        }
    })
    .unwrap();
    assert_eq!(
        checked.get(),
        r.treelets,
        "progress adds up to the treelets"
    );
    r
}

/// Two verifications of one scene found the same, problem by problem.
fn assert_same_report(a: &VerifyReport, b: &VerifyReport) {
    assert_eq!(a.problems, b.problems);
    assert_eq!(
        (
            a.problem_count,
            a.treelets,
            a.node_records,
            a.voxels,
            a.leaf_voxels,
            a.bytes_read
        ),
        (
            b.problem_count,
            b.treelets,
            b.node_records,
            b.voxels,
            b.leaf_voxels,
            b.bytes_read
        )
    );
}

/// A real scan verified in batches of 5 treelets with the pool closed and opened again after
/// each (links from a leaf to its subtreelet cross batches and openings) finds exactly what one
/// pass finds, every invariant holding, and matches the description's counts; the pool is
/// only read.
#[test]
fn verify_in_stretches_with_the_pool_reopened_matches_one_pass() {
    let scratch = tempfile::tempdir().unwrap();
    let lion = real_scan("points/lion_takanawa.copc.laz", scratch.path());
    let dir = tempfile::tempdir().unwrap();
    let one_pass = {
        let pool = Pool::open(dir.path()).unwrap();
        let mut txn = pool.begin_import("lion", false).unwrap();
        let desc = build_scene(&lion, "lion", "lion", &opts(), scratch.path(), &mut txn);
        txn.commit(&desc.unwrap()).unwrap();
        // A killed import's leftovers: verify changes nothing, so they stay for the next
        // server or import to drop.
        let mut left = pool.begin_import("killed", false).unwrap();
        left.set_channels(&[Channel::Color]).unwrap();
        left.abandon_as_if_crashed().unwrap();
        verify_scene(&pool.scene("lion").unwrap()).unwrap()
    };
    assert!(one_pass.is_ok(), "{:?}", one_pass.problems);
    let trees = || {
        let mut names: Vec<_> = raw_sled(dir.path()).tree_names();
        names.sort();
        names
    };
    let trees_before = trees();
    let r = verify_in_stretches(dir.path(), "lion", 5);
    assert_eq!(trees(), trees_before, "the leftovers are still there");
    assert!(
        trees_before
            .iter()
            .any(|t| t.as_ref().ends_with(b":ch:color"))
    );
    assert!(r.is_ok(), "{:?}", r.problems);
    assert_same_report(&r, &one_pass);
    let pool = reopen(dir.path());
    let d = pool.scene("lion").unwrap().description;
    assert_eq!(r.treelets, u64::from(d.treelet_count));
    assert_eq!(r.voxels, d.stats.voxels);
    assert!(
        r.treelets > 100,
        "{} treelets: too few to cross batches",
        r.treelets
    );
    assert_eq!(
        u64::from(r.reopens),
        r.treelets.div_ceil(5),
        "one reopening per batch (the last finds the scene's end)"
    );

    // On a pool that stays open (the daemon's check), batch by batch: the same report, the
    // progress adding up, and a stop when asked, before the first batch or after the third.
    let scene = pool.scene("lion").unwrap();
    let mut told = Vec::new();
    let observed = verify_scene_observed(&scene, 5, &mut |p| {
        told.push(p);
        ControlFlow::Continue(())
    })
    .unwrap()
    .expect("not stopped");
    assert_same_report(&observed, &one_pass);
    assert_eq!(
        told[0],
        VerifyProgress::Planned {
            treelets: r.treelets
        }
    );
    let checked: Vec<u64> = told[1..]
        .iter()
        .map(|p| match p {
            VerifyProgress::Checked(n) => *n,
            p => panic!("{p:?} after the start"),
        })
        .collect();
    assert_eq!(checked.iter().sum::<u64>(), r.treelets);
    assert!(checked.iter().all(|&n| n <= 5), "{checked:?}");
    let stopped = verify_scene_observed(&scene, 5, &mut |_| ControlFlow::Break(())).unwrap();
    assert!(stopped.is_none());
    let mut batches = 0;
    let stopped = verify_scene_observed(&scene, 5, &mut |p| {
        if matches!(p, VerifyProgress::Checked(_)) {
            batches += 1;
        }
        if batches == 3 {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    })
    .unwrap();
    assert!(stopped.is_none());
    assert_eq!(batches, 3, "went on after being told to stop");
}

/// A scene removed, or replaced, between two of the verification's openings is named, not
/// reported against the other scene's blocks; a directory without a pool is refused, and none
/// is made there.
#[test]
fn verify_names_a_scene_changed_between_openings_and_a_missing_pool() {
    let scratch = tempfile::tempdir().unwrap();
    let source = bunny(scratch.path());
    let dir = tempfile::tempdir().unwrap();
    {
        let pool = Pool::open(dir.path()).unwrap();
        import(&pool, &source, scratch.path(), "d", false);
    }
    let options = VerifyOptions {
        reopen_after_bytes: 1,
        batch_treelets: 3,
    };
    for replace in [false, true] {
        let changed = std::cell::Cell::new(false);
        let e = verify_pool_scene(dir.path(), "d", &options, &|p| {
            if matches!(p, VerifyProgress::Checked(_)) && !changed.get() {
                let pool = reopen(dir.path());
                if replace {
                    import(&pool, &source, scratch.path(), "d", true);
                } else {
                    pool.remove("d").unwrap();
                }
                changed.set(true);
            }
        })
        .unwrap_err();
        assert!(changed.get());
        assert!(
            matches!(e, PoolError::ChangedWhileRead(ref n) if n == "d"),
            "{e}"
        );
        assert!(e.to_string().contains("while it was being read"), "{e}");
        if !replace {
            import(&reopen(dir.path()), &source, scratch.path(), "d", false);
        }
    }
    let missing = dir.path().join("no-pool-here");
    let e = verify_pool_scene(&missing, "d", &options, &|_| {}).unwrap_err();
    assert!(matches!(e, PoolError::NoPool(_)), "{e}");
    assert!(e.to_string().contains("not a pool directory"), "{e}");
    assert!(!missing.exists(), "no pool is made at a missing path");
    let e = Pool::open_existing(&missing).unwrap_err();
    assert!(matches!(e, PoolError::NoPool(_)), "{e}");
    assert!(!missing.exists());
}

/// The pool's database opened directly (in the segment size this build makes pools with), once
/// the pool that had it has let go of its lock.
fn raw_sled(dir: &Path) -> sled::Db {
    (0..100)
        .find_map(|_| {
            sled::Config::new()
                .path(dir)
                .segment_size(arbor_server::pool::POOL_SEGMENT_BYTES)
                .open()
                .map_err(|_| std::thread::sleep(std::time::Duration::from_millis(50)))
                .ok()
        })
        .expect("sled lock released")
}

#[test]
fn a_pool_of_another_format_is_refused_naming_both() {
    let scratch = tempfile::tempdir().unwrap();
    let source = bunny(scratch.path());
    let dir = tempfile::tempdir().unwrap();
    {
        let pool = Pool::open(dir.path()).unwrap();
        import(&pool, &source, scratch.path(), "f", false);
    }
    // No format key beside scenes: a pool of format 1 (one value per block); a later number:
    // a newer build's pool.
    for (stored, found) in [(None, 1), (Some(3u32), 3)] {
        {
            let db = raw_sled(dir.path());
            match stored {
                None => db.remove(b"arbor.pool.format").unwrap(),
                Some(v) => db.insert(b"arbor.pool.format", &v.to_be_bytes()).unwrap(),
            };
            db.flush().unwrap();
        }
        let e = open_when_unlocked(dir.path()).unwrap_err();
        assert!(
            matches!(e, PoolError::Format { found: f, expected: 2 } if f == found),
            "{e}"
        );
        assert!(e.to_string().contains("import the scenes again"), "{e}");
    }
    // A new, empty pool takes this build's format.
    let fresh = tempfile::tempdir().unwrap();
    drop(Pool::open(fresh.path()).unwrap());
    assert!(open_when_unlocked(fresh.path()).is_ok());
}

/// sled's record of the segment size the database in `dir` was made with.
fn segment_size_in_conf(dir: &Path) -> Option<usize> {
    let conf = std::fs::read(dir.join("conf")).unwrap();
    String::from_utf8_lossy(&conf)
        .lines()
        .find_map(|l| l.strip_prefix("segment_size:"))?
        .trim()
        .parse()
        .ok()
}

/// A new pool is made with `POOL_SEGMENT_BYTES` segments (sled reads one header per segment
/// when it opens); a pool made with sled's default 512 KiB ones, as every pool before, still
/// opens, takes an import, reads back and verifies, and keeps its segment size.
#[test]
fn a_new_pool_has_large_segments_and_an_older_one_keeps_its_own() {
    let scratch = tempfile::tempdir().unwrap();
    let source = bunny(scratch.path());

    let fresh = tempfile::tempdir().unwrap();
    let pool = Pool::open(fresh.path()).unwrap();
    assert_eq!(pool.segment_bytes(), arbor_server::pool::POOL_SEGMENT_BYTES);
    drop(pool);
    assert_eq!(
        segment_size_in_conf(fresh.path()),
        Some(arbor_server::pool::POOL_SEGMENT_BYTES)
    );

    let older = tempfile::tempdir().unwrap();
    drop(sled::open(older.path()).unwrap());
    assert_eq!(segment_size_in_conf(older.path()), Some(512 << 10));
    {
        let pool = open_when_unlocked(older.path()).unwrap();
        import(&pool, &source, scratch.path(), "old", false);
    }
    let pool = reopen(older.path());
    assert_eq!(pool.segment_bytes(), 512 << 10);
    let scene = pool.scene("old").unwrap();
    assert!(scene.nodes(arbor_proto::TreeletId(0)).unwrap().is_some());
    assert!(verify_scene(&scene).unwrap().is_ok());
    drop((scene, pool));
    assert_eq!(segment_size_in_conf(older.path()), Some(512 << 10));

    // A conf this build cannot read is left to sled, which refuses it (its checksum).
    let odd = tempfile::tempdir().unwrap();
    drop(sled::open(odd.path()).unwrap());
    let conf = std::fs::read(odd.path().join("conf")).unwrap();
    let text = String::from_utf8_lossy(&conf).replace("524288", "524287");
    std::fs::write(odd.path().join("conf"), text.as_bytes()).unwrap();
    let e = Pool::open(odd.path()).unwrap_err().to_string();
    assert!(e.contains("pool database"), "{e}");
}

fn nodes_tree(db: &sled::Db, g: u64) -> sled::Tree {
    db.open_tree(format!("g{g}:nodes")).unwrap()
}

/// A treelet's stored block, read from its pack.
fn stored_block(t: &sled::Tree, id: u32) -> Vec<u8> {
    let (key, slot) = pack::locate(TreeletId(id));
    let p = t.get(key).unwrap().expect("pack stored");
    pack::block(&p, slot)
        .unwrap()
        .expect("block stored")
        .to_vec()
}

/// Rewrites a treelet's block in its pack (empty: the treelet is absent).
fn store_block(t: &sled::Tree, id: u32, block: Vec<u8>) {
    let (key, slot) = pack::locate(TreeletId(id));
    let mut blocks = pack::blocks(&t.get(key).unwrap().expect("pack stored")).unwrap();
    blocks[slot] = block;
    t.insert(key, pack::encode(&blocks)).unwrap();
}

#[test]
fn verify_catches_garbage_blocks() {
    let p = damaged(|db, g, _| {
        store_block(&nodes_tree(db, g), 3, vec![0xAB; 40]);
    });
    assert!(p.iter().any(|p| p.starts_with("treelet 3:")), "{p:?}");
}

#[test]
fn verify_catches_missing_subtreelets() {
    let p = damaged(|db, g, d| {
        store_block(&nodes_tree(db, g), d.treelet_count - 1, Vec::new());
    });
    assert!(p.iter().any(|p| p.contains("does not exist")), "{p:?}");
}

#[test]
fn verify_catches_swapped_treelets() {
    let p = damaged(|db, g, _| {
        let t = nodes_tree(db, g);
        let (a, b) = (stored_block(&t, 5), stored_block(&t, 6));
        store_block(&t, 5, b);
        store_block(&t, 6, a);
    });
    assert!(p.iter().any(|p| p.contains("says it is")), "{p:?}");
}

#[test]
fn verify_catches_wrong_links_and_attributes() {
    // Re-encode treelet 1 claiming another parent leaf, with a valid encoding and dictionary.
    let p = damaged(|db, g, d| {
        let t = nodes_tree(db, g);
        let dict = d.node_dictionary.as_deref();
        let stored = stored_block(&t, 1);
        let mut tr = codec::decode_compressed_treelet(&stored, d.max_depth, dict).unwrap();
        tr.header.parent_leaf_index ^= 1;
        let packed = codec::compress(&codec::encode_treelet(&tr), 3, dict).unwrap();
        store_block(&t, 1, packed);
    });
    assert!(p.iter().any(|p| p.contains("header says parent")), "{p:?}");
    // Flip an inner node's normal in the root treelet.
    let p = damaged(|db, g, d| {
        let c = db.open_tree(format!("g{g}:ch:normal")).unwrap();
        let dict = d.channel_dictionary(Channel::Normal);
        let nodes = stored_block(&nodes_tree(db, g), 0);
        let tr =
            codec::decode_compressed_treelet(&nodes, d.max_depth, d.node_dictionary.as_deref())
                .unwrap();
        let stored = stored_block(&c, 0);
        let mut block = codec::decode_compressed_attributes(
            &stored,
            Channel::Normal,
            tr.header.used_nodes,
            dict,
        )
        .unwrap();
        block[0] ^= 0x80;
        block[1] ^= 0x80;
        store_block(&c, 0, codec::compress(&block, 3, dict).unwrap());
    });
    assert!(p.iter().any(|p| p.contains("is not the mean")), "{p:?}");
}

/// A refinable leaf made to name its neighbour's subtreelet: two leaves claim one subtreelet
/// and the neighbour's own is orphaned. Matching each subtreelet with the leaf its header names,
/// batch by batch, names the orphan, and the count of matched pairs names the leaf left over.
#[test]
fn verify_catches_a_subtreelet_claimed_by_two_leaves() {
    let orphan = std::cell::Cell::new(0);
    let p = damaged(|db, g, d| {
        let t = nodes_tree(db, g);
        let dict = d.node_dictionary.as_deref();
        let stored = stored_block(&t, 0);
        let (mut tr, places) =
            codec::decode_compressed_treelet_with_places(&stored, d.max_depth, dict).unwrap();
        let refinable: Vec<usize> = (0..places.len())
            .filter(|&i| places[i].is_leaf && tr.nodes[i].first_child != arbor_proto::Node::NONE)
            .collect();
        assert!(refinable.len() >= 2, "the root treelet refines two leaves");
        let (first, second) = (refinable[0], refinable[1]);
        orphan.set(tr.nodes[second].first_child);
        tr.nodes[second].first_child = tr.nodes[first].first_child;
        let packed = codec::compress(&codec::encode_treelet(&tr), 3, dict).unwrap();
        store_block(&t, 0, packed);
    });
    let orphan = format!("treelet {}:", orphan.get());
    assert!(
        p.iter()
            .any(|p| p.starts_with(&orphan) && p.contains("that leaf does not refer to it")),
        "the orphan is named: {p:?}"
    );
    assert!(
        p.iter()
            .any(|p| p.starts_with("1 of ") && p.contains("does not name them back")),
        "the leaf left over is counted: {p:?}"
    );
}

#[test]
fn an_unfinished_snapshot_left_by_a_killed_process_does_not_lock_the_pool_out() {
    let scratch = tempfile::tempdir().unwrap();
    let source = bunny(scratch.path());
    let dir = tempfile::tempdir().unwrap();
    {
        let pool = Pool::open(dir.path()).unwrap();
        import(&pool, &source, scratch.path(), "kept", false);
    }
    // What sled leaves when killed between writing a snapshot and renaming it: the newest
    // `snap.*` name, holding no whole snapshot.
    let unfinished = dir.path().join("snap.FFFFFFFFFFFFFFFF.generating");
    std::fs::write(&unfinished, b"cut").unwrap();
    let pool = reopen(dir.path());
    assert!(!unfinished.exists(), "the unfinished snapshot is removed");
    let names: Vec<String> = pool.scenes().unwrap().into_iter().map(|d| d.name).collect();
    assert_eq!(names, ["kept"]);
    assert!(verify_scene(&pool.scene("kept").unwrap()).unwrap().is_ok());
}

/// Every treelet's node and channel blocks of a scene, read one by one.
fn all_blocks(s: &arbor_server::pool::StoredScene) -> Vec<Vec<Option<Vec<u8>>>> {
    let channels = s.description.layout.channels().to_vec();
    (0..s.description.treelet_count)
        .map(|id| {
            let id = TreeletId(id);
            let mut blocks = vec![s.nodes(id).unwrap().map(|b| b.to_vec())];
            for &c in &channels {
                blocks.push(s.channel(c, id).unwrap().map(|b| b.to_vec()));
            }
            blocks
        })
        .collect()
}

/// `arbor-server copy`'s core: an older pool (sled's 512 KiB segments, a replaced scene's
/// space in its log, server state files beside it) is copied into a new directory with this
/// build's segments; every scene comes back block for block and verifies, the progress adds up
/// to the scenes' stored bytes, the files asked for go with it, and the source is left as it
/// was.
#[test]
fn an_older_pool_is_copied_whole_into_this_builds_layout() {
    use arbor_server::pool::copy::{CopyOptions, CopyProgress, copy_pool, partial_dir};
    use std::sync::atomic::{AtomicU64, Ordering};
    let scratch = tempfile::tempdir().unwrap();
    let bunny = bunny(scratch.path());
    // Each source's columns in a scratch directory of its own (they have the same names).
    let lion_scratch = tempfile::tempdir().unwrap();
    let lion = real_scan("points/lion_takanawa.copc.laz", lion_scratch.path());
    let root = tempfile::tempdir().unwrap();
    let older = root.path().join("older");
    drop(sled::open(&older).unwrap());
    {
        let pool = open_when_unlocked(&older).unwrap();
        import(&pool, &bunny, scratch.path(), "bunny", false);
        import(&pool, &bunny, scratch.path(), "bunny", true);
        let mut txn = pool.begin_import("lion", false).unwrap();
        let desc = build_scene(
            &lion,
            "lion",
            "lion",
            &opts(),
            lion_scratch.path(),
            &mut txn,
        );
        txn.commit(&desc.unwrap()).unwrap();
    }
    std::fs::write(older.join("admin-token"), "secret\n").unwrap();
    let carry = ["cert.pem", "admin-token"];

    let copy = root.path().join("copy");
    // A partial directory of a copy killed before is removed first.
    let partial = partial_dir(&copy).unwrap();
    std::fs::create_dir(&partial).unwrap();
    std::fs::write(partial.join("db"), "left by a killed copy").unwrap();

    let progress = AtomicU64::new(0);
    // Both pools opened again every 4 KiB: within every tree, so each resumes after its last
    // pack many times.
    let options = CopyOptions {
        scenes: &[],
        carry_files: &carry,
        reopen_after_bytes: 4096,
        stop: None,
    };
    let planned = AtomicU64::new(0);
    let report = copy_pool(&older, &copy, &options, &|p| match p {
        CopyProgress::Planned { bytes } => planned.store(bytes, Ordering::Relaxed),
        CopyProgress::Copied(n) => {
            assert_ne!(planned.load(Ordering::Relaxed), 0, "planned before copied");
            progress.fetch_add(n, Ordering::Relaxed);
        }
    })
    .unwrap();
    let packs: u64 = report.scenes.iter().map(|s| s.packs).sum();
    assert!(
        u64::from(report.reopens) > packs / 4,
        "{} reopenings for {packs} packs",
        report.reopens
    );
    let names: Vec<&str> = report.scenes.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(names, ["bunny", "lion"]);
    assert_eq!(report.carried, ["admin-token"]);
    assert!(report.source_disk_bytes > 0 && report.disk_bytes > 0);
    assert!(!partial.exists(), "the partial directory is renamed");
    assert_eq!(
        segment_size_in_conf(&copy),
        Some(arbor_server::pool::POOL_SEGMENT_BYTES)
    );
    assert_eq!(segment_size_in_conf(&older), Some(512 << 10));
    assert_eq!(
        std::fs::read_to_string(copy.join("admin-token")).unwrap(),
        "secret\n"
    );

    let source = reopen(&older);
    let copied = reopen(&copy);
    let mut stored = 0;
    for name in ["bunny", "lion"] {
        let (a, b) = (source.scene(name).unwrap(), copied.scene(name).unwrap());
        assert_eq!(a.description, b.description, "{name}");
        assert_ne!(a.generation, 0);
        let blocks = all_blocks(&b);
        assert_eq!(all_blocks(&a), blocks, "{name}");
        assert!(
            blocks.iter().all(|t| t.iter().all(Option::is_some)),
            "{name}: every treelet has every block"
        );
        assert!(verify_scene(&b).unwrap().is_ok(), "{name}");
        stored += b.description.stats.stored_bytes();
    }
    let lion_channels = copied
        .scene("lion")
        .unwrap()
        .description
        .layout
        .channels()
        .len();
    assert_eq!(lion_channels, 2, "colour and normal, each its own tree");
    assert_eq!(progress.into_inner(), stored);
    assert_eq!(planned.into_inner(), stored);
    assert_eq!(copied.stored_generations().len(), 2, "no leftovers copied");
    drop((copied, source));

    // The destination exists now: refused, and left alone.
    let e = copy_pool(&older, &copy, &options, &|_| {}).unwrap_err();
    assert!(e.to_string().contains("already exists"), "{e}");
    assert_eq!(
        std::fs::read_to_string(copy.join("admin-token")).unwrap(),
        "secret\n"
    );

    // Some scenes only; one that is not there fails before anything is written.
    let only_lion = root.path().join("lion-only");
    let options = CopyOptions {
        scenes: &["lion".to_owned(), "lion".to_owned()],
        ..CopyOptions::default()
    };
    copy_pool(&older, &only_lion, &options, &|_| {}).unwrap();
    let names: Vec<String> = reopen(&only_lion)
        .scenes()
        .unwrap()
        .into_iter()
        .map(|d| d.name)
        .collect();
    assert_eq!(names, ["lion"]);
    let nowhere = root.path().join("nowhere");
    let options = CopyOptions {
        scenes: &["lion".to_owned(), "puma".to_owned()],
        ..CopyOptions::default()
    };
    let e = copy_pool(&older, &nowhere, &options, &|_| {}).unwrap_err();
    assert!(e.to_string().contains("\"puma\""), "{e}");
    assert!(!nowhere.exists() && !partial_dir(&nowhere).unwrap().exists());
    let scenes = reopen(&older).scenes().unwrap();
    assert_eq!(scenes.len(), 2, "the source keeps its scenes");
}

/// A damaged source pack fails the copy naming it, leaving no pool at the destination; a copy
/// that differs from its source is named by the comparison the copy ends with.
/// A scene replaced or removed in the source between the copy's plan and its opening (another
/// process opened the pool meanwhile) fails the copy naming the scene; the copy makes no pool,
/// and leaves no tree in the source (before, the dropped trees were opened by name — made again,
/// empty — and the copy published the scene with no treelets, comparing equal to them).
#[test]
fn a_copy_names_a_scene_changed_between_its_openings() {
    use arbor_server::pool::copy::{CopyError, CopyOptions, CopyProgress, copy_pool, partial_dir};
    let scratch = tempfile::tempdir().unwrap();
    let source = bunny(scratch.path());
    let root = tempfile::tempdir().unwrap();
    let (src, copy) = (root.path().join("src"), root.path().join("copy"));
    import(
        &Pool::open(&src).unwrap(),
        &source,
        scratch.path(),
        "b",
        false,
    );
    for replace in [true, false] {
        let e = copy_pool(&src, &copy, &CopyOptions::default(), &|p| {
            if let CopyProgress::Planned { .. } = p {
                let pool = reopen(&src);
                if replace {
                    import(&pool, &source, scratch.path(), "b", true);
                } else {
                    pool.remove("b").unwrap();
                }
            }
        })
        .unwrap_err();
        assert!(
            matches!(e, CopyError::Pool(PoolError::ChangedWhileRead(ref n)) if n == "b"),
            "{e}"
        );
        assert!(!copy.exists() && !partial_dir(&copy).unwrap().exists());
        // The source's trees as they are on disk (a pool's opening would drop strays).
        let mut generations: Vec<String> = raw_sled(&src)
            .tree_names()
            .iter()
            .filter_map(|n| {
                let n = String::from_utf8_lossy(n);
                n.strip_prefix('g')?
                    .split_once(':')
                    .map(|(g, _)| g.to_owned())
            })
            .collect();
        generations.dedup();
        let pool = reopen(&src);
        if replace {
            let g = pool.scene("b").unwrap().generation;
            assert_eq!(generations, [g.to_string()], "no tree made again");
            assert!(verify_scene(&pool.scene("b").unwrap()).unwrap().is_ok());
        } else {
            assert!(
                generations.is_empty(),
                "no tree made again: {generations:?}"
            );
            import(&pool, &source, scratch.path(), "b", false);
        }
    }
}

#[test]
fn a_copy_never_carries_damage_or_differences_unnamed() {
    use arbor_server::pool::copy::{CopyOptions, compare_scene, copy_pool, partial_dir};
    let scratch = tempfile::tempdir().unwrap();
    let source = bunny(scratch.path());
    let root = tempfile::tempdir().unwrap();
    let (src, copy) = (root.path().join("src"), root.path().join("copy"));
    let generation = {
        let pool = Pool::open(&src).unwrap();
        import(&pool, &source, scratch.path(), "b", false);
        pool.scene("b").unwrap().generation
    };
    let options = CopyOptions::default();
    let no_pool = root.path().join("no-pool");
    let e = copy_pool(&no_pool, &copy, &options, &|_| {}).unwrap_err();
    assert!(e.to_string().contains("is not a pool directory"), "{e}");
    assert!(!no_pool.exists() && !copy.exists());
    copy_pool(&src, &copy, &options, &|_| {}).unwrap();

    // The copy altered behind the pool's back: one pack's bytes, then one pack gone.
    let copied_generation = reopen(&copy).scene("b").unwrap().generation;
    for (damage, expected) in [
        (0u32, "nodes: pack [0, 0, 0, 2] differs"),
        (1, "nodes: pack [0, 0, 0, 1] missing in the copy"),
        (2, "nodes: pack [0, 0, 0, 0] missing in the copy"),
    ] {
        {
            let db = raw_sled(&copy);
            let t = nodes_tree(&db, copied_generation);
            match damage {
                0 => store_block(&t, 32, vec![1, 2, 3]),
                n => drop(t.remove((2 - n).to_be_bytes()).unwrap()),
            }
            db.flush().unwrap();
        }
        let (a, b) = (reopen(&src), reopen(&copy));
        let e = compare_scene(&a.scene("b").unwrap(), &b.scene("b").unwrap()).unwrap_err();
        assert!(e.to_string().contains(expected), "{e}");
        assert!(e.to_string().contains("scene \"b\""), "{e}");
    }

    // A source pack whose table does not match its length.
    {
        let db = raw_sled(&src);
        nodes_tree(&db, generation)
            .insert(1u32.to_be_bytes(), vec![3, 0, 9])
            .unwrap();
        db.flush().unwrap();
    }
    let again = root.path().join("again");
    let e = copy_pool(&src, &again, &options, &|_| {}).unwrap_err();
    let text = format!("{:#}", anyhow::Error::from(e));
    assert!(
        text.contains("nodes pack [0, 0, 0, 1] of scene \"b\""),
        "{text}"
    );
    assert!(!again.exists() && !partial_dir(&again).unwrap().exists());
}

/// The daemon's live copy reads a pool this process keeps open, by a `get` per pack: every
/// scene comes back pack for pack (a pack missing from the middle of a source tree is missing
/// in the copy too, and the compare agrees), resuming after its last pack at every reopening of
/// the copy; the state files come from the directory given. A copy asked to stop — open source
/// or closed — fails `Cancelled` and leaves neither the destination nor its partial directory;
/// one without room on the destination's file system is refused before anything is written.
#[test]
fn a_served_pool_is_copied_by_get_and_a_copy_stops_when_asked() {
    use arbor_server::pool::copy::{
        CopyError, CopyOptions, CopyProgress, compare_scene, copy_pool, copy_served, partial_dir,
    };
    use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
    let scratch = tempfile::tempdir().unwrap();
    let source = bunny(scratch.path());
    let root = tempfile::tempdir().unwrap();
    let (src, state) = (root.path().join("src"), root.path().join("state"));
    std::fs::create_dir(&state).unwrap();
    std::fs::write(state.join("cert.pem"), "the daemon's certificate").unwrap();
    let pool = Pool::open(&src).unwrap();
    for name in ["b", "c"] {
        import(&pool, &source, scratch.path(), name, false);
    }
    // A hole in the middle of b's node packs.
    let gap = 1u32.to_be_bytes();
    {
        let b = pool.scene("b").unwrap();
        let nodes = b.trees()[0].1;
        assert!(nodes.len() > 2, "b needs three node packs");
        nodes.remove(gap).unwrap().expect("pack 1 stored");
    }

    let copy = root.path().join("copy");
    let (planned, copied) = (AtomicU64::new(0), AtomicU64::new(0));
    let pace = std::sync::Arc::new(arbor_server::pace::ReadPace::new(None));
    let options = CopyOptions {
        carry_files: &["cert.pem", "admin-token"],
        reopen_after_bytes: 4096,
        ..CopyOptions::default()
    };
    let never = std::sync::Arc::new(AtomicBool::new(false));
    let paced = scenes_of(&pool)
        .into_iter()
        .map(|s| s.paced(pace.clone(), never.clone()))
        .collect();
    let report = copy_served(&pool, paced, &state, &copy, &options, &|p| match p {
        CopyProgress::Planned { bytes } => planned.store(bytes, Ordering::Relaxed),
        CopyProgress::Copied(n) => drop(copied.fetch_add(n, Ordering::Relaxed)),
    })
    .unwrap();
    assert!(report.reopens > 4, "{} reopenings", report.reopens);
    assert_eq!(report.carried, ["cert.pem"]);
    // Every source pack was read through the pace twice: copied, then compared.
    let source_bytes: u64 = scenes_of(&pool)
        .iter()
        .flat_map(|s| {
            s.trees()
                .into_iter()
                .map(|(_, t)| t.clone())
                .collect::<Vec<_>>()
        })
        .flat_map(|t| {
            t.iter()
                .map(|e| e.unwrap().1.len() as u64)
                .collect::<Vec<_>>()
        })
        .sum();
    assert_eq!(pace.figures().read_bytes, 2 * source_bytes);
    assert!(!partial_dir(&copy).unwrap().exists());
    assert_eq!(
        std::fs::read(copy.join("cert.pem")).unwrap(),
        b"the daemon's certificate"
    );
    {
        let copied_pool = reopen(&copy);
        for name in ["b", "c"] {
            let (a, b) = (pool.scene(name).unwrap(), copied_pool.scene(name).unwrap());
            compare_scene(&a, &b).unwrap();
        }
        let b = copied_pool.scene("b").unwrap();
        assert!(b.trees()[0].1.get(gap).unwrap().is_none(), "hole filled");
        assert!(b.trees()[0].1.get(2u32.to_be_bytes()).unwrap().is_some());
    }
    let stored: u64 = scenes_of(&pool)
        .iter()
        .map(|s| s.description.stats.stored_bytes())
        .sum();
    assert_eq!(planned.load(Ordering::Relaxed), stored);
    assert!(copied.load(Ordering::Relaxed) > 0);
    assert!(
        copied.load(Ordering::Relaxed) <= stored,
        "the hole's blocks are not counted"
    );

    // Stopped after the first pack: nothing left, from an open source or a closed one.
    let stop = AtomicBool::new(false);
    let stopping = CopyOptions {
        stop: Some(&stop),
        ..CopyOptions::default()
    };
    let halted = root.path().join("halted");
    let on_copied = |p| {
        if let CopyProgress::Copied(_) = p {
            stop.store(true, Ordering::Release);
        }
    };
    let e = copy_served(
        &pool,
        scenes_of(&pool),
        &state,
        &halted,
        &stopping,
        &on_copied,
    )
    .unwrap_err();
    assert!(matches!(e, CopyError::Cancelled), "{e}");
    assert!(!halted.exists() && !partial_dir(&halted).unwrap().exists());
    drop(pool);
    stop.store(false, Ordering::Release);
    let e = copy_pool(&src, &halted, &stopping, &on_copied).unwrap_err();
    assert!(matches!(e, CopyError::Cancelled), "{e}");
    assert!(!halted.exists() && !partial_dir(&halted).unwrap().exists());
    // An existing destination is refused before anything is read.
    let pool = reopen(&src);
    let e = copy_served(&pool, scenes_of(&pool), &state, &copy, &options, &|_| {}).unwrap_err();
    assert!(matches!(e, CopyError::DestinationExists(_)), "{e}");
    // A copy the destination's file system has no room for is refused before it writes: the
    // pool made to look 8 TiB on disk (a sparse file where sled counts its blobs' sizes).
    let huge = std::fs::File::create(src.join("blobs").join("sparse-for-the-test")).unwrap();
    huge.set_len(8 << 40).unwrap();
    let roomless = root.path().join("roomless");
    let planned = AtomicBool::new(false);
    let e = copy_served(
        &pool,
        scenes_of(&pool),
        &state,
        &roomless,
        &options,
        &|_| planned.store(true, Ordering::Relaxed),
    )
    .unwrap_err();
    match &e {
        CopyError::NoRoom { free, need, .. } => assert!(need > free, "{e}"),
        other => panic!("not NoRoom: {other}"),
    }
    assert!(e.to_string().contains("bytes free"), "{e}");
    assert!(
        !planned.load(Ordering::Relaxed),
        "progress before the room was checked"
    );
    assert!(!roomless.exists() && !partial_dir(&roomless).unwrap().exists());
}

fn scenes_of(pool: &Pool) -> Vec<arbor_server::pool::StoredScene> {
    ["b", "c"].iter().map(|n| pool.scene(n).unwrap()).collect()
}
