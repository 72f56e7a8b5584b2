//! A single-owner store of sessions by id: the in-process engine's, which a caller serializes
//! (one `&mut` at a time). Slots are reused, and each stored session has a serial number unique
//! in the process, so that a [`Key`] cached by a caller can tell whether its slot still holds
//! the session it found.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};

use esa_core::Session;

use crate::{assign_id, check_same_config, check_session_limit, find, resolve_batch, Error};

/// Serial numbers of stored sessions, unique in the process (across stores too).
static NEXT_SERIAL: AtomicU64 = AtomicU64::new(1);

/// Where a session is stored: its slot, and the serial of the session it found there.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Key {
    /// The slot.
    pub slot: usize,
    /// The serial of the session found in it.
    pub serial: u64,
}

/// One stored session.
struct Slot {
    serial: u64,
    session: Session,
}

/// A session moved out of its slot ([`Sessions::take`]), so that a batch holds several sessions
/// as disjoint `&mut`; [`Sessions::put`] gives it back.
pub struct Taken {
    slot: usize,
    inner: Box<Slot>,
}

impl Taken {
    /// The session.
    pub fn session(&mut self) -> &mut Session {
        &mut self.inner.session
    }

    /// Where it was stored.
    pub fn key(&self) -> Key {
        Key {
            slot: self.slot,
            serial: self.inner.serial,
        }
    }
}

/// Sessions by id, at most `max_sessions` of them.
pub struct Sessions {
    /// Sessions by slot; a freed slot is `None` and reused.
    slots: Vec<Option<Box<Slot>>>,
    free: Vec<usize>,
    ids: HashMap<String, usize>,
    max_sessions: usize,
}

impl Sessions {
    /// An empty store that holds at most `max_sessions` live sessions.
    pub fn new(max_sessions: usize) -> Self {
        Self {
            slots: Vec::new(),
            free: Vec::new(),
            ids: HashMap::new(),
            max_sessions,
        }
    }

    /// Number of live sessions.
    pub fn live(&self) -> usize {
        self.ids.len()
    }

    /// The live-session limit.
    pub fn max_sessions(&self) -> usize {
        self.max_sessions
    }

    /// Whether `id` names a live session.
    pub fn contains(&self, id: &str) -> bool {
        self.ids.contains_key(id)
    }

    /// Stores `session` under `id` (a fresh UUID when `id` is empty) and returns the id. An
    /// existing session with the same id is kept, and its id returned, when its config equals
    /// the new one; otherwise ALREADY_EXISTS. The id is checked first, then an existing
    /// session, then the limit.
    pub fn create(&mut self, id: &str, session: Session) -> Result<String, Error> {
        let id = assign_id(id)?;
        if let Some(existing) = self.lookup(&id).and_then(|key| self.session(key)) {
            check_same_config(&id, existing, &session)?;
            return Ok(id);
        }
        check_session_limit(self.ids.len(), self.max_sessions)?;
        let slot = Box::new(Slot {
            serial: NEXT_SERIAL.fetch_add(1, Ordering::Relaxed),
            session,
        });
        let index = match self.free.pop() {
            Some(index) => index,
            None => {
                self.slots.push(None);
                self.slots.len() - 1
            }
        };
        if let Some(free) = self.slots.get_mut(index) {
            *free = Some(slot);
        }
        self.ids.insert(id.clone(), index);
        Ok(id)
    }

    /// Removes the session `id`; NOT_FOUND when there is none.
    pub fn close(&mut self, id: &str) -> Result<(), Error> {
        let index = find(id, |id| self.ids.remove(id))?;
        if let Some(slot) = self.slots.get_mut(index) {
            *slot = None;
        }
        self.free.push(index);
        Ok(())
    }

    /// The session `id` (INVALID_ARGUMENT for a malformed id, NOT_FOUND for an unknown one).
    pub fn get_mut(&mut self, id: &str) -> Result<&mut Session, Error> {
        let index = find(id, |id| self.ids.get(id).copied())?;
        self.slots
            .get_mut(index)
            .and_then(Option::as_deref_mut)
            .map(|slot| &mut slot.session)
            .ok_or_else(|| Error::NotFound(id.to_owned()))
    }

    /// Where the session `id` is stored (errors as [`Sessions::get_mut`]).
    pub fn key(&self, id: &str) -> Result<Key, Error> {
        find(id, |id| self.lookup(id))
    }

    /// Where the sessions of a batch's `ids` are stored, in item order ([`resolve_batch`]).
    pub fn resolve<S: AsRef<str>>(&self, ids: &[S]) -> Result<Vec<Key>, Error> {
        resolve_batch(ids, |id| self.lookup(id), |key| key.slot).map(|resolved| resolved.items)
    }

    /// The session at `key`, if its slot still holds it.
    pub fn session(&self, key: Key) -> Option<&Session> {
        self.slots
            .get(key.slot)?
            .as_deref()
            .filter(|slot| slot.serial == key.serial)
            .map(|slot| &slot.session)
    }

    /// Moves the session at `key` out of its slot, if the slot still holds it (and it is not
    /// taken already); give it back with [`Sessions::put`].
    pub fn take(&mut self, key: Key) -> Option<Taken> {
        let slot = self.slots.get_mut(key.slot)?;
        if slot.as_ref()?.serial != key.serial {
            return None;
        }
        slot.take().map(|inner| Taken {
            slot: key.slot,
            inner,
        })
    }

    /// Puts back a session that [`Sessions::take`] moved out.
    pub fn put(&mut self, taken: Taken) {
        if let Some(slot) = self.slots.get_mut(taken.slot) {
            *slot = Some(taken.inner);
        }
    }

    fn lookup(&self, id: &str) -> Option<Key> {
        let slot = *self.ids.get(id)?;
        let serial = self.slots.get(slot)?.as_ref()?.serial;
        Some(Key { slot, serial })
    }
}
