//! `esa-soak`: minutes of load on the real `esa-server` with floods and
//! faults (see the `soak` module). Writes `--json`, which
//! `tests/soak/report.py` turns into `tests/soak/RESULTS.md`.

mod soak;

use std::path::PathBuf;
use std::time::Duration;

use clap::Parser;
use esa_bench::error::Result;
use soak::Plan;

/// Soaks esa-server with load, floods and faults; writes JSON.
#[derive(Debug, Parser)]
#[command(name = "esa-soak", version)]
struct Cli {
    /// The esa-server binary to start.
    #[arg(long, default_value = "target/release/esa-server")]
    server: PathBuf,
    /// Where to write the results.
    #[arg(long, default_value = "tests/soak/results/soak.json")]
    json: PathBuf,
    /// Length of the run, seconds.
    #[arg(long, default_value_t = 180.0)]
    seconds: f64,
    /// Clients stepping sessions throughout (even: ProbeBatch/ReportBatch, odd: StepStream).
    #[arg(long, default_value_t = 4)]
    load_clients: usize,
    /// Sessions per load client.
    #[arg(long, default_value_t = 64)]
    batch: usize,
    /// Action dimension of the load's sessions.
    #[arg(long, default_value_t = 6)]
    dim: usize,
    /// The server's open-files limit (a common default; it cannot raise it).
    #[arg(long, default_value_t = 1024)]
    open_files: u64,
    /// The server's --session-ttl, seconds: one client pauses longer.
    #[arg(long, default_value_t = 15.0)]
    session_ttl: f64,
    /// Silent TCP connections per flood cycle (more than the server's descriptors).
    #[arg(long, default_value_t = 3000)]
    silent_connections: usize,
    /// Idle HTTP/2 connections per flood cycle.
    #[arg(long, default_value_t = 300)]
    idle_h2_connections: usize,
    /// Never-finished 20 MB StepStream messages per flood cycle.
    #[arg(long, default_value_t = 16)]
    stalled_streams: usize,
    /// Seconds between samples of the server's memory and connections.
    #[arg(long, default_value_t = 2.0)]
    sample_every: f64,
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    // The floods hold thousands of sockets on this side too.
    if let Err(err) = rlimit::increase_nofile_limit(u64::MAX) {
        eprintln!("esa-soak: cannot raise the open-files limit: {err}");
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build();
    let outcome = match runtime {
        Ok(runtime) => runtime.block_on(run(cli)),
        Err(err) => Err(err.into()),
    };
    match outcome {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("esa-soak: {err}");
            std::process::ExitCode::FAILURE
        }
    }
}

async fn run(cli: Cli) -> Result<()> {
    let plan = Plan {
        server: cli.server,
        duration: Duration::from_secs_f64(cli.seconds),
        load_clients: cli.load_clients,
        batch: cli.batch,
        dim: cli.dim,
        open_files: cli.open_files,
        session_ttl: Duration::from_secs_f64(cli.session_ttl),
        silent_connections: cli.silent_connections,
        idle_h2_connections: cli.idle_h2_connections,
        stalled_streams: cli.stalled_streams,
        sample_every: Duration::from_secs_f64(cli.sample_every),
    };
    let report = soak::run(plan).await?;
    eprintln!(
        "soak: {} calls served in {:.0} s; pair p99 {:.0} us quiet, {:.0} us all; \
         {} sessions recovered; {} lost clients",
        report.calls_served,
        report.seconds,
        report.latency.get("quiet").map_or(f64::NAN, |l| l.p99_us),
        report.latency.get("all").map_or(f64::NAN, |l| l.p99_us),
        report.sessions_recovered,
        report.lost_clients,
    );
    if let Some(dir) = cli.json.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(&cli.json, serde_json::to_string_pretty(&report)?)?;
    eprintln!("wrote {}", cli.json.display());
    Ok(())
}
