//! Starting servers and building requests for the tests.

use std::net::SocketAddr;
use std::sync::Arc;

use esa_server::pb;
use esa_server::pb::esa_service_client::EsaServiceClient;
use esa_server::{EsaHandler, EsaServer, Listener, ServerBuilder};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tonic::transport::Channel;
use tonic::{Code, Status};

pub type Client = EsaServiceClient<Channel>;

/// A server running in this process until [`TestServer::stop`] (or the end
/// of the test's runtime).
pub struct TestServer {
    pub addr: SocketAddr,
    pub handler: Arc<EsaHandler>,
    stop: oneshot::Sender<()>,
    task: JoinHandle<Result<(), esa_server::Error>>,
}

pub async fn start() -> TestServer {
    start_with(EsaServer::builder()).await
}

pub async fn start_with(builder: ServerBuilder) -> TestServer {
    let listener = Listener::tcp(SocketAddr::from(([127, 0, 0, 1], 0)))
        .await
        .expect("bind 127.0.0.1:0");
    let addr = listener
        .address()
        .expect("bound address")
        .parse()
        .expect("a socket address");
    let (handler, stop, task) = spawn(builder, listener);
    TestServer {
        addr,
        handler,
        stop,
        task,
    }
}

/// Serves `listener` in a task; returns the handler, the stop trigger and the task.
pub fn spawn(
    builder: ServerBuilder,
    listener: Listener,
) -> (
    Arc<EsaHandler>,
    oneshot::Sender<()>,
    JoinHandle<Result<(), esa_server::Error>>,
) {
    let server = builder.build();
    let handler = server.handler();
    let (stop, stopped) = oneshot::channel::<()>();
    let task = tokio::spawn(server.serve(listener, until(stopped)));
    (handler, stop, task)
}

async fn until(stopped: oneshot::Receiver<()>) {
    let _ = stopped.await;
}

impl TestServer {
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    pub async fn client(&self) -> Client {
        Client::connect(self.url()).await.expect("connect")
    }

    /// Stops the server and checks that it shut down cleanly.
    pub async fn stop(self) {
        let _ = self.stop.send(());
        self.task
            .await
            .expect("server task")
            .expect("server ended cleanly");
    }
}

/// The paper's Example 1 settings for D dimensions: dt = 0.01, K = 0.2,
/// w = 60 rad/s, alpha = 0.25, default high-pass.
pub fn config(action_dim: u32) -> pb::SessionConfig {
    pb::SessionConfig {
        action_dim,
        dt: 0.01,
        amplitude: vec![0.2],
        frequency: vec![60.0],
        learning_rate: vec![0.25],
        ..Default::default()
    }
}

pub async fn create(client: &mut Client, id: &str, config: pb::SessionConfig) -> String {
    client
        .create_session(pb::CreateSessionRequest {
            session_id: id.into(),
            config: Some(config),
        })
        .await
        .expect("create session")
        .into_inner()
        .session_id
}

pub async fn get(client: &mut Client, id: &str) -> Result<pb::GetSessionResponse, Status> {
    client
        .get_session(pb::GetSessionRequest {
            session_id: id.into(),
        })
        .await
        .map(tonic::Response::into_inner)
}

pub async fn probe(
    client: &mut Client,
    id: &str,
    step: u64,
    action: &[f64],
    episode_start: bool,
) -> Result<pb::ProbeResponse, Status> {
    client
        .probe(pb::ProbeRequest {
            session_id: id.into(),
            step,
            action: action.to_vec(),
            episode_start,
            ..Default::default()
        })
        .await
        .map(tonic::Response::into_inner)
}

pub async fn report(
    client: &mut Client,
    id: &str,
    step: u64,
    q_value: f64,
) -> Result<pb::ReportResponse, Status> {
    client
        .report(pb::ReportRequest {
            session_id: id.into(),
            step,
            q_value,
            ..Default::default()
        })
        .await
        .map(tonic::Response::into_inner)
}

pub async fn end_episode(client: &mut Client, id: &str) -> Result<pb::EndEpisodeResponse, Status> {
    client
        .end_episode(pb::EndEpisodeRequest {
            session_id: id.into(),
        })
        .await
        .map(tonic::Response::into_inner)
}

pub async fn close(client: &mut Client, id: &str) -> Result<pb::CloseSessionResponse, Status> {
    client
        .close_session(pb::CloseSessionRequest {
            session_id: id.into(),
        })
        .await
        .map(tonic::Response::into_inner)
}

/// Asserts that `result` failed with `code` and a message containing every
/// one of `needles`.
#[track_caller]
pub fn assert_error<T: std::fmt::Debug>(result: Result<T, Status>, code: Code, needles: &[&str]) {
    let status = result.expect_err("expected an error");
    assert_eq!(status.code(), code, "message: {}", status.message());
    for needle in needles {
        assert!(
            status.message().contains(needle),
            "message {:?} should contain {needle:?}",
            status.message()
        );
    }
}

/// Q of the paper's Example 1 (static case): -J(u), J = sum (u_i - 0.1 (i+1))^2.
pub fn q_of(probe: &[f64]) -> f64 {
    -probe
        .iter()
        .enumerate()
        .map(|(i, u)| (u - 0.1 * (i as f64 + 1.0)).powi(2))
        .sum::<f64>()
}
