//! One client's view of a set of sessions: connect over TCP, a Unix socket
//! or Zenoh, create the sessions, and run probe + report pairs over one of
//! the three ways the contract offers (Probe/Report, ProbeBatch/ReportBatch,
//! or StepStream messages).

use esa_proto::v1 as pb;
use esa_proto::v1::esa_service_client::EsaServiceClient;
use esa_proto::v1::step_stream_request::Kind as Req;
use esa_proto::v1::step_stream_response::Kind as Resp;
use esa_proto::Rpc;
use hyper_util::rt::TokioIo;
use prost::Message;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::{Channel, Endpoint};
use tonic::Streaming;

use crate::error::{Error, Result};
use crate::server_process::Address;
use crate::zenoh_client::ZenohClient;

/// A connection to the server over one of its transports.
#[derive(Clone)]
pub enum Client {
    /// The generated gRPC client on a tonic channel (TCP or Unix socket).
    Grpc(EsaServiceClient<Channel>),
    /// A Zenoh peer session: one query per call.
    Zenoh(ZenohClient),
}

/// The unary calls, each over gRPC or as a query on `<prefix>/<Rpc>`.
macro_rules! unary_calls {
    ($($method:ident: $rpc:ident($request:ty) -> $response:ty;)*) => {
        impl Client {
            $(
                async fn $method(&mut self, request: $request) -> Result<$response> {
                    match self {
                        Client::Grpc(client) => Ok(client.$method(request).await?.into_inner()),
                        Client::Zenoh(client) => client.call(Rpc::$rpc, &request).await,
                    }
                }
            )*
        }
    };
}

unary_calls! {
    create_session: CreateSession(pb::CreateSessionRequest) -> pb::CreateSessionResponse;
    close_session: CloseSession(pb::CloseSessionRequest) -> pb::CloseSessionResponse;
    probe: Probe(pb::ProbeRequest) -> pb::ProbeResponse;
    report: Report(pb::ReportRequest) -> pb::ReportResponse;
    probe_batch: ProbeBatch(pb::ProbeBatchRequest) -> pb::ProbeBatchResponse;
    report_batch: ReportBatch(pb::ReportBatchRequest) -> pb::ReportBatchResponse;
}

/// Steps per episode, as in the MuJoCo tasks: keeps `t` (and so the sine
/// arguments) realistic and exercises the episode-start path.
const EPISODE_STEPS: u64 = 1000;

/// How the pairs travel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Api {
    /// `Probe` + `Report`, one session per call.
    Unary,
    /// `ProbeBatch` + `ReportBatch` unary calls.
    Batch,
    /// `ProbeBatch` + `ReportBatch` messages on one `StepStream` (over
    /// Zenoh: one query per message on the `StepStream` key).
    Stream,
}

/// Opens a new HTTP/2 connection (or Zenoh session) to `address`.
pub async fn connect(address: &Address) -> Result<Client> {
    match address {
        Address::Zenoh(locators) => Ok(Client::Zenoh(ZenohClient::connect(locators).await?)),
        _ => Ok(Client::Grpc(EsaServiceClient::new(channel(address).await?))),
    }
}

/// Opens a new HTTP/2 connection to a TCP or Unix socket address.
pub async fn channel(address: &Address) -> Result<Channel> {
    Ok(match address {
        Address::Zenoh(_) => {
            return Err(Error::Protocol(
                "a Zenoh address has no HTTP/2 channel".into(),
            ))
        }
        Address::Tcp(addr) => {
            Endpoint::try_from(format!("http://{addr}"))?
                .tcp_nodelay(true)
                .connect()
                .await?
        }
        Address::Unix(path) => {
            let path = path.clone();
            // The URI is only the :authority; the connector ignores it.
            Endpoint::from_static("http://localhost")
                .connect_with_connector(tower::service_fn(move |_| {
                    let path = path.clone();
                    async move {
                        Ok::<_, std::io::Error>(TokioIo::new(
                            tokio::net::UnixStream::connect(path).await?,
                        ))
                    }
                }))
                .await?
        }
    })
}

/// A session config like the SB3 drop-ins send for a `dim`-D Box in [-1, 1].
pub fn session_config(dim: usize) -> pb::SessionConfig {
    pb::SessionConfig {
        action_dim: dim as u32,
        dt: 0.01,
        amplitude: vec![0.2],
        frequency: (0..dim).map(|i| 40.0 + 5.0 * i as f64).collect(),
        learning_rate: vec![0.05],
        action_low: vec![-1.0; dim],
        action_high: vec![1.0; dim],
        ..Default::default()
    }
}

/// Creates sessions `<prefix>-0 .. <prefix>-<n-1>`; returns their ids.
pub async fn create_sessions(
    client: &mut Client,
    prefix: &str,
    n: usize,
    dim: usize,
) -> Result<Vec<String>> {
    let mut ids = Vec::with_capacity(n);
    for i in 0..n {
        let request = pb::CreateSessionRequest {
            session_id: format!("{prefix}-{i}"),
            config: Some(session_config(dim)),
            progress: None,
        };
        ids.push(client.create_session(request).await?.session_id);
    }
    Ok(ids)
}

/// Closes the given sessions.
pub async fn close_sessions(client: &mut Client, ids: &[String]) -> Result<()> {
    for id in ids {
        let request = pb::CloseSessionRequest {
            session_id: id.clone(),
        };
        client.close_session(request).await?;
    }
    Ok(())
}

/// One StepStream: a gRPC stream, or StepStream queries over Zenoh.
// One per Stepper: its size does not matter, an extra pointer hop on the
// measured path would.
#[allow(clippy::large_enum_variant)]
enum Stream {
    Grpc {
        requests: mpsc::Sender<pb::StepStreamRequest>,
        responses: Streaming<pb::StepStreamResponse>,
    },
    Zenoh(ZenohClient),
}

impl Stream {
    async fn open(client: &mut Client) -> Result<Self> {
        let client = match client {
            Client::Grpc(client) => client,
            Client::Zenoh(client) => return Ok(Self::Zenoh(client.clone())),
        };
        // One message in flight at a time: a pair is two strict round trips.
        let (requests, rx) = mpsc::channel(1);
        let responses = client
            .step_stream(ReceiverStream::new(rx))
            .await?
            .into_inner();
        Ok(Self::Grpc {
            requests,
            responses,
        })
    }

    async fn round_trip(&mut self, kind: Req) -> Result<Resp> {
        let request = pb::StepStreamRequest { kind: Some(kind) };
        let response: pb::StepStreamResponse = match self {
            Self::Grpc {
                requests,
                responses,
            } => {
                requests
                    .send(request)
                    .await
                    .map_err(|_| Error::Protocol("StepStream closed by the server".into()))?;
                responses
                    .message()
                    .await?
                    .ok_or_else(|| Error::Protocol("StepStream ended".into()))?
            }
            Self::Zenoh(client) => client.call(Rpc::StepStream, &request).await?,
        };
        match response.kind {
            Some(Resp::Error(err)) => Err(Error::Stream {
                code: err.code,
                message: err.message,
            }),
            Some(kind) => Ok(kind),
            None => Err(Error::Protocol("StepStream response without a kind".into())),
        }
    }
}

/// N sessions stepped together, the way a trainer with N envs steps them:
/// sampled actions in, probes out, Q at the probes in, improved actions out.
pub struct Stepper {
    client: Client,
    stream: Option<Stream>,
    api: Api,
    ids: Vec<String>,
    dim: usize,
    step: u64,
    actions: Vec<f64>,
}

impl Stepper {
    /// Prepares pairs over `api` for the sessions `ids` (one id for
    /// [`Api::Unary`]); opens the StepStream when `api` is [`Api::Stream`].
    pub async fn new(mut client: Client, api: Api, ids: Vec<String>, dim: usize) -> Result<Self> {
        if api == Api::Unary && ids.len() != 1 {
            return Err(Error::Protocol(format!(
                "Probe/Report pairs step one session, got {}",
                ids.len()
            )));
        }
        let stream = match api {
            Api::Stream => Some(Stream::open(&mut client).await?),
            Api::Unary | Api::Batch => None,
        };
        let actions = (0..ids.len() * dim)
            .map(|i| 0.1 * (i % 7) as f64 - 0.3)
            .collect();
        Ok(Self {
            client,
            stream,
            api,
            ids,
            dim,
            step: 0,
            actions,
        })
    }

    /// Makes the first pair start a new episode, for sessions stepped
    /// before (by an earlier stepper that failed halfway, say).
    pub fn starting_episode(mut self) -> Self {
        self.step = EPISODE_STEPS;
        self
    }

    /// One probe + report round trip for every session; a new episode
    /// starts every [`EPISODE_STEPS`] steps.
    pub async fn pair(&mut self) -> Result<()> {
        let episode_start = self.step == EPISODE_STEPS;
        if episode_start {
            self.step = 0;
        }
        let probes = self.probe(episode_start).await?;
        self.check_len("probes", probes.len())?;
        let q_values: Vec<f64> = probes
            .chunks_exact(self.dim)
            .map(|p| -p.iter().map(|x| x * x).sum::<f64>())
            .collect();
        let improved = self.report(q_values).await?;
        self.check_len("actions", improved.len())?;
        self.step += 1;
        Ok(())
    }

    fn check_len(&self, what: &str, len: usize) -> Result<()> {
        let expected = self.ids.len() * self.dim;
        if len == expected {
            Ok(())
        } else {
            Err(Error::Protocol(format!(
                "expected {expected} {what}, got {len}"
            )))
        }
    }

    /// The encoded sizes of this stepper's probe and report requests (not at an episode
    /// start): what an echo of the same pair carries.
    pub fn request_sizes(&self) -> (usize, usize) {
        let q_values = vec![0.0; self.ids.len()];
        match self.api {
            Api::Unary => (
                self.unary_probe(false).encoded_len(),
                self.unary_report(&q_values).encoded_len(),
            ),
            Api::Batch | Api::Stream => (
                self.probe_batch(false).encoded_len(),
                self.report_batch(q_values).encoded_len(),
            ),
        }
    }

    fn unary_probe(&self, episode_start: bool) -> pb::ProbeRequest {
        pb::ProbeRequest {
            session_id: self.ids.concat(),
            step: self.step,
            action: self.actions.clone(),
            episode_start,
            ..Default::default()
        }
    }

    fn unary_report(&self, q_values: &[f64]) -> pb::ReportRequest {
        pb::ReportRequest {
            session_id: self.ids.concat(),
            step: self.step,
            q_value: q_values.iter().sum(),
            ..Default::default()
        }
    }

    fn probe_batch(&self, episode_start: bool) -> pb::ProbeBatchRequest {
        let n = self.ids.len();
        pb::ProbeBatchRequest {
            session_ids: self.ids.clone(),
            steps: vec![self.step; n],
            actions: self.actions.clone(),
            episode_starts: if episode_start { vec![true; n] } else { vec![] },
            ..Default::default()
        }
    }

    fn report_batch(&self, q_values: Vec<f64>) -> pb::ReportBatchRequest {
        pb::ReportBatchRequest {
            session_ids: self.ids.clone(),
            steps: vec![self.step; self.ids.len()],
            q_values,
            ..Default::default()
        }
    }

    async fn probe(&mut self, episode_start: bool) -> Result<Vec<f64>> {
        if self.api == Api::Unary {
            let request = self.unary_probe(episode_start);
            return Ok(self.client.probe(request).await?.probe);
        }
        let request = self.probe_batch(episode_start);
        match self.stream.as_mut() {
            Some(stream) => match stream.round_trip(Req::ProbeBatch(request)).await? {
                Resp::ProbeBatch(response) => Ok(response.probes),
                other => Err(unexpected("ProbeBatchResponse", &other)),
            },
            None => Ok(self.client.probe_batch(request).await?.probes),
        }
    }

    async fn report(&mut self, q_values: Vec<f64>) -> Result<Vec<f64>> {
        if self.api == Api::Unary {
            let request = self.unary_report(&q_values);
            return Ok(self.client.report(request).await?.action);
        }
        let request = self.report_batch(q_values);
        match self.stream.as_mut() {
            Some(stream) => match stream.round_trip(Req::ReportBatch(request)).await? {
                Resp::ReportBatch(response) => Ok(response.actions),
                other => Err(unexpected("ReportBatchResponse", &other)),
            },
            None => Ok(self.client.report_batch(request).await?.actions),
        }
    }

    /// Ends the stream (if any) and closes the sessions.
    pub async fn close(mut self) -> Result<()> {
        drop(self.stream.take());
        close_sessions(&mut self.client, &self.ids).await
    }
}

fn unexpected(expected: &str, got: &Resp) -> Error {
    Error::Protocol(format!("expected a {expected}, got {got:?}"))
}
