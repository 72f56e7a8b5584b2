//! Sessions of `esa_core` by id, the layer between esa-core and its two wrappers (`esa-server`
//! and the in-process `esa_client._native`).
//!
//! What a session id means lives here, once: the id rules ([`check_id`], [`assign_id`],
//! [`MAX_ID_BYTES`]), what creating an id that exists answers ([`check_same_config`]), the
//! session limit ([`check_session_limit`], [`DEFAULT_MAX_SESSIONS`]), how a batch finds its
//! sessions ([`resolve_batch`]), and the one [`Error`] every wrapper reports, with its [`Code`]
//! and its messages (CONTRACT.md section 2), and the unary calls on one session
//! ([`unary`]). [`Sessions`] puts them together as a single-owner
//! store; a concurrent store (the server's: a lock per session, TTL, a memory budget) builds on
//! the same functions. Nothing here knows a network or an async runtime.

mod batch;
mod error;
mod ids;
mod sessions;
pub mod unary;

pub use batch::{resolve_batch, Resolved};
pub use error::{Code, Error};
pub use ids::{assign_id, check_id, find, MAX_ID_BYTES};
pub use sessions::{Key, Sessions, Taken};

use esa_core::Session;

/// Default limit of live sessions (`esa-server --max-sessions`, `Engine(max_sessions=...)`).
pub const DEFAULT_MAX_SESSIONS: usize = 100_000;

/// Creating `id` again: Ok when the session stored under it has the config of `new` (the
/// existing one is kept), else ALREADY_EXISTS.
pub fn check_same_config(id: &str, existing: &Session, new: &Session) -> Result<(), Error> {
    if existing.config() == new.config() {
        Ok(())
    } else {
        Err(Error::AlreadyExists(id.to_owned()))
    }
}

/// Whether one more session fits beside `live` ones under a limit of `max_sessions`
/// (RESOURCE_EXHAUSTED when not).
pub fn check_session_limit(live: usize, max_sessions: usize) -> Result<(), Error> {
    if live < max_sessions {
        Ok(())
    } else {
        Err(Error::session_limit(live, max_sessions))
    }
}
