//! The client connection against the in-test fake server (`common`).

mod common;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use arbor_client_net::{Backoff, ClientConfig, ClientEvent, ReceivedTreelet, TreeletClient, Trust};
use arbor_proto::wire::ErrorCode;
use arbor_proto::{Channel, SceneDescription, TreeletId};
use common::{Behaviour, FakeServer, Identity, channel_block, node_block, used_nodes};

const TOKEN: &str = "secret";
const WAIT: Duration = Duration::from_secs(15);

fn loopback() -> SocketAddr {
    "127.0.0.1:0".parse().unwrap()
}

fn fast_backoff() -> Backoff {
    Backoff {
        initial: Duration::from_millis(50),
        max: Duration::from_millis(400),
        factor: 2.0,
    }
}

fn config(server: &FakeServer, id: &Identity) -> ClientConfig {
    ClientConfig::new(
        server.url("lion"),
        Trust::Fingerprint(id.fingerprint.clone()),
    )
    .with_token(TOKEN)
    .with_channels([Channel::Color])
    .with_backoff(fast_backoff())
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

async fn treelets(client: &mut TreeletClient, n: usize) -> Vec<ReceivedTreelet> {
    let mut out = Vec::new();
    while out.len() < n {
        match event(client).await {
            ClientEvent::Treelet(t) => out.push(t),
            other => panic!("expected a treelet, got {other:?}"),
        }
    }
    out
}

fn ids(list: &[(TreeletId, f32)]) -> Vec<u32> {
    list.iter().map(|i| i.0.0).collect()
}

/// The treelet as the fake server sends it to a client asking for `Color` only.
fn check_bytes(t: &ReceivedTreelet, node_bytes: usize) {
    assert_eq!(t.used_nodes, used_nodes(t.id));
    assert_eq!(t.nodes, node_block(t.id, node_bytes));
    let channels: Vec<(Channel, &[u8])> = t.channels.iter().collect();
    assert_eq!(
        channels,
        [(
            Channel::Color,
            &channel_block(t.id, Channel::Color, node_bytes / 2)[..]
        )]
    );
    assert_eq!(
        t.channels.get(Channel::Color),
        Some(&channel_block(t.id, Channel::Color, node_bytes / 2)[..])
    );
    assert_eq!(t.channels.get(Channel::Normal), None);
    let header = 4 + 2 + 1 + 5 + 4;
    assert_eq!(t.wire_bytes, header + node_bytes + node_bytes / 2);
}

#[tokio::test]
async fn connects_and_receives_the_treelets_asked_for() {
    let id = Identity::self_signed();
    let server = FakeServer::start(&id, loopback(), Behaviour::new(TOKEN)).await;
    let mut client = TreeletClient::start(config(&server, &id)).unwrap();
    client
        .request(vec![
            (TreeletId(7), 1.0),
            (TreeletId(3), 3.0),
            (TreeletId(5), 2.0),
        ])
        .unwrap();
    let scene = connected(&mut client).await;
    assert_eq!(scene.name, "lion");
    assert_eq!(scene.treelet_count, 1000);
    assert_eq!(client.scene().unwrap(), scene);
    let got = treelets(&mut client, 3).await;
    // One stream each, sent in priority order; arrival order over separate streams may vary.
    let mut got_ids: Vec<u32> = got.iter().map(|t| t.id.0).collect();
    got_ids.sort();
    assert_eq!(got_ids, [3, 5, 7]);
    for t in &got {
        check_bytes(t, 600);
        assert!(t.latency > Duration::ZERO, "{:?}", t.latency);
        assert!(t.latency < WAIT);
    }
    let stats = client.stats();
    assert_eq!(stats.connects, 1);
    assert_eq!(stats.disconnects, 0);
    assert_eq!(stats.lists_sent, 1);
    assert_eq!(stats.treelets_received, 3);
    assert_eq!(
        stats.bytes_received,
        got.iter().map(|t| t.wire_bytes as u64).sum::<u64>()
    );
    assert_eq!(stats.buffered_bytes, 0);
    assert!(client.try_next_event().is_none());
    {
        let log = server.log();
        assert_eq!(log.hellos, [(vec![Channel::Color], TOKEN.to_owned())]);
        assert_eq!(log.lists.len(), 1);
        assert_eq!(ids(&log.lists[0].2), [7, 3, 5]);
        assert_eq!(log.sent, [TreeletId(3), TreeletId(5), TreeletId(7)]);
    }
    client.close().await;
    server.stop(ErrorCode::NoError).await;
}

#[tokio::test]
async fn a_new_list_replaces_the_old_one_with_a_higher_seq() {
    let id = Identity::self_signed();
    let server = FakeServer::start(&id, loopback(), Behaviour::new(TOKEN)).await;
    let mut client = TreeletClient::start(config(&server, &id)).unwrap();
    connected(&mut client).await;
    client
        .request(vec![(TreeletId(1), 1.0), (TreeletId(2), 1.0)])
        .unwrap();
    treelets(&mut client, 2).await;
    client
        .request(vec![(TreeletId(2), 5.0), (TreeletId(9), 4.0)])
        .unwrap();
    // Only 9 is new to this connection.
    let t = treelets(&mut client, 1).await;
    assert_eq!(t[0].id, TreeletId(9));
    client.request(vec![]).unwrap();
    tokio::time::timeout(WAIT, async {
        while server.log().lists.len() < 3 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await
    .unwrap();
    {
        let log = server.log();
        let seqs: Vec<u64> = log.lists.iter().map(|l| l.1).collect();
        assert!(seqs.windows(2).all(|w| w[0] < w[1]), "{seqs:?}");
        assert_eq!(ids(&log.lists[0].2), [1, 2]);
        assert_eq!(log.lists[1].2, [(TreeletId(2), 5.0), (TreeletId(9), 4.0)]);
        assert!(log.lists[2].2.is_empty());
    }
    assert_eq!(client.stats().lists_sent, 3);
    // Invalid lists are refused at the call, not sent.
    assert!(client.request(vec![(TreeletId(1), f32::NAN)]).is_err());
    assert!(client.request(vec![(TreeletId::NONE, 1.0)]).is_err());
    assert!(
        client
            .request(vec![
                (TreeletId(1), 1.0);
                arbor_proto::limits::MAX_REQUEST_ITEMS + 1
            ])
            .is_err()
    );
    client.close().await;
    server.stop(ErrorCode::NoError).await;
}

/// Waits until the connection task has taken `n` lists (sent or found unchanged).
async fn wait_handled(c: &TreeletClient, n: u64) {
    tokio::time::timeout(WAIT, async {
        while c.stats().lists_sent + c.stats().lists_unchanged < n {
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    })
    .await
    .expect("the list was taken");
}

#[tokio::test]
async fn a_list_saying_exactly_what_the_last_said_is_not_sent_again() {
    let id = Identity::self_signed();
    let server = FakeServer::start(&id, loopback(), Behaviour::new(TOKEN)).await;
    let mut client = TreeletClient::start(config(&server, &id)).unwrap();
    connected(&mut client).await;
    let list = vec![(TreeletId(1), 1.0), (TreeletId(2), 1.0)];
    client.request(list.clone()).unwrap();
    treelets(&mut client, 2).await;
    client.request(list.clone()).unwrap();
    wait_handled(&client, 2).await;
    assert_eq!(
        (client.stats().lists_sent, client.stats().lists_unchanged),
        (1, 1)
    );
    // A priority differing in one bit is a different list.
    client
        .request(vec![
            (TreeletId(1), 1.0),
            (TreeletId(2), f32::from_bits(1.0f32.to_bits() + 1)),
        ])
        .unwrap();
    wait_handled(&client, 3).await;
    // The same items with a view are a deep list: different again.
    let view = arbor_proto::wire::ViewHint {
        eye: [0.5, 0.5, 3.0],
        forward: [0.0, 0.0, -1.0],
        up: [0.0, 1.0, 0.0],
        tan_half_fov_y: 0.5,
        aspect: 1.0,
        footprint: 0.001,
        free_slots: 8,
    };
    let deep = vec![(TreeletId(1), 1.0, 2.0), (TreeletId(2), 1.0, 2.0)];
    client.request_deep(deep.clone(), view, 2).unwrap();
    wait_handled(&client, 4).await;
    client.request_deep(deep.clone(), view, 2).unwrap();
    wait_handled(&client, 5).await;
    assert_eq!(
        (client.stats().lists_sent, client.stats().lists_unchanged),
        (3, 2)
    );
    // Fewer free slots change the view: sent.
    client
        .request_deep(
            deep.clone(),
            arbor_proto::wire::ViewHint {
                free_slots: 7,
                ..view
            },
            2,
        )
        .unwrap();
    tokio::time::timeout(WAIT, async {
        while server.log().lists.len() < 4 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await
    .unwrap();
    assert_eq!(server.log().lists.len(), 4);
    assert_eq!(client.stats().lists_sent, 4);
    // Another prefetch start changes the list: sent. An id the scene does not have is left
    // out, and the start counts only the items kept before it.
    let mut with_unknown = deep.clone();
    with_unknown.insert(0, (TreeletId(u32::MAX - 1), 3.0, 1.0));
    for (list, prefetch_from, logged) in [(deep.clone(), 1, 5), (with_unknown, 2, 6)] {
        client.request_deep(list, view, prefetch_from).unwrap();
        tokio::time::timeout(WAIT, async {
            while server.log().lists.len() < logged {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        })
        .await
        .unwrap();
    }
    {
        let log = server.log();
        assert_eq!(log.prefetch_starts, [2, 2, 1, 1]);
        assert_eq!(
            log.lists[5].2,
            [(TreeletId(1), 2.0), (TreeletId(2), 1.0)],
            "the unknown id is not sent; equal priorities ranked by id"
        );
    }
    client.close().await;
    server.stop(ErrorCode::NoError).await;
}

#[tokio::test]
async fn reconnects_after_shutting_down_and_sends_the_latest_list_again() {
    let id = Identity::self_signed();
    let mut behaviour = Behaviour::new(TOKEN);
    behaviour.close_after_lists = Some((1, ErrorCode::ShuttingDown));
    let server = FakeServer::start(&id, loopback(), behaviour.clone()).await;
    let addr = server.addr;
    let mut client = TreeletClient::start(config(&server, &id).with_backoff(Backoff {
        initial: Duration::from_millis(200),
        max: Duration::from_secs(1),
        factor: 2.0,
    }))
    .unwrap();
    let first = vec![(TreeletId(1), 2.0), (TreeletId(2), 1.0)];
    client.request(first.clone()).unwrap();
    connected(&mut client).await;
    treelets(&mut client, 2).await;
    let ClientEvent::Disconnected {
        code,
        reconnect_in,
        reason,
    } = event(&mut client).await
    else {
        panic!("expected Disconnected");
    };
    assert_eq!(code, Some(ErrorCode::ShuttingDown), "{reason}");
    let delay = reconnect_in.expect("ShuttingDown must lead to a reconnect");
    assert!(delay <= Duration::from_millis(200) && delay >= Duration::from_millis(180));

    // The server comes back on the same port; nothing new was asked: the same list again.
    server.stop(ErrorCode::ShuttingDown).await;
    let server = FakeServer::start(&id, addr, behaviour.clone()).await;
    assert_eq!(server.addr, addr);
    connected(&mut client).await;
    treelets(&mut client, 2).await;
    let ClientEvent::Disconnected { code, .. } = event(&mut client).await else {
        panic!("expected Disconnected");
    };
    assert_eq!(code, Some(ErrorCode::ShuttingDown));
    let seq_before = {
        let log = server.log();
        assert_eq!(log.lists.len(), 1);
        assert_eq!(log.lists[0].2, first);
        log.lists[0].1
    };

    // A new list asked for while disconnected is the one sent after the next reconnect.
    let second = vec![(TreeletId(4), 1.0), (TreeletId(5), 0.5)];
    client.request(second.clone()).unwrap();
    server.stop(ErrorCode::ShuttingDown).await;
    let server = FakeServer::start(&id, addr, behaviour).await;
    connected(&mut client).await;
    let got = treelets(&mut client, 2).await;
    let mut got_ids: Vec<u32> = got.iter().map(|t| t.id.0).collect();
    got_ids.sort();
    assert_eq!(got_ids, [4, 5]);
    {
        let log = server.log();
        assert_eq!(log.lists[0].2, second);
        assert!(log.lists[0].1 > seq_before);
    }
    let stats = client.stats();
    assert_eq!(stats.connects, 3);
    assert!(stats.disconnects >= 2);
    assert_eq!(stats.last_close_code, Some(ErrorCode::ShuttingDown));
    client.close().await;
    server.stop(ErrorCode::NoError).await;
}

#[tokio::test]
async fn unauthorized_is_final() {
    let id = Identity::self_signed();
    let server = FakeServer::start(&id, loopback(), Behaviour::new(TOKEN)).await;
    let mut client = TreeletClient::start(config(&server, &id).with_token("wrong token")).unwrap();
    client.request(vec![(TreeletId(1), 1.0)]).unwrap();
    let ClientEvent::Disconnected {
        code,
        reconnect_in,
        reason,
    } = event(&mut client).await
    else {
        panic!("expected Disconnected");
    };
    assert_eq!(code, Some(ErrorCode::Unauthorized), "{reason}");
    assert_eq!(reconnect_in, None);
    assert!(reason.contains("unauthorized"), "{reason}");
    // No more events, no more attempts.
    assert!(
        tokio::time::timeout(WAIT, client.next_event())
            .await
            .unwrap()
            .is_none()
    );
    assert!(client.is_finished());
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(server.log().connections, 1);
    assert!(server.log().lists.is_empty());
    let stats = client.stats();
    assert_eq!((stats.connects, stats.disconnects), (0, 1));
    assert_eq!(stats.last_close_code, Some(ErrorCode::Unauthorized));
    server.stop(ErrorCode::NoError).await;
}

#[tokio::test]
async fn refusals_are_final_or_retried_by_code() {
    let id = Identity::self_signed();
    for (code, is_final) in [
        (ErrorCode::UnknownScene, true),
        (ErrorCode::UnsupportedVersion, true),
        (ErrorCode::UnknownChannel, true),
        (ErrorCode::ServerBusy, false),
    ] {
        let mut b = Behaviour::new(TOKEN);
        b.refuse = Some(code);
        let server = FakeServer::start(&id, loopback(), b).await;
        let mut client = TreeletClient::start(config(&server, &id)).unwrap();
        let ClientEvent::Disconnected {
            code: got,
            reconnect_in,
            reason,
        } = event(&mut client).await
        else {
            panic!("expected Disconnected");
        };
        assert_eq!(got, Some(code), "{reason}");
        assert_eq!(reconnect_in.is_none(), is_final, "{code}: {reason}");
        if !is_final {
            // It keeps trying (and is refused again).
            let ClientEvent::Disconnected { code: again, .. } = event(&mut client).await else {
                panic!("expected another Disconnected");
            };
            assert_eq!(again, Some(code));
            assert!(server.log().connections >= 2);
        }
        client.close().await;
        server.stop(ErrorCode::NoError).await;
    }
}

#[tokio::test]
async fn backpressure_bounds_the_buffered_bytes() {
    let id = Identity::self_signed();
    let mut behaviour = Behaviour::new(TOKEN);
    behaviour.node_bytes = 4000;
    let server = FakeServer::start(&id, loopback(), behaviour).await;
    let bound = 20_000;
    let mut client =
        TreeletClient::start(config(&server, &id).with_max_buffered_bytes(bound)).unwrap();
    connected(&mut client).await;
    let n = 40u32;
    client
        .request((1..=n).map(|i| (TreeletId(i), i as f32)).collect())
        .unwrap();
    // Wait until the server has written everything (QUIC buffers it on the client side).
    tokio::time::timeout(WAIT, async {
        while server.log().sent.len() < n as usize {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await
    .unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let message = 4 + 2 + 1 + 5 + 4 + 4000 + 2000;
    let stats = client.stats();
    assert!(stats.buffered_bytes <= bound, "{stats:?}");
    assert!(stats.peak_buffered_bytes <= bound, "{stats:?}");
    // The caller took nothing: the client holds what fits and reads no further.
    assert_eq!(
        stats.treelets_received as usize,
        bound / message,
        "{stats:?}"
    );
    // Draining lets the rest in, never beyond the bound.
    let mut got = Vec::new();
    while got.len() < n as usize {
        let t = treelets(&mut client, 1).await.pop().unwrap();
        check_bytes(&t, 4000);
        got.push(t.id.0);
        let s = client.stats();
        assert!(
            s.buffered_bytes <= bound && s.peak_buffered_bytes <= bound,
            "{s:?}"
        );
    }
    got.sort();
    assert_eq!(got, (1..=n).collect::<Vec<_>>());
    assert_eq!(client.stats().treelets_received, u64::from(n));
    client.close().await;
    server.stop(ErrorCode::NoError).await;
}

#[tokio::test]
async fn an_unrequested_channel_is_a_protocol_violation() {
    let id = Identity::self_signed();
    let mut behaviour = Behaviour::new(TOKEN);
    behaviour.all_channels = true;
    let server = FakeServer::start(&id, loopback(), behaviour).await;
    let mut client = TreeletClient::start(config(&server, &id)).unwrap();
    client.request(vec![(TreeletId(1), 1.0)]).unwrap();
    connected(&mut client).await;
    let ClientEvent::Disconnected {
        code,
        reconnect_in,
        reason,
    } = event(&mut client).await
    else {
        panic!("expected Disconnected, not a treelet");
    };
    assert_eq!(code, Some(ErrorCode::ProtocolViolation), "{reason}");
    assert!(reason.contains("normal"), "{reason}");
    assert!(reconnect_in.is_some());
    assert_eq!(client.stats().treelets_received, 0);
    tokio::time::timeout(WAIT, async {
        while server.log().client_close_codes.is_empty() {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await
    .unwrap();
    assert_eq!(
        server.log().client_close_codes[0],
        u64::from(ErrorCode::ProtocolViolation.to_u32())
    );
    client.close().await;
    server.stop(ErrorCode::NoError).await;
}

#[tokio::test]
async fn messages_on_one_stream_split_at_any_byte_arrive_whole() {
    let id = Identity::self_signed();
    let mut behaviour = Behaviour::new(TOKEN);
    // 916 bytes per message (16 of header, 600 node bytes, 300 colour bytes) written 97 bytes
    // at a time: messages start and end inside chunks, and headers straddle chunks. The 100
    // messages copied together take more than one of the reader's 64 KiB join buffers.
    behaviour.one_stream_pieces = Some(97);
    let node_bytes = behaviour.node_bytes;
    let server = FakeServer::start(&id, loopback(), behaviour).await;
    let mut client = TreeletClient::start(config(&server, &id)).unwrap();
    let list: Vec<(TreeletId, f32)> = (1..=100)
        .map(|i| (TreeletId(i), 200.0 - i as f32))
        .collect();
    client.request(list.clone()).unwrap();
    connected(&mut client).await;
    let got = treelets(&mut client, list.len()).await;
    // One stream carries them in the list's order.
    assert_eq!(got.iter().map(|t| t.id.0).collect::<Vec<_>>(), ids(&list));
    for t in &got {
        check_bytes(t, node_bytes);
    }
    assert_eq!(client.stats().treelets_received, list.len() as u64);
    client.close().await;
    server.stop(ErrorCode::NoError).await;
}

#[tokio::test]
async fn a_stream_cut_inside_a_message_is_a_protocol_violation() {
    let id = Identity::self_signed();
    let mut behaviour = Behaviour::new(TOKEN);
    behaviour.one_stream_pieces = Some(500);
    behaviour.cut_last = 10;
    let server = FakeServer::start(&id, loopback(), behaviour).await;
    let mut client = TreeletClient::start(config(&server, &id)).unwrap();
    client
        .request(vec![(TreeletId(1), 2.0), (TreeletId(2), 1.0)])
        .unwrap();
    connected(&mut client).await;
    // The first message is whole and arrives; the second ends 10 bytes short.
    let ClientEvent::Treelet(first) = event(&mut client).await else {
        panic!("expected the whole first treelet");
    };
    assert_eq!(first.id, TreeletId(1));
    let ClientEvent::Disconnected { code, reason, .. } = event(&mut client).await else {
        panic!("expected Disconnected, not a cut treelet");
    };
    assert_eq!(code, Some(ErrorCode::ProtocolViolation), "{reason}");
    assert!(reason.contains("block bytes of treelet 2"), "{reason}");
    assert_eq!(client.stats().treelets_received, 1);
    client.close().await;
    server.stop(ErrorCode::NoError).await;
}

#[tokio::test]
async fn certificate_trust_pin_and_ca() {
    // A CA-signed server, trusted through its CA, by IP address and by name.
    let ca_signed = Identity::ca_signed();
    let server = FakeServer::start(&ca_signed, loopback(), Behaviour::new(TOKEN)).await;
    let localhost_is_v4 = tokio::net::lookup_host(("localhost", 1))
        .await
        .is_ok_and(|mut a| a.next().is_some_and(|a| a.is_ipv4()));
    let hosts: &[&str] = if localhost_is_v4 {
        &["127.0.0.1", "localhost"]
    } else {
        eprintln!("localhost does not resolve to IPv4 first here; testing by address only");
        &["127.0.0.1"]
    };
    for &host in hosts {
        let mut url = server.url("lion");
        url.host = host.into();
        let cfg = ClientConfig::new(url, Trust::CaPem(ca_signed.trust_pem.clone().into_bytes()))
            .with_token(TOKEN)
            .with_backoff(fast_backoff());
        let mut client = TreeletClient::start(cfg).unwrap();
        match event(&mut client).await {
            ClientEvent::Connected(_) => {}
            other => panic!("{host}: {other:?}"),
        }
        client.close().await;
    }
    // The wrong CA, or the wrong pin: the handshake fails and the client gives up.
    let other = Identity::self_signed();
    for trust in [
        Trust::CaPem(other.trust_pem.clone().into_bytes()),
        Trust::Fingerprint(other.fingerprint.clone()),
    ] {
        let cfg = ClientConfig::new(server.url("lion"), trust.clone())
            .with_token(TOKEN)
            .with_backoff(fast_backoff());
        let mut client = TreeletClient::start(cfg).unwrap();
        let ClientEvent::Disconnected {
            code,
            reconnect_in,
            reason,
        } = event(&mut client).await
        else {
            panic!("{trust:?}: expected Disconnected");
        };
        assert_eq!(code, None);
        assert_eq!(reconnect_in, None, "{reason}");
        assert!(reason.contains("TLS"), "{reason}");
        assert!(client.next_event().await.is_none());
    }
    server.stop(ErrorCode::NoError).await;
}

#[tokio::test]
async fn ipv6_and_graceful_close() {
    let id = Identity::self_signed();
    let Ok(addr) = "[::1]:0".parse::<SocketAddr>() else {
        unreachable!()
    };
    if std::net::UdpSocket::bind(addr).is_err() {
        eprintln!("no IPv6 loopback here; skipping");
        return;
    }
    let server = FakeServer::start(&id, addr, Behaviour::new(TOKEN)).await;
    let url =
        arbor_client_net::parse_server_url(&format!("quic://[::1]:{}/lion", server.addr.port()))
            .unwrap();
    let cfg = ClientConfig::new(url, Trust::Fingerprint(id.fingerprint.clone()))
        .with_token(TOKEN)
        .with_channels([Channel::Color]);
    let mut client = TreeletClient::start(cfg).unwrap();
    client.request(vec![(TreeletId(42), 1.0)]).unwrap();
    connected(&mut client).await;
    let t = treelets(&mut client, 1).await;
    check_bytes(&t[0], 600);
    client.close().await;
    tokio::time::timeout(WAIT, async {
        while server.log().client_close_codes.is_empty() {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await
    .unwrap();
    {
        let log = server.log();
        assert_eq!(log.goodbyes, 1);
        assert_eq!(
            log.client_close_codes,
            [u64::from(ErrorCode::NoError.to_u32())]
        );
    }
    server.stop(ErrorCode::NoError).await;
}

#[test]
fn start_outside_a_runtime_is_an_error() {
    let cfg = ClientConfig::new(
        arbor_client_net::parse_server_url("quic://127.0.0.1:1/lion").unwrap(),
        Trust::Fingerprint("00".repeat(32)),
    );
    assert!(matches!(
        TreeletClient::start(cfg.clone()),
        Err(arbor_client_net::ClientError::NoRuntime)
    ));
    let bad = cfg.clone().with_channels([Channel::Color, Channel::Color]);
    assert!(matches!(
        TreeletClient::start(bad),
        Err(arbor_client_net::ClientError::InvalidConfig(_))
    ));
    let no_window = cfg.with_list_send_window(0);
    match TreeletClient::start(no_window) {
        Err(arbor_client_net::ClientError::InvalidConfig(m)) => {
            assert!(m.contains("list_send_window"), "{m}")
        }
        other => panic!("a list send window of 0 bytes: {:?}", other.err()),
    }
}
