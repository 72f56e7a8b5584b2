//! The in-process session store: sessions by id, and batches over them through
//! `esa_core::batch`, with the validation and gRPC status codes of `esa-server`
//! (CONTRACT.md section 2). Pure Rust; `lib.rs` wraps it for Python.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

use esa_core::batch::{self, BatchError};
use esa_core::{CoreError, Session, SessionConfig};

use esa_proto::convert::session_snapshot;
use esa_proto::v1 as pb;

/// Longest accepted session id, in bytes (the server's limit).
pub const MAX_ID_BYTES: usize = 128;

/// Default limit of live sessions (the server's `--max-sessions` default).
pub const DEFAULT_MAX_SESSIONS: usize = 100_000;

/// The gRPC status codes an engine answers with, numbered as gRPC numbers them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(i32)]
pub enum Code {
    /// A malformed request: bad config, wrong length, NaN/inf, bad id, batch size.
    InvalidArgument = 3,
    /// Unknown or closed session.
    NotFound = 5,
    /// Same id, different config.
    AlreadyExists = 6,
    /// More live sessions than the engine's limit.
    ResourceExhausted = 8,
    /// Step mismatch, report without probe.
    FailedPrecondition = 9,
}

/// Why a request was refused; nothing changed.
#[derive(Clone, Debug, PartialEq)]
pub struct EngineError {
    /// The gRPC status code the server answers the same case with.
    pub code: Code,
    /// What to fix, as the server words it.
    pub message: String,
    /// The failing item of a batch; `None` for the request as a whole.
    pub index: Option<usize>,
}

impl EngineError {
    fn new(code: Code, message: String) -> Self {
        Self {
            code,
            message,
            index: None,
        }
    }

    fn invalid(message: String) -> Self {
        Self::new(Code::InvalidArgument, message)
    }

    fn not_found(id: &str) -> Self {
        Self::new(
            Code::NotFound,
            format!("session {id:?} not found: it is unknown or was closed; create it first"),
        )
    }

    /// Attributes `self` to batch item `index`, worded like the server (`item {index}: ...`).
    fn item(self, index: usize) -> Self {
        Self {
            code: self.code,
            message: format!("item {index}: {}", self.message),
            index: Some(index),
        }
    }
}

impl std::fmt::Display for EngineError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for EngineError {}

fn core_code(err: &CoreError) -> Code {
    match err {
        CoreError::InvalidConfig(_) | CoreError::InvalidArgument(_) => Code::InvalidArgument,
        CoreError::StepMismatch { .. } | CoreError::NoPendingProbe { .. } => {
            Code::FailedPrecondition
        }
    }
}

impl From<CoreError> for EngineError {
    fn from(err: CoreError) -> Self {
        Self::new(core_code(&err), err.to_string())
    }
}

impl From<BatchError> for EngineError {
    fn from(err: BatchError) -> Self {
        let code = match &err {
            BatchError::Request(_) => Code::InvalidArgument,
            BatchError::Item { error, .. } => core_code(error),
        };
        Self {
            code,
            index: err.index(),
            message: err.to_string(),
        }
    }
}

/// Serial numbers of stored sessions, unique in the process, so that a handle can tell whether its
/// slot still holds the session it resolved (and not a later one, or one of another engine).
static NEXT_SERIAL: AtomicU64 = AtomicU64::new(1);

/// One stored session.
struct Slot {
    serial: u64,
    session: Session,
}

/// Sessions by id, at most `max_sessions` of them.
pub struct Engine {
    /// Sessions by slot; a freed slot is `None` and reused.
    slots: Vec<Option<Box<Slot>>>,
    free: Vec<usize>,
    ids: HashMap<String, usize>,
    max_sessions: usize,
}

/// A list of session ids resolved to their slots once, so batch calls need no hashing. It names the
/// sessions by id, like a batch request: a session closed and created again under the same id is
/// found again (one lookup, then cached); a closed one is NOT_FOUND for its item.
pub struct Handle {
    entries: Box<[Entry]>,
    /// The action values of the sessions when resolved (a hint for how long a call takes).
    values: usize,
}

struct Entry {
    id: String,
    slot: AtomicUsize,
    serial: AtomicU64,
}

impl Handle {
    /// The ids, in item order.
    pub fn ids(&self) -> impl ExactSizeIterator<Item = &str> {
        self.entries.iter().map(|e| e.id.as_str())
    }

    /// N, the number of items.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// The sessions' action dimensions added up, when the handle was resolved.
    pub fn values(&self) -> usize {
        self.values
    }
}

/// What a probe batch returns: the probes and Algorithm 1's applied actions, concatenated, and the
/// action dimension shared by every item (`None` when the items' dimensions differ).
pub struct ProbeOutput {
    pub probes: Vec<f64>,
    pub applied: Vec<f64>,
    pub dim: Option<usize>,
}

/// What a report batch returns: the improved actions, concatenated, and the shared dimension.
pub struct ReportOutput {
    pub actions: Vec<f64>,
    pub dim: Option<usize>,
}

impl Engine {
    /// An empty engine that holds at most `max_sessions` live sessions.
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

    /// Creates a session (a UUID id when `id` is `None` or empty), or returns the existing one with
    /// the same id and an identical config (ALREADY_EXISTS for another config). The config is
    /// validated first, then the id, then the limit, as the server does.
    pub fn create_session(
        &mut self,
        id: Option<&str>,
        config: SessionConfig,
    ) -> Result<String, EngineError> {
        let session = Session::new(config)?;
        let id = match id {
            None | Some("") => uuid::Uuid::new_v4().to_string(),
            Some(id) => {
                check_id(id)?;
                id.to_owned()
            }
        };
        if let Some(&slot) = self.ids.get(&id) {
            let existing = self.slot(slot);
            return if existing.session.config() == session.config() {
                Ok(id)
            } else {
                Err(EngineError::new(
                    Code::AlreadyExists,
                    format!(
                        "session {id:?} already exists with a different config; close it first, \
                         or create it with another id"
                    ),
                ))
            };
        }
        if self.ids.len() >= self.max_sessions {
            return Err(EngineError::new(
                Code::ResourceExhausted,
                format!(
                    "session limit reached: the engine holds {} live sessions (max_sessions {}); \
                     close finished sessions or raise the limit",
                    self.ids.len(),
                    self.max_sessions
                ),
            ));
        }
        let slot = Box::new(Slot {
            serial: NEXT_SERIAL.fetch_add(1, Ordering::Relaxed),
            session,
        });
        let index = match self.free.pop() {
            Some(index) => {
                self.slots[index] = Some(slot);
                index
            }
            None => {
                self.slots.push(Some(slot));
                self.slots.len() - 1
            }
        };
        self.ids.insert(id.clone(), index);
        Ok(id)
    }

    /// Removes a session; NOT_FOUND when there is none with this id.
    pub fn close_session(&mut self, id: &str) -> Result<(), EngineError> {
        check_id(id)?;
        let index = self
            .ids
            .remove(id)
            .ok_or_else(|| EngineError::not_found(id))?;
        self.slots[index] = None;
        self.free.push(index);
        Ok(())
    }

    /// Ends a session's episode; returns its completed episodes.
    pub fn end_episode(&mut self, id: &str) -> Result<u64, EngineError> {
        Ok(self.session_mut(id)?.end_episode())
    }

    /// A snapshot of a session, as GetSession answers it.
    pub fn get_session(&mut self, id: &str) -> Result<pb::GetSessionResponse, EngineError> {
        let session = self.session_mut(id)?;
        Ok(session_snapshot(session))
    }

    /// The session `id` (INVALID_ARGUMENT for a malformed id, NOT_FOUND for an unknown one).
    pub fn session_mut(&mut self, id: &str) -> Result<&mut Session, EngineError> {
        check_id(id)?;
        let index = *self.ids.get(id).ok_or_else(|| EngineError::not_found(id))?;
        Ok(&mut self.slot_mut(index).session)
    }

    /// Probe of one session (the server's unary Probe): returns the probe and the applied action.
    pub fn probe_one(
        &mut self,
        id: &str,
        step: u64,
        action: &[f64],
        action_scale: &[f64],
        episode_start: bool,
    ) -> Result<(Vec<f64>, Vec<f64>), EngineError> {
        let session = self.session_mut(id)?;
        let mut probe = Vec::with_capacity(session.action_dim());
        session.probe(step, action, action_scale, episode_start, &mut probe)?;
        let mut applied = Vec::with_capacity(session.action_dim());
        session.applied_action(&mut applied);
        Ok((probe, applied))
    }

    /// Report of one session (the server's unary Report): returns the improved action.
    pub fn report_one(
        &mut self,
        id: &str,
        step: u64,
        q_value: f64,
        q_reference: Option<f64>,
    ) -> Result<Vec<f64>, EngineError> {
        let session = self.session_mut(id)?;
        let mut action = Vec::with_capacity(session.action_dim());
        session.report(step, q_value, q_reference, &mut action)?;
        Ok(action)
    }

    /// Resolves `ids` into a handle: 1 to `MAX_BATCH_ITEMS` ids, each well formed, live and at
    /// most once (errors name the item, as a batch request's would).
    pub fn resolve<S: AsRef<str>>(&self, ids: &[S]) -> Result<Handle, EngineError> {
        batch::check_probe_lengths(ids.len(), ids.len(), 0)?;
        let mut first_at: HashMap<usize, usize> = HashMap::with_capacity(ids.len());
        let mut entries = Vec::with_capacity(ids.len());
        let mut values = 0;
        for (index, id) in ids.iter().enumerate() {
            let id = id.as_ref();
            check_id(id).map_err(|err| err.item(index))?;
            let slot = *self
                .ids
                .get(id)
                .ok_or_else(|| EngineError::not_found(id).item(index))?;
            entries.push(Entry {
                id: id.to_owned(),
                slot: AtomicUsize::new(slot),
                serial: AtomicU64::new(self.slot(slot).serial),
            });
            first_at.entry(slot).or_insert(index);
            values += self.slot(slot).session.action_dim();
        }
        for (index, entry) in entries.iter().enumerate() {
            let first = first_at[&entry.slot.load(Ordering::Relaxed)];
            if first != index {
                return Err(duplicate(&entry.id, first).item(index));
            }
        }
        Ok(Handle {
            entries: entries.into_boxed_slice(),
            values,
        })
    }

    /// ProbeBatch over the sessions of `handle` (see `esa_core::batch::probe`); all-or-nothing.
    pub fn probe(
        &mut self,
        handle: &Handle,
        steps: &[u64],
        actions: &[f64],
        episode_starts: &[bool],
        action_scales: &[f64],
    ) -> Result<ProbeOutput, EngineError> {
        batch::check_probe_lengths(handle.len(), steps.len(), episode_starts.len())?;
        self.with_sessions(handle, |sessions| {
            let (mut probes, mut applied) = (Vec::new(), Vec::new());
            batch::probe(
                sessions,
                steps,
                actions,
                episode_starts,
                action_scales,
                &mut probes,
                &mut applied,
            )?;
            Ok(ProbeOutput {
                probes,
                applied,
                dim: shared_dim(sessions),
            })
        })
    }

    /// ReportBatch over the sessions of `handle` (see `esa_core::batch::report`); all-or-nothing.
    pub fn report(
        &mut self,
        handle: &Handle,
        steps: &[u64],
        q_values: &[f64],
        q_references: &[f64],
    ) -> Result<ReportOutput, EngineError> {
        batch::check_report_lengths(
            handle.len(),
            steps.len(),
            q_values.len(),
            q_references.len(),
        )?;
        self.with_sessions(handle, |sessions| {
            let mut actions = Vec::new();
            batch::report(
                sessions,
                steps,
                q_values,
                q_references,
                &mut actions,
                |_, _| {},
            )?;
            Ok(ReportOutput {
                actions,
                dim: shared_dim(sessions),
            })
        })
    }

    /// Runs `f` on the sessions of `handle`, in item order. A session that is no longer live is
    /// NOT_FOUND for its item (the first such item), before `f` runs.
    fn with_sessions<R>(
        &mut self,
        handle: &Handle,
        f: impl FnOnce(&mut [&mut Session]) -> Result<R, EngineError>,
    ) -> Result<R, EngineError> {
        // The sessions are moved out of their slots for the call (a pointer each) and put back
        // after it, so `f` gets disjoint `&mut` without unsafe code.
        let mut taken: Vec<(usize, Box<Slot>)> = Vec::with_capacity(handle.len());
        let mut missing = None;
        for (index, entry) in handle.entries.iter().enumerate() {
            match self.take(entry) {
                Ok(slot) => taken.push(slot),
                Err(err) => {
                    missing = Some(err.item(index));
                    break;
                }
            }
        }
        let result = match missing {
            Some(err) => Err(err),
            None => {
                let mut sessions: Vec<&mut Session> = taken
                    .iter_mut()
                    .map(|(_, slot)| &mut slot.session)
                    .collect();
                f(&mut sessions)
            }
        };
        for (index, slot) in taken {
            self.slots[index] = Some(slot);
        }
        result
    }

    /// Moves the session of `entry` out of its slot (refreshing the entry when the id now lives in
    /// another slot).
    fn take(&mut self, entry: &Entry) -> Result<(usize, Box<Slot>), EngineError> {
        let cached = entry.slot.load(Ordering::Relaxed);
        let serial = entry.serial.load(Ordering::Relaxed);
        if let Some(slot) = self.slots.get_mut(cached) {
            if slot.as_ref().is_some_and(|s| s.serial == serial) {
                if let Some(slot) = slot.take() {
                    return Ok((cached, slot));
                }
            }
        }
        let index = *self
            .ids
            .get(&entry.id)
            .ok_or_else(|| EngineError::not_found(&entry.id))?;
        // Only a repeated id could find its slot taken already; `resolve` refuses those.
        let slot = self.slots[index]
            .take()
            .ok_or_else(|| duplicate(&entry.id, 0))?;
        entry.slot.store(index, Ordering::Relaxed);
        entry.serial.store(slot.serial, Ordering::Relaxed);
        Ok((index, slot))
    }

    fn slot(&self, index: usize) -> &Slot {
        self.slots[index]
            .as_deref()
            .expect("the id map names only filled slots")
    }

    fn slot_mut(&mut self, index: usize) -> &mut Slot {
        self.slots[index]
            .as_deref_mut()
            .expect("the id map names only filled slots")
    }
}

/// Session ids are 1 to [`MAX_ID_BYTES`] bytes.
fn check_id(id: &str) -> Result<(), EngineError> {
    if id.is_empty() || id.len() > MAX_ID_BYTES {
        return Err(EngineError::invalid(format!(
            "session_id: expected 1 to {MAX_ID_BYTES} bytes, got {}",
            id.len()
        )));
    }
    Ok(())
}

fn duplicate(id: &str, first: usize) -> EngineError {
    EngineError::invalid(format!(
        "session id {id:?} also appears at item {first}; a session may appear at most once per \
         batch"
    ))
}

fn shared_dim(sessions: &[&mut Session]) -> Option<usize> {
    let first = sessions.first()?.action_dim();
    sessions
        .iter()
        .all(|s| s.action_dim() == first)
        .then_some(first)
}
