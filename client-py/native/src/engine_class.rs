//! The `Engine` and `BatchHandle` classes: esa-core in-process, over numpy arrays.
//!
//! An [`Engine`] holds sessions by id, like an `esa-server` does, and runs the same
//! all-or-nothing batches (`esa_core::batch`) without a process or a socket in between. A refused
//! call raises `EngineError` ([`crate::errors`]) and changes nothing.

use numpy::{IntoPyArray, PyArray1, PyArrayMethods};
use parking_lot::{Mutex, MutexGuard};
use prost::Message;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyTuple};

use esa_core::fused_step::{LinearCritic, QuadraticCritic};
use esa_core::{CoreError, SessionConfig};
use esa_proto::v1 as pb;
use esa_store::{Error, DEFAULT_MAX_SESSIONS};

use crate::arrays::{shaped, shaped_tuple, tiled, Values};
use crate::engine;
use crate::errors::engine_error;

/// By default, batches of more action values than this run with the GIL released (measured:
/// `native/bench_engine.py --gil`); below it, releasing the GIL and taking it back (and copying the
/// inputs, which Python threads could write to meanwhile) costs a larger part of the call.
pub(crate) const DETACH_VALUES: usize = 4096;

/// Sessions by id, each stepped by esa-core; see the module stub for the API.
#[pyclass(frozen, module = "esa_client._native")]
pub(crate) struct Engine {
    inner: Mutex<engine::Engine>,
    /// Batches of more action values than this release the GIL.
    detach_values: usize,
}

/// A list of session ids resolved once (`Engine.resolve`), for batch calls without hashing.
#[pyclass(frozen, module = "esa_client._native")]
pub(crate) struct BatchHandle {
    inner: engine::Handle,
}

impl Engine {
    /// The engine's state. A thread that holds the GIL never blocks on the lock: a batch that
    /// released the GIL may hold it, and it needs no GIL to finish.
    fn lock<'a>(&'a self, py: Python<'_>) -> MutexGuard<'a, engine::Engine> {
        loop {
            if let Some(guard) = self.inner.try_lock() {
                return guard;
            }
            py.detach(|| drop(self.inner.lock()));
        }
    }

    /// `run` on the engine's state, its error raised as `EngineError`.
    fn call<R>(
        &self,
        py: Python<'_>,
        run: impl FnOnce(&mut engine::Engine) -> Result<R, Error>,
    ) -> PyResult<R> {
        run(&mut self.lock(py)).map_err(|err| engine_error(py, err))
    }

    /// [`Self::call`] for a batch of `handle`, with the GIL released for batches of more than
    /// `detach_values` action values (their inputs are owned copies, so Python threads may write
    /// to the arrays they came from meanwhile).
    fn batch<R: Send>(
        &self,
        py: Python<'_>,
        handle: &engine::Handle,
        run: impl FnOnce(&mut engine::Engine) -> Result<R, Error> + Send,
    ) -> PyResult<R> {
        if handle.values() > self.detach_values {
            py.detach(|| run(&mut self.inner.lock()))
                .map_err(|err| engine_error(py, err))
        } else {
            self.call(py, run)
        }
    }
}

/// The step each session's probe carries: its tracked step, or 0 at an episode start.
fn step_of_each(tracked: &[i64], starts: &[bool]) -> PyResult<Vec<u64>> {
    let mut steps = Values::<u64>::unsigned(tracked)?.owned();
    for (step, _) in steps.iter_mut().zip(starts).filter(|(_, &start)| start) {
        *step = 0;
    }
    Ok(steps)
}

#[pymethods]
impl Engine {
    #[new]
    #[pyo3(signature = (max_sessions = DEFAULT_MAX_SESSIONS, detach_values = DETACH_VALUES))]
    fn new(max_sessions: usize, detach_values: usize) -> Self {
        Self {
            inner: Mutex::new(engine::Engine::new(max_sessions)),
            detach_values,
        }
    }

    /// Batches of more action values than this release the GIL while they run.
    #[getter]
    fn detach_values(&self) -> usize {
        self.detach_values
    }

    /// The live-session limit.
    #[getter]
    fn max_sessions(&self, py: Python<'_>) -> usize {
        self.lock(py).max_sessions()
    }

    fn __len__(&self, py: Python<'_>) -> usize {
        self.lock(py).live()
    }

    fn __contains__(&self, py: Python<'_>, session_id: &str) -> bool {
        self.lock(py).contains(session_id)
    }

    /// Creates a session from an encoded `esa.v1.SessionConfig` (resuming an encoded
    /// `esa.v1.SessionProgress` when given); returns its id.
    #[pyo3(signature = (session_id, config, progress = None))]
    fn create_session(
        &self,
        py: Python<'_>,
        session_id: Option<&str>,
        config: &[u8],
        progress: Option<&[u8]>,
    ) -> PyResult<String> {
        self.call(py, |engine| {
            let config = decode_config(config)?;
            let progress = progress.map(decode_progress).transpose()?;
            engine.create_session(session_id, config, progress)
        })
    }

    /// An encoded `esa.v1.GetSessionResponse` for the session.
    fn get_session<'py>(&self, py: Python<'py>, session_id: &str) -> PyResult<Bound<'py, PyBytes>> {
        let response = self.call(py, |engine| engine.get_session(session_id))?;
        Ok(PyBytes::new(py, &response.encode_to_vec()))
    }

    /// Closes the session.
    fn close_session(&self, py: Python<'_>, session_id: &str) -> PyResult<()> {
        self.call(py, |engine| engine.close_session(session_id))
    }

    /// Ends the session's episode; returns its completed episodes.
    fn end_episode(&self, py: Python<'_>, session_id: &str) -> PyResult<u64> {
        self.call(py, |engine| engine.end_episode(session_id))
    }

    /// Probe of one session: returns (probe, applied), each of the session's dimension.
    #[pyo3(signature = (session_id, step, action, episode_start = false, action_scale = None))]
    fn probe_one<'py>(
        &self,
        py: Python<'py>,
        session_id: &str,
        step: u64,
        action: &Bound<'py, PyAny>,
        episode_start: bool,
        action_scale: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let action = Values::<f64>::floats(action)?.owned();
        let scale = Values::<f64>::floats_or_empty(action_scale)?.owned();
        let (probe, applied) = self.call(py, |engine| {
            engine.probe_one(session_id, step, &action, &scale, episode_start)
        })?;
        PyTuple::new(py, [probe.into_pyarray(py), applied.into_pyarray(py)])
    }

    /// Report of one session: returns the improved action.
    #[pyo3(signature = (session_id, step, q_value, q_reference = None))]
    fn report_one<'py>(
        &self,
        py: Python<'py>,
        session_id: &str,
        step: u64,
        q_value: f64,
        q_reference: Option<f64>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let action = self.call(py, |engine| {
            engine.report_one(session_id, step, q_value, q_reference)
        })?;
        Ok(action.into_pyarray(py).into_any())
    }

    /// Resolves session ids into a handle for `probe` and `report`.
    fn resolve(&self, py: Python<'_>, session_ids: Vec<String>) -> PyResult<BatchHandle> {
        let inner = self.call(py, |engine| engine.resolve(&session_ids))?;
        Ok(BatchHandle { inner })
    }

    /// ProbeBatch: returns (probes, applied).
    #[pyo3(signature = (handle, steps, actions, episode_starts = None, action_scales = None))]
    fn probe<'py>(
        &self,
        py: Python<'py>,
        handle: &Bound<'py, BatchHandle>,
        steps: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        episode_starts: Option<&Bound<'py, PyAny>>,
        action_scales: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let handle = &handle.get().inner;
        let n = handle.len();
        let steps = Values::<u64>::steps(steps)?;
        let actions = Values::<f64>::floats(actions)?;
        let starts = episode_starts.map_or_else(|| Ok(Values::empty()), Values::<bool>::bools)?;
        let scales = Values::<f64>::floats_or_empty(action_scales)?;
        let input = engine::ProbeInput {
            steps: steps.as_slice(),
            actions: actions.as_slice(),
            starts: starts.as_slice(),
            scales: scales.as_slice(),
        };
        let output = self.batch(py, handle, |engine| engine.probe(handle, &input))?;
        shaped_tuple(py, [output.probes, output.applied], n, output.dim)
    }

    /// ProbeBatch, then ReportBatch of a closed-form critic's values, in one call: returns
    /// (probes, applied). Without `curvature` the critic is linear, `Q_i(a) = gain_i . a +
    /// offset_i` (`esa_core::fused_step::LinearCritic`); with it, concave quadratic in the
    /// clipped action, `Q_i(a) = offset_i + sum_j (gain_ij x_j + curvature_ij x_j^2)`,
    /// `x = clip(a, low, high)` (`esa_core::fused_step::QuadraticCritic`), where `low` and
    /// `high` are the box's D bounds, or None for an unbounded box. `steps` are the sessions'
    /// tracked steps (an episode start steps at 0), advanced in place when the step is applied,
    /// so that a batch keeps its count without a numpy operation per step.
    #[pyo3(signature = (
        handle, steps, actions, episode_starts, action_scales, gain, offset, paired,
        curvature = None, low = None, high = None
    ))]
    #[allow(clippy::too_many_arguments)] // the Python signature: ProbeBatch's and the critic's
    fn step_closed_form<'py>(
        &self,
        py: Python<'py>,
        handle: &Bound<'py, BatchHandle>,
        steps: &Bound<'py, PyArray1<i64>>,
        actions: &Bound<'py, PyAny>,
        episode_starts: &Bound<'py, PyAny>,
        action_scales: Option<&Bound<'py, PyAny>>,
        gain: &Bound<'py, PyAny>,
        offset: &Bound<'py, PyAny>,
        paired: bool,
        curvature: Option<&Bound<'py, PyAny>>,
        low: Option<&Bound<'py, PyAny>>,
        high: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let handle = &handle.get().inner;
        let (n, values) = (handle.len(), handle.values());
        let actions = Values::<f64>::floats(actions)?.owned();
        let starts = Values::<bool>::bools(episode_starts)?.owned();
        let steps_error =
            |err: &dyn std::fmt::Display| PyValueError::new_err(format!("steps: {err}"));
        // Borrowed for writing before the step, so that a read-only array changes nothing.
        let mut tracked = steps.try_readwrite().map_err(|err| steps_error(&err))?;
        let tracked = tracked.as_slice_mut().map_err(|err| steps_error(&err))?;
        let carried = step_of_each(tracked, &starts)?;
        let scales = Values::<f64>::floats_or_empty(action_scales)?.owned();
        let input = engine::ProbeInput {
            steps: &carried,
            actions: &actions,
            starts: &starts,
            scales: &scales,
        };
        let gains = Values::<f64>::floats(gain)?.owned();
        let offsets = Values::<f64>::floats(offset)?.owned();
        let output = match curvature {
            None => {
                if low.is_some() || high.is_some() {
                    return Err(PyValueError::new_err(
                        "low, high: expected None for a linear critic (no curvature), got bounds",
                    ));
                }
                let critic = LinearCritic {
                    gains: &gains,
                    offsets: &offsets,
                    paired,
                };
                self.batch(py, handle, |engine| {
                    engine.step_critic(handle, &input, &critic)
                })?
            }
            Some(curvature) => {
                let curvatures = Values::<f64>::floats(curvature)?.owned();
                let [lows, highs] = tiled([low, high], n, values)?;
                let critic = QuadraticCritic {
                    gains: &gains,
                    curvatures: &curvatures,
                    offsets: &offsets,
                    lows: &lows,
                    highs: &highs,
                    paired,
                };
                self.batch(py, handle, |engine| {
                    engine.step_critic(handle, &input, &critic)
                })?
            }
        };
        for (count, step) in tracked.iter_mut().zip(&carried) {
            *count = i64::try_from(step + 1).unwrap_or(i64::MAX);
        }
        shaped_tuple(py, [output.probes, output.applied], n, output.dim)
    }

    /// ReportBatch: returns the improved actions.
    #[pyo3(signature = (handle, steps, q_values, q_references = None))]
    fn report<'py>(
        &self,
        py: Python<'py>,
        handle: &Bound<'py, BatchHandle>,
        steps: &Bound<'py, PyAny>,
        q_values: &Bound<'py, PyAny>,
        q_references: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let handle = &handle.get().inner;
        let steps = Values::<u64>::steps(steps)?.owned();
        let q_values = Values::<f64>::floats(q_values)?.owned();
        let references = Values::<f64>::floats_or_empty(q_references)?.owned();
        let output = self.batch(py, handle, |engine| {
            engine.report(handle, &steps, &q_values, &references)
        })?;
        shaped(py, output.actions, handle.len(), output.dim)
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        let engine = self.lock(py);
        format!(
            "Engine(live={}, max_sessions={})",
            engine.live(),
            engine.max_sessions()
        )
    }
}

#[pymethods]
impl BatchHandle {
    /// The session ids, in item order.
    #[getter]
    fn ids(&self) -> Vec<String> {
        self.inner.ids().map(str::to_owned).collect()
    }

    fn __len__(&self) -> usize {
        self.inner.len()
    }

    fn __repr__(&self) -> String {
        format!("BatchHandle(n={})", self.inner.len())
    }
}

/// An encoded `esa.v1.SessionConfig`, as esa-core's config (INVALID_ARGUMENT for bytes that are
/// not one). Not yet validated: creating a session does that.
pub(crate) fn decode_config(bytes: &[u8]) -> Result<SessionConfig, Error> {
    pb::SessionConfig::decode(bytes)
        .map(esa_proto::convert::config_from_proto)
        .map_err(|err| {
            Error::InvalidArgument(format!(
                "config: expected an encoded esa.v1.SessionConfig message: {err}"
            ))
        })
}

/// Checks an encoded `esa.v1.SessionConfig` against every rule of CONTRACT.md sections 1 and 1b,
/// as creating a session does, so that a config is refused where it is built, by the same rules
/// and words as on every transport.
///
/// Raises `ValueError` naming the first bad field ("frequency[1]: expected ..., got ...").
#[pyfunction]
pub(crate) fn check_config(config: &[u8]) -> PyResult<()> {
    let config = decode_config(config).map_err(|err| PyValueError::new_err(err.to_string()))?;
    config.validate().map_err(|err| match err {
        CoreError::InvalidConfig(message) => PyValueError::new_err(message),
        other => PyValueError::new_err(other.to_string()),
    })
}

/// An encoded `esa.v1.SessionProgress` (INVALID_ARGUMENT for bytes that are not one).
pub(crate) fn decode_progress(bytes: &[u8]) -> Result<pb::SessionProgress, Error> {
    pb::SessionProgress::decode(bytes).map_err(|err| {
        Error::InvalidArgument(format!(
            "progress: expected an encoded esa.v1.SessionProgress message: {err}"
        ))
    })
}
