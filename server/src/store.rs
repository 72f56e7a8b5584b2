//! Concurrent session store: sessions keyed by id in a sharded map, each
//! behind its own mutex, so requests for different sessions never wait on
//! each other and the step path takes no global lock. What an id means (its
//! rules, creating an existing one, the session limit, how a batch finds its
//! sessions) and the errors are esa-store's; this store adds concurrency, the
//! TTL and the memory budget.
//!
//! Idle sessions expire after the TTL. Expiry is checked on every lookup (so
//! an expired session is NOT_FOUND exactly when its TTL has passed), and a
//! periodic sweep frees the memory of sessions nobody asks for again.
//!
//! Two limits bound what the store holds: a count of sessions and a budget of
//! bytes, since a D = 4096 session costs 400 times a D = 6 one. Both are
//! checked before a session is stored, so reaching either is a
//! RESOURCE_EXHAUSTED answer rather than an allocation failure.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use dashmap::mapref::entry::Entry as MapEntry;
use dashmap::DashMap;
use esa_core::{footprint, SavedSession, Session};
use esa_store::{assign_id, check_same_config, check_session_limit, find, resolve_batch, Error};
use parking_lot::{Mutex, MutexGuard, RwLock};

/// Where the store's clock starts, in nanoseconds: not at 0, so that a session imported from a
/// state file can have been used last before this store existed (its idle time carries over).
/// 2^62 ns is about 146 years of idle time.
const CLOCK_ORIGIN: u64 = 1 << 62;

/// One stored session. parking_lot's mutex does not poison, so a panic in one
/// request could never make a session unusable for the next.
struct Slot {
    session: Mutex<Session>,
    /// Nanoseconds since the store's epoch of the last request that used it.
    last_used: AtomicU64,
    /// Bytes charged to the memory budget for this session ([`session_cost`]).
    cost: usize,
}

/// The bytes one stored session costs: the session ([`footprint::session_bytes`]),
/// the rest of its slot with the `Arc`'s two counters, its id, its map entry
/// (counted twice: a hash table that has just grown holds as much slack as
/// entries), and an allocator header for each of its three allocations (slot,
/// state matrix, id).
pub fn session_cost(id: &str, action_dim: usize) -> usize {
    const ALLOCATOR_HEADER: usize = 16;
    footprint::session_bytes(action_dim) + size_of::<Slot>() - size_of::<Session>()
        + 2 * size_of::<usize>()
        + id.len()
        + 2 * (size_of::<(String, Arc<Slot>)>() + 1)
        + 3 * ALLOCATOR_HEADER
}

/// All live sessions of one server, shared by every transport.
pub struct SessionStore {
    // foldhash: several times faster than SipHash on short ids, still seeded
    // per process.
    sessions: DashMap<String, Arc<Slot>, foldhash::fast::RandomState>,
    live: AtomicUsize,
    memory: AtomicUsize,
    expired_total: AtomicU64,
    ttl_nanos: Option<u64>,
    max_sessions: usize,
    max_memory: usize,
    epoch: Instant,
    /// True once [`SessionStore::freeze`] ran. Every request holds the read side while it uses
    /// sessions, so freezing waits for the requests in flight and refuses the later ones.
    frozen: RwLock<bool>,
}

/// One session as a state file holds it: its id, everything it holds, and how long it had been
/// idle.
#[derive(Clone, Debug, PartialEq)]
pub struct Exported {
    /// The session id.
    pub id: String,
    /// Everything the session holds.
    pub session: SavedSession,
    /// Time since its last request.
    pub idle: Duration,
}

impl SessionStore {
    /// A store whose sessions expire after `ttl` without use (`None` = never)
    /// and which refuses to hold more than `max_sessions` at once, or sessions
    /// costing more than `max_memory` bytes together ([`session_cost`]).
    pub fn new(ttl: Option<Duration>, max_sessions: usize, max_memory: usize) -> Self {
        Self {
            sessions: DashMap::default(),
            live: AtomicUsize::new(0),
            memory: AtomicUsize::new(0),
            expired_total: AtomicU64::new(0),
            ttl_nanos: ttl.map(duration_nanos),
            max_sessions,
            max_memory,
            epoch: Instant::now(),
            frozen: RwLock::new(false),
        }
    }

    /// The idle-session TTL; `None` = never.
    pub fn ttl(&self) -> Option<Duration> {
        self.ttl_nanos.map(Duration::from_nanos)
    }

    /// Stops serving: waits for the requests that are using sessions, then refuses every later
    /// one with UNAVAILABLE (nothing changed), so the sessions hold still for [`export`].
    ///
    /// [`export`]: SessionStore::export
    pub fn freeze(&self) {
        *self.frozen.write() = true;
    }

    /// Every live session (not expired), in no particular order, each saved under its lock as the
    /// iterator reaches it, so that a writer holds one saved session at a time. Call it after
    /// [`freeze`](SessionStore::freeze): then no request changes them meanwhile.
    pub fn export(&self) -> impl Iterator<Item = Exported> + '_ {
        let now = self.now();
        let slots: Vec<(String, Arc<Slot>)> = self
            .sessions
            .iter()
            .map(|entry| (entry.key().clone(), Arc::clone(entry.value())))
            .collect();
        slots
            .into_iter()
            .filter(move |(_, slot)| !self.is_expired(slot, now))
            .map(move |(id, slot)| Exported {
                session: slot.session.lock().save(),
                idle: Duration::from_nanos(
                    now.saturating_sub(slot.last_used.load(Ordering::Relaxed)),
                ),
                id,
            })
    }

    /// Stores a session that a state file held, as if it had been used last `idle` ago: it
    /// expires when its TTL has passed since then, and one idle for longer than the TTL already
    /// is not stored (false). The id must be new here; the limits apply as to a created session.
    pub fn import(&self, id: String, session: Session, idle: Duration) -> Result<bool, Error> {
        esa_store::check_id(&id)?;
        let cost = session_cost(&id, session.action_dim());
        let last_used = self.now().saturating_sub(duration_nanos(idle));
        if self.ttl_nanos.is_some_and(|ttl| duration_nanos(idle) > ttl) {
            return Ok(false);
        }
        match self.sessions.entry(id) {
            MapEntry::Vacant(vacant) => {
                self.reserve(cost)?;
                vacant.insert(Slot::new(session, last_used, cost));
                Ok(true)
            }
            MapEntry::Occupied(occupied) => Err(Error::InvalidArgument(format!(
                "session {:?} appears twice",
                occupied.key()
            ))),
        }
    }

    /// The read side of the freeze gate, or UNAVAILABLE once the store is frozen.
    fn open(&self) -> Result<parking_lot::RwLockReadGuard<'_, bool>, Error> {
        let frozen = self.frozen.read();
        if *frozen {
            return Err(Error::Unavailable(
                "the server is shutting down; retry: a server restarted with its --state-file \
                 continues this session"
                    .into(),
            ));
        }
        Ok(frozen)
    }

    /// Number of sessions currently held (expired ones count until they are
    /// looked up or swept).
    pub fn live(&self) -> usize {
        self.live.load(Ordering::Relaxed)
    }

    /// Bytes the sessions currently held cost, by [`session_cost`].
    pub fn memory(&self) -> usize {
        self.memory.load(Ordering::Relaxed)
    }

    /// The session memory budget in bytes.
    pub fn max_memory(&self) -> usize {
        self.max_memory
    }

    /// Number of sessions removed because their TTL passed.
    pub fn expired_total(&self) -> u64 {
        self.expired_total.load(Ordering::Relaxed)
    }

    /// Stores `session` under `id` (a fresh UUID when `id` is empty) and
    /// returns the id. An existing live session with the same id is kept and
    /// its id returned when its config equals the new one; otherwise
    /// ALREADY_EXISTS.
    pub fn create(&self, id: String, session: Session) -> Result<String, Error> {
        let _open = self.open()?;
        let id = assign_id(&id)?;
        let now = self.now();
        let cost = session_cost(&id, session.action_dim());
        let existing = loop {
            match self.sessions.entry(id.clone()) {
                MapEntry::Vacant(vacant) => {
                    self.reserve(cost)?;
                    vacant.insert(Slot::new(session, now, cost));
                    return Ok(id);
                }
                MapEntry::Occupied(occupied) if self.is_expired(occupied.get(), now) => {
                    // Same id as an expired session: it goes, and the new one is
                    // charged like any other (its config, and so its cost, may differ).
                    let (_, slot) = occupied.remove_entry();
                    self.release(&slot);
                    self.expired_total.fetch_add(1, Ordering::Relaxed);
                }
                MapEntry::Occupied(occupied) => break Arc::clone(occupied.get()),
            }
        };
        // Compared after releasing the shard lock so that a long batch holding
        // this session's mutex cannot stall other ids of the shard.
        check_same_config(&id, &existing.session.lock(), &session)?;
        existing.touch(now);
        Ok(id)
    }

    /// Runs `f` on the session `id` while holding its lock.
    pub fn with_session<R>(
        &self,
        id: &str,
        f: impl FnOnce(&mut Session) -> Result<R, Error>,
    ) -> Result<R, Error> {
        let _open = self.open()?;
        let slot = self.lookup(id)?;
        let mut session = slot.session.lock();
        f(&mut session)
    }

    /// Runs `f` on the sessions of `ids` (in request order) while holding all
    /// their locks, so `f` can validate every item before changing any.
    /// Errors name the item index; an id may appear only once
    /// ([`resolve_batch`]).
    pub fn with_batch<R>(
        &self,
        ids: &[String],
        f: impl FnOnce(&mut [&mut Session]) -> Result<R, Error>,
    ) -> Result<R, Error> {
        let _open = self.open()?;
        let now = self.now();
        let resolved = resolve_batch(ids, |id| self.live_slot(id, now), Arc::as_ptr)?;
        let (slots, order) = (resolved.items, resolved.order);
        // Locks are taken in address order, the same order for every batch,
        // so two batches sharing sessions cannot deadlock.
        let mut guards: Vec<Option<MutexGuard<'_, Session>>> = Vec::with_capacity(slots.len());
        guards.resize_with(slots.len(), || None);
        for &index in &order {
            if let (Some(guard), Some(slot)) = (guards.get_mut(index), slots.get(index)) {
                *guard = Some(slot.session.lock());
            }
        }
        let mut sessions: Vec<&mut Session> =
            guards.iter_mut().flatten().map(|g| &mut **g).collect();
        f(&mut sessions)
    }

    /// Removes the session `id`; NOT_FOUND when it does not exist or expired.
    pub fn close(&self, id: &str) -> Result<(), Error> {
        let _open = self.open()?;
        let (_, slot) = find(id, |id| self.sessions.remove(id))?;
        self.release(&slot);
        if self.is_expired(&slot, self.now()) {
            self.expired_total.fetch_add(1, Ordering::Relaxed);
            return Err(Error::NotFound(id.to_owned()));
        }
        Ok(())
    }

    /// Removes every expired session and returns how many there were.
    pub fn sweep(&self) -> usize {
        let now = self.now();
        let mut removed = 0;
        self.sessions.retain(|_, slot| {
            let keep = !self.is_expired(slot, now);
            if !keep {
                self.release(slot);
                removed += 1;
            }
            keep
        });
        self.expired_total
            .fetch_add(removed as u64, Ordering::Relaxed);
        removed
    }

    /// The live session `id`, marked as used now.
    fn lookup(&self, id: &str) -> Result<Arc<Slot>, Error> {
        let now = self.now();
        find(id, |id| self.live_slot(id, now))
    }

    /// The session `id` if it has not expired at `now`, marked as used then;
    /// an expired one is removed.
    fn live_slot(&self, id: &str, now: u64) -> Option<Arc<Slot>> {
        match self.sessions.get(id) {
            None => return None,
            Some(slot) if !self.is_expired(&slot, now) => {
                // Touched under the shard's read lock: a sweep (which holds the
                // write lock) cannot remove it between this check and the use.
                slot.touch(now);
                return Some(Arc::clone(&slot));
            }
            Some(_) => {}
        }
        if let Some((_, slot)) = self
            .sessions
            .remove_if(id, |_, slot| self.is_expired(slot, now))
        {
            self.release(&slot);
            self.expired_total.fetch_add(1, Ordering::Relaxed);
        }
        None
    }

    /// Counts one more session costing `cost` bytes, or says which limit it would pass.
    fn reserve(&self, cost: usize) -> Result<(), Error> {
        self.live
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                check_session_limit(n, self.max_sessions)
                    .ok()
                    .map(|()| n + 1)
            })
            .map_err(|n| Error::session_limit(n, self.max_sessions))?;
        self.memory
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |used| {
                used.checked_add(cost)
                    .filter(|&total| total <= self.max_memory)
            })
            .map(drop)
            .map_err(|used| {
                self.live.fetch_sub(1, Ordering::AcqRel);
                Error::ResourceExhausted(format!(
                    "session memory budget reached: the server's sessions take {used} bytes \
                     and this one needs {cost} more (--max-session-memory {}); close finished \
                     sessions, use fewer action dimensions or raise the budget",
                    self.max_memory
                ))
            })
    }

    /// Uncounts a session that left the map.
    fn release(&self, slot: &Slot) {
        self.live.fetch_sub(1, Ordering::AcqRel);
        self.memory.fetch_sub(slot.cost, Ordering::AcqRel);
    }

    fn is_expired(&self, slot: &Slot, now: u64) -> bool {
        self.ttl_nanos
            .is_some_and(|ttl| now.saturating_sub(slot.last_used.load(Ordering::Relaxed)) > ttl)
    }

    fn now(&self) -> u64 {
        CLOCK_ORIGIN.saturating_add(duration_nanos(self.epoch.elapsed()))
    }
}

impl Slot {
    fn new(session: Session, now: u64, cost: usize) -> Arc<Self> {
        Arc::new(Slot {
            session: Mutex::new(session),
            last_used: AtomicU64::new(now),
            cost,
        })
    }

    fn touch(&self, now: u64) {
        self.last_used.fetch_max(now, Ordering::Relaxed);
    }
}

fn duration_nanos(d: Duration) -> u64 {
    u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;
    use esa_core::SessionConfig;

    fn session() -> Session {
        Session::new(SessionConfig::new(
            1,
            0.01,
            vec![0.2],
            vec![60.0],
            vec![0.25],
        ))
        .unwrap()
    }

    fn store_with(ids: &[&str]) -> SessionStore {
        let store = SessionStore::new(None, 100, usize::MAX);
        for id in ids {
            store.create((*id).to_owned(), session()).unwrap();
        }
        store
    }

    #[test]
    fn batch_sessions_come_in_request_order() {
        let store = store_with(&["b", "a", "c"]);
        store
            .with_session("a", |s| {
                s.end_episode();
                Ok(())
            })
            .unwrap();
        let ids = ["c".to_owned(), "a".to_owned(), "b".to_owned()];
        let episodes = store
            .with_batch(&ids, |sessions| {
                Ok(sessions
                    .iter()
                    .map(|s| s.episodes_completed())
                    .collect::<Vec<_>>())
            })
            .unwrap();
        assert_eq!(episodes, vec![0, 1, 0]);
    }

    #[test]
    fn batches_in_opposite_orders_do_not_deadlock() {
        let store = Arc::new(store_with(&["a", "b", "c", "d"]));
        let forward: Vec<String> = ["a", "b", "c", "d"].map(String::from).to_vec();
        let backward: Vec<String> = forward.iter().rev().cloned().collect();
        let workers: Vec<_> = [forward, backward]
            .into_iter()
            .map(|ids| {
                let store = Arc::clone(&store);
                std::thread::spawn(move || {
                    for _ in 0..20_000 {
                        store
                            .with_batch(&ids, |sessions| {
                                sessions.iter_mut().for_each(|s| {
                                    s.end_episode();
                                });
                                Ok(())
                            })
                            .unwrap();
                    }
                })
            })
            .collect();
        for worker in workers {
            worker.join().unwrap();
        }
        let total = store
            .with_session("c", |s| Ok(s.episodes_completed()))
            .unwrap();
        assert_eq!(total, 40_000);
    }

    #[test]
    fn the_memory_budget_refuses_what_does_not_fit_and_frees_what_closes() {
        let cost = session_cost("a", 1);
        let store = SessionStore::new(Some(Duration::from_secs(60)), 100, 2 * cost);
        store.create("a".into(), session()).unwrap();
        store.create("b".into(), session()).unwrap();
        let err = store.create("c".into(), session()).unwrap_err();
        assert_eq!(err.code(), esa_store::Code::ResourceExhausted);
        assert!(err.to_string().contains("--max-session-memory"), "{err}");
        assert_eq!((store.live(), store.memory()), (2, 2 * cost));
        store.close("a").unwrap();
        store.create("c".into(), session()).unwrap();
        assert_eq!((store.live(), store.memory()), (2, 2 * cost));
    }

    #[test]
    fn a_frozen_store_refuses_every_request_and_changes_nothing() {
        let store = store_with(&["a", "b"]);
        store.freeze();
        let ids = ["a".to_owned(), "b".to_owned()];
        let errors = [
            store.create("c".into(), session()).unwrap_err(),
            store.with_session("a", |_| Ok(())).unwrap_err(),
            store.with_batch(&ids, |_| Ok(())).unwrap_err(),
            store.close("a").unwrap_err(),
        ];
        for err in errors {
            assert_eq!(err.code(), esa_store::Code::Unavailable);
            assert!(err.to_string().contains("shutting down"), "{err}");
        }
        let mut exported: Vec<String> = store.export().map(|e| e.id).collect();
        exported.sort();
        assert_eq!(exported, ["a", "b"]);
    }

    #[test]
    fn an_imported_session_keeps_its_state_and_its_idle_time() {
        let ttl = Duration::from_secs(60);
        let old = SessionStore::new(Some(ttl), 10, usize::MAX);
        old.create("a".into(), session()).unwrap();
        old.with_session("a", |s| {
            s.end_episode();
            Ok(())
        })
        .unwrap();
        let [exported] = <[Exported; 1]>::try_from(old.export().collect::<Vec<_>>()).unwrap();
        assert_eq!(exported.session.episodes_completed, 1);
        let new = SessionStore::new(Some(ttl), 10, usize::MAX);
        let restored = Session::restore(exported.session.clone()).unwrap();
        let idle = Duration::from_secs(30);
        assert!(new.import("a".into(), restored.clone(), idle).unwrap());
        let [again] = <[Exported; 1]>::try_from(new.export().collect::<Vec<_>>()).unwrap();
        assert!(again.idle >= idle && again.idle < ttl, "{:?}", again.idle);
        assert_eq!(again.session, exported.session);
        assert_eq!(new.memory(), session_cost("a", 1));
        let err = new.import("a".into(), restored.clone(), idle).unwrap_err();
        assert!(err.to_string().contains("twice"), "{err}");
        // Past its TTL it stays dead, and costs nothing.
        assert!(!new.import("b".into(), restored, ttl * 2).unwrap());
        assert_eq!(new.live(), 1);
        let err = new.with_session("b", |_| Ok(())).unwrap_err();
        assert_eq!(err.code(), esa_store::Code::NotFound);
    }

    #[test]
    fn an_expired_id_is_replaced_and_counted_once() {
        let store = SessionStore::new(Some(Duration::ZERO), 1, usize::MAX);
        store.create("x".into(), session()).unwrap();
        std::thread::sleep(Duration::from_millis(2));
        // At the limit, but the expired session's slot is reused.
        store.create("x".into(), session()).unwrap();
        assert_eq!((store.live(), store.expired_total()), (1, 1));
        assert_eq!(store.memory(), session_cost("x", 1));
        std::thread::sleep(Duration::from_millis(2));
        assert_eq!(store.sweep(), 1);
        assert_eq!((store.live(), store.expired_total()), (0, 2));
        assert_eq!(store.memory(), 0);
    }
}
