//! The servers a client may use — its URL and the replicas of the same pool — and which one it
//! uses now.
//!
//! The client stays with one server while it works. When an established connection is lost it
//! moves to the next server at once (the caller's slot buffer and latest list carry over: the
//! list is re-sent on the new connection); failed attempts move on too, with backoff. Every
//! server must describe the scene exactly as the first one the client connected to did — a
//! replica that differs would hand out treelets that do not fit the caller's tree — so one that
//! differs is refused and left out from then on.

use std::sync::Arc;

use arbor_proto::SceneDescription;

use super::url::ServerUrl;

/// The rotation over the configured servers (plain data; the connection task drives it).
#[derive(Debug)]
pub(crate) struct Replicas {
    servers: Vec<ServerUrl>,
    current: usize,
    /// Per server: refused for describing the scene differently.
    refused: Vec<bool>,
    /// The description the first connection gave; every later one must equal it.
    scene: Option<Arc<SceneDescription>>,
}

impl Replicas {
    /// `servers` in order of preference; the first is used first. Must not be empty.
    pub fn new(servers: Vec<ServerUrl>) -> Self {
        assert!(!servers.is_empty(), "at least one server");
        Self {
            refused: vec![false; servers.len()],
            servers,
            current: 0,
            scene: None,
        }
    }

    /// The server to use now.
    pub fn current(&self) -> &ServerUrl {
        &self.servers[self.current]
    }

    /// Whether there is another server to fail over to.
    pub fn can_fail_over(&self) -> bool {
        self.refused.iter().filter(|r| !**r).count() > 1
    }

    /// Moves to the next server that is not refused (the current one again when it is the only
    /// one left). Returns whether the server changed.
    pub fn advance(&mut self) -> bool {
        let n = self.servers.len();
        let from = self.current;
        for step in 1..=n {
            let i = (from + step) % n;
            if !self.refused[i] {
                self.current = i;
                break;
            }
        }
        self.current != from
    }

    /// Checks the current server's description of the scene: the first connection fixes it; a
    /// server that describes it differently is refused (and skipped from now on), with a reason
    /// for people.
    pub fn admit(&mut self, scene: &Arc<SceneDescription>) -> Result<(), String> {
        match &self.scene {
            None => {
                self.scene = Some(scene.clone());
                Ok(())
            }
            Some(known) if **known == **scene => Ok(()),
            Some(known) => {
                self.refused[self.current] = true;
                Err(format!(
                    "{} describes scene {:?} differently ({} treelets, {} voxels, {} bytes) \
                     than the server first connected to ({} treelets, {} voxels, {} bytes): \
                     not a replica of the same pool, refused",
                    self.current(),
                    scene.name,
                    scene.treelet_count,
                    scene.stats.voxels,
                    scene_bytes(scene),
                    known.treelet_count,
                    known.stats.voxels,
                    scene_bytes(known),
                ))
            }
        }
    }
}

fn scene_bytes(d: &SceneDescription) -> u64 {
    d.stats.node_bytes + d.stats.channel_bytes.iter().sum::<u64>()
}

#[cfg(test)]
mod tests {
    use super::*;
    use arbor_proto::{
        AttributeLayout, BuildParameters, Channel, SceneStats, SourceKind, TreeletId,
    };

    fn url(port: u16) -> ServerUrl {
        ServerUrl {
            host: "127.0.0.1".into(),
            port,
            scene: "lion".into(),
        }
    }

    fn scene(treelets: u32) -> Arc<SceneDescription> {
        Arc::new(SceneDescription {
            name: "lion".into(),
            origin: [0.0; 3],
            edge: 1.0,
            treelet_nodes: 512,
            max_depth: 10,
            layout: AttributeLayout::new([Channel::Color]),
            treelet_count: treelets,
            root_treelet: TreeletId::ROOT,
            source_kind: SourceKind::Points,
            source: "lion.laz".into(),
            primitives: 100,
            build: BuildParameters {
                requested_depth: None,
                data_resolution: 0.01,
                treelet_bytes: 4096,
                iso: None,
                zstd_level: 9,
                dictionary: false,
            },
            stats: SceneStats::default(),
            node_dictionary: None,
            channel_dictionaries: vec![None],
        })
    }

    #[test]
    fn rotates_through_the_servers_in_order() {
        let mut r = Replicas::new(vec![url(1), url(2), url(3)]);
        assert_eq!(r.current().port, 1);
        assert!(r.can_fail_over());
        let ports: Vec<u16> = (0..4)
            .map(|_| {
                assert!(r.advance());
                r.current().port
            })
            .collect();
        assert_eq!(ports, [2, 3, 1, 2]);
        let mut one = Replicas::new(vec![url(1)]);
        assert!(!one.can_fail_over());
        assert!(!one.advance());
        assert_eq!(one.current().port, 1);
    }

    #[test]
    fn a_server_describing_the_scene_differently_is_refused_and_skipped() {
        let mut r = Replicas::new(vec![url(1), url(2), url(3)]);
        r.admit(&scene(10)).unwrap();
        r.advance();
        let reason = r.admit(&scene(11)).unwrap_err();
        assert!(
            reason.contains("127.0.0.1:2") && reason.contains("differently"),
            "{reason}"
        );
        r.advance();
        assert_eq!(r.current().port, 3);
        r.admit(&scene(10)).unwrap();
        // Port 2 is skipped from now on.
        r.advance();
        assert_eq!(r.current().port, 1);
        r.advance();
        assert_eq!(r.current().port, 3);
        assert!(r.can_fail_over());
    }

    #[test]
    fn with_every_other_server_refused_it_stays_on_the_first() {
        let mut r = Replicas::new(vec![url(1), url(2)]);
        r.admit(&scene(10)).unwrap();
        r.advance();
        assert!(r.admit(&scene(9)).is_err());
        assert!(!r.can_fail_over());
        r.advance();
        assert_eq!(r.current().port, 1);
        assert!(!r.advance());
        assert_eq!(r.current().port, 1);
    }
}
