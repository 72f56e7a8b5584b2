//! esa-client: a Rust client of esa-server (the `esa.v1.EsaService` of
//! [esa-proto](https://docs.rs/esa-proto)), for trainers written in Rust and for the native
//! transport of the Python client (`esa_client._native`), which is built on it.
//!
//! - [`Client`]: one connection (TCP `host:port`, `unix:/path`, or `https://` with [`Tls`]),
//!   every call with a deadline and the optional bearer token;
//! - sessions: [`Client::create_session`], [`Client::probe`], [`Client::report`],
//!   [`Client::end_episode`], [`Client::close_session`], [`Client::get_session`];
//! - [`Batch`]: N sessions stepped together (ProbeBatch / ReportBatch, or a pipelined
//!   [`StepStream`] whose deferred report rides with the next probe: one round trip per step);
//! - [`Error`]: every failure, typed ([`Kind`]) with the failing batch item;
//! - [`blocking::Client`]: the same calls for synchronous code, on a private runtime.
//!
//! ```no_run
//! # async fn run() -> Result<(), esa_client::Error> {
//! use esa_client::{pb, Client, Options};
//!
//! let client = Client::connect("127.0.0.1:50051", Options::default()).await?;
//! let config = pb::SessionConfig {
//!     action_dim: 1,
//!     dt: 0.05,
//!     amplitude: vec![0.2],
//!     frequency: vec![10.0],
//!     learning_rate: vec![0.05],
//!     ..Default::default()
//! };
//! let mut batch = client.create_batch(config, 4, true).await?;
//! let (probes, applied) = batch.probe(&[0.0; 4], &[true; 4], None).await?;
//! let q: Vec<f64> = probes.iter().map(|a| -(a - 0.5) * (a - 0.5)).collect();
//! batch.report(&q, None, true).await?; // sent with the next probe
//! # let _ = applied; Ok(()) }
//! ```

use std::time::{Duration, Instant};

use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio_stream::wrappers::ReceiverStream;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::transport::{Channel, Endpoint};
use tonic::{Code, Request, Response, Status, Streaming};
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

pub use esa_proto::v1 as pb;
use pb::esa_service_client::EsaServiceClient;

pub mod blocking;
mod error;

pub use error::{Error, Kind};

/// A call's result.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Requests and responses up to this size (the server's own limit is usually lower).
pub const MAX_MESSAGE_BYTES: usize = 256 * 1024 * 1024;
/// The pause between health checks while waiting for a server to come up.
const READY_RETRY: Duration = Duration::from_millis(20);
/// How many StepStream requests may wait to be sent.
const STREAM_QUEUE: usize = 16;

/// How to connect: the deadline of every call, the token, TLS.
#[derive(Clone, Debug)]
pub struct Options {
    /// Each call's deadline (also the connect timeout). Default 10 s.
    pub timeout: Duration,
    /// Sent as `authorization: Bearer <token>` (a server started with `--auth-token-file`).
    pub token: Option<String>,
    /// TLS for the connection (a server started with `--tls-cert`); `https://` addresses.
    pub tls: Option<Tls>,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            timeout: Duration::from_secs(10),
            token: None,
            tls: None,
        }
    }
}

impl Options {
    /// These options with `timeout`.
    pub fn timeout(mut self, timeout: Duration) -> Self {
        self.timeout = timeout;
        self
    }

    /// These options with a bearer token.
    pub fn token(mut self, token: impl Into<String>) -> Self {
        self.token = Some(token.into());
        self
    }

    /// These options with TLS.
    pub fn tls(mut self, tls: Tls) -> Self {
        self.tls = Some(tls);
        self
    }
}

/// TLS settings: the CA that signed the server's certificate, the name to check it against,
/// and a client identity for mutual TLS. Needs the `tls` feature (on by default).
#[derive(Clone, Debug, Default)]
pub struct Tls {
    ca_pem: Option<Vec<u8>>,
    domain: Option<String>,
    identity: Option<(Vec<u8>, Vec<u8>)>,
    webpki_roots: bool,
}

impl Tls {
    /// Trust the CA certificate(s) in this PEM.
    pub fn ca_pem(mut self, pem: impl Into<Vec<u8>>) -> Self {
        self.ca_pem = Some(pem.into());
        self
    }

    /// Check the server's certificate against this name (default: the address's host).
    pub fn domain(mut self, domain: impl Into<String>) -> Self {
        self.domain = Some(domain.into());
        self
    }

    /// Present this certificate chain and private key (PEM) to the server (mutual TLS).
    pub fn identity(mut self, cert_pem: impl Into<Vec<u8>>, key_pem: impl Into<Vec<u8>>) -> Self {
        self.identity = Some((cert_pem.into(), key_pem.into()));
        self
    }

    /// Also trust the Mozilla roots (feature `tls-webpki-roots`).
    pub fn webpki_roots(mut self) -> Self {
        self.webpki_roots = true;
        self
    }

    #[cfg(feature = "tls")]
    fn apply(&self, endpoint: Endpoint) -> Result<Endpoint> {
        use tonic::transport::{Certificate, ClientTlsConfig, Identity};
        let mut config = ClientTlsConfig::new();
        if let Some(pem) = &self.ca_pem {
            config = config.ca_certificate(Certificate::from_pem(pem));
        }
        if let Some(domain) = &self.domain {
            config = config.domain_name(domain.clone());
        }
        if let Some((cert, key)) = &self.identity {
            config = config.identity(Identity::from_pem(cert, key));
        }
        if self.webpki_roots {
            #[cfg(feature = "tls-webpki-roots")]
            {
                config = config.with_webpki_roots();
            }
            #[cfg(not(feature = "tls-webpki-roots"))]
            return Err(Error::new(
                Code::InvalidArgument,
                "tls: webpki_roots needs esa-client's feature tls-webpki-roots",
            ));
        }
        endpoint
            .tls_config(config)
            .map_err(|err| Error::invalid("tls", &err))
    }

    #[cfg(not(feature = "tls"))]
    fn apply(&self, _endpoint: Endpoint) -> Result<Endpoint> {
        Err(Error::new(
            Code::InvalidArgument,
            "tls: esa-client was built without its feature tls",
        ))
    }
}

/// A connection to one esa-server. Cheap to clone: clones share the connection.
#[derive(Clone, Debug)]
pub struct Client {
    service: EsaServiceClient<Channel>,
    health: HealthClient<Channel>,
    authorization: Option<MetadataValue<Ascii>>,
    timeout: Duration,
}

impl Client {
    /// Connects now: fails as UNAVAILABLE if no server answers within the timeout.
    pub async fn connect(address: &str, options: Options) -> Result<Self> {
        let (endpoint, client) = Self::prepare(address, &options)?;
        let channel = endpoint.connect().await.map_err(|err| {
            Error::new(
                Code::Unavailable,
                format!("cannot connect to {address}: {}", chain(&err)),
            )
        })?;
        Ok(client(channel))
    }

    /// Connects at the first call, as a grpcio channel does: a server not up yet fails the
    /// calls, not the client. Must be called within a tokio runtime.
    pub fn connect_lazy(address: &str, options: Options) -> Result<Self> {
        let (endpoint, client) = Self::prepare(address, &options)?;
        Ok(client(endpoint.connect_lazy()))
    }

    fn prepare(
        address: &str,
        options: &Options,
    ) -> Result<(Endpoint, impl FnOnce(Channel) -> Self)> {
        let authorization = options
            .token
            .as_ref()
            .map(|token| format!("Bearer {token}").parse())
            .transpose()
            .map_err(|err| Error::invalid("token", &err))?;
        // tonic reads `unix:/path` as a Unix socket; a bare host:port is http (https with TLS).
        let uri = if address.starts_with("unix:") || address.contains("://") {
            address.to_string()
        } else if options.tls.is_some() {
            format!("https://{address}")
        } else {
            format!("http://{address}")
        };
        let mut endpoint = Endpoint::from_shared(uri)
            .map_err(|err| Error::invalid("address", &err))?
            .tcp_nodelay(true)
            .connect_timeout(options.timeout);
        if let Some(tls) = &options.tls {
            endpoint = tls.apply(endpoint)?;
        }
        let timeout = options.timeout;
        Ok((endpoint, move |channel: Channel| Self {
            service: EsaServiceClient::new(channel.clone())
                .max_decoding_message_size(MAX_MESSAGE_BYTES)
                .max_encoding_message_size(MAX_MESSAGE_BYTES),
            health: HealthClient::new(channel),
            authorization,
            timeout,
        }))
    }

    /// Each call's deadline.
    pub fn timeout(&self) -> Duration {
        self.timeout
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

    /// One unary call; the deadline also holds if the server never answers.
    async fn call<M, R, F, Fut>(&self, message: M, rpc: F) -> Result<R>
    where
        F: FnOnce(EsaServiceClient<Channel>, Request<M>) -> Fut,
        Fut: std::future::Future<Output = Result<Response<R>, Status>>,
    {
        let request = self.request(message);
        match tokio::time::timeout(self.timeout, rpc(self.service.clone(), request)).await {
            Ok(answer) => answer.map(Response::into_inner).map_err(Error::from),
            Err(_) => Err(Error::deadline(self.timeout)),
        }
    }

    /// CreateSession; an empty `session_id` lets the server pick one. Returns the id.
    pub async fn create_session(
        &self,
        session_id: impl Into<String>,
        config: pb::SessionConfig,
    ) -> Result<String> {
        self.create(session_id.into(), config, None).await
    }

    /// CreateSession of a session the server lost (a restart without its state file, a crash,
    /// an expiry): it starts an episode with `progress`, the episode count and mean square it had
    /// (the last batch answer's, [`pb::ProbeBatchResponse::episodes_completed`] and
    /// [`pb::ProbeBatchResponse::response_mean_squares`], or a GetSession's). An existing session
    /// with the same id and config is kept as it is. Returns the id.
    pub async fn resume_session(
        &self,
        session_id: impl Into<String>,
        config: pb::SessionConfig,
        progress: pb::SessionProgress,
    ) -> Result<String> {
        self.create(session_id.into(), config, Some(progress)).await
    }

    async fn create(
        &self,
        session_id: String,
        config: pb::SessionConfig,
        progress: Option<pb::SessionProgress>,
    ) -> Result<String> {
        let request = pb::CreateSessionRequest {
            session_id,
            config: Some(config),
            progress,
        };
        let response = self
            .call(request, |mut s, r| async move { s.create_session(r).await })
            .await?;
        Ok(response.session_id)
    }

    /// GetSession: the session's config and state.
    pub async fn get_session(
        &self,
        session_id: impl Into<String>,
    ) -> Result<pb::GetSessionResponse> {
        let request = pb::GetSessionRequest {
            session_id: session_id.into(),
        };
        self.call(request, |mut s, r| async move { s.get_session(r).await })
            .await
    }

    /// CloseSession.
    pub async fn close_session(&self, session_id: impl Into<String>) -> Result<()> {
        let request = pb::CloseSessionRequest {
            session_id: session_id.into(),
        };
        self.call(request, |mut s, r| async move { s.close_session(r).await })
            .await
            .map(drop)
    }

    /// EndEpisode; returns the episodes completed.
    pub async fn end_episode(&self, session_id: impl Into<String>) -> Result<u64> {
        let request = pb::EndEpisodeRequest {
            session_id: session_id.into(),
        };
        let response = self
            .call(request, |mut s, r| async move { s.end_episode(r).await })
            .await?;
        Ok(response.episodes_completed)
    }

    /// Probe of one session: the probe to evaluate the critic at, and the action to apply.
    pub async fn probe(&self, request: pb::ProbeRequest) -> Result<pb::ProbeResponse> {
        self.call(request, |mut s, r| async move { s.probe(r).await })
            .await
    }

    /// Report of one session: the improved action.
    pub async fn report(&self, request: pb::ReportRequest) -> Result<pb::ReportResponse> {
        self.call(request, |mut s, r| async move { s.report(r).await })
            .await
    }

    /// ProbeBatch of N sessions.
    pub async fn probe_batch(
        &self,
        request: pb::ProbeBatchRequest,
    ) -> Result<pb::ProbeBatchResponse> {
        self.call(request, |mut s, r| async move { s.probe_batch(r).await })
            .await
    }

    /// ReportBatch of N sessions.
    pub async fn report_batch(
        &self,
        request: pb::ReportBatchRequest,
    ) -> Result<pb::ReportBatchResponse> {
        self.call(request, |mut s, r| async move { s.report_batch(r).await })
            .await
    }

    /// Opens a StepStream: batches over one bidirectional stream, pipelined.
    ///
    /// The call goes out at once but is not waited for: a server may send its response
    /// headers only with its first answer (a grpcio server's generator does), so waiting for
    /// them before the first request would deadlock. A refusal of the call itself (a wrong
    /// token, an unreachable server) is the error of the first answer read.
    pub async fn step_stream(&self) -> Result<StepStream> {
        let (sender, receiver) = mpsc::channel(STREAM_QUEUE);
        let mut request = Request::new(ReceiverStream::new(receiver));
        if let Some(authorization) = &self.authorization {
            request
                .metadata_mut()
                .insert("authorization", authorization.clone());
        }
        let mut service = self.service.clone();
        let call = tokio::spawn(async move { service.step_stream(request).await });
        Ok(StepStream {
            sender,
            responses: Responses::Opening(call),
            pending: 0,
            timeout: self.timeout,
        })
    }

    /// Whether the server's health check answers SERVING within `timeout`; with
    /// `wait_for_ready`, an unreachable server is asked again until then.
    pub async fn healthy(&self, timeout: Duration, wait_for_ready: bool) -> bool {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let mut request = self.request(HealthCheckRequest::default());
            request.set_timeout(left);
            let mut health = self.health.clone();
            match tokio::time::timeout(left, health.check(request)).await {
                Ok(Ok(answer)) => {
                    return answer.into_inner().status == ServingStatus::Serving as i32
                }
                Ok(Err(status))
                    if wait_for_ready
                        && matches!(status.code(), Code::Unavailable | Code::Unknown) => {}
                _ => return false,
            }
            if Instant::now() + READY_RETRY >= deadline {
                return false;
            }
            tokio::time::sleep(READY_RETRY).await;
        }
    }

    /// Creates `n` sessions of `config` (ids chosen by the server) and steps them together;
    /// with `use_stream`, over a StepStream (deferred reports ride with the next probe).
    pub async fn create_batch(
        &self,
        config: pb::SessionConfig,
        n: usize,
        use_stream: bool,
    ) -> Result<Batch> {
        let dim = config.action_dim as usize;
        let mut ids = Vec::with_capacity(n);
        for _ in 0..n {
            ids.push(self.create_session("", config.clone()).await?);
        }
        let stream = if use_stream {
            Some(self.step_stream().await?)
        } else {
            None
        };
        Ok(Batch {
            client: self.clone(),
            steps: vec![0; ids.len()],
            ids,
            dim,
            stream,
            deferred: false,
        })
    }
}

/// One request of a StepStream.
#[derive(Clone, Debug)]
pub enum Step {
    /// A ProbeBatch.
    Probe(pb::ProbeBatchRequest),
    /// A ReportBatch.
    Report(pb::ReportBatchRequest),
    /// A whole step for a linear critic (a probe and the critic's report, one request).
    StepLinear(pb::StepLinearBatchRequest),
    /// A whole step with the critic's values given at probes computed ahead (a probe and the
    /// report of those values, one request): the wire's `step_batch`.
    Fused(pb::StepBatchRequest),
}

/// One answer of a StepStream, in request order.
#[derive(Clone, Debug)]
pub enum Answer {
    /// The answer to a ProbeBatch.
    Probe(pb::ProbeBatchResponse),
    /// The answer to a ReportBatch.
    Report(pb::ReportBatchResponse),
    /// The answer to a whole step ([`Step::StepLinear`] or [`Step::Fused`]).
    Step(pb::StepBatchResponse),
}

/// A StepStream: batch requests sent without waiting ([`StepStream::send`]), answers read in
/// the same order ([`StepStream::next`]). A refused request fails only its own answer; the
/// stream stays open.
#[derive(Debug)]
pub struct StepStream {
    sender: mpsc::Sender<pb::StepStreamRequest>,
    responses: Responses,
    pending: usize,
    timeout: Duration,
}

/// The answers of a StepStream: the call until its response headers came, then their stream.
#[derive(Debug)]
enum Responses {
    Opening(JoinHandle<std::result::Result<Response<Streaming<pb::StepStreamResponse>>, Status>>),
    Open(Box<Streaming<pb::StepStreamResponse>>),
}

impl Drop for Responses {
    /// A stream dropped before its call opened ends the call too.
    fn drop(&mut self) {
        if let Responses::Opening(call) = self {
            call.abort();
        }
    }
}

impl Responses {
    /// The next answer: `None` when the server ended the stream.
    async fn message(&mut self) -> Result<Option<pb::StepStreamResponse>> {
        if let Responses::Opening(call) = self {
            let opened = call
                .await
                .map_err(|_| Error::new(Code::Unavailable, "the step stream's call was lost"))??;
            *self = Responses::Open(Box::new(opened.into_inner()));
        }
        match self {
            Responses::Open(responses) => Ok(responses.message().await?),
            Responses::Opening(_) => Err(Error::new(
                Code::Unavailable,
                "the step stream did not open",
            )),
        }
    }
}

impl StepStream {
    /// Sends a request; its answer comes from a later [`StepStream::next`].
    pub async fn send(&mut self, step: Step) -> Result<()> {
        use pb::step_stream_request::Kind as K;
        let kind = match step {
            Step::Probe(request) => K::ProbeBatch(request),
            Step::Report(request) => K::ReportBatch(request),
            Step::StepLinear(request) => K::StepLinearBatch(request),
            Step::Fused(request) => K::StepBatch(request),
        };
        self.sender
            .send(pb::StepStreamRequest { kind: Some(kind) })
            .await
            .map_err(|_| Error::new(Code::Unavailable, "the step stream is closed"))?;
        self.pending += 1;
        Ok(())
    }

    /// How many sent requests wait for their answer.
    pub fn pending(&self) -> usize {
        self.pending
    }

    /// The answer to the oldest request not yet answered.
    pub async fn next(&mut self) -> Result<Answer> {
        use pb::step_stream_response::Kind as K;
        if self.pending == 0 {
            return Err(Error::new(
                Code::FailedPrecondition,
                "no request waits for an answer",
            ));
        }
        // The first answer waits for the call's response headers too, within the same deadline.
        let message = match tokio::time::timeout(self.timeout, self.responses.message()).await {
            Ok(message) => message?,
            Err(_) => return Err(Error::deadline(self.timeout)),
        };
        self.pending -= 1;
        match message.and_then(|message| message.kind) {
            Some(K::ProbeBatch(response)) => Ok(Answer::Probe(response)),
            Some(K::ReportBatch(response)) => Ok(Answer::Report(response)),
            Some(K::StepLinearBatch(response) | K::StepBatch(response)) => {
                Ok(Answer::Step(response))
            }
            Some(K::Error(error)) => Err(Error::from_stream(error)),
            None => Err(Error::new(
                Code::Unavailable,
                "the step stream ended before its answer",
            )),
        }
    }

    /// A ProbeBatch: send, then read its answer.
    pub async fn probe_batch(
        &mut self,
        request: pb::ProbeBatchRequest,
    ) -> Result<pb::ProbeBatchResponse> {
        self.send(Step::Probe(request)).await?;
        match self.next().await? {
            Answer::Probe(response) => Ok(response),
            _ => Err(out_of_order()),
        }
    }

    /// A ReportBatch: send, then read its answer.
    pub async fn report_batch(
        &mut self,
        request: pb::ReportBatchRequest,
    ) -> Result<pb::ReportBatchResponse> {
        self.send(Step::Report(request)).await?;
        match self.next().await? {
            Answer::Report(response) => Ok(response),
            _ => Err(out_of_order()),
        }
    }

    /// A ReportBatch and the next step's ProbeBatch, both sent before either answer is read:
    /// one round trip (CONTRACT.md section 1b's pipelined step). The report's failure is
    /// returned before the probe's; both answers are read, so a refused request leaves the
    /// stream in step. After an error of the wire ([`Error::is_retryable`]) the stream is out
    /// of step: open a new one.
    pub async fn report_then_probe(
        &mut self,
        report: pb::ReportBatchRequest,
        probe: pb::ProbeBatchRequest,
    ) -> Result<pb::ProbeBatchResponse> {
        self.send(Step::Report(report)).await?;
        self.send(Step::Probe(probe)).await?;
        let report = self.next().await;
        if let Err(error) = &report {
            if error.is_retryable() {
                return Err(error.clone());
            }
        }
        let probe = self.next().await;
        report?;
        match probe? {
            Answer::Probe(response) => Ok(response),
            _ => Err(out_of_order()),
        }
    }

    /// A whole step for a linear critic: send, then read its answer.
    pub async fn step_linear_batch(
        &mut self,
        request: pb::StepLinearBatchRequest,
    ) -> Result<pb::StepBatchResponse> {
        self.step(Step::StepLinear(request)).await
    }

    /// A whole step with the critic's values given: send, then read its answer.
    pub async fn step_batch(
        &mut self,
        request: pb::StepBatchRequest,
    ) -> Result<pb::StepBatchResponse> {
        self.step(Step::Fused(request)).await
    }

    async fn step(&mut self, step: Step) -> Result<pb::StepBatchResponse> {
        self.send(step).await?;
        match self.next().await? {
            Answer::Step(response) => Ok(response),
            _ => Err(out_of_order()),
        }
    }
}

fn out_of_order() -> Error {
    Error::new(Code::Internal, "a StepStream answer out of order")
}

/// N sessions stepped together: per step one [`Batch::probe`] and one [`Batch::report`]. The
/// batch counts each session's step (0 again at an episode start).
#[derive(Debug)]
pub struct Batch {
    client: Client,
    ids: Vec<String>,
    dim: usize,
    steps: Vec<u64>,
    stream: Option<StepStream>,
    /// A report sent on the stream whose answer is not read yet.
    deferred: bool,
}

impl Batch {
    /// The session ids, in batch order.
    pub fn ids(&self) -> &[String] {
        &self.ids
    }

    /// How many sessions.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// Whether the batch has no session.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// The action dimension.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// ProbeBatch: `actions` (N x dim, row-major), which sessions start an episode, and the
    /// optional action scales (N x dim, or empty). Returns `(probes, applied)`, each N x dim:
    /// evaluate the critic at the probes; execute `applied`, Algorithm 1's `a_t + v(t)`.
    pub async fn probe(
        &mut self,
        actions: &[f64],
        episode_starts: &[bool],
        action_scales: Option<&[f64]>,
    ) -> Result<(Vec<f64>, Vec<f64>)> {
        for (step, start) in self.steps.iter_mut().zip(episode_starts) {
            if *start {
                *step = 0;
            }
        }
        let request = pb::ProbeBatchRequest {
            session_ids: self.ids.clone(),
            steps: self.steps.clone(),
            actions: actions.to_vec(),
            episode_starts: episode_starts.to_vec(),
            action_scales: action_scales.map(<[f64]>::to_vec).unwrap_or_default(),
        };
        let response = match &mut self.stream {
            Some(stream) => {
                stream.send(Step::Probe(request)).await?;
                if std::mem::take(&mut self.deferred) {
                    // The deferred report's answer comes first; its failure is this call's.
                    let report = stream.next().await;
                    let probe = stream.next().await;
                    report?;
                    probe?
                } else {
                    stream.next().await?
                }
            }
            None => Answer::Probe(self.client.probe_batch(request).await?),
        };
        match response {
            Answer::Probe(response) => Ok((response.probes, response.actions)),
            _ => Err(out_of_order()),
        }
    }

    /// ReportBatch: the critic's Q at the probes (N), and optionally at the applied actions
    /// (the paired reference, N). Returns the improved actions (N x dim), or, with `defer` on
    /// a stream, an empty vector: the report is sent now and its answer read by the next probe.
    pub async fn report(
        &mut self,
        q_values: &[f64],
        q_references: Option<&[f64]>,
        defer: bool,
    ) -> Result<Vec<f64>> {
        let request = pb::ReportBatchRequest {
            session_ids: self.ids.clone(),
            steps: self.steps.clone(),
            q_values: q_values.to_vec(),
            q_references: q_references.map(<[f64]>::to_vec).unwrap_or_default(),
        };
        let actions = match &mut self.stream {
            Some(stream) if defer => {
                stream.send(Step::Report(request)).await?;
                self.deferred = true;
                Vec::new()
            }
            Some(stream) => stream.report_batch(request).await?.actions,
            None => self.client.report_batch(request).await?.actions,
        };
        for step in &mut self.steps {
            *step += 1;
        }
        Ok(actions)
    }

    /// Reads a deferred report's answer (if any) and closes the sessions.
    pub async fn close(mut self) -> Result<()> {
        if let (Some(stream), true) = (&mut self.stream, self.deferred) {
            stream.next().await?;
        }
        for id in &self.ids {
            self.client.close_session(id.clone()).await?;
        }
        Ok(())
    }
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
