//! The soak: minutes of steady load on a real `esa-server` while
//! floods and faults come and go, to show that memory stays flat, that no
//! client is lost, and what the load's latency becomes meanwhile.
//!
//! The server runs as a user's server would: default limits, with an
//! open-files limit of 1,024 (a common default) that it cannot raise, and a
//! short session TTL so that an expiry happens within the run. Throughout,
//! `load_clients` clients step `batch` sessions each (half of them over
//! ProbeBatch/ReportBatch, half over a StepStream). Meanwhile:
//! - flood cycles, each held for a while: more silent TCP connections than
//!   the server has file descriptors; idle HTTP/2 connections; StepStreams
//!   that announce a 20 MB message and never finish it; a client creating
//!   D = 4096 sessions until the session memory budget refuses one;
//! - one client pauses for longer than the TTL, so its sessions expire;
//! - the server is killed (SIGKILL) and restarted on the same port.
//!
//! A client whose sessions are gone (NOT_FOUND) recreates them under the same
//! ids and starts a new episode, as `EsaClient.restore_sessions` does.
//! Every few seconds the server's RSS, descriptors and connection metrics are
//! sampled. Everything stays on loopback.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use esa_proto::v1 as pb;
use hdrhistogram::Histogram;
use serde::Serialize;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tonic::Code;

use esa_bench::driver::{connect, session_config, Api, Client, Stepper};
use esa_bench::error::{Error, Result};
use esa_bench::measure::Latency;
use esa_bench::server_process::{rss_kib, Address, ServerProcess};

/// What to run; see the module documentation.
#[derive(Clone, Debug, Serialize)]
pub struct Plan {
    pub server: PathBuf,
    pub duration: Duration,
    pub load_clients: usize,
    pub batch: usize,
    pub dim: usize,
    pub open_files: u64,
    pub session_ttl: Duration,
    pub silent_connections: usize,
    pub idle_h2_connections: usize,
    pub stalled_streams: usize,
    pub sample_every: Duration,
}

/// Where the run is, for the latency histograms.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "lowercase")]
enum Phase {
    Quiet = 0,
    Flood = 1,
    Restart = 2,
}

impl Phase {
    const ALL: [Phase; 3] = [Phase::Quiet, Phase::Flood, Phase::Restart];
}

/// One sample of the server's state.
#[derive(Clone, Debug, Serialize)]
pub struct Sample {
    pub t_s: f64,
    pub phase: &'static str,
    pub rss_mib: f64,
    pub open_files: usize,
    pub connections_open: u64,
    pub sessions_live: u64,
    pub session_memory_mib: f64,
    pub pairs_so_far: u64,
}

/// What one flood cycle did and got.
#[derive(Clone, Debug, Serialize)]
pub struct FloodCycle {
    pub start_s: f64,
    pub silent_opened: usize,
    pub idle_h2_opened: usize,
    /// How the stalled StepStreams ended, by gRPC code name.
    pub stalled_ended: BTreeMap<String, usize>,
    pub big_sessions_created: usize,
    /// The answer that stopped the big sessions (RESOURCE_EXHAUSTED expected).
    pub big_sessions_refused_with: String,
    pub peak_rss_mib: f64,
}

/// One load client's record.
#[derive(Clone, Debug, Serialize)]
pub struct ClientReport {
    pub api: Api,
    pub pairs: u64,
    /// Failed pairs by gRPC code name (transport failures as UNAVAILABLE).
    pub failures: BTreeMap<String, u64>,
    pub sessions_recovered: u64,
    /// Longest time between two successful pairs, planned pause excluded.
    pub longest_gap_s: f64,
    /// No successful pair in the run's last 10 s, or a gap over 15 s.
    pub lost: bool,
}

/// Everything the soak measured; `tests/soak/report.py` renders it.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub plan: Plan,
    pub seconds: f64,
    pub pairs: u64,
    /// Successful calls (two per pair) plus the recovery calls.
    pub calls_served: u64,
    pub latency: BTreeMap<String, Latency>,
    pub samples: Vec<Sample>,
    pub floods: Vec<FloodCycle>,
    pub restart_downtime_s: f64,
    pub connections_evicted: u64,
    pub connections_refused: u64,
    pub max_connections_open: u64,
    pub max_open_files: usize,
    pub sessions_recovered: u64,
    pub lost_clients: usize,
    pub clients: Vec<ClientReport>,
    pub machine: Machine,
}

/// The machine the soak shared, at its start and end.
#[derive(Clone, Debug, Serialize)]
pub struct Machine {
    pub cores: usize,
    pub loadavg_start: String,
    pub loadavg_end: String,
    /// Share of CPU time the hypervisor gave other guests during the run (`/proc/stat`).
    pub steal_percent: f64,
}

/// The 1-, 5- and 15-minute load averages and the `cpu` line of `/proc/stat`.
fn machine_state() -> (String, Vec<u64>) {
    let loadavg = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let stat = std::fs::read_to_string("/proc/stat").unwrap_or_default();
    let cpu = stat
        .lines()
        .find_map(|line| line.strip_prefix("cpu "))
        .map(|fields| {
            fields
                .split_whitespace()
                .filter_map(|f| f.parse().ok())
                .collect()
        })
        .unwrap_or_default();
    let load = loadavg
        .split_whitespace()
        .take(3)
        .collect::<Vec<_>>()
        .join(" ");
    (load, cpu)
}

fn machine(start: (String, Vec<u64>), end: (String, Vec<u64>)) -> Machine {
    // Fields: user nice system idle iowait irq softirq steal.
    let spent: Vec<u64> = end
        .1
        .iter()
        .zip(&start.1)
        .take(8)
        .map(|(b, a)| b.saturating_sub(*a))
        .collect();
    let total: u64 = spent.iter().sum();
    Machine {
        cores: std::thread::available_parallelism().map_or(0, usize::from),
        loadavg_start: start.0,
        loadavg_end: end.0,
        steal_percent: spent
            .get(7)
            .map_or(0.0, |&steal| 100.0 * steal as f64 / total.max(1) as f64),
    }
}

/// Shared between the load clients and the orchestrator.
struct Shared {
    started: Instant,
    phase: AtomicU8,
    pairs: AtomicU64,
    recovery_calls: AtomicU64,
    latency: Mutex<Vec<Histogram<u64>>>,
    server_pid: AtomicU32,
}

impl Shared {
    fn phase(&self) -> Phase {
        match self.phase.load(Ordering::Relaxed) {
            1 => Phase::Flood,
            2 => Phase::Restart,
            _ => Phase::Quiet,
        }
    }

    fn elapsed(&self) -> Duration {
        self.started.elapsed()
    }
}

/// Runs the plan; see the module documentation.
pub async fn run(plan: Plan) -> Result<Report> {
    let machine_start = machine_state();
    let ttl = plan.session_ttl.as_secs_f64().to_string();
    let mut args = vec![
        "--listen".to_string(),
        "127.0.0.1:0".to_string(),
        "--metrics-listen".to_string(),
        "127.0.0.1:0".to_string(),
        "--session-ttl".to_string(),
        ttl,
        "--max-session-memory".to_string(),
        "256MiB".to_string(),
        "--request-timeout".to_string(),
        "5".to_string(),
    ];
    let mut server = ServerProcess::start_tcp_limited(&plan.server, &args, plan.open_files)?;
    let Address::Tcp(addr) = server.address().clone() else {
        return Err(Error::Server("expected a TCP address".into()));
    };
    let metrics = metrics_addr(&server)?;
    // The restarted server must come back where the clients and the metrics reader look.
    args[1] = addr.to_string();
    args[3] = metrics.to_string();

    let histogram =
        || Histogram::<u64>::new_with_bounds(1, 120_000_000_000, 3).expect("valid bounds");
    let shared = Arc::new(Shared {
        started: Instant::now(),
        phase: AtomicU8::new(Phase::Quiet as u8),
        pairs: AtomicU64::new(0),
        recovery_calls: AtomicU64::new(0),
        latency: Mutex::new(Phase::ALL.iter().map(|_| histogram()).collect()),
        server_pid: AtomicU32::new(server.pid()),
    });
    let duration = plan.duration;
    let at = |fraction: f64| duration.mul_f64(fraction);
    let hold = duration.mul_f64(0.1).min(Duration::from_secs(15));
    let pause = (
        at(0.17),
        at(0.17) + plan.session_ttl + Duration::from_secs(5),
    );

    let clients: Vec<_> = (0..plan.load_clients)
        .map(|index| {
            let api = if index % 2 == 0 {
                Api::Batch
            } else {
                Api::Stream
            };
            let planned_pause = (index == 0).then_some(pause);
            tokio::spawn(load_client(
                index,
                api,
                addr,
                plan.clone(),
                Arc::clone(&shared),
                planned_pause,
            ))
        })
        .collect();
    let sampler = tokio::spawn(sample(
        Arc::clone(&shared),
        metrics,
        plan.sample_every,
        duration,
    ));

    let mut floods = Vec::new();
    let mut restart_downtime = Duration::ZERO;
    let mut counted = BTreeMap::new();
    for (start, restart) in [(0.06, false), (0.28, false), (0.53, true), (0.78, false)] {
        tokio::time::sleep(at(start).saturating_sub(shared.elapsed())).await;
        if restart {
            shared.phase.store(Phase::Restart as u8, Ordering::Relaxed);
            // The counters start over with the new process.
            counted = add_counters(counted, read_metrics(metrics).await.unwrap_or_default());
            let down = Instant::now();
            drop(server);
            server = ServerProcess::start_tcp_limited(&plan.server, &args, plan.open_files)?;
            restart_downtime = down.elapsed();
            shared.server_pid.store(server.pid(), Ordering::Relaxed);
            tokio::time::sleep(Duration::from_secs(3)).await;
        } else {
            shared.phase.store(Phase::Flood as u8, Ordering::Relaxed);
            floods.push(flood(addr, &plan, hold, &shared).await);
        }
        shared.phase.store(Phase::Quiet as u8, Ordering::Relaxed);
    }

    let mut reports = Vec::new();
    for client in clients {
        reports.push(
            client
                .await
                .map_err(|err| Error::Protocol(format!("load client failed: {err}")))?,
        );
    }
    let samples = sampler
        .await
        .map_err(|err| Error::Protocol(format!("sampler failed: {err}")))?;
    for cycle in &mut floods {
        let window = cycle.start_s..cycle.start_s + hold.as_secs_f64() + 1.0;
        cycle.peak_rss_mib = samples
            .iter()
            .filter(|s| window.contains(&s.t_s))
            .map(|s| s.rss_mib)
            .fold(0.0, f64::max);
    }
    let counters = add_counters(counted, read_metrics(metrics).await.unwrap_or_default());
    let pairs = shared.pairs.load(Ordering::Relaxed);
    let latency = shared.latency.lock().map_err(poisoned)?;
    let mut by_phase: BTreeMap<String, Latency> = Phase::ALL
        .iter()
        .zip(latency.iter())
        .filter(|(_, h)| !h.is_empty())
        .map(|(phase, h)| (format!("{phase:?}").to_lowercase(), Latency::of(h)))
        .collect();
    let mut all = histogram();
    for h in latency.iter() {
        all.add(h).map_err(|err| Error::Protocol(err.to_string()))?;
    }
    by_phase.insert("all".into(), Latency::of(&all));
    drop(latency);
    Ok(Report {
        seconds: shared.elapsed().as_secs_f64(),
        pairs,
        calls_served: 2 * pairs + shared.recovery_calls.load(Ordering::Relaxed),
        latency: by_phase,
        restart_downtime_s: restart_downtime.as_secs_f64(),
        connections_evicted: counters
            .get("esa_connections_evicted_total")
            .copied()
            .unwrap_or(0),
        connections_refused: counters
            .get("esa_connections_refused_total")
            .copied()
            .unwrap_or(0),
        max_connections_open: samples
            .iter()
            .map(|s| s.connections_open)
            .max()
            .unwrap_or(0),
        max_open_files: samples.iter().map(|s| s.open_files).max().unwrap_or(0),
        sessions_recovered: reports.iter().map(|r| r.sessions_recovered).sum(),
        lost_clients: reports.iter().filter(|r| r.lost).count(),
        clients: reports,
        samples,
        floods,
        plan,
        machine: machine(machine_start, machine_state()),
    })
}

fn add_counters(
    mut total: BTreeMap<String, u64>,
    more: BTreeMap<String, u64>,
) -> BTreeMap<String, u64> {
    for (name, value) in more {
        *total.entry(name).or_default() += value;
    }
    total
}

fn poisoned<T>(_: T) -> Error {
    Error::Protocol("a soak task panicked".into())
}

fn metrics_addr(server: &ServerProcess) -> Result<SocketAddr> {
    server
        .metrics()
        .and_then(|url| url.strip_prefix("http://"))
        .and_then(|rest| rest.strip_suffix("/metrics"))
        .and_then(|addr| addr.parse().ok())
        .ok_or_else(|| Error::Server("no `metrics on` line".into()))
}

/// One load client: steps its sessions until the run ends, recovering from
/// whatever the floods and faults do to it.
async fn load_client(
    index: usize,
    api: Api,
    addr: SocketAddr,
    plan: Plan,
    shared: Arc<Shared>,
    planned_pause: Option<(Duration, Duration)>,
) -> ClientReport {
    let ids: Vec<String> = (0..plan.batch)
        .map(|i| format!("soak-{index}-{i:0>4}"))
        .collect();
    let mut report = ClientReport {
        api,
        pairs: 0,
        failures: BTreeMap::new(),
        sessions_recovered: 0,
        longest_gap_s: 0.0,
        lost: false,
    };
    let mut stepper: Option<Stepper> = None;
    let mut created = false;
    let mut last_ok = Instant::now();
    let mut paused = false;
    while shared.elapsed() < plan.duration {
        if let Some((from, until)) = planned_pause {
            if !paused && shared.elapsed() >= from {
                paused = true;
                stepper = None;
                tokio::time::sleep(until.saturating_sub(shared.elapsed())).await;
                last_ok = Instant::now();
            }
        }
        let Some(active) = stepper.as_mut() else {
            match start(addr, api, &ids, plan.dim, &shared).await {
                Ok((started, recreated)) => {
                    // The first start creates the sessions; later ones recover them.
                    if created {
                        report.sessions_recovered += recreated;
                    }
                    created = true;
                    stepper = Some(started);
                }
                Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
            }
            continue;
        };
        let begun = Instant::now();
        match active.pair().await {
            Ok(()) => {
                let took = begun.elapsed();
                if let Ok(mut histograms) = shared.latency.lock() {
                    if let Some(h) = histograms.get_mut(shared.phase() as usize) {
                        let _ = h.record(took.as_nanos().max(1) as u64);
                    }
                }
                shared.pairs.fetch_add(1, Ordering::Relaxed);
                report.pairs += 1;
                report.longest_gap_s = report.longest_gap_s.max(last_ok.elapsed().as_secs_f64());
                last_ok = Instant::now();
            }
            Err(err) => {
                let code = code_of(&err);
                *report.failures.entry(format!("{code:?}")).or_default() += 1;
                // Any failure may have left the stream or the steps out of
                // line: start over (recreating lost sessions), as a trainer would.
                stepper = None;
                if code != Code::NotFound {
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            }
        }
    }
    report.longest_gap_s = report.longest_gap_s.max(last_ok.elapsed().as_secs_f64());
    report.lost = last_ok.elapsed() > Duration::from_secs(10) || report.longest_gap_s > 15.0;
    report
}

/// Connects, creates whichever of `ids` the server does not hold (returning
/// how many), and opens a stepper at step 0 of a new episode.
async fn start(
    addr: SocketAddr,
    api: Api,
    ids: &[String],
    dim: usize,
    shared: &Shared,
) -> Result<(Stepper, u64)> {
    let mut client = connect(&Address::Tcp(addr)).await?;
    let Client::Grpc(grpc) = &mut client else {
        return Err(Error::Protocol("expected a gRPC client".into()));
    };
    let mut recovered = 0;
    for id in ids {
        let state = grpc
            .get_session(pb::GetSessionRequest {
                session_id: id.clone(),
            })
            .await;
        shared.recovery_calls.fetch_add(1, Ordering::Relaxed);
        match state {
            Ok(_) => {}
            Err(status) if status.code() == Code::NotFound => {
                grpc.create_session(pb::CreateSessionRequest {
                    session_id: id.clone(),
                    config: Some(session_config(dim)),
                    progress: None,
                })
                .await?;
                shared.recovery_calls.fetch_add(1, Ordering::Relaxed);
                recovered += 1;
            }
            Err(status) => return Err(status.into()),
        }
    }
    // A session that was probed but not reported (the failure came between
    // the two) starts its new episode with the first probe.
    let stepper = Stepper::new(client, api, ids.to_vec(), dim)
        .await?
        .starting_episode();
    Ok((stepper, recovered))
}

fn code_of(err: &Error) -> Code {
    match err {
        Error::Rpc(status) => status.code(),
        Error::Stream { code, .. } => Code::from(*code),
        _ => Code::Unavailable,
    }
}

/// One flood cycle, held for `hold`; see the module documentation.
async fn flood(addr: SocketAddr, plan: &Plan, hold: Duration, shared: &Shared) -> FloodCycle {
    let start_s = shared.elapsed().as_secs_f64();
    let silent = open_silent(addr, plan.silent_connections).await;
    let idle = open_idle_h2(addr, plan.idle_h2_connections).await;
    let mut stalled = Vec::new();
    for _ in 0..plan.stalled_streams {
        if let Ok(call) = start_stalled(addr).await {
            stalled.push(call);
        }
    }
    let (big, refused) = create_big_sessions(addr).await;
    tokio::time::sleep(hold).await;
    let mut stalled_ended = BTreeMap::new();
    for (response, _body) in stalled {
        let code = tokio::time::timeout(Duration::from_secs(10), stalled_code(response))
            .await
            .unwrap_or(Code::Unknown);
        *stalled_ended.entry(format!("{code:?}")).or_default() += 1;
    }
    let cycle = FloodCycle {
        start_s,
        silent_opened: silent.len(),
        idle_h2_opened: idle.len(),
        stalled_ended,
        big_sessions_created: big.len(),
        big_sessions_refused_with: refused,
        peak_rss_mib: 0.0,
    };
    drop((silent, idle));
    close_all(addr, &big).await;
    cycle
}

async fn open_silent(addr: SocketAddr, n: usize) -> Vec<TcpStream> {
    let mut held = Vec::with_capacity(n);
    let mut refused = 0;
    // A few failures in a row: the backlog is full, the flood is as big as it gets.
    while held.len() < n && refused < 5 {
        match tokio::time::timeout(Duration::from_secs(1), TcpStream::connect(addr)).await {
            Ok(Ok(stream)) => {
                held.push(stream);
                refused = 0;
            }
            _ => refused += 1,
        }
    }
    held
}

async fn open_idle_h2(addr: SocketAddr, n: usize) -> Vec<h2::client::SendRequest<Bytes>> {
    let mut held = Vec::with_capacity(n);
    for _ in 0..n {
        let Ok(Ok(tcp)) =
            tokio::time::timeout(Duration::from_secs(1), TcpStream::connect(addr)).await
        else {
            break;
        };
        if let Ok((client, connection)) = h2::client::handshake(tcp).await {
            tokio::spawn(connection);
            held.push(client);
        }
    }
    held
}

type StalledCall = (h2::client::ResponseFuture, h2::SendStream<Bytes>);

/// A StepStream announcing a 20 MB message, of which it sends 5 MB.
async fn start_stalled(addr: SocketAddr) -> Result<StalledCall> {
    let protocol = |err: h2::Error| Error::Protocol(format!("h2: {err}"));
    let tcp = TcpStream::connect(addr).await?;
    let (client, connection) = h2::client::handshake(tcp).await.map_err(protocol)?;
    tokio::spawn(connection);
    let request = http::Request::post(format!("http://{addr}/esa.v1.EsaService/StepStream"))
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .body(())
        .map_err(|err| Error::Protocol(err.to_string()))?;
    let mut client = client.ready().await.map_err(protocol)?;
    let (response, mut body) = client.send_request(request, false).map_err(protocol)?;
    let mut message = vec![0u8; 5 + 5_000_000];
    if let Some(length) = message.get_mut(1..5) {
        length.copy_from_slice(&20_000_000u32.to_be_bytes());
    }
    body.send_data(message.into(), false).map_err(protocol)?;
    Ok((response, body))
}

/// The gRPC code a stalled call ended with.
async fn stalled_code(response: h2::client::ResponseFuture) -> Code {
    let code = |headers: &http::HeaderMap| {
        headers
            .get("grpc-status")
            .map(|value| Code::from_bytes(value.as_bytes()))
    };
    let Ok(response) = response.await else {
        return Code::Unavailable;
    };
    if let Some(code) = code(response.headers()) {
        return code;
    }
    let mut body = response.into_body();
    while let Some(Ok(data)) = body.data().await {
        let _ = body.flow_control().release_capacity(data.len());
    }
    match body.trailers().await {
        Ok(Some(trailers)) => code(&trailers).unwrap_or(Code::Unknown),
        _ => Code::Unavailable,
    }
}

/// Creates D = 4096 sessions until the server refuses one (at most 10,000).
async fn create_big_sessions(addr: SocketAddr) -> (Vec<String>, String) {
    let Ok(Client::Grpc(mut grpc)) = connect(&Address::Tcp(addr)).await else {
        return (Vec::new(), "no connection".into());
    };
    let mut ids = Vec::new();
    for i in 0..10_000 {
        let id = format!("big-{i}");
        let answer = grpc
            .create_session(pb::CreateSessionRequest {
                session_id: id.clone(),
                // One frequency for all 4096 dimensions keeps w * dt below pi.
                config: Some(pb::SessionConfig {
                    action_dim: 4096,
                    ..session_config(1)
                }),
                progress: None,
            })
            .await;
        match answer {
            Ok(_) => ids.push(id),
            Err(status) => return (ids, format!("{:?}", status.code())),
        }
    }
    (ids, "none".into())
}

async fn close_all(addr: SocketAddr, ids: &[String]) {
    if let Ok(Client::Grpc(mut grpc)) = connect(&Address::Tcp(addr)).await {
        for id in ids {
            let _ = grpc
                .close_session(pb::CloseSessionRequest {
                    session_id: id.clone(),
                })
                .await;
        }
    }
}

/// Samples the server every `every` until `duration` has passed.
async fn sample(
    shared: Arc<Shared>,
    metrics: SocketAddr,
    every: Duration,
    duration: Duration,
) -> Vec<Sample> {
    let mut samples = Vec::new();
    let mut ticks = tokio::time::interval(every);
    while shared.elapsed() < duration {
        ticks.tick().await;
        let pid = shared.server_pid.load(Ordering::Relaxed);
        let counters = read_metrics(metrics).await.unwrap_or_default();
        let gauge = |name: &str| counters.get(name).copied().unwrap_or(0);
        samples.push(Sample {
            t_s: shared.elapsed().as_secs_f64(),
            phase: match shared.phase() {
                Phase::Quiet => "quiet",
                Phase::Flood => "flood",
                Phase::Restart => "restart",
            },
            rss_mib: rss_kib(pid).unwrap_or(0) as f64 / 1024.0,
            open_files: std::fs::read_dir(format!("/proc/{pid}/fd")).map_or(0, |d| d.count()),
            connections_open: gauge("esa_connections_open"),
            sessions_live: gauge("esa_sessions_live"),
            session_memory_mib: gauge("esa_session_memory_bytes") as f64 / (1 << 20) as f64,
            pairs_so_far: shared.pairs.load(Ordering::Relaxed),
        });
    }
    samples
}

/// The unlabelled metrics of the server's Prometheus page.
async fn read_metrics(addr: SocketAddr) -> Result<BTreeMap<String, u64>> {
    let mut stream = tokio::time::timeout(Duration::from_secs(2), TcpStream::connect(addr))
        .await
        .map_err(|_| Error::Protocol("metrics endpoint not answering".into()))??;
    stream
        .write_all(b"GET /metrics HTTP/1.1\r\nHost: soak\r\nConnection: close\r\n\r\n")
        .await?;
    let mut page = String::new();
    tokio::time::timeout(Duration::from_secs(2), stream.read_to_string(&mut page))
        .await
        .map_err(|_| Error::Protocol("metrics endpoint not answering".into()))??;
    Ok(page
        .lines()
        .filter(|line| !line.starts_with('#') && !line.contains('{'))
        .filter_map(|line| {
            let (name, value) = line.split_once(' ')?;
            Some((name.to_string(), value.trim().parse().ok()?))
        })
        .collect())
}
