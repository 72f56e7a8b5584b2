//! A gRPC client of esa-server for Python: tonic on a private runtime, the GIL released while a
//! call waits.
//!
//! The runtime is single-threaded and driven by the calling thread itself (`block_on`), so a
//! round trip costs no hand-off between threads: the request is written, and the answer read, by
//! the thread that asked. Between calls nothing would answer the server's HTTP/2 pings, so a
//! keeper thread drives the runtime for a moment every few seconds (a connection left unanswered
//! for the server's keepalive timeout would be dropped).

use std::future::Future;
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::Arc;
use std::thread;
use std::time::{Duration, Instant};

use numpy::IntoPyArray;
use parking_lot::RwLock;
use prost::Message;
use pyo3::exceptions::{PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyTuple};
use tokio::runtime::Runtime;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::transport::{Channel, Endpoint};
use tonic::{Code, Request, Response, Status, TimeoutExpired};
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

use esa_proto::v1 as pb;
use pb::esa_service_client::EsaServiceClient;

use crate::arrays::{shaped, Values};
use crate::errors::{status_error, StatusError};

/// How often the keeper thread answers what arrived while no call was waiting; well within the
/// server's keepalive timeout (10 s by default).
const KEEPER_INTERVAL: Duration = Duration::from_secs(2);
/// How long the keeper drives the runtime each time.
const KEEPER_DRIVE: Duration = Duration::from_millis(1);
/// The pause between health checks while waiting for a server to come up.
const READY_RETRY: Duration = Duration::from_millis(20);
/// Requests and responses up to this size, as the grpcio channel allows.
const MAX_MESSAGE_BYTES: usize = 256 * 1024 * 1024;

/// The connection: the runtime that drives it and what every call sends.
struct Remote {
    runtime: Arc<Runtime>,
    service: EsaServiceClient<Channel>,
    health: HealthClient<Channel>,
    authorization: Option<MetadataValue<Ascii>>,
    timeout: Duration,
    /// Dropped with the connection: ends the keeper thread.
    _keeper: mpsc::Sender<()>,
}

impl Remote {
    fn connect(address: &str, timeout: Duration, token: Option<&str>) -> PyResult<Self> {
        let invalid = |what: &str, err: &dyn std::fmt::Display| {
            PyValueError::new_err(format!("{what}: {err}"))
        };
        let authorization = token
            .map(|token| format!("Bearer {token}").parse())
            .transpose()
            .map_err(|err| invalid("token", &err))?;
        // tonic reads `unix:/path` as a Unix socket; anything else is host:port over TCP.
        let uri = if address.starts_with("unix:") {
            address.to_string()
        } else {
            format!("http://{address}")
        };
        let endpoint = Endpoint::from_shared(uri)
            .map_err(|err| invalid("address", &err))?
            .tcp_nodelay(true)
            .connect_timeout(timeout);
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|err| PyOSError::new_err(format!("the client's runtime: {err}")))?;
        let runtime = Arc::new(runtime);
        // Lazily, as a grpcio channel: a server not up yet fails the calls, not the client.
        let channel = {
            let _context = runtime.enter();
            endpoint.connect_lazy()
        };
        let service = EsaServiceClient::new(channel.clone())
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES);
        Ok(Self {
            health: HealthClient::new(channel),
            service,
            authorization,
            timeout,
            _keeper: keeper(Arc::clone(&runtime)),
            runtime,
        })
    }

    /// `message` with the call's deadline and the auth token.
    fn request<M>(&self, message: M) -> Request<M> {
        let mut request = Request::new(message);
        request.set_timeout(self.timeout);
        if let Some(authorization) = &self.authorization {
            request
                .metadata_mut()
                .insert("authorization", authorization.clone());
        }
        request
    }

    /// Runs one call to completion without the GIL; the deadline also holds if the server
    /// never answers.
    fn call<M, R, F, Fut>(&self, py: Python<'_>, message: M, rpc: F) -> PyResult<R>
    where
        M: Send,
        R: Send,
        F: Send + FnOnce(EsaServiceClient<Channel>, Request<M>) -> Fut,
        Fut: Future<Output = Result<Response<R>, Status>>,
    {
        let request = self.request(message);
        let service = self.service.clone();
        let timeout = self.timeout;
        py.detach(|| {
            self.runtime.block_on(async move {
                match tokio::time::timeout(timeout, rpc(service, request)).await {
                    Ok(answer) => answer.map(Response::into_inner),
                    Err(_) => Err(Status::deadline_exceeded(format!(
                        "no answer within {} s",
                        timeout.as_secs_f64()
                    ))),
                }
            })
        })
        .map_err(|status| error_of(py, &status))
    }

    /// Whether the server's health service says it is serving, within `timeout`.
    fn healthy(&self, timeout: Duration, wait_for_ready: bool) -> bool {
        let deadline = Instant::now() + timeout;
        self.runtime.block_on(async {
            loop {
                let mut request = self.request(HealthCheckRequest::default());
                let left = deadline.saturating_duration_since(Instant::now());
                request.set_timeout(left);
                let mut health = self.health.clone();
                match tokio::time::timeout(left, health.check(request)).await {
                    Ok(Ok(answer)) => {
                        return answer.into_inner().status == ServingStatus::Serving as i32
                    }
                    Ok(Err(status)) if wait_for_ready && status.code() == Code::Unavailable => {}
                    _ => return false,
                }
                if Instant::now() + READY_RETRY >= deadline {
                    return false;
                }
                tokio::time::sleep(READY_RETRY).await;
            }
        })
    }
}

/// Drives `runtime` for a moment every `KEEPER_INTERVAL` until `stop`'s sender is dropped.
fn keeper(runtime: Arc<Runtime>) -> mpsc::Sender<()> {
    let (stop, stopped) = mpsc::channel::<()>();
    // Without a keeper, a connection idle for the server's keepalive timeout is dropped and
    // reopened by the next call: slower, never wrong.
    let _detached = thread::Builder::new()
        .name("esa-grpc-keeper".into())
        .spawn(move || {
            while let Err(RecvTimeoutError::Timeout) = stopped.recv_timeout(KEEPER_INTERVAL) {
                runtime.block_on(async { tokio::time::sleep(KEEPER_DRIVE).await });
            }
        });
    stop
}

/// The `StatusError` of a failed call, with the batch item its details name.
///
/// Two of tonic's own statuses get grpcio's (and the contract's) code: a passed deadline is
/// CANCELLED in tonic, and a connection lost mid-call UNKNOWN, with the error as its source (a
/// status the server sent has none).
fn error_of(py: Python<'_>, status: &Status) -> PyErr {
    let index = esa_proto::details::batch_item(status.details()).map(|index| index as usize);
    let (code, message) = match std::error::Error::source(status) {
        Some(source) if status.code() == Code::Unknown => (
            Code::Unavailable,
            format!("{}: {}", status.message(), chain(source)),
        ),
        _ if status.code() == Code::Cancelled
            && status.message() == TimeoutExpired(()).to_string() =>
        {
            (Code::DeadlineExceeded, status.message().to_string())
        }
        _ => (status.code(), status.message().to_string()),
    };
    status_error(
        py,
        StatusError::new_err(message.clone()),
        code as i32,
        message,
        index,
    )
}

/// An error and its sources, `outer: inner: ...`.
fn chain(error: &(dyn std::error::Error + 'static)) -> String {
    let mut text = error.to_string();
    let mut next = error.source();
    while let Some(source) = next {
        text = format!("{text}: {source}");
        next = source.source();
    }
    text
}

fn closed() -> PyErr {
    StatusError::new_err("the client is closed")
}

/// A connection to one esa-server; see the module stub for the API.
#[pyclass(frozen, module = "esa_client._native")]
pub(crate) struct GrpcClient {
    remote: RwLock<Option<Arc<Remote>>>,
}

impl GrpcClient {
    fn remote(&self, py: Python<'_>) -> PyResult<Arc<Remote>> {
        self.remote.read().clone().ok_or_else(|| {
            status_error(
                py,
                closed(),
                Code::Unavailable as i32,
                "the client is closed".into(),
                None,
            )
        })
    }
}

#[pymethods]
impl GrpcClient {
    #[new]
    #[pyo3(signature = (address, timeout, token = None))]
    fn new(address: &str, timeout: f64, token: Option<&str>) -> PyResult<Self> {
        let timeout = Duration::try_from_secs_f64(timeout)
            .map_err(|err| PyValueError::new_err(format!("timeout: {err}")))?;
        let remote = Remote::connect(address, timeout, token)?;
        Ok(Self {
            remote: RwLock::new(Some(Arc::new(remote))),
        })
    }

    /// CreateSession from an encoded `esa.v1.SessionConfig`; returns the id.
    fn create_session(
        &self,
        py: Python<'_>,
        session_id: String,
        config: &[u8],
    ) -> PyResult<String> {
        let config = pb::SessionConfig::decode(config)
            .map_err(|err| PyValueError::new_err(format!("config: {err}")))?;
        let request = pb::CreateSessionRequest {
            session_id,
            config: Some(config),
        };
        let remote = self.remote(py)?;
        let response = remote.call(
            py,
            request,
            |mut s, r| async move { s.create_session(r).await },
        )?;
        Ok(response.session_id)
    }

    /// GetSession: the encoded `esa.v1.GetSessionResponse`.
    fn get_session<'py>(
        &self,
        py: Python<'py>,
        session_id: String,
    ) -> PyResult<Bound<'py, PyBytes>> {
        let request = pb::GetSessionRequest { session_id };
        let remote = self.remote(py)?;
        let response = remote.call(
            py,
            request,
            |mut s, r| async move { s.get_session(r).await },
        )?;
        Ok(PyBytes::new(py, &response.encode_to_vec()))
    }

    /// CloseSession.
    fn close_session(&self, py: Python<'_>, session_id: String) -> PyResult<()> {
        let request = pb::CloseSessionRequest { session_id };
        let remote = self.remote(py)?;
        remote.call(
            py,
            request,
            |mut s, r| async move { s.close_session(r).await },
        )?;
        Ok(())
    }

    /// EndEpisode; returns the completed episodes.
    fn end_episode(&self, py: Python<'_>, session_id: String) -> PyResult<u64> {
        let request = pb::EndEpisodeRequest { session_id };
        let remote = self.remote(py)?;
        let response = remote.call(
            py,
            request,
            |mut s, r| async move { s.end_episode(r).await },
        )?;
        Ok(response.episodes_completed)
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
            action_scale: optional_floats(action_scale)?,
        };
        let remote = self.remote(py)?;
        let response = remote.call(py, request, |mut s, r| async move { s.probe(r).await })?;
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
        let remote = self.remote(py)?;
        let response = remote.call(py, request, |mut s, r| async move { s.report(r).await })?;
        Ok(response.action.into_pyarray(py).into_any())
    }

    /// The ProbeBatch / ReportBatch calls of the sessions `session_ids`, answers `(N, dim)`.
    fn batch(slf: Py<Self>, session_ids: Vec<String>, dim: usize) -> GrpcBatch {
        GrpcBatch {
            client: slf,
            session_ids,
            dim,
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

/// Float values, or none for None (the wire's "all 1" / "no reference").
fn optional_floats(values: Option<&Bound<'_, PyAny>>) -> PyResult<Vec<f64>> {
    values.map_or(Ok(Vec::new()), |values| {
        Values::<f64>::floats(values).map(|values| values.owned())
    })
}

/// The batch calls of N sessions of one client.
#[pyclass(frozen, module = "esa_client._native")]
pub(crate) struct GrpcBatch {
    client: Py<GrpcClient>,
    session_ids: Vec<String>,
    dim: usize,
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
        let request = pb::ProbeBatchRequest {
            session_ids: self.session_ids.clone(),
            steps: Values::<u64>::steps(steps)?.owned(),
            actions: Values::<f64>::floats(actions)?.owned(),
            episode_starts: Values::<bool>::bools(episode_starts)?.owned(),
            action_scales: optional_floats(action_scales)?,
        };
        let remote = self.client.get().remote(py)?;
        let response = remote.call(
            py,
            request,
            |mut s, r| async move { s.probe_batch(r).await },
        )?;
        let n = self.session_ids.len();
        PyTuple::new(
            py,
            [
                shaped(py, response.probes, n, Some(self.dim))?,
                shaped(py, response.actions, n, Some(self.dim))?,
            ],
        )
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
        let request = pb::ReportBatchRequest {
            session_ids: self.session_ids.clone(),
            steps: Values::<u64>::steps(steps)?.owned(),
            q_values: Values::<f64>::floats(q_values)?.owned(),
            q_references: optional_floats(q_references)?,
        };
        let remote = self.client.get().remote(py)?;
        let response = remote.call(
            py,
            request,
            |mut s, r| async move { s.report_batch(r).await },
        )?;
        shaped(py, response.actions, self.session_ids.len(), Some(self.dim))
    }

    fn __len__(&self) -> usize {
        self.session_ids.len()
    }
}
