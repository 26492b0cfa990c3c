//! The treelet service end to end: the real server (`arbor_server::service::start`) serving a
//! real pool built from a real scan, and the real client (`arbor_client_net`), over loopback
//! QUIC and over the link emulator.
//!
//! One pool is built (autzen, 1 KiB treelets) and one server started; the scenarios run one
//! after another against it, each with its own clients:
//!
//! * exact delivery: a list of treelets arrives exactly, each once, bytes identical to the pool,
//!   and decodes with the dictionaries of the `SceneInfo`;
//! * channels: fewer channels asked for → fewer bytes and never a channel not asked for; refusals
//!   (unknown channel, wrong token, unknown scene) are final;
//! * order over a 25 ms / 100 Mbit/s link with a fixed in-flight window: a 500-item list arrives
//!   in priority order except within the window, and after a replacement list nothing of the old
//!   list arrives beyond the window.

use std::collections::{HashMap, HashSet};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_client_net::{
    ClientConfig, ClientEvent, ReceivedTreelet, ServerUrl, TreeletClient, Trust,
};
use arbor_proto::codec;
use arbor_proto::wire::ErrorCode;
use arbor_proto::{Channel, SceneDescription, TreeletId};
use arbor_server::daemon::{RunningServer, start};
use arbor_server::octree::BuildOptions;
use arbor_server::service::ServeConfig;
use arbor_server::service::config::{AdminTokenSource, SceneAccess};
use arbor_tests::link::{LinkConfig, LinkEmulator};
use arbor_tests::support::{Built, build_file};
use tempfile::TempDir;

const SCENE: &str = "autzen";
const TOKEN: &str = "e2e-token";
/// The server's in-flight window, fixed (`window_min = window_max`) so the order bounds are
/// exact.
const WINDOW: usize = 16;
const WAIT: Duration = Duration::from_secs(60);

struct Service {
    server: RunningServer,
    scene: SceneDescription,
    _pool_dir: TempDir,
    _data_dir: TempDir,
}

async fn start_service() -> Service {
    let t0 = Instant::now();
    let built = tokio::task::spawn_blocking(|| {
        build_file(
            "points/autzen_trim.las",
            SCENE,
            &BuildOptions {
                treelet_bytes: 1024,
                ..BuildOptions::default()
            },
        )
    })
    .await
    .unwrap();
    let Built {
        pool,
        scene,
        pool_dir,
        source,
        scratch,
    } = built;
    let description = scene.description.clone();
    // The server opens the pool itself: sled allows one opener.
    drop((pool, scene, source, scratch));
    eprintln!(
        "built {SCENE}: {} treelets, channels {:?}, in {:.1?}",
        description.treelet_count,
        description.layout.channels(),
        t0.elapsed()
    );
    let data_dir = tempfile::tempdir().unwrap();
    let mut cfg = ServeConfig::new(pool_dir.path());
    cfg.listen = "127.0.0.1:0".parse().unwrap();
    cfg.admin_listen = None;
    cfg.data_dir = Some(data_dir.path().to_owned());
    cfg.admin_token = AdminTokenSource::Inline("admin-e2e".into());
    cfg.window_min = WINDOW;
    cfg.window_max = WINDOW;
    cfg.scenes
        .insert(SCENE.into(), SceneAccess::Tokens(vec![TOKEN.into()]));
    let server = start(cfg).await.unwrap();
    Service {
        server,
        scene: description,
        _pool_dir: pool_dir,
        _data_dir: data_dir,
    }
}

fn config(addr: SocketAddr, svc: &Service, channels: &[Channel]) -> ClientConfig {
    let url = ServerUrl {
        host: addr.ip().to_string(),
        port: addr.port(),
        scene: SCENE.into(),
    };
    ClientConfig::new(url, Trust::Fingerprint(svc.server.fingerprint.clone()))
        .with_token(TOKEN)
        .with_channels(channels.iter().copied())
}

async fn event(client: &mut TreeletClient) -> ClientEvent {
    tokio::time::timeout(WAIT, client.next_event())
        .await
        .expect("no event in time")
        .expect("the client ended")
}

async fn connected(client: &mut TreeletClient) -> Arc<SceneDescription> {
    match event(client).await {
        ClientEvent::Connected(scene) => scene,
        other => panic!("expected Connected, got {other:?}"),
    }
}

async fn treelet(client: &mut TreeletClient) -> ReceivedTreelet {
    match event(client).await {
        ClientEvent::Treelet(t) => t,
        other => panic!("expected a treelet, got {other:?}"),
    }
}

async fn treelets(client: &mut TreeletClient, n: usize) -> Vec<ReceivedTreelet> {
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        out.push(treelet(client).await);
    }
    out
}

/// Nothing more arrives within `d`.
async fn quiet_for(client: &mut TreeletClient, d: Duration) {
    if let Ok(e) = tokio::time::timeout(d, client.next_event()).await {
        panic!("expected nothing more, got {e:?}");
    }
}

/// A deterministic shuffle of `0..n`.
fn shuffled(n: u32, seed: u64) -> Vec<u32> {
    arbor_proto::rng::SplitMix64::new(seed).shuffled(n)
}

/// Rank of each id in the server's order: priority descending, ties by lower id.
fn ranks(list: &[(TreeletId, f32)]) -> HashMap<TreeletId, usize> {
    let mut sorted = list.to_vec();
    sorted.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    sorted
        .iter()
        .enumerate()
        .map(|(r, (id, _))| (*id, r))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn service_end_to_end() {
    let svc = start_service().await;
    assert!(
        svc.scene.treelet_count >= 1000,
        "the order scenario needs 1000 treelets, the scene has {}",
        svc.scene.treelet_count
    );
    exact_delivery(&svc).await;
    channels(&svc).await;
    refusals(&svc).await;
    order_over_a_slow_link(&svc).await;
    re_request_within_the_guard(&svc).await;
    svc.server.shutdown().await;
}

async fn exact_delivery(svc: &Service) {
    let layout = svc.scene.layout.channels().to_vec();
    let mut client = TreeletClient::start(config(svc.server.quic_addr, svc, &layout)).unwrap();
    let info = connected(&mut client).await;
    assert_eq!(*info, svc.scene, "SceneInfo is the stored description");
    let count = svc.scene.treelet_count;
    let ids: Vec<u32> = (0..count)
        .step_by((count as usize / 300).max(1))
        .take(300)
        .collect();
    let list: Vec<(TreeletId, f32)> = ids
        .iter()
        .enumerate()
        .map(|(i, &id)| (TreeletId(id), -(i as f32)))
        .collect();
    client.request(list.clone()).unwrap();
    let got = treelets(&mut client, list.len()).await;
    quiet_for(&mut client, Duration::from_millis(300)).await;

    let got_ids: HashSet<TreeletId> = got.iter().map(|t| t.id).collect();
    assert_eq!(got_ids.len(), got.len(), "a treelet arrived twice");
    assert_eq!(got_ids, list.iter().map(|i| i.0).collect());
    let stored = svc.server.pool().scene(SCENE).unwrap();
    let mut canonical = layout.clone();
    canonical.sort_by_key(|c| c.id());
    for t in &got {
        assert_eq!(t.nodes[..], stored.nodes(t.id).unwrap().unwrap()[..]);
        let chans: Vec<Channel> = t.channels.iter().map(|c| c.0).collect();
        assert_eq!(t.channels.len(), chans.len());
        assert_eq!(chans, canonical, "treelet {}", t.id);
        for (c, block) in &t.channels {
            assert_eq!(block[..], stored.channel(c, t.id).unwrap().unwrap()[..]);
        }
        // What arrives is usable with the SceneInfo alone.
        let tr = codec::decode_compressed_treelet(
            &t.nodes,
            info.max_depth,
            info.node_dictionary.as_deref(),
        )
        .unwrap();
        assert_eq!(tr.header.id, t.id);
        assert_eq!(tr.used().len(), usize::from(t.used_nodes));
        for (c, block) in &t.channels {
            codec::decode_compressed_attributes(block, c, t.used_nodes, info.channel_dictionary(c))
                .unwrap();
        }
        assert!(t.latency > Duration::ZERO);
    }
    let stats = client.stats();
    assert_eq!(stats.treelets_received, list.len() as u64);
    assert_eq!(
        stats.bytes_received,
        got.iter().map(|t| t.wire_bytes as u64).sum::<u64>()
    );
    assert_eq!((stats.connects, stats.disconnects), (1, 0));
    client.close().await;
}

async fn channels(svc: &Service) {
    let layout = svc.scene.layout.channels().to_vec();
    assert!(layout.len() >= 2, "autzen stores normals and colours");
    let fewer = vec![layout[0]];
    let list: Vec<(TreeletId, f32)> = (0..200)
        .map(|i| (TreeletId(i), 1000.0 - i as f32))
        .collect();
    let mut all_client = TreeletClient::start(config(svc.server.quic_addr, svc, &layout)).unwrap();
    let mut few_client = TreeletClient::start(config(svc.server.quic_addr, svc, &fewer)).unwrap();
    connected(&mut all_client).await;
    connected(&mut few_client).await;
    all_client.request(list.clone()).unwrap();
    few_client.request(list.clone()).unwrap();
    let (all, few) = tokio::join!(
        treelets(&mut all_client, list.len()),
        treelets(&mut few_client, list.len())
    );
    let all: HashMap<TreeletId, ReceivedTreelet> = all.into_iter().map(|t| (t.id, t)).collect();
    let few: HashMap<TreeletId, ReceivedTreelet> = few.into_iter().map(|t| (t.id, t)).collect();
    assert_eq!(all.len(), list.len());
    assert_eq!(few.len(), list.len());
    for (id, f) in &few {
        let chans: Vec<Channel> = f.channels.iter().map(|c| c.0).collect();
        assert_eq!(chans, fewer, "treelet {id}: only the channel asked for");
        let a = &all[id];
        assert_eq!(f.nodes, a.nodes);
        assert_eq!(f.channels.get(fewer[0]), a.channels.get(fewer[0]));
        assert!(f.channels.get(fewer[0]).is_some());
        assert!(f.wire_bytes < a.wire_bytes);
    }
    let (a, f) = (all_client.stats(), few_client.stats());
    eprintln!(
        "channels: {:?} → {} bytes, {:?} → {} bytes for {} treelets",
        layout,
        a.bytes_received,
        fewer,
        f.bytes_received,
        list.len()
    );
    assert!(f.bytes_received < a.bytes_received);
    all_client.close().await;
    few_client.close().await;
}

/// Refusals the client must treat as final, from the real server.
async fn refusals(svc: &Service) {
    let missing = Channel::ALL
        .into_iter()
        .find(|c| !svc.scene.layout.contains(*c))
        .expect("autzen has no density channel");
    let mut wrong_scene = config(svc.server.quic_addr, svc, &[]);
    wrong_scene.url.scene = "no-such-scene".into();
    let cases = [
        (
            config(svc.server.quic_addr, svc, &[missing]),
            ErrorCode::UnknownChannel,
        ),
        (
            config(svc.server.quic_addr, svc, &[]).with_token("wrong"),
            ErrorCode::Unauthorized,
        ),
        (wrong_scene, ErrorCode::UnknownScene),
    ];
    for (cfg, want) in cases {
        let mut client = TreeletClient::start(cfg).unwrap();
        client.request(vec![(TreeletId(0), 1.0)]).unwrap();
        let ClientEvent::Disconnected {
            code,
            reconnect_in,
            reason,
        } = event(&mut client).await
        else {
            panic!("{want}: expected Disconnected");
        };
        assert_eq!(code, Some(want), "{reason}");
        assert_eq!(reconnect_in, None, "{want} is final: {reason}");
        assert!(
            tokio::time::timeout(WAIT, client.next_event())
                .await
                .unwrap()
                .is_none()
        );
    }
}

/// A client evicts a treelet right after it arrived and asks for it again, and the list stays
/// the same from then on (a client sends a list only when it changes). The list came within the
/// server's redelivery guard, or even before the server saw the delivery end (a CI run on 2
/// cores failed that way while only the guard deferred), so the treelet is not sent at once;
/// it must come once the guard has passed, exactly once. Before, it never came: on a 16-core machine `client_e2e`'s
/// loopback views stalled that way in 6 of 8 runs.
async fn re_request_within_the_guard(svc: &Service) {
    let layout = svc.scene.layout.channels().to_vec();
    let mut client = TreeletClient::start(config(svc.server.quic_addr, svc, &layout)).unwrap();
    connected(&mut client).await;
    let (x, y) = (TreeletId(7), TreeletId(8));
    client.request(vec![(x, 1.0)]).unwrap();
    assert_eq!(treelet(&mut client).await.id, x);
    let asked = Instant::now();
    client.request(vec![(x, 1.0), (y, 0.5)]).unwrap();
    let mut got = vec![treelet(&mut client).await.id, treelet(&mut client).await.id];
    got.sort();
    assert_eq!(
        got,
        vec![x, y],
        "asked again, x comes again (after the guard)"
    );
    eprintln!(
        "re-request within the guard answered in {:.1?}",
        asked.elapsed()
    );
    quiet_for(&mut client, Duration::from_millis(300)).await;
    client.close().await;
}

async fn order_over_a_slow_link(svc: &Service) {
    let link = LinkEmulator::start(
        svc.server.quic_addr,
        LinkConfig::wan(Duration::from_millis(25), 100_000_000 / 8),
    )
    .await
    .unwrap();
    let layout = svc.scene.layout.channels().to_vec();
    let mut client = TreeletClient::start(config(link.local_addr(), svc, &layout)).unwrap();
    connected(&mut client).await;

    // Two disjoint 500-item lists with shuffled priorities.
    let perm = shuffled(svc.scene.treelet_count, 7);
    let prio = shuffled(1000, 11);
    let first: Vec<(TreeletId, f32)> = (0..500)
        .map(|i| (TreeletId(perm[i]), prio[i] as f32))
        .collect();
    let second: Vec<(TreeletId, f32)> = (500..1000)
        .map(|i| (TreeletId(perm[i]), prio[i] as f32))
        .collect();
    let (r1, r2) = (ranks(&first), ranks(&second));
    // The window bounds how far an arrival can be from its rank: when the server starts rank r
    // it has started every better rank and at most WINDOW - 1 of them are still in flight.
    let check_order = |what: &str, k: usize, r: usize| {
        assert!(
            r < k + WINDOW && k < r + WINDOW,
            "{what}: arrival {k} has rank {r}, outside the window of {WINDOW}"
        );
    };

    let t0 = Instant::now();
    client.request(first.clone()).unwrap();
    let before = 150;
    let mut seen = HashSet::new();
    for k in 0..before {
        let t = treelet(&mut client).await;
        assert!(seen.insert(t.id), "treelet {} twice", t.id);
        let r = *r1
            .get(&t.id)
            .unwrap_or_else(|| panic!("{} not asked for", t.id));
        check_order("first list", k, r);
    }
    let first_part = t0.elapsed();

    let t1 = Instant::now();
    client.request(second.clone()).unwrap();
    let mut old_after_request = 0usize;
    // Counted only once the connection has written the new list (the caller's own task may be
    // slow to get there on a busy machine).
    let mut old_after_send = 0usize;
    let mut old_after_first_new = 0usize;
    let mut new_arrivals = 0usize;
    let mut first_new_at = None;
    while new_arrivals < second.len() {
        let t = treelet(&mut client).await;
        assert!(seen.insert(t.id), "treelet {} twice", t.id);
        if let Some(&r) = r2.get(&t.id) {
            check_order("second list", new_arrivals, r);
            new_arrivals += 1;
            first_new_at.get_or_insert(t1.elapsed());
        } else {
            assert!(r1.contains_key(&t.id), "{} was never asked for", t.id);
            old_after_request += 1;
            if client.stats().lists_sent >= 2 {
                old_after_send += 1;
            }
            if new_arrivals > 0 {
                old_after_first_new += 1;
            }
        }
    }
    let second_list = t1.elapsed();
    // Stragglers of the old list, if any, arrive now or never.
    while let Ok(Some(e)) =
        tokio::time::timeout(Duration::from_millis(300), client.next_event()).await
    {
        match e {
            ClientEvent::Treelet(t) => {
                assert!(r1.contains_key(&t.id) && seen.insert(t.id), "{}", t.id);
                old_after_request += 1;
                old_after_send += 1;
                old_after_first_new += 1;
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    let stats = client.stats();
    let link_stats = link.stats();
    eprintln!(
        "order over 25 ms / 100 Mbit/s, window {WINDOW}: first {before} of list 1 in \
         {first_part:.2?}; list 2 (500) complete {second_list:.2?} after the replacement, its \
         first treelet after {:.2?}; old-list treelets arriving after the replacement: \
         {old_after_request} ({old_after_send} after it was sent, {old_after_first_new} after \
         the first new one); {} bytes received",
        first_new_at.unwrap(),
        stats.bytes_received,
    );
    eprintln!("link: {link_stats:?}");
    // Once the server works on the new list it starts nothing of the old one: only what was in
    // flight can still arrive.
    assert!(
        old_after_first_new < WINDOW,
        "{old_after_first_new} old-list treelets after the new list took effect"
    );
    // Counted from the moment the new list left, its one-way trip adds at most what the
    // deliveries during that trip let the server start: another window at most.
    assert!(
        old_after_send < 2 * WINDOW,
        "{old_after_send} old-list treelets after the new list was sent"
    );
    assert_eq!(stats.disconnects, 0);
    client.close().await;
}
