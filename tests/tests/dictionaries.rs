//! Prepared zstd dictionaries (`codec::PreparedDictionaries`, what the client session and the
//! server load once per scene) decode every stored block of the real scans exactly as the raw
//! dictionaries do, and another scene's dictionaries fail with a clear error, never a panic or a
//! wrong treelet.

use arbor_client_core::slots::{DecodedTreelet, SlotError};
use arbor_proto::codec::PreparedDictionaries;
use arbor_proto::{Channel, TreeletId};
use arbor_server::octree::{BuildOptions, DepthChoice};
use arbor_server::pool::StoredScene;
use arbor_tests::support::{SCANS, build_file};

/// A treelet's stored blocks: the node block and each channel's block.
type Blocks = (Vec<u8>, Vec<(Channel, Vec<u8>)>);

/// Every treelet's blocks of `scene`, by treelet id.
fn blocks(scene: &StoredScene) -> Vec<Blocks> {
    let channels = scene.description.layout.channels().to_vec();
    (0..scene.description.treelet_count)
        .map(|id| {
            let id = TreeletId(id);
            let nodes = scene
                .nodes(id)
                .unwrap()
                .expect("node block stored")
                .to_vec();
            let attrs = channels
                .iter()
                .map(|&c| (c, scene.channel(c, id).unwrap().expect("stored").to_vec()))
                .collect();
            (nodes, attrs)
        })
        .collect()
}

#[test]
fn prepared_dictionaries_decode_every_real_block_like_raw_ones() {
    let opts = BuildOptions {
        depth: DepthChoice::Fixed(8),
        treelet_bytes: 4096,
        ..BuildOptions::default()
    };
    let mut with_dictionary = 0;
    let mut other: Option<(String, PreparedDictionaries)> = None;
    for (name, rel) in SCANS {
        let built = build_file(rel, name, &opts);
        let d = &built.scene.description;
        with_dictionary += usize::from(d.node_dictionary.is_some());
        let channels = d.layout.channels().to_vec();
        let prepared = PreparedDictionaries::of(d);
        for (i, (nodes, attrs)) in blocks(&built.scene).iter().enumerate() {
            let id = TreeletId(i as u32);
            let refs: Vec<(Channel, &[u8])> = attrs.iter().map(|(c, b)| (*c, &b[..])).collect();
            let raw = DecodedTreelet::from_blocks(id, nodes, &refs, d, &channels).unwrap();
            let fast =
                DecodedTreelet::from_blocks_prepared(id, nodes, &refs, d, &prepared, &channels)
                    .unwrap();
            assert_eq!(fast, raw, "{name} treelet {i}");
            let message = DecodedTreelet::decode_message(
                id,
                raw.treelet.header.used_nodes,
                nodes,
                &refs,
                d,
                &prepared,
                &channels,
            )
            .unwrap();
            assert_eq!(message, raw, "{name} treelet {i} as a message");
            // Another scene's dictionaries: a decode error naming the treelet, or (where the
            // other dictionary happens to decode the bytes) a tree that fails validation — never
            // a panic and never this treelet.
            if let Some((other_name, other)) = &other
                && d.node_dictionary.is_some()
            {
                match DecodedTreelet::from_blocks_prepared(id, nodes, &refs, d, other, &channels) {
                    Err(SlotError::Decode { id: bad, .. }) => assert_eq!(bad, id),
                    Err(_) => {}
                    Ok(t) => {
                        panic!("{name} treelet {i} decoded with {other_name}'s dictionary: {t:?}")
                    }
                }
            }
        }
        if d.node_dictionary.is_some() {
            other = Some((name.to_owned(), prepared));
        }
    }
    assert!(
        with_dictionary >= 2,
        "only {with_dictionary} scans have a node dictionary: the test compares nothing prepared"
    );
}
