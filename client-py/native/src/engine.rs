//! The in-process engine: esa-store's sessions by id (ids, create, the session limit, batches by
//! id and the errors, all as `esa-server` has them), stepped through `esa_core::batch`, with a
//! handle cache so that batch calls need no hashing. Pure Rust; [`crate::engine_class`] wraps it
//! for Python.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

use esa_core::batch::{self, BatchError};
use esa_core::fused_step::{self, StepCritic};
use esa_core::{Session, SessionConfig};
use esa_proto::convert::{new_session, session_snapshot};
use esa_proto::v1 as pb;
use esa_store::{unary, Error, Key, Sessions, Taken};

/// Sessions by id, at most `max_sessions` of them.
pub struct Engine {
    sessions: Sessions,
}

/// A list of session ids resolved to their slots once, so batch calls need no hashing. It names the
/// sessions by id, like a batch request: a session closed and created again under the same id is
/// found again (one lookup, then cached); a closed one is NOT_FOUND for its item.
pub struct Handle {
    entries: Box<[Entry]>,
    /// The action values of the sessions when resolved (a hint for how long a call takes).
    values: usize,
}

/// One item of a handle: its id and where its session was last found.
struct Entry {
    id: String,
    slot: AtomicUsize,
    serial: AtomicU64,
}

impl Entry {
    fn key(&self) -> Key {
        Key {
            slot: self.slot.load(Ordering::Relaxed),
            serial: self.serial.load(Ordering::Relaxed),
        }
    }

    fn remember(&self, key: Key) {
        self.slot.store(key.slot, Ordering::Relaxed);
        self.serial.store(key.serial, Ordering::Relaxed);
    }
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

/// The arrays of a probe batch (ProbeBatchRequest's), concatenated over its items.
pub struct ProbeInput<'a> {
    pub steps: &'a [u64],
    pub actions: &'a [f64],
    pub starts: &'a [bool],
    pub scales: &'a [f64],
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
            sessions: Sessions::new(max_sessions),
        }
    }

    /// Number of live sessions.
    pub fn live(&self) -> usize {
        self.sessions.live()
    }

    /// The live-session limit.
    pub fn max_sessions(&self) -> usize {
        self.sessions.max_sessions()
    }

    /// Whether `id` names a live session.
    pub fn contains(&self, id: &str) -> bool {
        self.sessions.contains(id)
    }

    /// Creates a session (a UUID id when `id` is `None` or empty), or returns the existing one with
    /// the same id and an identical config (ALREADY_EXISTS for another config). With `progress`,
    /// a new session resumes it (CreateSession's `progress`). The config is validated first, then
    /// the id, then the limit, as the server does.
    pub fn create_session(
        &mut self,
        id: Option<&str>,
        config: SessionConfig,
        progress: Option<pb::SessionProgress>,
    ) -> Result<String, Error> {
        let session = new_session(config, progress)?;
        self.sessions.create(id.unwrap_or_default(), session)
    }

    /// Removes a session; NOT_FOUND when there is none with this id.
    pub fn close_session(&mut self, id: &str) -> Result<(), Error> {
        self.sessions.close(id)
    }

    /// Ends a session's episode; returns its completed episodes.
    pub fn end_episode(&mut self, id: &str) -> Result<u64, Error> {
        Ok(self.sessions.get_mut(id)?.end_episode())
    }

    /// A snapshot of a session, as GetSession answers it.
    pub fn get_session(&mut self, id: &str) -> Result<pb::GetSessionResponse, Error> {
        Ok(session_snapshot(self.sessions.get_mut(id)?))
    }

    /// Probe of one session (the server's unary Probe): returns the probe and the applied action.
    pub fn probe_one(
        &mut self,
        id: &str,
        step: u64,
        action: &[f64],
        action_scale: &[f64],
        episode_start: bool,
    ) -> Result<(Vec<f64>, Vec<f64>), Error> {
        let session = self.sessions.get_mut(id)?;
        let probed = unary::probe(session, step, action, action_scale, episode_start)?;
        Ok((probed.probe, probed.applied))
    }

    /// Report of one session (the server's unary Report): returns the improved action.
    pub fn report_one(
        &mut self,
        id: &str,
        step: u64,
        q_value: f64,
        q_reference: Option<f64>,
    ) -> Result<Vec<f64>, Error> {
        let session = self.sessions.get_mut(id)?;
        Ok(unary::report(session, step, q_value, q_reference)?.action)
    }

    /// Resolves `ids` into a handle: 1 to `MAX_BATCH_ITEMS` ids, each well formed, live and at
    /// most once (errors name the item, as a batch request's would).
    pub fn resolve<S: AsRef<str>>(&self, ids: &[S]) -> Result<Handle, Error> {
        batch::check_probe_lengths(ids.len(), ids.len(), 0)?;
        let keys = self.sessions.resolve(ids)?;
        let values = keys
            .iter()
            .filter_map(|&key| self.sessions.session(key))
            .map(Session::action_dim)
            .sum();
        let entries = ids
            .iter()
            .zip(keys)
            .map(|(id, key)| Entry {
                id: id.as_ref().to_owned(),
                slot: AtomicUsize::new(key.slot),
                serial: AtomicU64::new(key.serial),
            })
            .collect();
        Ok(Handle { entries, values })
    }

    /// ProbeBatch over the sessions of `handle` (see `esa_core::batch::probe`); all-or-nothing.
    pub fn probe(&mut self, handle: &Handle, input: &ProbeInput<'_>) -> Result<ProbeOutput, Error> {
        self.probing(handle, input, |sessions, probes, applied| {
            batch::probe(
                sessions,
                input.steps,
                input.actions,
                input.starts,
                input.scales,
                probes,
                applied,
            )
        })
    }

    /// ReportBatch over the sessions of `handle` (see `esa_core::batch::report`); all-or-nothing.
    pub fn report(
        &mut self,
        handle: &Handle,
        steps: &[u64],
        q_values: &[f64],
        q_references: &[f64],
    ) -> Result<ReportOutput, Error> {
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

    /// One step of Algorithm 1 for a critic the engine evaluates itself (see
    /// `esa_core::fused_step::step`): ProbeBatch, then ReportBatch of `critic` at the probes,
    /// in one call; all-or-nothing. The critic is linear or quadratic (`esa_core::fused_step`).
    pub fn step_critic(
        &mut self,
        handle: &Handle,
        input: &ProbeInput<'_>,
        critic: &impl StepCritic,
    ) -> Result<ProbeOutput, Error> {
        self.probing(handle, input, |sessions, probes, applied| {
            fused_step::step(
                sessions,
                input.steps,
                input.actions,
                input.starts,
                input.scales,
                critic,
                probes,
                applied,
                |_, _| {},
            )
        })
    }

    /// Runs `run` (a probe's or a step's) on the sessions of `handle` after the checks of a probe
    /// that need no session, collecting its probes and applied actions.
    fn probing(
        &mut self,
        handle: &Handle,
        input: &ProbeInput<'_>,
        run: impl FnOnce(&mut [&mut Session], &mut Vec<f64>, &mut Vec<f64>) -> Result<(), BatchError>,
    ) -> Result<ProbeOutput, Error> {
        batch::check_probe_lengths(handle.len(), input.steps.len(), input.starts.len())?;
        self.with_sessions(handle, |sessions| {
            let (mut probes, mut applied) = (Vec::new(), Vec::new());
            run(sessions, &mut probes, &mut applied)?;
            Ok(ProbeOutput {
                probes,
                applied,
                dim: shared_dim(sessions),
            })
        })
    }

    /// Runs `f` on the sessions of `handle`, in item order. A session that is no longer live is
    /// NOT_FOUND for its item (the first such item), before `f` runs.
    fn with_sessions<R>(
        &mut self,
        handle: &Handle,
        f: impl FnOnce(&mut [&mut Session]) -> Result<R, Error>,
    ) -> Result<R, Error> {
        // The sessions are moved out of their slots for the call (a pointer each) and put back
        // after it, so `f` gets disjoint `&mut` without unsafe code.
        let mut taken = Vec::with_capacity(handle.len());
        let mut entries = handle.entries.iter().enumerate();
        let result = entries
            .try_for_each(|(index, entry)| {
                taken.push(self.take(entry).map_err(|err| Error::item(index, err))?);
                Ok(())
            })
            .and_then(|()| f(&mut taken.iter_mut().map(Taken::session).collect::<Vec<_>>()));
        for session in taken {
            self.sessions.put(session);
        }
        result
    }

    /// Moves the session of `entry` out of its slot: where the entry last found it, else where
    /// its id lives now (remembered for the next call).
    fn take(&mut self, entry: &Entry) -> Result<Taken, Error> {
        if let Some(taken) = self.sessions.take(entry.key()) {
            return Ok(taken);
        }
        let key = self.sessions.key(&entry.id)?;
        // Only an id repeated in the handle could find its session taken already, and `resolve`
        // refuses those.
        let taken = self
            .sessions
            .take(key)
            .ok_or_else(|| Error::NotFound(entry.id.clone()))?;
        entry.remember(key);
        Ok(taken)
    }
}

fn shared_dim(sessions: &[&mut Session]) -> Option<usize> {
    let first = sessions.first()?.action_dim();
    sessions
        .iter()
        .all(|s| s.action_dim() == first)
        .then_some(first)
}
