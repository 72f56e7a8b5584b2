//! `esa-bench`: load generator for the real `esa-server` binary.
//!
//! Starts the server as a child process on loopback TCP, on a Unix socket
//! and with Zenoh on loopback, and measures, for D-dimensional sessions:
//! - pair latency (probe + report; p50/p90/p99) of one client, per socket
//!   and API (Probe/Report, ProbeBatch/ReportBatch, StepStream), for each
//!   batch size (over Zenoh each call, and each StepStream message, is one
//!   query on `esa/v1/<RpcName>`);
//! - session-steps per second of several concurrent clients per batch size;
//! - resident memory per session with many live sessions (a fresh server).
//!
//! Beside each gRPC latency row it times a bare tonic echo of the same
//! requests' sizes on the same kind of socket, sent the same way (calls, or
//! messages on one stream), the floor the row is compared with (`echo`).
//! Every loop is bounded in pairs and time; everything stays on loopback.
//! Results go to `--json`.

use std::path::PathBuf;
use std::time::Duration;

use clap::Parser;
use serde::Serialize;

use esa_bench::driver::{connect, create_sessions, Api, Stepper};
use esa_bench::echo::{EchoPair, EchoServer};
use esa_bench::error::Result;
use esa_bench::measure::{self, Bounds, Latency, Throughput, Workload};
use esa_bench::memory::{self, Rss};
use esa_bench::server_process::{Address, ServerProcess, Socket};

/// Measures esa-server latency, throughput and memory; writes JSON.
#[derive(Debug, Parser)]
#[command(name = "esa-bench", version)]
struct Cli {
    /// The esa-server binary to start.
    #[arg(long, default_value = "target/release/esa-server")]
    server: PathBuf,
    /// Where to write the results.
    #[arg(long, default_value = "bench/results/server.json")]
    json: PathBuf,
    /// Action dimension D of every session.
    #[arg(long, default_value_t = 6)]
    dim: usize,
    /// Transports to measure, each on its own server.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "tcp,uds,zenoh"
    )]
    sockets: Vec<Socket>,
    /// Batch sizes (sessions per pair).
    #[arg(long, value_delimiter = ',', default_value = "1,8,64,256,1024")]
    batches: Vec<usize>,
    /// Concurrent clients (connections, one pair in flight each) in the
    /// throughput runs.
    #[arg(long, default_value_t = 4)]
    concurrency: usize,
    /// Tokio worker threads of this load generator (the server has its own).
    #[arg(long, default_value_t = 1)]
    client_threads: usize,
    /// Unmeasured warm-up per measurement, seconds.
    #[arg(long, default_value_t = 0.3)]
    warmup: f64,
    /// Longest measured window per measurement, seconds.
    #[arg(long, default_value_t = 2.0)]
    window: f64,
    /// Most measured pairs per client and measurement.
    #[arg(long, default_value_t = 100_000)]
    max_pairs: u64,
    /// Sessions created for the memory measurement (0 skips it).
    #[arg(long, default_value_t = 100_000)]
    rss_sessions: usize,
}

/// A latency measurement and what it measured.
#[derive(Debug, Serialize)]
struct LatencyRow {
    socket: Socket,
    api: Api,
    batch: usize,
    #[serde(flatten)]
    latency: Latency,
    /// The bare tonic echo of the same requests' sizes on the same kind of
    /// socket (none over Zenoh).
    echo: Option<Latency>,
}

/// A throughput measurement and what it measured.
#[derive(Debug, Serialize)]
struct ThroughputRow {
    socket: Socket,
    api: Api,
    batch: usize,
    #[serde(flatten)]
    throughput: Throughput,
}

/// Everything one run measured; the report generator reads this.
#[derive(Debug, Serialize)]
struct Results {
    server: PathBuf,
    dim: usize,
    client_threads: usize,
    bounds: Bounds,
    latency: Vec<LatencyRow>,
    throughput: Vec<ThroughputRow>,
    rss: Option<Rss>,
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(cli.client_threads.max(1))
        .enable_all()
        .build();
    let outcome = match runtime {
        Ok(runtime) => runtime.block_on(run(&cli)),
        Err(err) => Err(err.into()),
    };
    match outcome {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("esa-bench: {err}");
            std::process::ExitCode::FAILURE
        }
    }
}

async fn run(cli: &Cli) -> Result<()> {
    let bounds = Bounds {
        warmup: Duration::from_secs_f64(cli.warmup),
        window: Duration::from_secs_f64(cli.window),
        max_pairs: cli.max_pairs,
    };
    let mut results = Results {
        server: cli.server.clone(),
        dim: cli.dim,
        client_threads: cli.client_threads,
        bounds,
        latency: Vec::new(),
        throughput: Vec::new(),
        rss: None,
    };
    // Room for every session the latency and throughput runs hold at once.
    let max_sessions = cli.concurrency.max(1) * cli.batches.iter().max().copied().unwrap_or(1) + 16;
    for &socket in &cli.sockets {
        let server = ServerProcess::start(&cli.server, socket, max_sessions)?;
        let address = server.address();
        let echo = match socket {
            Socket::Zenoh => None,
            Socket::Tcp | Socket::Uds => Some(EchoServer::start(socket)?),
        };
        for (api, batch) in workloads(&cli.batches) {
            let workload = Workload {
                api,
                batch,
                dim: cli.dim,
            };
            let name = format!("{socket:?}-{api:?}-{batch}").to_lowercase();
            let (latency, sizes) = measure_latency(address, workload, bounds, &name).await?;
            let echo = match &echo {
                Some(server) => {
                    let mut pair = EchoPair::connect(server, sizes, api).await?;
                    Some(measure::latency(&mut pair, bounds).await?)
                }
                None => None,
            };
            eprintln!(
                "latency    {name:<18} p50 {:>9.1} us  p99 {:>9.1} us  ({} pairs; echo p50 {})",
                latency.p50_us,
                latency.p99_us,
                latency.pairs,
                echo.as_ref()
                    .map_or("n/a".into(), |echo| format!("{:.1} us", echo.p50_us))
            );
            results.latency.push(LatencyRow {
                socket,
                api,
                batch,
                latency,
                echo,
            });
            if api == Api::Unary {
                continue;
            }
            let throughput =
                measure::throughput(address, workload, cli.concurrency, bounds, &name).await?;
            eprintln!(
                "throughput {name:<18} {:>12.0} session-steps/s  ({} clients)",
                throughput.session_steps_per_s, throughput.concurrency
            );
            results.throughput.push(ThroughputRow {
                socket,
                api,
                batch,
                throughput,
            });
        }
    }
    if cli.rss_sessions > 0 {
        let rss = memory::rss_per_session(&cli.server, cli.rss_sessions, cli.dim, cli.concurrency)
            .await?;
        eprintln!(
            "rss        {} sessions: {:.0} B/session idle, {:.0} B/session stepped",
            rss.sessions, rss.idle_bytes_per_session, rss.stepped_bytes_per_session
        );
        results.rss = Some(rss);
    }
    if let Some(dir) = cli.json.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(&cli.json, serde_json::to_string_pretty(&results)?)?;
    eprintln!("wrote {}", cli.json.display());
    Ok(())
}

/// Single-session Probe/Report, then ProbeBatch/ReportBatch and StepStream
/// pairs for every batch size.
fn workloads(batches: &[usize]) -> Vec<(Api, usize)> {
    let mut out = vec![(Api::Unary, 1)];
    for api in [Api::Batch, Api::Stream] {
        out.extend(batches.iter().map(|&batch| (api, batch)));
    }
    out
}

/// One client's pair latency on fresh sessions named after `name`, and the
/// sizes of its probe and report requests.
async fn measure_latency(
    address: &Address,
    workload: Workload,
    bounds: Bounds,
    name: &str,
) -> Result<(Latency, (usize, usize))> {
    let mut client = connect(address).await?;
    let ids = create_sessions(&mut client, name, workload.batch, workload.dim).await?;
    let mut stepper = Stepper::new(client, workload.api, ids, workload.dim).await?;
    let latency = measure::latency(&mut stepper, bounds).await?;
    let sizes = stepper.request_sizes();
    stepper.close().await?;
    Ok((latency, sizes))
}
