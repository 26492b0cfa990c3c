//! The QUIC treelet service over loopback with a real bunny pool and a raw quinn client:
//! exact delivery byte for byte, hostile clients ending only their own connection with the
//! matching close code while a well-behaved client keeps its rate, the connection cap, and
//! graceful shutdown.

mod common;

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use arbor_proto::frame::{self, decode_treelet_message};
use arbor_proto::limits::{MAX_FRAME_BYTES, MAX_REQUEST_ITEMS};
use arbor_proto::wire::{ErrorCode, Frame, HELLO_SEND_ROOT, HELLO_VIEW, ViewHint};
use arbor_proto::{Channel, TreeletId, codec};
use arbor_server::service::schedule::batch_limit;
use arbor_server::service::shapes::ShapeCache;
use arbor_server::service::treelets::{
    MAX_CHUNKS_PER_STREAM, MAX_TREELETS_PER_STREAM, MessageCache,
};
use common::*;

const LONG: Duration = Duration::from_secs(10);

/// Median of a few full rounds of the well-behaved client (fresh list each time, past the
/// redelivery guard).
async fn rounds(
    good: &Client,
    control: &mut Control,
    seq: &mut u64,
    ids: &[TreeletId],
    n: usize,
) -> Duration {
    let mut t = Vec::new();
    for _ in 0..n {
        tokio::time::sleep(Duration::from_millis(150)).await;
        *seq += 1;
        t.push(round(good, control, *seq, ids).await.unwrap());
    }
    t.sort();
    t[t.len() / 2]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_list_arrives_exactly_and_byte_identical_to_the_pool() {
    let tp = TestPool::new();
    let t0 = Instant::now();
    let server = start(tp.config()).await;
    let started = t0.elapsed();
    let stored = server.pool().scene(SCENE).unwrap();
    let d = stored.description.clone();
    assert_eq!(server.fingerprint.len(), 64);

    let t0 = Instant::now();
    let client = connect(server.quic_addr, &server.fingerprint).await;
    let handshake = t0.elapsed();
    let (mut control, info) = hello(&client.conn, SCENE, &[Channel::Normal], TOKEN).await;
    let hello_done = t0.elapsed();
    assert_eq!(info.unwrap(), d, "SceneInfo is the stored description");

    // A list of N treelets, shuffled priorities, with a duplicate: exactly N distinct arrive.
    let n = (d.treelet_count as usize).min(200);
    assert!(
        n >= 20,
        "the bunny at depth 6 has {} treelets",
        d.treelet_count
    );
    let mut items: Vec<(TreeletId, f32)> = (0..n as u32)
        .map(|i| (TreeletId(i), ((i * 7919) % 1000) as f32))
        .collect();
    items.push((TreeletId(3), -5.0));
    let t1 = Instant::now();
    control.send(&Frame::RequestList { seq: 1, items }).await;
    let got = receive(&client.conn, n, LONG).await.unwrap();
    let elapsed = t1.elapsed();
    let mut ids: Vec<u32> = got.iter().map(|(t, _)| t.0).collect();
    ids.sort_unstable();
    assert_eq!(ids, (0..n as u32).collect::<Vec<_>>());
    // Nothing else comes.
    assert!(
        tokio::time::timeout(Duration::from_millis(300), client.conn.accept_uni())
            .await
            .is_err(),
        "an extra stream arrived"
    );
    let dict = d.node_dictionary.as_deref();
    for (id, bytes) in &got {
        let m = decode_treelet_message(bytes).unwrap();
        assert_eq!(
            m.nodes,
            &stored.nodes(*id).unwrap().unwrap()[..],
            "node block of {id:?}"
        );
        assert_eq!(m.channels.len(), 1);
        assert_eq!(m.channels[0].0, Channel::Normal);
        assert_eq!(
            m.channels[0].1,
            &stored.channel(Channel::Normal, *id).unwrap().unwrap()[..]
        );
        let t = codec::decode_compressed_treelet(m.nodes, d.max_depth, dict).unwrap();
        assert_eq!(t.header.id, *id);
        assert_eq!(m.used_nodes, t.header.used_nodes);
    }
    let bytes: usize = got.iter().map(|g| g.1.len()).sum();
    eprintln!(
        "start {started:?}; handshake {handshake:?}; hello→SceneInfo {:?}; {n} treelets ({bytes} B) in {elapsed:?}: {:.0} treelets/s",
        hello_done - handshake,
        n as f64 / elapsed.as_secs_f64()
    );

    // The session shows up with its counters; the metrics count what was sent.
    let s = server.state.sessions();
    assert_eq!(s.len(), 1);
    assert_eq!(s[0].scene, SCENE);
    assert_eq!(s[0].channels, vec!["normal"]);
    assert_eq!(s[0].request_lists, 1);
    assert_eq!(s[0].treelets_sent, n as u64);
    assert_eq!(s[0].bytes_sent, bytes as u64);
    let m = &server.state.metrics;
    assert_eq!(m.treelets_sent.load(Ordering::Relaxed), n as u64);
    assert_eq!(m.treelet_bytes_sent.load(Ordering::Relaxed), bytes as u64);
    // Batched: a few treelets per stream, at most the most a stream carries.
    let streams = m.treelet_streams.load(Ordering::Relaxed);
    assert!(
        streams >= n.div_ceil(MAX_TREELETS_PER_STREAM) as u64 && streams < n as u64,
        "{n} treelets on {streams} streams"
    );
    assert_eq!(m.request_lists.load(Ordering::Relaxed), 1);
    assert_eq!(m.request_items.load(Ordering::Relaxed), n as u64 + 1);
    assert_eq!(m.request_to_send.count(), n as u64);

    // A client asking for no channels receives node blocks only.
    let bare = connect(server.quic_addr, &server.fingerprint).await;
    let (mut c2, info) = hello(&bare.conn, SCENE, &[], TOKEN).await;
    info.unwrap();
    c2.send(&Frame::RequestList {
        seq: 7,
        items: vec![(TreeletId(0), 1.0), (TreeletId(1), 0.5)],
    })
    .await;
    for (id, bytes) in receive(&bare.conn, 2, LONG).await.unwrap() {
        let m = decode_treelet_message(&bytes).unwrap();
        assert!(m.channels.is_empty());
        assert_eq!(m.nodes, &stored.nodes(id).unwrap().unwrap()[..]);
    }

    // A replacement list takes effect: the new treelets arrive.
    tokio::time::sleep(Duration::from_millis(150)).await;
    let fresh: Vec<TreeletId> = (n as u32..d.treelet_count.min(n as u32 + 10))
        .map(TreeletId)
        .collect();
    if !fresh.is_empty() {
        round(&client, &mut control, 2, &fresh).await.unwrap();
    }
    server.shutdown().await;
}

/// A `Hello` with a view (eye in root-cube units) gets the root and the view's refinement
/// below it before any list, exactly as many as the free slots it announced; the same `Hello`
/// without the view gets the root alone.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hello_view_pushes_the_roots_refinement_within_its_free_slots() {
    let tp = TestPool::new();
    let server = start(tp.config()).await;
    let d = server.pool().scene(SCENE).unwrap().description;
    let view = in_front_of_the_cube();
    let greet = |view: Option<ViewHint>| {
        let flags = HELLO_SEND_ROOT | if view.is_some() { HELLO_VIEW } else { 0 };
        hello_frame_with(SCENE, &[Channel::Normal], TOKEN, flags, view)
    };
    for (view, expected) in [(Some(view), 24), (None, 1)] {
        let c = connect(server.quic_addr, &server.fingerprint).await;
        let mut control = Control::open(&c.conn).await;
        control.send(&greet(view)).await;
        assert!(matches!(
            control.read().await,
            Some(Frame::SceneInfo { .. })
        ));
        let got = receive(&c.conn, expected, LONG).await.unwrap();
        assert!(got.iter().any(|(id, _)| *id == d.root_treelet));
        let mut ids: Vec<TreeletId> = got.iter().map(|(id, _)| *id).collect();
        ids.sort_unstable();
        ids.dedup();
        assert_eq!(ids.len(), expected, "{view:?}");
        // Nothing beyond the free slots follows.
        let more = receive(&c.conn, 1, Duration::from_millis(300)).await;
        assert!(more.is_err(), "{view:?}: more than announced: {more:?}");
        c.conn.close(0u32.into(), b"done");
    }
    assert_eq!(
        server.state.metrics.pushes_planned.load(Ordering::Relaxed),
        23
    );
    // Nothing was cached: the first plan and every batch were read by the pool's readers,
    // and none is left waiting.
    let reads = &server.state.metrics.pool_reads;
    assert!(reads.run.load(Ordering::Relaxed) >= 2);
    assert_eq!(reads.waiting.load(Ordering::Relaxed), 0);
    server.shutdown().await;
}

/// While the view rests, the plan goes on below what was already sent for it: a list that
/// names none of the treelets the Hello's plan sent (a client stops listing what is on its way)
/// still gets the refinement below them, within its free slots and never a second copy; the
/// same kind of list from another view gets only what it names.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resting_view_is_pushed_on_below_what_was_sent_for_it() {
    use std::collections::HashSet;
    let tp = TestPool::new();
    let server = start(tp.config()).await;
    let d = server.pool().scene(SCENE).unwrap().description;
    let view = in_front_of_the_cube();
    let (c, mut control) = hello_with_root_and_view(&server, view).await;
    assert!(matches!(
        control.read().await,
        Some(Frame::SceneInfo { .. })
    ));
    let sent: HashSet<TreeletId> = receive(&c.conn, 24, LONG)
        .await
        .unwrap()
        .into_iter()
        .map(|(id, _)| id)
        .collect();
    assert_eq!(sent.len(), 24);
    // Lists carry the eye in the scene's world, Hello in root-cube units.
    let world = ViewHint {
        eye: std::array::from_fn(|i| d.origin[i] + view.eye[i] * d.edge),
        ..view
    };
    let unsent = |skip: &HashSet<TreeletId>| {
        (0..d.treelet_count)
            .rev()
            .map(TreeletId)
            .find(|id| !skip.contains(id))
            .unwrap()
    };
    // One treelet elsewhere, with no error of its own: nothing to push below it.
    let other = unsent(&sent);
    let pushes = 20;
    control
        .send(&Frame::DeepRequestList {
            seq: 1,
            view: ViewHint {
                free_slots: 1 + pushes,
                ..world
            },
            items: vec![(other, 1.0, 0.0)],
            prefetch_from: 1,
        })
        .await;
    let more: HashSet<TreeletId> = receive(&c.conn, 1 + pushes as usize, LONG)
        .await
        .unwrap()
        .into_iter()
        .map(|(id, _)| id)
        .collect();
    assert_eq!(more.len(), 1 + pushes as usize, "distinct");
    assert!(more.contains(&other));
    assert!(more.is_disjoint(&sent), "nothing sent twice");
    let beyond = receive(&c.conn, 1, Duration::from_millis(300)).await;
    assert!(beyond.is_err(), "more than announced: {beyond:?}");

    // Another view: what was sent for the first one implies nothing.
    let all: HashSet<TreeletId> = sent.union(&more).copied().collect();
    let another = unsent(&all);
    let mut moved = world;
    moved.eye[0] += 0.01 * d.edge;
    control
        .send(&Frame::DeepRequestList {
            seq: 2,
            view: ViewHint {
                free_slots: 1 + pushes,
                ..moved
            },
            items: vec![(another, 1.0, 0.0)],
            prefetch_from: 1,
        })
        .await;
    let got = receive(&c.conn, 1, LONG).await.unwrap();
    assert_eq!(got[0].0, another);
    let beyond = receive(&c.conn, 1, Duration::from_millis(300)).await;
    assert!(
        beyond.is_err(),
        "pushed below another view's treelets: {beyond:?}"
    );
    c.conn.close(0u32.into(), b"done");
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_timeline_records_what_was_listed_pushed_sent_and_acknowledged() {
    use arbor_server::service::timeline::{Breakdown, Event, NamedBy};
    use std::collections::HashSet;
    let tp = TestPool::new();
    let server = start(tp.config()).await;
    let d = server.pool().scene(SCENE).unwrap().description;
    let view = in_front_of_the_cube();
    let timeline = &server.state.timeline;
    timeline.start();
    let start = Instant::now();
    let (c, _control) = hello_with_root_and_view(&server, view).await;
    let got = receive(&c.conn, 24, LONG).await.unwrap();
    let received: HashSet<TreeletId> = got.iter().map(|(id, _)| *id).collect();
    // A batch ends (acknowledged) at the server a little after its last byte arrived here.
    let delivered = |events: &[Event]| -> HashSet<TreeletId> {
        events
            .iter()
            .filter_map(|e| match e {
                Event::Ended {
                    batch,
                    delivered: true,
                    ..
                } => Some(batch.clone()),
                _ => None,
            })
            .flatten()
            .collect()
    };
    let deadline = Instant::now() + LONG;
    while delivered(&timeline.snapshot().events) != received && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let recording = timeline.take();
    assert!(!recording.truncated);
    let lists: Vec<(&Vec<TreeletId>, &Vec<TreeletId>)> = recording
        .events
        .iter()
        .filter_map(|e| match e {
            Event::Listed { listed, pushed, .. } => Some((listed, pushed)),
            _ => None,
        })
        .collect();
    // The shape cache was empty: the Hello's list went as listed while a reader planned its
    // pushes, and then again with them.
    assert_eq!(lists.len(), 2, "the Hello's list, then with its pushes");
    assert_eq!(
        server
            .state
            .metrics
            .plans_on_readers
            .load(Ordering::Relaxed),
        1
    );
    for (listed, _) in &lists {
        assert_eq!(*listed, &vec![d.root_treelet]);
    }
    assert!(lists[0].1.is_empty());
    assert_eq!(lists[1].1.len(), 23);
    let dispatched: HashSet<TreeletId> = recording
        .events
        .iter()
        .filter_map(|e| match e {
            Event::Dispatched { batch, .. } => Some(batch.clone()),
            _ => None,
        })
        .flatten()
        .collect();
    assert_eq!(dispatched, received);
    assert_eq!(delivered(&recording.events), received);
    let session = match recording.events[0] {
        Event::Listed { session, .. } => session,
        ref e => panic!("the first event is the list, not {e:?}"),
    };
    let b = Breakdown::of(&recording, session, start, &received, |_| 10);
    assert_eq!(b.needed_missing, 0);
    assert_eq!(b.before_last[&(NamedBy::List, true)], (1, 10));
    assert_eq!(b.before_last[&(NamedBy::Push, true)], (23, 230));
    let (_, m) = b.last_needed.unwrap();
    let (named, sent, acked) = (m.named.unwrap().0, m.sent.unwrap(), m.delivered.unwrap());
    assert!(named <= sent && sent <= acked, "{m:?}");
    c.conn.close(0u32.into(), b"done");
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resting_view_gets_its_visible_cut_pushed_in_place_of_the_frustum_plan() {
    use std::collections::HashSet;
    let tp = TestPool::new();
    let Cutting {
        server, view, cut, ..
    } = cutting(&tp).await;
    assert!(cut.complete);
    let expected: HashSet<TreeletId> = cut.treelets.iter().map(|&(_, id)| id).collect();
    assert!(
        expected.len() > 4,
        "the view needs several treelets below the root"
    );

    // A first client fills the shape cache, so that the Hello's frustum plan below is made at
    // once, not on a reader (which would deliver the whole view before the cut came).
    {
        let (warm, _control) = hello_with_root_and_view(&server, view).await;
        let m = &server.state.metrics;
        wait_for("the first client's plan and cut", || {
            m.pushes_planned.load(Ordering::Relaxed) > 0
                && m.visible_cuts.load(Ordering::Relaxed) > 0
        })
        .await;
        warm.conn.close(0u32.into(), b"done");
    }
    // Only the second client's lists count: the first one's re-plan with its cut may land in
    // the timeline after it starts. Under load the second's own plan may also be made on a
    // reader and come as a list of its own before the cut: waited for are the second cut and
    // a list after Hello's whose pushes are all the cut's.
    let earlier: HashSet<u64> = server.state.sessions().iter().map(|s| s.id).collect();
    let timeline = &server.state.timeline;
    timeline.start();
    let (c, _control) = hello_with_root_and_view(&server, view).await;
    let cuts = &server.state.metrics.visible_cuts;
    let deadline = Instant::now() + LONG;
    loop {
        let lists = pushes_per_list(timeline, |session| !earlier.contains(&session));
        let counted = cuts.load(Ordering::Relaxed);
        // The re-plan pushes what of the cut the frustum plan has not sent: often nothing.
        let replanned = lists
            .last()
            .filter(|_| lists.len() >= 2)
            .is_some_and(|l| l.iter().all(|id| expected.contains(id)));
        if counted >= 2 && replanned {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "no list re-planned with the cut: {counted} cuts counted, pushes per list {:?}",
            lists.iter().map(Vec::len).collect::<Vec<_>>()
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    // Everything the cut names arrives: pushed now, or sent under the frustum plan before.
    receive_all_of(&c, &expected).await;
    c.conn.close(0u32.into(), b"done");
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn prefetch_the_cut_does_not_hold_is_set_apart_and_still_arrives() {
    use std::collections::HashSet;
    let tp = TestPool::new();
    let Cutting {
        server,
        view,
        world,
        cut,
        treelet_count,
    } = cutting(&tp).await;
    let in_cut: HashSet<TreeletId> = cut.treelets.iter().map(|&(_, id)| id).collect();
    // Prefetch the cut does not hold, after one listed item the cut holds.
    let outside: Vec<TreeletId> = (1..treelet_count)
        .map(TreeletId)
        .filter(|id| !in_cut.contains(id))
        .take(6)
        .collect();
    assert_eq!(
        outside.len(),
        6,
        "the scene has treelets the view does not need"
    );
    let first = cut.treelets[0].1;
    let mut items = vec![(first, 10.0, 1.0)];
    items.extend(outside.iter().map(|&id| (id, 1.0, 0.0)));
    let (c, mut control) = hello_with_root_and_view(&server, view).await;
    // The same view as Hello's: resting, so its cut answers this list (at once, or when it is
    // ready and the list is planned again).
    control
        .send(&Frame::DeepRequestList {
            seq: 1,
            view: world,
            items,
            prefetch_from: 1,
        })
        .await;
    let set_apart = &server.state.metrics.prefetch_set_apart;
    wait_for("the prefetch set apart", || {
        set_apart.load(Ordering::Relaxed) >= outside.len() as u64
    })
    .await;
    // Set apart, not dropped: it arrives after the cut.
    let mut wanted: HashSet<TreeletId> = outside.iter().copied().collect();
    wanted.insert(first);
    receive_all_of(&c, &wanted).await;
    c.conn.close(0u32.into(), b"done");
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scene_whose_fine_cuts_go_unused_skips_them_and_keeps_its_coarse_cuts() {
    use arbor_server::service::push::{WorldCube, plan_pushes};
    use arbor_server::service::treelets::ServedScene;
    use arbor_server::service::visibility::FINE_CUTS_WASTED_BEFORE_SKIPPING;
    let tp = TestPool::new();
    const FINE: u32 = 4 * CUT_GRID;
    // A share that follows the coarse cut of the view and no cut larger than it: every fine
    // cut is cast from a followed coarse cut and wasted.
    let (view, share) = {
        let Cutting {
            server,
            view,
            world,
            cut: coarse,
            ..
        } = cutting(&tp).await;
        let stored = server.pool().scene(SCENE).unwrap();
        let served = ServedScene::new(stored.clone());
        let d = &stored.description;
        let fine = served
            .visible_cut(&world, FINE, &[], 1 << 26, |_| true)
            .unwrap();
        let (c, f) = (coarse.treelets.len(), fine.treelets.len());
        assert!(
            coarse.complete && fine.complete && f > c,
            "{c} then {f} treelets"
        );
        let root = [(d.root_treelet, f32::MAX, ViewHint::MAX_ERROR)];
        let frustum = plan_pushes(WorldCube::of(d), &world, &root, usize::MAX, |id| {
            served.shape(id)
        })
        .len();
        assert!(frustum > c, "{frustum} in the frustum plan");
        server.shutdown().await;
        (view, (c as f64 + 0.5) / frustum as f64)
    };
    let server = start(with_cuts(&tp, FINE, share)).await;
    let metrics = &server.state.metrics;
    // Clients one after another, each closed before the next (the scene's served state goes
    // with the last connection holding it; what the service learned of the scene stays): each
    // rests on the view, gets its coarse cut and then a fine one, until enough were wasted.
    let per_view = 2u64;
    for k in 1..=u64::from(FINE_CUTS_WASTED_BEFORE_SKIPPING) {
        let (c, _control) = hello_with_root_and_view(&server, view).await;
        let cuts = &metrics.visible_cuts;
        wait_for(&format!("cut {}", per_view * k), || {
            cuts.load(Ordering::Relaxed) >= per_view * k
        })
        .await;
        c.conn.close(0u32.into(), b"done");
        let open = &metrics.connections_open;
        wait_for("the connection's end", || open.load(Ordering::Relaxed) == 0).await;
    }
    // The next client's view gets its coarse cut only.
    let (c, _control) = hello_with_root_and_view(&server, view).await;
    let skipped = &metrics.fine_cuts_skipped;
    wait_for("a skipped fine cut", || {
        skipped.load(Ordering::Relaxed) == 1
    })
    .await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    let cast = u64::from(FINE_CUTS_WASTED_BEFORE_SKIPPING) * per_view + 1;
    assert_eq!(metrics.visible_cuts.load(Ordering::Relaxed), cast);
    assert_eq!(
        skipped.load(Ordering::Relaxed),
        1,
        "skipped once for the view, not once per list"
    );
    c.conn.close(0u32.into(), b"done");
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resting_list_that_fills_every_free_slot_itself_gets_no_cut_until_one_has_room() {
    let tp = TestPool::new();
    let setup = cutting(&tp).await;
    let (server, view, world) = (&setup.server, setup.view, setup.world);
    let metrics = &server.state.metrics;
    let (cuts, idle) = (&metrics.visible_cuts, &metrics.cuts_without_work);
    // Hello names the root and announces one free slot: the root takes it, nothing is left to
    // push and there is no prefetch, so its view, resting by definition, gets no cut.
    let full = ViewHint {
        free_slots: 1,
        ..view
    };
    let (c, mut control) = hello_with_root_and_view(server, full).await;
    wait_for("Hello's list counted without work", || {
        idle.load(Ordering::Relaxed) == 1
    })
    .await;
    // The same view again, a budget-bound client's list: as many items as free slots.
    let listed: Vec<(TreeletId, f32, f32)> = setup.cut.treelets[..2]
        .iter()
        .map(|&(_, id)| (id, 10.0, 1.0))
        .collect();
    let send = |seq: u64, free_slots: u32, prefetch_from: u32| Frame::DeepRequestList {
        seq,
        view: ViewHint {
            free_slots,
            ..world
        },
        items: listed.clone(),
        prefetch_from,
    };
    control.send(&send(1, 2, 2)).await;
    wait_for("the second list counted without work", || {
        idle.load(Ordering::Relaxed) == 2
    })
    .await;
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert_eq!(
        cuts.load(Ordering::Relaxed),
        0,
        "no cut for lists without room"
    );
    // Still no room, but prefetch for a cut to set apart: cast.
    control.send(&send(2, 2, 1)).await;
    wait_for("a cut for prefetch to set apart", || {
        cuts.load(Ordering::Relaxed) == 1
    })
    .await;
    assert_eq!(idle.load(Ordering::Relaxed), 2);
    c.conn.close(0u32.into(), b"done");
    // A new client of the same view with room beyond its list gets its cut.
    let (c, _control) = hello_with_root_and_view(server, view).await;
    wait_for("a cut for a list with room", || {
        cuts.load(Ordering::Relaxed) == 2
    })
    .await;
    assert_eq!(idle.load(Ordering::Relaxed), 2);
    c.conn.close(0u32.into(), b"done");
    setup.server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cut_that_saves_too_little_leaves_the_frustum_plan_in_place() {
    use std::collections::HashSet;
    let tp = TestPool::new();
    // No cut of a view that sees several treelets holds a millionth of its frustum plan.
    let server = start(with_cuts(&tp, 2 * CUT_GRID, 1e-6)).await;
    let view = ViewHint {
        free_slots: 4096,
        ..in_front_of_the_cube()
    };
    let timeline = &server.state.timeline;
    timeline.start();
    let (c, _control) = hello_with_root_and_view(&server, view).await;
    let cuts = &server.state.metrics.visible_cuts;
    wait_for("a visible cut", || cuts.load(Ordering::Relaxed) > 0).await;
    // A followed cut re-plans the list in the same step that counts it; give it ample time.
    tokio::time::sleep(Duration::from_millis(200)).await;
    let lists = pushes_per_list(timeline, |_| true);
    assert_eq!(
        lists.len(),
        2,
        "only Hello's list, then with the pushes a reader planned (the shape cache was empty): \
         the cut was not followed"
    );
    assert!(lists[0].is_empty());
    let lists = &lists[1..];
    assert!(lists[0].len() > 4, "Hello's frustum plan pushes the view");
    assert_eq!(
        cuts.load(Ordering::Relaxed),
        1,
        "no finer cut is cast for a view whose cut is not followed"
    );
    // The frustum plan's pushes all arrive.
    let planned: HashSet<TreeletId> = lists[0].iter().copied().collect();
    receive_all_of(&c, &planned).await;
    c.conn.close(0u32.into(), b"done");
    server.shutdown().await;
}

/// A server following every cut (however much of the frustum plan it holds; no finer cut), a
/// view in front of the cube (root-cube units, as `Hello` takes it, and in the world), and the
/// cut the server should find for it, cast here through the same pool.
struct Cutting {
    server: arbor_server::daemon::RunningServer,
    view: ViewHint,
    world: ViewHint,
    cut: arbor_server::service::visibility::VisibleCut,
    treelet_count: u32,
}

async fn cutting(tp: &TestPool) -> Cutting {
    use arbor_server::service::treelets::ServedScene;
    let config = with_cuts(tp, 0, 1.0);
    let budget = config.visibility_cache_bytes;
    let server = start(config).await;
    let stored = server.pool().scene(SCENE).unwrap();
    let d = stored.description.clone();
    let view = ViewHint {
        free_slots: 4096,
        ..in_front_of_the_cube()
    };
    let world = ViewHint {
        eye: std::array::from_fn(|i| d.origin[i] + view.eye[i] * d.edge),
        ..view
    };
    let cut = ServedScene::new(stored)
        .visible_cut(&world, CUT_GRID, &[], budget, |_| true)
        .unwrap();
    Cutting {
        server,
        view,
        world,
        cut,
        treelet_count: d.treelet_count,
    }
}

/// Waits until `ok` holds, at most [`LONG`]; fails naming `what` it waited for.
async fn wait_for(what: &str, ok: impl Fn() -> bool) {
    let deadline = Instant::now() + LONG;
    while !ok() {
        assert!(Instant::now() < deadline, "waited in vain for {what}");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// Rays along the longer side of the visible cuts in these tests.
const CUT_GRID: u32 = 48;

/// The pool's config with visible cuts on: [`CUT_GRID`] rays, a finer cut of `fine` (0: none),
/// followed where they hold at most `share` of the frustum plan.
fn with_cuts(tp: &TestPool, fine: u32, share: f64) -> arbor_server::service::config::ServeConfig {
    let mut config = tp.config();
    config.visibility_grid = CUT_GRID;
    config.visibility_fine_grid = fine;
    config.visibility_follow_share = share;
    config
}

/// Connects and says `Hello` asking for the root and the refinement of `view`.
async fn hello_with_root_and_view(
    server: &arbor_server::daemon::RunningServer,
    view: ViewHint,
) -> (Client, Control) {
    let c = connect(server.quic_addr, &server.fingerprint).await;
    let mut control = Control::open(&c.conn).await;
    control
        .send(&hello_frame_with(
            SCENE,
            &[Channel::Normal],
            TOKEN,
            HELLO_SEND_ROOT | HELLO_VIEW,
            Some(view),
        ))
        .await;
    (c, control)
}

/// The pushes of every list the timeline recorded for the sessions `of_session` accepts, in
/// order.
fn pushes_per_list(
    timeline: &arbor_server::service::timeline::Timeline,
    of_session: impl Fn(u64) -> bool,
) -> Vec<Vec<TreeletId>> {
    use arbor_server::service::timeline::Event;
    timeline
        .snapshot()
        .events
        .iter()
        .filter_map(|e| match e {
            Event::Listed {
                session, pushed, ..
            } if of_session(*session) => Some(pushed.clone()),
            _ => None,
        })
        .collect()
}

/// Receives treelets until every one of `ids` has arrived.
async fn receive_all_of(c: &Client, ids: &std::collections::HashSet<TreeletId>) {
    let mut received = std::collections::HashSet::new();
    while !ids.is_subset(&received) {
        let got = receive(&c.conn, 1, LONG).await.unwrap();
        received.extend(got.iter().map(|(id, _)| *id));
    }
}

/// Two edges in front of the root cube's centre (root-cube units, as `Hello` takes them),
/// looking at it, 512 pixels high, 24 free slots.
fn in_front_of_the_cube() -> ViewHint {
    ViewHint {
        eye: [0.5, 0.5, 2.5],
        footprint: 1.0 / 512.0,
        free_slots: 24,
        ..looking_down_z()
    }
}

/// A view from `z = 10` looking down `-z`, 1 mrad per pixel, 64 free slots.
fn looking_down_z() -> ViewHint {
    ViewHint {
        eye: [0.0, 0.0, 10.0],
        forward: [0.0, 0.0, -1.0],
        up: [0.0, 1.0, 0.0],
        tan_half_fov_y: 0.5,
        aspect: 1.0,
        footprint: 0.001,
        free_slots: 64,
    }
}

/// Connects a hostile client with `opts`, says Hello (unless `hello` is false) and returns it.
async fn hostile(
    server: &arbor_server::daemon::RunningServer,
    hello_ok: bool,
) -> (Client, Control) {
    let c = connect(server.quic_addr, &server.fingerprint).await;
    if hello_ok {
        let (control, info) = hello(&c.conn, SCENE, &[Channel::Normal], TOKEN).await;
        info.unwrap();
        (c, control)
    } else {
        let control = Control::open(&c.conn).await;
        (c, control)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_clients_end_only_their_own_connection() {
    let tp = TestPool::new();
    let server = start(tp.config()).await;
    let d = server.pool().scene(SCENE).unwrap().description;
    let ids = all_ids(&d);
    let good = connect(server.quic_addr, &server.fingerprint).await;
    let (mut gc, info) = hello(&good.conn, SCENE, &[Channel::Normal], TOKEN).await;
    info.unwrap();
    let mut seq = 0;
    let alone = rounds(&good, &mut gc, &mut seq, &ids, 5).await;
    let rate_alone = ids.len() as f64 / alone.as_secs_f64();
    eprintln!(
        "good client alone: {} treelets in {alone:?} ({rate_alone:.0}/s)",
        ids.len()
    );
    // Generous: a loaded 2-core machine runs the hostile clients, the server and the good
    // client at once.
    let bound = alone * 10 + Duration::from_millis(500);

    let garbage: Vec<u8> = {
        let mut g = vec![0x10, 0, 0, 0, 0xEE];
        g.extend_from_slice(b"this is not an arbor frame at all");
        g
    };
    let mut over = Vec::new();
    over.extend_from_slice(&(MAX_FRAME_BYTES as u32 + 1).to_le_bytes());
    over.push(3);
    over.extend_from_slice(&[0u8; 1000]);
    let long_list = {
        let count = MAX_REQUEST_ITEMS as u32 + 1;
        let mut p = 1u64.to_le_bytes().to_vec();
        p.extend_from_slice(&count.to_le_bytes());
        for i in 0..count {
            p.extend_from_slice(&(i % d.treelet_count).to_le_bytes());
            p.extend_from_slice(&1.0f32.to_le_bytes());
        }
        let mut f = (p.len() as u32).to_le_bytes().to_vec();
        f.push(3);
        f.extend_from_slice(&p);
        assert!(p.len() <= MAX_FRAME_BYTES);
        f
    };
    let unknown_treelet = frame::encode(&Frame::RequestList {
        seq: 1,
        items: vec![(TreeletId(0), 1.0), (TreeletId(d.treelet_count), 2.0)],
    })
    .unwrap();

    // Deep request lists (docs/design.md §10) forged past the encoder's checks.
    let view = looking_down_z();
    let deep = frame::encode(&Frame::DeepRequestList {
        seq: 1,
        view,
        items: vec![(TreeletId(0), 1.0, 3.0)],
        prefetch_from: 1,
    })
    .unwrap();
    let forge = |at: usize, bytes: &[u8]| {
        let mut f = deep.clone();
        f[at..at + bytes.len()].copy_from_slice(bytes);
        f
    };
    // The view starts after the 5-byte header and the 8-byte seq.
    let nan_eye = forge(13 + 8, &f64::NAN.to_bits().to_le_bytes());
    let huge_free_slots = forge(13 + ViewHint::BYTES - 4, &u32::MAX.to_le_bytes());
    let absurd_levels = forge(deep.len() - 4, &1.0e6f32.to_bits().to_le_bytes());
    // The prefetch start follows the view.
    let prefetch_past_the_items = forge(13 + ViewHint::BYTES, &2u32.to_le_bytes());
    let long_deep_list = {
        let count = MAX_REQUEST_ITEMS as u32 + 1;
        let mut p = deep[5..13 + ViewHint::BYTES].to_vec();
        p.extend_from_slice(&count.to_le_bytes());
        p.extend_from_slice(&count.to_le_bytes());
        for i in 0..count {
            p.extend_from_slice(&(i % d.treelet_count).to_le_bytes());
            p.extend_from_slice(&1.0f32.to_le_bytes());
            p.extend_from_slice(&2.0f32.to_le_bytes());
        }
        assert!(p.len() <= MAX_FRAME_BYTES);
        let mut f = (p.len() as u32).to_le_bytes().to_vec();
        f.push(6);
        f.extend_from_slice(&p);
        f
    };
    let deep_unknown_treelet = frame::encode(&Frame::DeepRequestList {
        seq: 1,
        view,
        items: vec![(TreeletId(d.treelet_count), 1.0, 3.0)],
        prefetch_from: 1,
    })
    .unwrap();

    // Ranked lists (the client's compact deep lists) forged past the encoder: an id delta in a
    // varint of six bytes, a delta below id 0, and an id the scene lacks.
    let ranked_unknown_treelet = frame::encode(&Frame::RankedRequestList {
        seq: 1,
        view,
        items: vec![(TreeletId(0), 0), (TreeletId(d.treelet_count), 512)],
        prefetch_from: 2,
    })
    .unwrap();
    let ranked_with_items = |items: &[u8]| {
        let head = frame::encode(&Frame::RankedRequestList {
            seq: 1,
            view,
            items: vec![],
            prefetch_from: 0,
        })
        .unwrap();
        let mut f = head[..head.len() - 4].to_vec();
        f.extend_from_slice(&1u32.to_le_bytes());
        f.extend_from_slice(items);
        let len = (f.len() - 5) as u32;
        f[..4].copy_from_slice(&len.to_le_bytes());
        f
    };
    let ranked_long_varint = ranked_with_items(&[0x80, 0x80, 0x80, 0x80, 0x80, 0x01, 0, 0]);
    let ranked_below_zero = ranked_with_items(&[0x03, 0, 0]);

    // A Hello view (root-cube units) forged past the encoder: a NaN eye, and the view flag
    // without the send-root flag.
    let hello_view = frame::encode(&hello_frame_with(
        SCENE,
        &[Channel::Normal],
        TOKEN,
        HELLO_SEND_ROOT | HELLO_VIEW,
        Some(view),
    ))
    .unwrap();
    let view_at = hello_view.len() - ViewHint::BYTES;
    let mut hello_nan_view = hello_view.clone();
    hello_nan_view[view_at..view_at + 8].copy_from_slice(&f64::NAN.to_bits().to_le_bytes());
    let mut hello_view_no_root = hello_view.clone();
    hello_view_no_root[view_at - 1] = HELLO_VIEW;

    // (name, say Hello first, bytes to send, expected code)
    let cases: Vec<(&str, bool, Vec<u8>, ErrorCode)> = vec![
        (
            "garbage instead of Hello",
            false,
            garbage.clone(),
            ErrorCode::ProtocolViolation,
        ),
        (
            "garbage after Hello",
            true,
            garbage,
            ErrorCode::ProtocolViolation,
        ),
        (
            "frame over the size limit",
            true,
            over,
            ErrorCode::FrameTooLarge,
        ),
        (
            "list over the length limit",
            true,
            long_list,
            ErrorCode::ListTooLong,
        ),
        (
            "unknown treelet id",
            true,
            unknown_treelet,
            ErrorCode::UnknownTreelet,
        ),
        (
            "deep list with a NaN camera",
            true,
            nan_eye,
            ErrorCode::ProtocolViolation,
        ),
        (
            "Hello view with a NaN eye",
            false,
            hello_nan_view,
            ErrorCode::ProtocolViolation,
        ),
        (
            "Hello view without the root",
            false,
            hello_view_no_root,
            ErrorCode::ProtocolViolation,
        ),
        (
            "deep list announcing 2^32 - 1 free slots",
            true,
            huge_free_slots,
            ErrorCode::ProtocolViolation,
        ),
        (
            "deep list with an error of a million levels",
            true,
            absurd_levels,
            ErrorCode::ProtocolViolation,
        ),
        (
            "deep list whose prefetch starts past its items",
            true,
            prefetch_past_the_items,
            ErrorCode::ProtocolViolation,
        ),
        (
            "deep list over the length limit",
            true,
            long_deep_list,
            ErrorCode::ListTooLong,
        ),
        (
            "deep list naming an unknown treelet",
            true,
            deep_unknown_treelet,
            ErrorCode::UnknownTreelet,
        ),
        (
            "ranked list with an id delta of six bytes",
            true,
            ranked_long_varint,
            ErrorCode::ProtocolViolation,
        ),
        (
            "ranked list with an id below 0",
            true,
            ranked_below_zero,
            ErrorCode::ProtocolViolation,
        ),
        (
            "ranked list naming an unknown treelet",
            true,
            ranked_unknown_treelet,
            ErrorCode::UnknownTreelet,
        ),
        (
            "second Hello",
            true,
            frame::encode(&hello_frame(SCENE, &[], TOKEN)).unwrap(),
            ErrorCode::ProtocolViolation,
        ),
        (
            "unknown scene",
            false,
            frame::encode(&hello_frame("dragon", &[], TOKEN)).unwrap(),
            ErrorCode::UnknownScene,
        ),
        (
            "wrong token",
            false,
            frame::encode(&hello_frame(SCENE, &[], "guess")).unwrap(),
            ErrorCode::Unauthorized,
        ),
        (
            "channel the scene lacks",
            false,
            frame::encode(&hello_frame(SCENE, &[Channel::Color], TOKEN)).unwrap(),
            ErrorCode::UnknownChannel,
        ),
        (
            "unsupported version",
            false,
            {
                let mut p = 9u16.to_le_bytes().to_vec();
                p.extend_from_slice(b"future");
                let mut f = (p.len() as u32).to_le_bytes().to_vec();
                f.push(1);
                f.extend_from_slice(&p);
                f
            },
            ErrorCode::UnsupportedVersion,
        ),
    ];
    for (name, say_hello, bytes, expected) in cases {
        let (h, mut hc) = hostile(&server, say_hello).await;
        let attack = async {
            hc.send_raw(&bytes).await;
            // Where the server answers with an Error frame, it carries the same code.
            let frame = tokio::time::timeout(Duration::from_secs(5), hc.read()).await;
            let got = close_code_and_reason(&h.conn, LONG).await;
            (frame, got)
        };
        // Past the redelivery guard of the previous round, then both at once.
        tokio::time::sleep(Duration::from_millis(150)).await;
        seq += 1;
        let (res, during) = tokio::join!(attack, round(&good, &mut gc, seq, &ids));
        let (frame, got) = res;
        let (got, reason) = match got {
            Ok((c, reason)) => (Ok(c), reason),
            Err(e) => (Err(e), String::new()),
        };
        assert_eq!(got, code(expected), "{name}");
        // The server's Error frame, with the same code, arrives before the close, and the
        // close says the same (for a client that did not read the frame in time).
        match frame {
            Ok(Some(Frame::Error { code: c, message })) => {
                assert_eq!(c, expected, "{name}");
                assert!(!message.is_empty(), "{name}");
                assert_eq!(reason, message, "{name}: the close's reason");
            }
            other => panic!("{name}: expected an Error frame, got {other:?}"),
        }
        let during = during.unwrap_or_else(|e| panic!("{name}: good client: {e}"));
        assert!(
            during <= bound,
            "{name}: the good client's round took {during:?} (alone {alone:?})"
        );
        eprintln!("{name}: closed with {expected}; good client's round {during:?}");
        assert!(
            server.state.metrics.errors(expected) >= 1,
            "{name}: not counted"
        );
    }

    // Refused deep lists cost no work: nothing was planned for any of them.
    assert_eq!(
        server.state.metrics.pushes_planned.load(Ordering::Relaxed),
        0
    );

    // No Hello at all: closed when the hello timeout passes.
    let (h, _hc) = hostile(&server, false).await;
    let t0 = Instant::now();
    let (got, reason) = close_code_and_reason(&h.conn, LONG).await.unwrap();
    assert_eq!(Ok(got), code(ErrorCode::ProtocolViolation), "silent client");
    assert!(
        reason.starts_with("no Hello within"),
        "silent client: {reason}"
    );
    assert!(
        t0.elapsed() >= Duration::from_millis(1500),
        "{:?}",
        t0.elapsed()
    );

    // Wrong ALPN: the TLS handshake itself fails (no_application_protocol, QUIC 0x178).
    let opts = ClientOptions {
        alpn: b"h3".to_vec(),
        ..ClientOptions::default()
    };
    tokio::time::sleep(Duration::from_millis(150)).await;
    seq += 1;
    let (alpn, during) = tokio::join!(
        connect_with(server.quic_addr, &server.fingerprint, opts),
        round(&good, &mut gc, seq, &ids)
    );
    match alpn {
        Err(quinn::ConnectionError::ConnectionClosed(c)) => {
            assert_eq!(u64::from(c.error_code), 0x178, "{c}");
        }
        Err(e) => panic!("wrong ALPN ended otherwise: {e}"),
        Ok(_) => panic!("a client with ALPN h3 was accepted"),
    }
    assert!(during.unwrap() <= bound);

    // A wrong fingerprint is refused by our own client (pinning works).
    assert!(
        connect_with(server.quic_addr, &"0".repeat(64), ClientOptions::default())
            .await
            .is_err()
    );

    // A client that never reads its streams: its own window stalls; it is closed with
    // SlowReader after the timeout while the good client keeps its rate meanwhile. Two stream
    // credits and a few KiB of flow-control credit each, so that no batch fits whole.
    let mut transport = quinn::TransportConfig::default();
    transport.max_concurrent_uni_streams(2u32.into());
    transport.stream_receive_window((4u32 << 10).into());
    let slow = connect_with(
        server.quic_addr,
        &server.fingerprint,
        ClientOptions {
            transport,
            ..ClientOptions::default()
        },
    )
    .await
    .unwrap();
    let (mut sc, info) = hello(&slow.conn, SCENE, &[Channel::Normal], TOKEN).await;
    info.unwrap();
    let t0 = Instant::now();
    sc.send(&Frame::RequestList {
        seq: 1,
        items: ids.iter().map(|&t| (t, 1.0)).collect(),
    })
    .await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let stalled = server
        .state
        .sessions()
        .into_iter()
        .find(|s| s.request_lists == 1 && s.treelets_sent < ids.len() as u64);
    assert!(stalled.is_some(), "the slow reader is not stalled");
    let during = rounds(&good, &mut gc, &mut seq, &ids, 3).await;
    eprintln!("during a stalled slow reader: good client's round {during:?}");
    assert!(during <= bound, "{during:?} vs alone {alone:?}");
    assert_eq!(
        close_code(&slow.conn, LONG).await,
        code(ErrorCode::SlowReader)
    );
    let took = t0.elapsed();
    assert!(
        took >= Duration::from_millis(1500) && took < Duration::from_millis(6000),
        "SlowReader after {took:?}"
    );

    // The good client is still connected and served after all of it.
    assert!(good.conn.close_reason().is_none());
    let after = rounds(&good, &mut gc, &mut seq, &ids, 3).await;
    assert!(after <= bound, "{after:?}");
    assert_eq!(server.state.sessions().len(), 1);
    let m = &server.state.metrics;
    assert_eq!(m.errors(ErrorCode::SlowReader), 1);
    // Garbage twice, a second Hello, four forged deep lists, two forged ranked lists, two
    // forged Hello views, the silent client.
    assert_eq!(m.errors(ErrorCode::ProtocolViolation), 12);
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_connection_cap_refuses_with_server_busy() {
    let tp = TestPool::new();
    let mut config = tp.config();
    config.max_connections = 2;
    let server = start(config).await;
    let a = connect(server.quic_addr, &server.fingerprint).await;
    let b = connect(server.quic_addr, &server.fingerprint).await;
    let (_ca, ia) = hello(&a.conn, SCENE, &[], TOKEN).await;
    ia.unwrap();
    let third = connect_with(
        server.quic_addr,
        &server.fingerprint,
        ClientOptions::default(),
    )
    .await;
    let got = match third {
        Ok(c) => close_code(&c.conn, LONG).await,
        Err(quinn::ConnectionError::ApplicationClosed(c)) => Ok(c.error_code.into_inner()),
        Err(e) => Err(e.to_string()),
    };
    assert_eq!(got, code(ErrorCode::ServerBusy));
    assert_eq!(
        server
            .state
            .metrics
            .connections_rejected
            .load(Ordering::Relaxed),
        1
    );
    // A freed slot is usable again.
    b.conn.close(0u32.into(), b"bye");
    drop(b);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let c = connect(server.quic_addr, &server.fingerprint).await;
    let (_cc, ic) = hello(&c.conn, SCENE, &[], TOKEN).await;
    ic.unwrap();
    assert!(a.conn.close_reason().is_none());
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_says_goodbye_and_returns_within_the_grace() {
    let tp = TestPool::new();
    let mut config = tp.config();
    // Longer than the drain: the stalled client must meet the shutdown, not the watchdog.
    config.slow_reader_timeout_ms = 10_000;
    let grace = Duration::from_millis(config.shutdown_grace_ms);
    let server = start(config).await;
    let d = server.pool().scene(SCENE).unwrap().description;
    let state = server.state.clone();
    assert!(state.is_ready());

    // A reading client.
    let reader = connect(server.quic_addr, &server.fingerprint).await;
    let (mut rc, info) = hello(&reader.conn, SCENE, &[Channel::Normal], TOKEN).await;
    info.unwrap();
    round(&reader, &mut rc, 1, &all_ids(&d)).await.unwrap();
    // A client whose streams stall, so the drain lasts the whole grace.
    let mut transport = quinn::TransportConfig::default();
    transport.max_concurrent_uni_streams(1u32.into());
    let stuck = connect_with(
        server.quic_addr,
        &server.fingerprint,
        ClientOptions {
            transport,
            ..ClientOptions::default()
        },
    )
    .await
    .unwrap();
    let (mut sc, info) = hello(&stuck.conn, SCENE, &[Channel::Normal], TOKEN).await;
    info.unwrap();
    sc.send(&Frame::RequestList {
        seq: 1,
        items: all_ids(&d).into_iter().map(|t| (t, 1.0)).collect(),
    })
    .await;
    tokio::time::sleep(Duration::from_millis(200)).await;

    let trigger = server.shutdown_trigger();
    let addr = server.quic_addr;
    let fp = server.fingerprint.clone();
    let t0 = Instant::now();
    trigger.trigger();
    let stopping = tokio::spawn(server.wait());
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!(!state.is_ready(), "readiness goes false at once");
    // A newcomer during the drain is refused with ShuttingDown.
    let late = match connect_with(addr, &fp, ClientOptions::default()).await {
        Ok(c) => close_code(&c.conn, LONG).await,
        Err(quinn::ConnectionError::ApplicationClosed(c)) => Ok(c.error_code.into_inner()),
        Err(e) => Err(e.to_string()),
    };
    assert_eq!(late, code(ErrorCode::ShuttingDown), "newcomer");

    // Both clients get Goodbye { ShuttingDown } and the close code.
    assert_eq!(
        tokio::time::timeout(LONG, rc.read()).await.unwrap(),
        Some(Frame::Goodbye {
            code: ErrorCode::ShuttingDown
        })
    );
    assert_eq!(
        close_code(&reader.conn, LONG).await,
        code(ErrorCode::ShuttingDown)
    );
    assert_eq!(
        close_code(&stuck.conn, LONG).await,
        code(ErrorCode::ShuttingDown)
    );
    tokio::time::timeout(grace + Duration::from_secs(2), stopping)
        .await
        .expect("shutdown within grace + 2 s")
        .unwrap();
    let took = t0.elapsed();
    eprintln!("shutdown with a stalled client took {took:?} (grace {grace:?})");
    assert!(took >= grace, "the stalled streams had the grace: {took:?}");
    assert!(took <= grace + Duration::from_secs(2));
    assert!(state.metrics.errors(ErrorCode::ShuttingDown) >= 3);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replacement_list_cancels_obsolete_treelets_in_flight() {
    const WINDOW: usize = 32;
    let batch = batch_limit(WINDOW);
    let tp = TestPool::new();
    // The client does not read for a while on purpose: not a slow reader to be closed.
    let mut config = tp.config();
    config.slow_reader_timeout_ms = 10_000;
    // A window of a few batches, so that the list is longer than one batch.
    config.window_min = WINDOW;
    config.window_max = WINDOW;
    let server = start(config).await;
    let d = server.pool().scene(SCENE).unwrap().description;
    // One stream credit and not reading yet: the first batch's stream is opened, the rest of
    // the window waits in flight for a credit.
    let mut transport = quinn::TransportConfig::default();
    transport.max_concurrent_uni_streams(1u32.into());
    let client = connect_with(
        server.quic_addr,
        &server.fingerprint,
        ClientOptions {
            transport,
            ..ClientOptions::default()
        },
    )
    .await
    .unwrap();
    let (mut control, info) = hello(&client.conn, SCENE, &[Channel::Normal], TOKEN).await;
    info.unwrap();
    let old: Vec<TreeletId> = (0..100).map(TreeletId).collect();
    control
        .send(&Frame::RequestList {
            seq: 1,
            items: old.iter().map(|&t| (t, 1000.0 - t.0 as f32)).collect(),
        })
        .await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let in_flight = server.state.sessions()[0].in_flight;
    assert!(in_flight >= 2, "in flight: {in_flight}");
    let new: Vec<TreeletId> = (d.treelet_count - 10..d.treelet_count)
        .map(TreeletId)
        .collect();
    control
        .send(&Frame::RequestList {
            seq: 2,
            items: new.iter().map(|&t| (t, 1.0)).collect(),
        })
        .await;
    // The server has taken the new list (a stream credit returned before that could still
    // carry the old list's next batch), and every batch but the one on the open stream is
    // cancelled.
    let t0 = Instant::now();
    while server.state.sessions()[0].request_lists < 2
        || server
            .state
            .metrics
            .treelets_cancelled
            .load(Ordering::Relaxed)
            < in_flight.saturating_sub(batch as u64)
    {
        assert!(t0.elapsed() < LONG, "obsolete treelets not cancelled");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // Reading now: the one stream already sent (a batch of the first treelets), then exactly
    // the new list.
    let mut ids: Vec<u32> = Vec::new();
    while !new.iter().all(|t| ids.contains(&t.0)) {
        let got = receive(&client.conn, 1, LONG).await.unwrap();
        ids.extend(got.iter().map(|g| g.0.0));
    }
    ids.sort_unstable();
    let first: Vec<u32> = ids.iter().copied().filter(|&i| i < 100).collect();
    assert!(
        !first.is_empty() && first.len() <= batch,
        "the open stream's batch: {first:?}"
    );
    assert_eq!(
        first,
        (0..first.len() as u32).collect::<Vec<_>>(),
        "the open stream carried the first-ranked treelets"
    );
    let mut want: Vec<u32> = new.iter().map(|t| t.0).collect();
    want.splice(0..0, first);
    assert_eq!(
        ids, want,
        "only the new list (and the one stream already sent)"
    );
    assert!(
        tokio::time::timeout(Duration::from_millis(300), client.conn.accept_uni())
            .await
            .is_err(),
        "an obsolete treelet arrived"
    );
    assert!(client.conn.close_reason().is_none());
    server.shutdown().await;
}

/// The push plans' shapes, decoded from the real bunny pool through a shape cache far smaller
/// than the scene's shapes: each equals the shape decoded through an unbounded cache, a child's
/// root voxel is the leaf its parent names, and the small cache never holds more than its
/// bytes while it keeps turning over.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shapes_through_a_small_shape_cache_are_exact_and_within_its_bytes() {
    let tp = TestPool::new();
    let server = start(tp.config()).await;
    let stored = server.pool().scene(SCENE).unwrap();
    let count = stored.description.treelet_count;
    let root = stored.description.root_treelet;
    let serve =
        |shapes: &Arc<ShapeCache>| served_with(&stored, MessageCache::new(0), shapes.clone());
    let whole = serve(&Arc::new(ShapeCache::for_shapes(usize::MAX)));
    let all: Vec<_> = (0..count)
        .map(|i| {
            whole
                .shape(TreeletId(i))
                .expect("every stored treelet has a shape")
        })
        .collect();
    let with_children = all.iter().filter(|s| !s.children.is_empty()).count();
    assert!(
        with_children > 4 && count > 40,
        "the bunny has a tree of treelets: {with_children} of {count} with children"
    );
    for s in &all {
        for &(child, cell) in &s.children {
            assert_eq!(all[child.0 as usize].root, cell, "treelet {}", child.0);
        }
    }

    // Room for the root and a few more: a small share of what the scene's shapes take.
    use arbor_server::service::shapes::shape_bytes;
    let capacity = 4 * shape_bytes(&all[root.0 as usize]);
    let total: usize = all.iter().map(|s| shape_bytes(s)).sum();
    assert!(capacity * 4 < total, "{capacity} of {total} bytes");
    let shapes = Arc::new(ShapeCache::for_shapes(capacity));
    let small = serve(&shapes);
    // Walks as the plans do: from the root down, the root again before every treelet.
    for round in 0..3 {
        for i in 0..count {
            assert_eq!(small.shape(root).as_deref(), Some(&*all[root.0 as usize]));
            let s = small.shape(TreeletId(i)).unwrap();
            assert_eq!(*s, *all[i as usize], "round {round}, treelet {i}");
            let f = shapes.figures();
            assert!(f.bytes <= capacity, "{} bytes held in {capacity}", f.bytes);
        }
    }
    let f = shapes.figures();
    assert!(
        f.misses > u64::from(count),
        "a cache of {capacity} bytes cannot hold the bunny's {count} shapes: {f:?}"
    );
    assert!(f.hits >= 3 * u64::from(count), "the root is kept: {f:?}");
    server.shutdown().await;
}

/// A stream's batches from the message cache over the real bunny pool: however the batches
/// fall and in whatever order, a batch's buffers carry exactly the messages built afresh from
/// the pool; the same batch again goes out as the very buffer it was first joined in, a batch
/// cut differently as slices of those buffers (not copied), never in more than
/// `MAX_CHUNKS_PER_STREAM` buffers; a cache far smaller than the scene stays within its bytes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn batches_from_the_message_cache_are_the_pool_messages_and_a_repeat_is_not_copied() {
    let tp = TestPool::new();
    let server = start(tp.config()).await;
    let stored = server.pool().scene(SCENE).unwrap();
    let count = stored.description.treelet_count;
    let channels = stored.description.layout.channels().to_vec();
    let serve = |messages: &Arc<MessageCache>| {
        served_with(
            &stored,
            messages.clone(),
            Arc::new(ShapeCache::for_shapes(0)),
        )
    };
    let fresh = serve(&Arc::new(MessageCache::new(0)));
    let reference: Vec<Vec<u8>> = (0..count)
        .map(|i| fresh.message(TreeletId(i), &channels).unwrap().to_vec())
        .collect();
    let expect = |ids: &[TreeletId]| -> Vec<u8> {
        ids.iter()
            .flat_map(|id| reference[id.0 as usize].iter().copied())
            .collect()
    };
    let joined = |chunks: &[_]| -> Vec<u8> {
        chunks
            .iter()
            .flat_map(|c: &bytes::Bytes| c.iter().copied())
            .collect()
    };
    let ids: Vec<TreeletId> = (0..count).map(TreeletId).collect();
    // Every seventh treelet's id further along: an order unlike the ids'.
    let stride = (1..count)
        .map(|s| 7 * s + 3)
        .find(|s| gcd(*s, count) == 1)
        .unwrap();
    let shuffled: Vec<TreeletId> = (0..count)
        .map(|i| TreeletId((i * stride) % count))
        .collect();

    let messages = Arc::new(MessageCache::new(64 << 20));
    let cached = serve(&messages);
    let first: Vec<_> = ids
        .chunks(7)
        .map(|b| cached.batch(b, &channels).unwrap())
        .collect();
    for (b, chunks) in ids.chunks(7).zip(&first) {
        assert_eq!(chunks.len(), 1, "built afresh and joined once");
        assert_eq!(joined(chunks), expect(b), "treelets {b:?}");
    }
    for (b, chunks) in ids.chunks(7).zip(&first) {
        let again = cached.batch(b, &channels).unwrap();
        assert_eq!(again.len(), 1);
        assert_eq!(
            (again[0].as_ptr(), again[0].len()),
            (chunks[0].as_ptr(), chunks[0].len()),
            "treelets {b:?} again: the same buffer"
        );
    }
    let within_first = |c: &bytes::Bytes| {
        first.iter().flatten().any(|f| {
            let (f0, c0) = (f.as_ptr() as usize, c.as_ptr() as usize);
            c0 >= f0 && c0 + c.len() <= f0 + f.len()
        })
    };
    for b in ids.chunks(10) {
        let chunks = cached.batch(b, &channels).unwrap();
        // Ten in a row lie in at most three runs of seven.
        assert!(
            chunks.len() <= 3,
            "treelets {b:?} in {} buffers",
            chunks.len()
        );
        assert!(chunks.iter().all(within_first), "treelets {b:?} copied");
        assert_eq!(joined(&chunks), expect(b), "treelets {b:?}");
    }
    // Every other treelet: in the same runs, not adjacent in them.
    let every_other: Vec<TreeletId> = ids.iter().copied().step_by(2).collect();
    for b in shuffled.chunks(9).chain(every_other.chunks(3)) {
        let chunks = cached.batch(b, &channels).unwrap();
        assert!(chunks.len() <= MAX_CHUNKS_PER_STREAM);
        assert_eq!(joined(&chunks), expect(b), "treelets {b:?}");
    }
    let (held, hits, misses) = messages.figures();
    assert_eq!(misses, u64::from(count), "each message built once");
    assert!(hits >= 3 * u64::from(count) && held > 0);

    // An eighth of the scene's messages: turned over and over, within its bytes, exact.
    let total: usize = reference.iter().map(Vec::len).sum();
    let small = Arc::new(MessageCache::new(total / 8));
    let turning = serve(&small);
    for round in 0..3 {
        let order = if round == 1 { &shuffled } else { &ids };
        for b in order.chunks(5) {
            let chunks = turning.batch(b, &channels).unwrap();
            assert_eq!(joined(&chunks), expect(b), "round {round}, treelets {b:?}");
            let (held, ..) = small.figures();
            assert!(held <= total / 8, "{held} bytes held of {}", total / 8);
        }
    }
    let (_, hits, misses) = small.figures();
    assert!(
        misses > 2 * u64::from(count) && hits > 0,
        "{hits} hits, {misses} misses"
    );
    server.shutdown().await;
}

/// `stored` served with these message and shape caches and no cut node cache.
/// A message announces the used-node count of its node block as the block's own header says
/// it. The server reads it from the zstd frame header, which records the raw length, without
/// decompressing: every block of the real bunny pool records it, and the count agrees with the
/// decompressed header. A block whose frame does not record its length (written by a streaming
/// encoder) is decompressed for it instead: a copy of the bunny with every third node block
/// written so is served with the same counts.
#[test]
fn messages_announce_the_used_nodes_their_blocks_hold_with_or_without_a_recorded_length() {
    let tp = TestPool::new();
    let pool = arbor_server::pool::Pool::open(&tp.db()).unwrap();
    let stored = pool.scene(SCENE).unwrap();
    let d = &stored.description;
    let dictionaries = codec::PreparedDictionaries::of(d);
    let channels = d.layout.channels().to_vec();
    let decoded_used = |block: &[u8]| {
        let raw =
            codec::decompress_using(block, codec::MAX_RAW_TREELET, dictionaries.nodes()).unwrap();
        codec::decode_header(&raw).unwrap().0.used_nodes
    };
    let announced = |served: &arbor_server::service::treelets::ServedScene, id| {
        let m = served.message(id, &channels).unwrap();
        decode_treelet_message(&m).unwrap().used_nodes
    };

    let ids: Vec<TreeletId> = (0..d.treelet_count).map(TreeletId).collect();
    let blocks: Vec<Vec<u8>> = ids
        .iter()
        .map(|&id| stored.nodes(id).unwrap().unwrap().to_vec())
        .collect();
    let served = served_with(
        &stored,
        MessageCache::new(0),
        ShapeCache::for_shapes(0).into(),
    );
    for (&id, block) in ids.iter().zip(&blocks) {
        let used = decoded_used(block);
        assert_eq!(codec::used_nodes_of_block(block), Some(used), "{id}");
        assert_eq!(announced(&served, id), used, "{id}");
    }

    // The copy: every third node block re-encoded by a streaming encoder that leaves the
    // length out, with the scene's dictionary.
    let rewritten = |i: usize, block: &Vec<u8>| -> Vec<u8> {
        if !i.is_multiple_of(3) {
            return block.clone();
        }
        let raw =
            codec::decompress_using(block, codec::MAX_RAW_TREELET, dictionaries.nodes()).unwrap();
        let dictionary = d.node_dictionary.as_deref().unwrap_or(&[]);
        let mut e = zstd::stream::Encoder::with_dictionary(Vec::new(), 3, dictionary).unwrap();
        e.include_contentsize(false).unwrap();
        std::io::Write::write_all(&mut e, &raw).unwrap();
        let out = e.finish().unwrap();
        assert_eq!(codec::used_nodes_of_block(&out), None);
        out
    };
    let mut import = pool.begin_import("copy", false).unwrap();
    import.set_channels(&channels).unwrap();
    use arbor_server::octree::TreeletSink;
    import
        .put_nodes(
            ids.iter()
                .zip(&blocks)
                .enumerate()
                .map(|(i, (&id, b))| (id, rewritten(i, b)))
                .collect(),
        )
        .unwrap();
    import
        .put_channels(
            ids.iter()
                .map(|&id| {
                    let per: Vec<Vec<u8>> = channels
                        .iter()
                        .map(|&c| stored.channel(c, id).unwrap().unwrap().to_vec())
                        .collect();
                    (id, per)
                })
                .collect(),
        )
        .unwrap();
    import.commit(d).unwrap();
    let copy = pool.scene("copy").unwrap();
    let served = served_with(
        &copy,
        MessageCache::new(0),
        ShapeCache::for_shapes(0).into(),
    );
    for (&id, block) in ids.iter().zip(&blocks) {
        assert_eq!(
            announced(&served, id),
            decoded_used(block),
            "{id} of the copy"
        );
    }
}

fn served_with(
    stored: &arbor_server::pool::StoredScene,
    messages: impl Into<Arc<MessageCache>>,
    shapes: Arc<ShapeCache>,
) -> arbor_server::service::treelets::ServedScene {
    let caches = arbor_server::service::state::ServiceCaches {
        messages: messages.into(),
        shapes,
        cut_nodes: Arc::new(arbor_server::service::visibility::NodeCache::for_nodes(0)),
        fine_cuts: Arc::default(),
    };
    arbor_server::service::treelets::ServedScene::with_caches(stored.clone(), &caches)
}

fn gcd(a: u32, b: u32) -> u32 {
    if b == 0 { a } else { gcd(b, a % b) }
}
