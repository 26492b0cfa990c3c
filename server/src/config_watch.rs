//! Noticing that a running daemon's configuration changed on disk, so that it reloads without a
//! signal (`config_watch_secs`; what SIGHUP does otherwise, [`crate::daemon::Reloader`]).
//!
//! Where the files are updated by something that cannot signal the process — the kubelet
//! rewriting a mounted ConfigMap or Secret (a cert-manager renewal, a rotated token), a
//! configuration tool — `arbor-server serve` looks every `config_watch_secs` at what a reload
//! would read: the configuration file as it loads (its token files read), and the bytes of the
//! certificate and key files and the admin-token file it names. Polling rather than inotify:
//! a mounted Secret is swapped by renaming a directory of symbolic links, which a watch on the
//! files does not see, and the files are a few kilobytes.
//!
//! [`ConfigWatch`] is plain data: it is handed a [`ConfigSnapshot`] per look and says when to
//! reload — once a snapshot differs from the one last put in force and has held still for one
//! look, so a file caught half-written (an editor saving in place, a certificate written
//! before its key) is not reloaded until it is whole. A configuration that does not load is a
//! snapshot too: it is tried once (the reload fails, is logged and counted) and not again until
//! the files change.

use std::path::{Path, PathBuf};

use crate::daemon::ADMIN_TOKEN_FILE;
use crate::service::ServeConfig;
use crate::service::config::{AdminTokenSource, ConfigOverrides, TlsSource};
use crate::service::tls::{CERT_FILE, KEY_FILE};

/// What a reload would read now.
#[derive(Clone, Debug, PartialEq)]
pub struct ConfigSnapshot {
    /// The configuration as it loads (token files read), or why it does not.
    config: Result<ServeConfig, String>,
    /// SHA-256 over each named file's path and bytes (or the kind of error reading it).
    files: [u8; 32],
}

impl ConfigSnapshot {
    /// Loads `file` as `serve` does and reads the certificates, keys and admin-token file it
    /// names; `data_dir` is where the running daemon keeps its self-signed pair and generated
    /// token.
    pub fn read(file: &Path, overrides: &ConfigOverrides, data_dir: &Path) -> Self {
        match ServeConfig::load(Some(file), overrides) {
            Ok(config) => Self {
                files: digest(&named_files(&config, data_dir)),
                config: Ok(config),
            },
            Err(e) => Self {
                config: Err(e.to_string()),
                files: [0; 32],
            },
        }
    }

    /// The configuration as it loaded, or why it did not.
    pub fn config(&self) -> Result<&ServeConfig, &str> {
        self.config.as_ref().map_err(String::as_str)
    }
}

/// The files besides the configuration a reload reads (`daemon::Reloader`'s `load`: keep them
/// in step).
fn named_files(config: &ServeConfig, data_dir: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    match &config.tls {
        TlsSource::Files { cert, key } => files.extend([cert.clone(), key.clone()]),
        TlsSource::SelfSigned => files.extend([data_dir.join(CERT_FILE), data_dir.join(KEY_FILE)]),
    }
    if let TlsSource::Files { cert, key } = &config.admin_identity {
        files.extend([cert.clone(), key.clone()]);
    }
    match &config.admin_token {
        AdminTokenSource::Inline(_) => {}
        AdminTokenSource::File(p) => files.push(p.clone()),
        AdminTokenSource::Generated => files.push(data_dir.join(ADMIN_TOKEN_FILE)),
    }
    files
}

fn digest(files: &[PathBuf]) -> [u8; 32] {
    let mut ctx = ring::digest::Context::new(&ring::digest::SHA256);
    for path in files {
        let bytes = path.as_os_str().as_encoded_bytes();
        ctx.update(&(bytes.len() as u64).to_le_bytes());
        ctx.update(bytes);
        match std::fs::read(path) {
            Ok(content) => {
                ctx.update(&[1]);
                ctx.update(&(content.len() as u64).to_le_bytes());
                ctx.update(&content);
            }
            Err(e) => {
                ctx.update(&[0]);
                ctx.update(format!("{:?}", e.kind()).as_bytes());
            }
        }
    }
    let mut out = [0; 32];
    out.copy_from_slice(ctx.finish().as_ref());
    out
}

/// When the files a reload reads have changed and held still ([`ConfigWatch::observe`]).
#[derive(Debug)]
pub struct ConfigWatch {
    /// What the last reload (or the start) read.
    applied: ConfigSnapshot,
    /// A different snapshot seen at the last look, waiting to hold still.
    pending: Option<ConfigSnapshot>,
}

impl ConfigWatch {
    /// A watch over what the daemon started with.
    pub fn new(applied: ConfigSnapshot) -> Self {
        Self {
            applied,
            pending: None,
        }
    }

    /// One look: true when `now` differs from what was last put in force and is what the look
    /// before saw too — reload now (the snapshot counts as put in force, whether the reload
    /// succeeds or not).
    pub fn observe(&mut self, now: ConfigSnapshot) -> bool {
        if now == self.applied {
            self.pending = None;
            return false;
        }
        if self.pending.as_ref() == Some(&now) {
            self.pending = None;
            self.applied = now;
            return true;
        }
        self.pending = Some(now);
        false
    }

    /// What the last reload (or the start) read: after [`ConfigWatch::observe`] said to
    /// reload, what to reload.
    pub fn applied(&self) -> &ConfigSnapshot {
        &self.applied
    }

    /// A reload happened without the watch (SIGHUP): `now` is what it read.
    pub fn reloaded(&mut self, now: ConfigSnapshot) {
        self.applied = now;
        self.pending = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Files {
        dir: tempfile::TempDir,
    }

    impl Files {
        fn new() -> Self {
            let files = Self {
                dir: tempfile::tempdir().unwrap(),
            };
            files.write("bunny.token", "alpha\n");
            files.write("admin.token", "admin\n");
            files.write("cert.pem", "certificate bytes");
            files.write("key.pem", "key bytes");
            let d = files.dir.path().display();
            files.write(
                "arbor.toml",
                &format!(
                    "db = \"{d}/pool\"\ncert = \"{d}/cert.pem\"\nkey = \"{d}/key.pem\"\n\
                     admin_token_file = \"{d}/admin.token\"\n\
                     [scenes.bunny]\ntoken_files = [\"{d}/bunny.token\"]\n"
                ),
            );
            files
        }

        fn write(&self, name: &str, text: &str) {
            std::fs::write(self.dir.path().join(name), text).unwrap();
        }

        fn snapshot(&self) -> ConfigSnapshot {
            ConfigSnapshot::read(
                &self.dir.path().join("arbor.toml"),
                &ConfigOverrides::default(),
                self.dir.path(),
            )
        }
    }

    #[test]
    fn every_file_a_reload_reads_is_seen_and_nothing_else() {
        let files = Files::new();
        let first = files.snapshot();
        assert!(first.config.is_ok(), "{:?}", first.config);
        assert_eq!(files.snapshot(), first, "nothing changed");
        files.write("bunny.token", "alpha\n");
        files.write("unrelated.txt", "x");
        assert_eq!(files.snapshot(), first, "the same bytes written again");
        for (name, text) in [
            ("bunny.token", "beta\n"),
            ("admin.token", "admin2\n"),
            ("cert.pem", "renewed certificate"),
            ("key.pem", "renewed key"),
        ] {
            let before = files.snapshot();
            files.write(name, text);
            assert_ne!(files.snapshot(), before, "{name} changed unseen");
        }
        std::fs::remove_file(files.dir.path().join("key.pem")).unwrap();
        let gone = files.snapshot();
        assert!(
            gone.config.is_ok(),
            "the key is read by the reload, not the load"
        );
        files.write("key.pem", "");
        assert_ne!(files.snapshot(), gone, "an empty file is not a missing one");
    }

    #[test]
    fn a_change_is_reloaded_once_it_held_still_for_one_look() {
        let files = Files::new();
        let mut watch = ConfigWatch::new(files.snapshot());
        assert!(!watch.observe(files.snapshot()));
        files.write("cert.pem", "renewed certificate");
        assert!(!watch.observe(files.snapshot()), "caught as it changed");
        files.write("key.pem", "renewed key");
        assert!(!watch.observe(files.snapshot()), "still changing");
        assert!(watch.observe(files.snapshot()), "held still: reload");
        assert!(!watch.observe(files.snapshot()), "reloaded once");

        // A file caught half-written and then restored is no reload.
        files.write("bunny.token", "");
        assert!(!watch.observe(files.snapshot()));
        files.write("bunny.token", "alpha\n");
        assert!(!watch.observe(files.snapshot()));
        assert!(!watch.observe(files.snapshot()));
    }

    #[test]
    fn a_configuration_that_does_not_load_is_tried_once() {
        let files = Files::new();
        let mut watch = ConfigWatch::new(files.snapshot());
        files.write("arbor.toml", "no_such_key = 1\n");
        let broken = files.snapshot();
        let text = broken.config.as_ref().unwrap_err();
        assert!(text.contains("no_such_key"), "{text}");
        assert!(!watch.observe(broken.clone()));
        assert!(watch.observe(broken.clone()), "tried (and logged) once");
        for _ in 0..3 {
            assert!(!watch.observe(files.snapshot()), "not again");
        }
        files.write(
            "arbor.toml",
            &format!("db = \"{}/pool\"\n", files.dir.path().display()),
        );
        assert!(!watch.observe(files.snapshot()));
        assert!(watch.observe(files.snapshot()), "mended: reloaded");
    }

    #[test]
    fn a_signalled_reload_is_not_repeated_by_the_watch() {
        let files = Files::new();
        let mut watch = ConfigWatch::new(files.snapshot());
        files.write("bunny.token", "beta\n");
        assert!(!watch.observe(files.snapshot()));
        watch.reloaded(files.snapshot());
        assert!(!watch.observe(files.snapshot()));
        assert!(!watch.observe(files.snapshot()));
    }
}
