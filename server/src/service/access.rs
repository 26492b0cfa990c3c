//! Who may open which scene while the service runs, and which sessions a new rule shuts out.
//!
//! The scene rules of the configuration (`[scenes.NAME]` with `access` or tokens,
//! `default_access`) are read at start and again when the daemon is told to
//! ([`super::AccessHandle::reload`], SIGHUP for `arbor-server serve`). A token
//! added opens its scene to the next `Hello`; a token removed, or a public scene made
//! token-only, also ends the sessions it let in (close code `Unauthorized`), so revoking a
//! token needs no restart and leaves every other client connected.
//!
//! A session keeps what it was let in with as a [`Grant`]: its scene and the HMAC tag of its
//! token under the process's random key. The token itself is not kept, and a new rule is
//! checked against the tag in constant time, as a `Hello` is. [`SceneAccess`] is generic over
//! the session's handle, so the rule swap and the choice of whom it shuts out are tested here
//! without sockets; the service keeps `quinn::Connection`s in it and closes those it is given.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, OnceLock, RwLock};

use arbor_proto::scene::validate_scene_name;
use arbor_proto::wire::ErrorCode;
use ring::hmac;

use super::config::{Access, SceneAccess as SceneRule, ServeConfig};

/// The scene rules in force: one per named scene, the default for the others.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AccessPolicy {
    default_access: Access,
    scenes: BTreeMap<String, SceneRule>,
}

/// What a session was let in with.
#[derive(Clone, Debug)]
pub struct Grant {
    /// The scene it opened.
    pub scene: String,
    /// Its token's tag under [`token_key`].
    tag: hmac::Tag,
}

impl AccessPolicy {
    /// The rules of `config` (its token files already read).
    pub fn of(config: &ServeConfig) -> AccessPolicy {
        AccessPolicy {
            default_access: config.default_access,
            scenes: config.scenes.clone(),
        }
    }

    /// Whether `token` opens `scene`; `exists` says whether the pool has the scene.
    ///
    /// Unknown scene → [`ErrorCode::UnknownScene`] (checked first); a scene that needs a token
    /// and did not get a matching one → [`ErrorCode::Unauthorized`]. Tokens are compared in
    /// constant time; every configured token of the scene is compared, whatever matched.
    pub fn admit(
        &self,
        scene: &str,
        token: &str,
        exists: impl FnOnce(&str) -> bool,
    ) -> Result<Grant, ErrorCode> {
        if validate_scene_name(scene).is_err() || !exists(scene) {
            return Err(ErrorCode::UnknownScene);
        }
        let grant = Grant {
            scene: scene.to_owned(),
            tag: hmac::sign(token_key(), token.as_bytes()),
        };
        if self.admits(&grant) {
            Ok(grant)
        } else {
            Err(ErrorCode::Unauthorized)
        }
    }

    /// Whether a session let in with `grant` may stay under these rules.
    pub fn admits(&self, grant: &Grant) -> bool {
        match self.scenes.get(&grant.scene) {
            Some(SceneRule::Public) => true,
            Some(SceneRule::Tokens(tokens)) => {
                let mut ok = false;
                for t in tokens {
                    ok |= hmac::verify(token_key(), t.as_bytes(), grant.tag.as_ref()).is_ok();
                }
                ok
            }
            None => self.default_access == Access::Public,
        }
    }
}

/// The rules in force and the sessions they let in, each with its handle `C`.
#[derive(Debug)]
pub struct SceneAccess<C> {
    policy: RwLock<Arc<AccessPolicy>>,
    sessions: Mutex<BTreeMap<u64, (Grant, C)>>,
}

impl<C> SceneAccess<C> {
    pub fn new(policy: AccessPolicy) -> SceneAccess<C> {
        SceneAccess {
            policy: RwLock::new(Arc::new(policy)),
            sessions: Mutex::new(BTreeMap::new()),
        }
    }

    /// The rules in force now.
    pub fn policy(&self) -> Arc<AccessPolicy> {
        Arc::clone(&self.policy.read().unwrap_or_else(|p| p.into_inner()))
    }

    /// Session `id` was let in with `grant`. Checked again under the rules in force now, in
    /// the same lock a new rule is put in force with: a session admitted under rules that were
    /// replaced meanwhile is refused here (`false`), not missed by both.
    pub fn enter(&self, id: u64, grant: Grant, session: C) -> bool {
        let mut sessions = self.lock();
        if !self.policy().admits(&grant) {
            return false;
        }
        sessions.insert(id, (grant, session));
        true
    }

    /// Session `id` ended.
    pub fn leave(&self, id: u64) {
        self.lock().remove(&id);
    }

    /// Puts `policy` in force and returns the sessions it no longer admits (no longer
    /// counted here), for the caller to end.
    pub fn replace(&self, policy: AccessPolicy) -> Vec<(u64, Grant, C)> {
        let mut sessions = self.lock();
        let shut_out: Vec<u64> = sessions
            .iter()
            .filter(|(_, (grant, _))| !policy.admits(grant))
            .map(|(&id, _)| id)
            .collect();
        *self.policy.write().unwrap_or_else(|p| p.into_inner()) = Arc::new(policy);
        shut_out
            .into_iter()
            .filter_map(|id| sessions.remove(&id).map(|(g, c)| (id, g, c)))
            .collect()
    }

    /// Sessions counted now.
    pub fn sessions(&self) -> usize {
        self.lock().len()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, (Grant, C)>> {
        // Single inserts and removals: a panic elsewhere cannot leave the map half-changed.
        self.sessions.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// Per-process random HMAC key for token comparison.
fn token_key() -> &'static hmac::Key {
    static KEY: OnceLock<hmac::Key> = OnceLock::new();
    KEY.get_or_init(|| {
        let rng = ring::rand::SystemRandom::new();
        hmac::Key::generate(hmac::HMAC_SHA256, &rng).unwrap_or_else(|_| {
            // The system RNG failing is not recoverable in any useful way; a fixed key keeps
            // the comparison constant-time (its secrecy is not what makes it so).
            hmac::Key::new(hmac::HMAC_SHA256, b"arbor token comparison")
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn policy(default_access: Access, rules: &[(&str, Option<&[&str]>)]) -> AccessPolicy {
        let mut c = ServeConfig::new("p");
        c.default_access = default_access;
        for (scene, tokens) in rules {
            let rule = match tokens {
                None => SceneRule::Public,
                Some(t) => SceneRule::Tokens(t.iter().map(|t| (*t).to_owned()).collect()),
            };
            c.scenes.insert((*scene).into(), rule);
        }
        AccessPolicy::of(&c)
    }

    #[test]
    fn access_rules() {
        let mut p = policy(
            Access::Token,
            &[("bunny", Some(&["s3cret", "other"])), ("lion", None)],
        );
        let pool = ["bunny", "lion", "igea"];
        let exists = |s: &str| pool.contains(&s);
        let admit = |p: &AccessPolicy, scene, token| p.admit(scene, token, exists).map(|_| ());
        assert_eq!(admit(&p, "bunny", "s3cret"), Ok(()));
        assert_eq!(admit(&p, "bunny", "other"), Ok(()));
        for wrong in ["s3cre", "s3cret!", ""] {
            assert_eq!(admit(&p, "bunny", wrong), Err(ErrorCode::Unauthorized));
        }
        assert_eq!(admit(&p, "lion", ""), Ok(()));
        assert_eq!(admit(&p, "lion", "anything"), Ok(()));
        // Not configured: the default rule.
        assert_eq!(admit(&p, "igea", "s3cret"), Err(ErrorCode::Unauthorized));
        p.default_access = Access::Public;
        assert_eq!(admit(&p, "igea", ""), Ok(()));
        // Not in the pool: unknown, whatever the token.
        assert_eq!(admit(&p, "dragon", "s3cret"), Err(ErrorCode::UnknownScene));
        assert_eq!(
            p.admit("../etc", "", |_| true).map(|_| ()),
            Err(ErrorCode::UnknownScene)
        );
    }

    #[test]
    fn a_new_rule_shuts_out_exactly_the_sessions_it_no_longer_admits() {
        let before = policy(
            Access::Public,
            &[("bunny", Some(&["old", "kept"])), ("lion", None)],
        );
        let access = SceneAccess::new(before.clone());
        let exists = |_: &str| true;
        let sessions = [
            (1, "bunny", "old"),
            (2, "bunny", "kept"),
            (3, "lion", ""),
            (4, "igea", "whatever"),
            (5, "bunny", "old"),
        ];
        for (id, scene, token) in sessions {
            let grant = access.policy().admit(scene, token, exists).unwrap();
            assert!(access.enter(id, grant, format!("conn {id}")));
        }
        // "old" revoked, "new" added, lion made token-only, the default made token-only.
        let after = policy(
            Access::Token,
            &[("bunny", Some(&["kept", "new"])), ("lion", Some(&["new"]))],
        );
        let shut_out = access.replace(after.clone());
        let ids: Vec<u64> = shut_out.iter().map(|(id, _, _)| *id).collect();
        assert_eq!(ids, [1, 3, 4, 5]);
        assert_eq!(shut_out[0].2, "conn 1");
        assert_eq!(shut_out[1].1.scene, "lion");
        assert_eq!(access.sessions(), 1);
        assert_eq!(*access.policy(), after);
        // The rules in force answer the next Hello; a grant made under the old rules that
        // enters after the swap is refused.
        assert!(access.policy().admit("bunny", "new", exists).is_ok());
        assert_eq!(
            access.policy().admit("bunny", "old", exists).map(|_| ()),
            Err(ErrorCode::Unauthorized)
        );
        let stale = before.admit("bunny", "old", exists).unwrap();
        assert!(!access.enter(6, stale, "conn 6".into()));
        // The same rules again shut out no one; an ended session is not counted.
        assert!(access.replace(after).is_empty());
        access.leave(2);
        assert_eq!(access.sessions(), 0);
    }
}
