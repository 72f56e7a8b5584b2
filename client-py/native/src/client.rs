//! A gRPC client of esa-server for Python: esa-client's blocking client (tonic on a private
//! runtime driven by the calling thread, with a keeper thread answering the server's pings
//! between calls), the GIL released while a call waits.

use std::sync::Arc;
use std::time::Duration;

use numpy::IntoPyArray;
use parking_lot::{Mutex, RwLock};
use prost::Message;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyTuple};
use tonic::Code;

use esa_client::blocking::{Client as Remote, StreamThread};
use esa_client::{Answer, Options, Step, StepStream, Tls};
use esa_proto::v1 as pb;

use crate::arrays::{shaped, shaped_tuple, Values};
use crate::errors::{status_error, StatusError};

/// The `StatusError` of a failed call: esa-client's code, message and batch item.
fn error_of(py: Python<'_>, error: esa_client::Error) -> PyErr {
    let message = error.message().to_string();
    status_error::<StatusError>(py, error.code() as i32, message, error.index())
}

/// The `StatusError` of a call that fails on the client's side, for no batch item.
fn failed(py: Python<'_>, code: Code, message: &str) -> PyErr {
    status_error::<StatusError>(py, code as i32, message.into(), None)
}

/// TLS trusting `ca` (else the Mozilla roots), presenting `cert` and `key` (mutual TLS) and
/// checking the server's certificate against `domain` (else the address's host).
fn tls_settings(
    ca: Option<&[u8]>,
    cert: Option<&[u8]>,
    key: Option<&[u8]>,
    domain: Option<String>,
) -> PyResult<Tls> {
    let mut tls = match ca {
        Some(pem) => Tls::default().ca_pem(pem),
        None => Tls::default().webpki_roots(),
    };
    match (cert, key) {
        (Some(cert), Some(key)) => tls = tls.identity(cert, key),
        (None, None) => {}
        _ => {
            return Err(PyValueError::new_err(
                "expected both cert and key (mutual TLS) or neither, got one",
            ))
        }
    }
    if let Some(domain) = domain {
        tls = tls.domain(domain);
    }
    Ok(tls)
}

/// A connection to one esa-server; see the module stub for the API.
#[pyclass(frozen, module = "esa_client._native")]
pub(crate) struct GrpcClient {
    remote: RwLock<Option<Arc<Remote>>>,
}

impl GrpcClient {
    fn remote(&self, py: Python<'_>) -> PyResult<Arc<Remote>> {
        self.remote
            .read()
            .clone()
            .ok_or_else(|| failed(py, Code::Unavailable, "the client is closed"))
    }

    /// Runs one call of the connection without the GIL.
    fn call<R: Send>(
        &self,
        py: Python<'_>,
        rpc: impl Send + FnOnce(&Remote) -> esa_client::Result<R>,
    ) -> PyResult<R> {
        let remote = self.remote(py)?;
        py.detach(|| rpc(&remote))
            .map_err(|error| error_of(py, error))
    }
}

#[pymethods]
impl GrpcClient {
    #[new]
    #[pyo3(signature = (
        address, timeout, token = None, *, tls = false, ca = None, cert = None, key = None,
        domain = None
    ))]
    #[allow(clippy::too_many_arguments)] // the connection's settings, each a keyword
    fn new(
        address: &str,
        timeout: f64,
        token: Option<&str>,
        tls: bool,
        ca: Option<&[u8]>,
        cert: Option<&[u8]>,
        key: Option<&[u8]>,
        domain: Option<String>,
    ) -> PyResult<Self> {
        let timeout = Duration::try_from_secs_f64(timeout)
            .map_err(|err| PyValueError::new_err(format!("timeout: {err}")))?;
        let mut options = Options::default().timeout(timeout);
        if let Some(token) = token {
            options = options.token(token);
        }
        if tls {
            options = options.tls(tls_settings(ca, cert, key, domain)?);
        } else if ca.is_some() || cert.is_some() || key.is_some() || domain.is_some() {
            return Err(PyValueError::new_err(
                "expected tls=True with ca, cert, key or domain, got tls=False",
            ));
        }
        let remote = Remote::connect(address, options)
            .map_err(|err| PyValueError::new_err(err.message().to_string()))?;
        Ok(Self {
            remote: RwLock::new(Some(Arc::new(remote))),
        })
    }

    /// CreateSession from an encoded `esa.v1.SessionConfig` (resuming an encoded
    /// `esa.v1.SessionProgress` when given); returns the id.
    #[pyo3(signature = (session_id, config, progress = None))]
    fn create_session(
        &self,
        py: Python<'_>,
        session_id: String,
        config: &[u8],
        progress: Option<&[u8]>,
    ) -> PyResult<String> {
        let config = pb::SessionConfig::decode(config)
            .map_err(|err| PyValueError::new_err(format!("config: {err}")))?;
        let progress = progress
            .map(pb::SessionProgress::decode)
            .transpose()
            .map_err(|err| PyValueError::new_err(format!("progress: {err}")))?;
        self.call(py, |r| match progress {
            Some(progress) => r.resume_session(session_id, config, progress),
            None => r.create_session(session_id, config),
        })
    }

    /// GetSession: the encoded `esa.v1.GetSessionResponse`.
    fn get_session<'py>(
        &self,
        py: Python<'py>,
        session_id: String,
    ) -> PyResult<Bound<'py, PyBytes>> {
        let response = self.call(py, |r| r.get_session(session_id))?;
        Ok(PyBytes::new(py, &response.encode_to_vec()))
    }

    /// CloseSession.
    fn close_session(&self, py: Python<'_>, session_id: String) -> PyResult<()> {
        self.call(py, |r| r.close_session(session_id))
    }

    /// EndEpisode; returns the completed episodes.
    fn end_episode(&self, py: Python<'_>, session_id: String) -> PyResult<u64> {
        self.call(py, |r| r.end_episode(session_id))
    }

    /// Probe of one session: returns (probe, applied).
    #[pyo3(signature = (session_id, step, action, episode_start, action_scale = None))]
    fn probe_one<'py>(
        &self,
        py: Python<'py>,
        session_id: String,
        step: u64,
        action: &Bound<'py, PyAny>,
        episode_start: bool,
        action_scale: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let request = pb::ProbeRequest {
            session_id,
            step,
            action: Values::<f64>::floats(action)?.owned(),
            episode_start,
            action_scale: Values::<f64>::floats_or_empty(action_scale)?.owned(),
        };
        let response = self.call(py, |r| r.probe(request))?;
        PyTuple::new(
            py,
            [
                response.probe.into_pyarray(py),
                response.action.into_pyarray(py),
            ],
        )
    }

    /// Report of one session: returns the improved action.
    #[pyo3(signature = (session_id, step, q_value, q_reference = None))]
    fn report_one<'py>(
        &self,
        py: Python<'py>,
        session_id: String,
        step: u64,
        q_value: f64,
        q_reference: Option<f64>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let request = pb::ReportRequest {
            session_id,
            step,
            q_value,
            q_reference,
        };
        let response = self.call(py, |r| r.report(request))?;
        Ok(response.action.into_pyarray(py).into_any())
    }

    /// The batch calls of the sessions `session_ids`, answers `(N, dim)`: ProbeBatch /
    /// ReportBatch calls, or with `use_stream` messages of a StepStream of the batch's own.
    #[pyo3(signature = (session_ids, dim, use_stream = false))]
    fn batch(slf: Py<Self>, session_ids: Vec<String>, dim: usize, use_stream: bool) -> GrpcBatch {
        GrpcBatch {
            client: slf,
            session_ids,
            dim,
            stream: use_stream.then(|| Mutex::new(None)),
            ahead: Mutex::new(None),
            sent_ahead: Mutex::new(None),
            progress: Mutex::new(None),
        }
    }

    /// Whether the server answers its health check as serving within `timeout` seconds.
    #[pyo3(signature = (timeout, wait_for_ready = false))]
    fn healthy(&self, py: Python<'_>, timeout: f64, wait_for_ready: bool) -> bool {
        let (Ok(remote), Ok(timeout)) = (self.remote(py), Duration::try_from_secs_f64(timeout))
        else {
            return false;
        };
        py.detach(|| remote.healthy(timeout, wait_for_ready))
    }

    /// Drops the connection; later calls fail as UNAVAILABLE. Idempotent.
    fn close(&self, py: Python<'_>) {
        let remote = self.remote.write().take();
        // The runtime's last reference may go here: its shutdown waits for no Python code.
        py.detach(|| drop(remote));
    }
}

/// The batch calls of N sessions of one client.
#[pyclass(frozen, module = "esa_client._native")]
pub(crate) struct GrpcBatch {
    client: Py<GrpcClient>,
    session_ids: Vec<String>,
    dim: usize,
    /// With `use_stream`, the StepStream that carries every call: opened by the first, dropped
    /// after a failure of the wire (the next call opens a new one; the server accepts a
    /// repeated step).
    stream: Option<Mutex<Option<StepStream>>>,
    /// The steps sent ahead (`send_step_linear`): a StepStream on a thread of its own, started
    /// by the first.
    ahead: Mutex<Option<StreamThread>>,
    /// The last step sent ahead, kept until its answer is read, so that a step whose answer the
    /// wire lost can be sent again (`resend_step`) without the caller keeping its arrays.
    sent_ahead: Mutex<Option<Step>>,
    /// The sessions' progress in the last answer that carried it (episodes completed, mean
    /// squares): what the client last saw, to resume sessions the server loses.
    progress: Mutex<Option<(Vec<u64>, Vec<f64>)>>,
}

/// What a batch sends over its StepStream.
enum Exchange {
    Probe(pb::ProbeBatchRequest),
    Report(pb::ReportBatchRequest),
    /// A report and the next probe, both sent before either answer is read.
    ReportThenProbe(pb::ReportBatchRequest, pb::ProbeBatchRequest),
}

impl Exchange {
    async fn over(self, stream: &mut StepStream) -> esa_client::Result<Answer> {
        match self {
            Self::Probe(probe) => stream.probe_batch(probe).await.map(Answer::Probe),
            Self::Report(report) => stream.report_batch(report).await.map(Answer::Report),
            Self::ReportThenProbe(report, probe) => stream
                .report_then_probe(report, probe)
                .await
                .map(Answer::Probe),
        }
    }
}

impl GrpcBatch {
    /// Queues `step` for the batch's stream thread, started here when there is none, and keeps a
    /// copy until its answer is read.
    fn send_ahead(&self, py: Python<'_>, step: Step) -> PyResult<()> {
        *self.sent_ahead.lock() = Some(step.clone());
        let mut ahead = self.ahead.lock();
        let thread = match ahead.as_mut() {
            Some(thread) => thread,
            None => {
                let remote = self.client.get().remote(py)?;
                let thread = remote.stream_thread().map_err(|err| error_of(py, err))?;
                ahead.insert(thread)
            }
        };
        let sent = thread.send(step);
        if sent.is_err() {
            // A stopped thread answers nothing more: the next step starts a new one.
            *ahead = None;
        }
        sent.map_err(|err| error_of(py, err))
    }

    fn probe_request(
        &self,
        steps: &Bound<'_, PyAny>,
        actions: &Bound<'_, PyAny>,
        episode_starts: &Bound<'_, PyAny>,
        action_scales: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<pb::ProbeBatchRequest> {
        Ok(pb::ProbeBatchRequest {
            session_ids: self.session_ids.clone(),
            steps: Values::<u64>::steps(steps)?.owned(),
            actions: Values::<f64>::floats(actions)?.owned(),
            episode_starts: Values::<bool>::bools(episode_starts)?.owned(),
            action_scales: Values::<f64>::floats_or_empty(action_scales)?.owned(),
        })
    }

    fn report_request(
        &self,
        steps: &Bound<'_, PyAny>,
        q_values: &Bound<'_, PyAny>,
        q_references: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<pb::ReportBatchRequest> {
        Ok(pb::ReportBatchRequest {
            session_ids: self.session_ids.clone(),
            steps: Values::<u64>::steps(steps)?.owned(),
            q_values: Values::<f64>::floats(q_values)?.owned(),
            q_references: Values::<f64>::floats_or_empty(q_references)?.owned(),
        })
    }

    /// Sends `exchange` without the GIL: over the batch's StepStream (opened here when there
    /// is none), or as unary calls when the batch has no stream.
    fn send(&self, py: Python<'_>, exchange: Exchange) -> PyResult<Answer> {
        if self.stream.is_some() {
            return self.on_stream(py, |remote, slot| {
                remote.block_on(async { exchange.over(opened(remote, slot).await?).await })
            });
        }
        self.client.get().call(py, |remote| match exchange {
            Exchange::Probe(probe) => remote.probe_batch(probe).map(Answer::Probe),
            Exchange::Report(report) => remote.report_batch(report).map(Answer::Report),
            Exchange::ReportThenProbe(report, probe) => {
                remote.report_batch(report)?;
                remote.probe_batch(probe).map(Answer::Probe)
            }
        })
    }

    /// The slot of the batch's StepStream; a ValueError for a batch opened without one.
    fn stream_slot(&self) -> PyResult<&Mutex<Option<StepStream>>> {
        self.stream.as_ref().ok_or_else(|| {
            PyValueError::new_err(
                "expected a batch opened with use_stream=True, got one without a stream",
            )
        })
    }

    /// Runs `f` on the batch's stream slot without the GIL; drops the stream after a failure of
    /// the wire (its answers are lost: the next call opens a new one).
    fn on_stream<R: Send>(
        &self,
        py: Python<'_>,
        f: impl Send + FnOnce(&Remote, &mut Option<StepStream>) -> esa_client::Result<R>,
    ) -> PyResult<R> {
        let slot = self.stream_slot()?;
        self.client.get().call(py, |remote| {
            let mut slot = slot.lock();
            let result = f(remote, &mut slot);
            if result.as_ref().is_err_and(esa_client::Error::is_retryable) {
                *slot = None;
            }
            result
        })
    }

    /// Keeps an answer's progress as what the client last saw of the sessions.
    fn saw(&self, episodes: Vec<u64>, mean_squares: Vec<f64>) {
        // An answer of an older server carries none: what was seen before still holds.
        if episodes.len() == self.session_ids.len() {
            *self.progress.lock() = Some((episodes, mean_squares));
        }
    }

    fn probe_answer<'py>(&self, py: Python<'py>, answer: Answer) -> PyResult<Bound<'py, PyTuple>> {
        let Answer::Probe(response) = answer else {
            return Err(out_of_order(py));
        };
        self.saw(response.episodes_completed, response.response_mean_squares);
        shaped_tuple(
            py,
            [response.probes, response.actions],
            self.session_ids.len(),
            Some(self.dim),
        )
    }
}

/// The stream in `slot`, opened first when there is none.
async fn opened<'s>(
    remote: &Remote,
    slot: &'s mut Option<StepStream>,
) -> esa_client::Result<&'s mut StepStream> {
    match slot {
        Some(stream) => Ok(stream),
        None => Ok(slot.insert(remote.client().step_stream().await?)),
    }
}

/// An answer of the other kind than the request's (a server bug, never expected).
fn out_of_order(py: Python<'_>) -> PyErr {
    failed(py, Code::Internal, "a StepStream answer out of order")
}

#[pymethods]
impl GrpcBatch {
    /// ProbeBatch: returns (probes, applied), each `(N, dim)`.
    #[pyo3(signature = (steps, actions, episode_starts, action_scales = None))]
    fn probe<'py>(
        &self,
        py: Python<'py>,
        steps: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        episode_starts: &Bound<'py, PyAny>,
        action_scales: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let probe = self.probe_request(steps, actions, episode_starts, action_scales)?;
        let answer = self.send(py, Exchange::Probe(probe))?;
        self.probe_answer(py, answer)
    }

    /// ReportBatch: returns the improved actions, `(N, dim)`.
    #[pyo3(signature = (steps, q_values, q_references = None))]
    fn report<'py>(
        &self,
        py: Python<'py>,
        steps: &Bound<'py, PyAny>,
        q_values: &Bound<'py, PyAny>,
        q_references: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let report = self.report_request(steps, q_values, q_references)?;
        let Answer::Report(response) = self.send(py, Exchange::Report(report))? else {
            return Err(out_of_order(py));
        };
        shaped(py, response.actions, self.session_ids.len(), Some(self.dim))
    }

    /// ReportBatch, then the next step's ProbeBatch: returns the probe's (probes, applied).
    /// On a stream both are sent before either answer is read (one round trip); the report's
    /// error is raised first.
    #[allow(clippy::too_many_arguments)] // the two requests' arrays, as probe() and report()
    #[pyo3(signature = (
        report_steps, q_values, q_references, steps, actions, episode_starts, action_scales = None
    ))]
    fn report_then_probe<'py>(
        &self,
        py: Python<'py>,
        report_steps: &Bound<'py, PyAny>,
        q_values: &Bound<'py, PyAny>,
        q_references: Option<&Bound<'py, PyAny>>,
        steps: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        episode_starts: &Bound<'py, PyAny>,
        action_scales: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let report = self.report_request(report_steps, q_values, q_references)?;
        let probe = self.probe_request(steps, actions, episode_starts, action_scales)?;
        let answer = self.send(py, Exchange::ReportThenProbe(report, probe))?;
        self.probe_answer(py, answer)
    }

    /// Queues a `step_linear_batch` for the batch's stream thread (started here when there is
    /// none) and returns at once, without its answer: read that with `receive_step`. The
    /// thread writes it and reads the answer while the caller goes on. A batch without a
    /// stream cannot send one.
    #[allow(clippy::too_many_arguments)] // ProbeBatch's arrays and the critic's
    #[pyo3(signature = (steps, actions, episode_starts, action_scales, gains, offsets, paired))]
    fn send_step_linear<'py>(
        &self,
        py: Python<'py>,
        steps: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        episode_starts: &Bound<'py, PyAny>,
        action_scales: Option<&Bound<'py, PyAny>>,
        gains: &Bound<'py, PyAny>,
        offsets: &Bound<'py, PyAny>,
        paired: bool,
    ) -> PyResult<()> {
        self.stream_slot()?;
        let request = pb::StepLinearBatchRequest {
            probe: Some(self.probe_request(steps, actions, episode_starts, action_scales)?),
            critic_gains: Values::<f64>::floats(gains)?.owned(),
            critic_offsets: Values::<f64>::floats(offsets)?.owned(),
            paired,
        };
        self.send_ahead(py, Step::StepLinear(request))
    }

    /// Queues a `step_batch` (the step's probe with the critic's values at the probes the
    /// caller computed ahead) like `send_step_linear`.
    #[allow(clippy::too_many_arguments)] // ProbeBatch's arrays and the critic's values
    #[pyo3(signature = (steps, actions, episode_starts, action_scales, q_values, q_references))]
    fn send_step<'py>(
        &self,
        py: Python<'py>,
        steps: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        episode_starts: &Bound<'py, PyAny>,
        action_scales: Option<&Bound<'py, PyAny>>,
        q_values: &Bound<'py, PyAny>,
        q_references: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<()> {
        self.stream_slot()?;
        let request = pb::StepBatchRequest {
            probe: Some(self.probe_request(steps, actions, episode_starts, action_scales)?),
            q_values: Values::<f64>::floats(q_values)?.owned(),
            q_references: Values::<f64>::floats_or_empty(q_references)?.owned(),
        };
        self.send_ahead(py, Step::Fused(request))
    }

    /// The answer to the oldest step sent ahead and not yet answered: `(probes, applied,
    /// shifts)`, each `(N, dim)`, or its error (the wire's, when the stream broke: its answers
    /// are lost).
    fn receive_step<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let answer = {
            let mut ahead = self.ahead.lock();
            let Some(thread) = ahead.as_mut() else {
                let message = "no step was sent ahead on this batch";
                return Err(failed(py, Code::FailedPrecondition, message));
            };
            let answer = py.detach(|| thread.answer());
            if answer.as_ref().is_err_and(esa_client::Error::is_retryable) {
                // The answer is lost (the thread stopped, or it missed its deadline): a later
                // answer would be taken for the next step's, so the next step starts anew.
                *ahead = None;
            }
            answer.map_err(|error| error_of(py, error))?
        };
        let Answer::Step(response) = answer else {
            return Err(out_of_order(py));
        };
        self.sent_ahead.lock().take();
        self.saw(response.episodes_completed, response.response_mean_squares);
        shaped_tuple(
            py,
            [response.probes, response.actions, response.shifts],
            self.session_ids.len(),
            Some(self.dim),
        )
    }

    /// Sends the last step sent ahead again, on a new stream (its answer is read with
    /// `receive_step`): for a step whose answer the wire lost and that the server did not apply.
    /// A FAILED_PRECONDITION when no step waits for its answer.
    fn resend_step(&self, py: Python<'_>) -> PyResult<()> {
        let Some(step) = self.sent_ahead.lock().clone() else {
            let message = "no step sent ahead on this batch waits for its answer";
            return Err(failed(py, Code::FailedPrecondition, message));
        };
        // Its answer, if the old stream still gave one, would be taken for the new step's.
        let stale = self.ahead.lock().take();
        py.detach(|| drop(stale));
        self.send_ahead(py, step)
    }

    /// What the last answer that carried it said of each session: `(episodes_completed,
    /// response_mean_squares)`, `uint64[N]` and `float64[N]` (empty when no session normalizes;
    /// -1 where m is unset); None before any such answer.
    fn progress<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyTuple>>> {
        let Some((episodes, mean_squares)) = self.progress.lock().clone() else {
            return Ok(None);
        };
        let arrays = [
            episodes.into_pyarray(py).into_any(),
            mean_squares.into_pyarray(py).into_any(),
        ];
        PyTuple::new(py, arrays).map(Some)
    }

    /// Ends the batch's StepStream and its stream thread, if open (answers not read are
    /// dropped); the sessions stay. Idempotent.
    fn close(&self, py: Python<'_>) {
        let stream = self.stream.as_ref().and_then(|slot| slot.lock().take());
        let ahead = self.ahead.lock().take();
        self.sent_ahead.lock().take();
        py.detach(|| drop((stream, ahead)));
    }

    fn __len__(&self) -> usize {
        self.session_ids.len()
    }
}
