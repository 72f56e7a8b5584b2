//! Starting servers (in this process, or the `esa-server` executable) and
//! building requests for the tests.

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::process::{Child, ChildStdout, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

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
    task: JoinHandle<Result<(), esa_server::StartError>>,
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
    JoinHandle<Result<(), esa_server::StartError>>,
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
            progress: None,
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
    probe_scaled(client, id, step, action, &[], episode_start).await
}

/// A Probe with CONTRACT.md section 1b's action scale (empty: unscaled).
pub async fn probe_scaled(
    client: &mut Client,
    id: &str,
    step: u64,
    action: &[f64],
    action_scale: &[f64],
    episode_start: bool,
) -> Result<pb::ProbeResponse, Status> {
    client
        .probe(pb::ProbeRequest {
            session_id: id.into(),
            step,
            action: action.to_vec(),
            episode_start,
            action_scale: action_scale.to_vec(),
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
    report_paired(client, id, step, q_value, None).await
}

/// A Report with CONTRACT.md section 1b's paired reference Q (None: unpaired).
pub async fn report_paired(
    client: &mut Client,
    id: &str,
    step: u64,
    q_value: f64,
    q_reference: Option<f64>,
) -> Result<pb::ReportResponse, Status> {
    client
        .report(pb::ReportRequest {
            session_id: id.into(),
            step,
            q_value,
            q_reference,
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

pub const BIN: &str = env!("CARGO_BIN_EXE_esa-server");

/// Starts the executable with `args`; stdout is piped for [`read_line_after`].
pub fn launch(args: &[&str]) -> (Child, BufReader<ChildStdout>) {
    launch_limited("", args)
}

/// [`launch`] under a bash `ulimit` prefix such as `ulimit -n 128` (empty:
/// none), so that the server starts with those resource limits.
pub fn launch_limited(ulimits: &str, args: &[&str]) -> (Child, BufReader<ChildStdout>) {
    let script = format!("{ulimits}\nexec \"$0\" \"$@\"");
    let mut child = Command::new("bash")
        .arg("-c")
        .arg(script)
        .arg(BIN)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("start esa-server");
    let stdout = BufReader::new(child.stdout.take().expect("piped stdout"));
    (child, stdout)
}

/// Reads stdout lines until one starts with `prefix`; returns the rest.
pub fn read_line_after(stdout: &mut BufReader<ChildStdout>, prefix: &str) -> String {
    let mut line = String::new();
    loop {
        line.clear();
        let n = stdout.read_line(&mut line).expect("read stdout");
        assert!(n > 0, "esa-server closed stdout before printing {prefix:?}");
        if let Some(rest) = line.trim_end().strip_prefix(prefix) {
            return rest.to_string();
        }
    }
}

/// Starts the executable on `127.0.0.1:0` with `args` (after `ulimits`, as
/// for [`launch_limited`]) and connects a client.
pub async fn launch_tcp(ulimits: &str, args: &[&str]) -> (Child, String) {
    let (child, mut stdout) =
        launch_limited(ulimits, &[&["--listen", "127.0.0.1:0"], args].concat());
    let addr = read_line_after(&mut stdout, "listening on ");
    (child, format!("http://{addr}"))
}

pub fn signal(child: &Child, name: &str) {
    signal_pid(child.id(), name);
}

pub fn signal_pid(pid: u32, name: &str) {
    let status = Command::new("kill")
        .args([&format!("-{name}"), &pid.to_string()])
        .status()
        .expect("run kill");
    assert!(status.success());
}

/// Waits for the child to exit and returns whether it succeeded. The servers
/// run with a shutdown grace far beyond this deadline, so exiting in time
/// means shutdown did not hang on connections. The wait is async so that
/// this runtime's client connections keep answering the server's goodbye.
pub async fn wait_exit(child: &mut Child) -> bool {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if let Some(status) = child.try_wait().expect("wait") {
            return status.success();
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("esa-server did not exit after the signal");
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// A field of `/proc/<pid>/status` in bytes (`VmRSS`, `VmHWM`, ...).
pub fn proc_status_bytes(pid: u32, field: &str) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("proc status");
    let kib: u64 = status
        .lines()
        .find_map(|line| line.strip_prefix(field)?.strip_prefix(':'))
        .and_then(|rest| rest.trim().trim_end_matches(" kB").parse().ok())
        .expect("a kB field");
    kib * 1024
}

/// CPU time (user + system) the process has used so far.
pub fn cpu_time(pid: u32) -> Duration {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).expect("proc stat");
    // Fields after the parenthesized command name; utime and stime are the 12th and 13th.
    let fields: Vec<&str> = stat
        .rsplit_once(')')
        .expect("comm")
        .1
        .split_whitespace()
        .collect();
    let ticks: u64 = fields[11].parse::<u64>().unwrap() + fields[12].parse::<u64>().unwrap();
    // USER_HZ is 100 on every Linux configuration that matters here.
    Duration::from_millis(ticks * 10)
}

/// Whether `pid` has exited (a zombie nobody reaped counts as exited).
pub fn exited(pid: u32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        Err(_) => true,
        Ok(stat) => stat
            .rsplit_once(')')
            .is_some_and(|(_, rest)| rest.trim_start().starts_with('Z')),
    }
}

/// Polls `done` every 20 ms for at most `limit`; returns whether it came true.
pub async fn eventually(limit: Duration, mut done: impl FnMut() -> bool) -> bool {
    let deadline = Instant::now() + limit;
    while Instant::now() < deadline {
        if done() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    done()
}

/// Passes request bytes through unencoded, so tests can send malformed or hostile messages.
#[derive(Clone, Copy, Default)]
pub struct RawCodec;

impl tonic::codec::Codec for RawCodec {
    type Encode = Vec<u8>;
    type Decode = Vec<u8>;
    type Encoder = RawCodec;
    type Decoder = RawCodec;

    fn encoder(&mut self) -> RawCodec {
        RawCodec
    }

    fn decoder(&mut self) -> RawCodec {
        RawCodec
    }
}

impl tonic::codec::Encoder for RawCodec {
    type Item = Vec<u8>;
    type Error = Status;

    fn encode(
        &mut self,
        item: Vec<u8>,
        buf: &mut tonic::codec::EncodeBuf<'_>,
    ) -> Result<(), Status> {
        bytes::BufMut::put_slice(buf, &item);
        Ok(())
    }
}

impl tonic::codec::Decoder for RawCodec {
    type Item = Vec<u8>;
    type Error = Status;

    fn decode(&mut self, buf: &mut tonic::codec::DecodeBuf<'_>) -> Result<Option<Vec<u8>>, Status> {
        use bytes::Buf as _;
        Ok(Some(buf.copy_to_bytes(buf.remaining()).to_vec()))
    }
}

/// Calls `method` of esa.v1.EsaService at `url` with `bytes` as the request message.
pub async fn call_raw(url: &str, method: &str, bytes: Vec<u8>) -> Result<Vec<u8>, Status> {
    let channel = tonic::transport::Endpoint::from_shared(url.to_string())
        .expect("url")
        .connect()
        .await
        .expect("connect");
    let mut grpc = tonic::client::Grpc::new(channel);
    grpc.ready().await.expect("ready");
    let path =
        http::uri::PathAndQuery::try_from(format!("/esa.v1.EsaService/{method}")).expect("path");
    grpc.unary(tonic::Request::new(bytes), path, RawCodec)
        .await
        .map(tonic::Response::into_inner)
}

/// xorshift64*: a dependency-free, seeded source of test inputs.
pub struct Rng(pub u64);

impl Rng {
    pub fn next_f64(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }

    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next_f64()
    }

    // Only bounded_law, compiled with the Zenoh feature, flips coins.
    #[cfg(feature = "zenoh")]
    pub fn coin(&mut self) -> bool {
        self.next_f64() < 0.5
    }

    /// An integer in 0..n.
    pub fn below(&mut self, n: u64) -> u64 {
        (self.next_f64() * n as f64) as u64
    }
}
