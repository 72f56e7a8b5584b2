//! The `esa-server` binary: parses flags, sets up logging, serves until
//! SIGINT/SIGTERM.

mod cli;

use std::io::{IsTerminal as _, Write as _};
use std::process::ExitCode;

use clap::Parser;
use esa_server::metrics::serve_metrics;
use esa_server::server::io_context;
use esa_server::zenoh_transport::ZenohService;
use esa_server::{Error, Listener};
use tracing_subscriber::EnvFilter;

use crate::cli::{Cli, LogFormat};

#[tokio::main]
async fn main() -> ExitCode {
    let cli = Cli::parse();
    init_tracing(cli.log_format);
    match run(cli).await {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            tracing::error!(%err, "esa-server failed");
            ExitCode::FAILURE
        }
    }
}

async fn run(cli: Cli) -> Result<(), Error> {
    let server = cli.server_builder().build();
    let listener = match &cli.uds {
        Some(path) => Listener::unix(path)?,
        None => Listener::tcp(cli.listen).await?,
    };
    if let Some(addr) = cli.metrics_listen {
        let metrics_listener = tokio::net::TcpListener::bind(addr)
            .await
            .map_err(|err| io_context(err, format!("cannot serve metrics on {addr}")))?;
        let url = format!("http://{}/metrics", metrics_listener.local_addr()?);
        announce(&format!("metrics on {url}"));
        let handler = server.handler();
        tokio::spawn(async move {
            if let Err(err) = serve_metrics(metrics_listener, handler).await {
                tracing::error!(%err, "metrics endpoint failed");
            }
        });
    }
    let zenoh = match cli.zenoh()? {
        Some((config, prefix)) => {
            let service = ZenohService::start(server.handler(), config, &prefix).await?;
            for locator in service.locators().await {
                announce(&format!("zenoh listening on {locator}"));
            }
            Some(service)
        }
        None => None,
    };
    let shutdown = shutdown_signal()?;
    // The line launchers (tests, the Python client) wait for; it comes after
    // binding, so connecting as soon as it is read succeeds.
    announce(&format!("listening on {}", listener.address()?));
    server.serve(listener, shutdown).await?;
    if let Some(service) = zenoh {
        service.close().await?;
    }
    tracing::info!("stopped");
    Ok(())
}

/// Prints a machine-readable line to stdout (logs go to stderr) and logs it.
fn announce(line: &str) {
    tracing::info!("{line}");
    let mut stdout = std::io::stdout().lock();
    // A closed stdout must not stop the server.
    let _ = writeln!(stdout, "{line}").and_then(|()| stdout.flush());
}

fn init_tracing(format: LogFormat) {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        // Colour codes only for a person at a terminal, not in log files.
        .with_ansi(std::io::stderr().is_terminal());
    match format {
        LogFormat::Text => builder.init(),
        LogFormat::Json => builder.json().init(),
    }
}

/// Installs SIGINT and SIGTERM handlers now (so a signal that arrives right
/// after the `listening on` line is not lost) and returns a future that
/// completes on the first of them.
fn shutdown_signal() -> Result<impl std::future::Future<Output = ()>, Error> {
    use tokio::signal::unix::{signal, SignalKind};
    let mut interrupt = signal(SignalKind::interrupt())?;
    let mut terminate = signal(SignalKind::terminate())?;
    Ok(async move {
        tokio::select! {
            _ = interrupt.recv() => {}
            _ = terminate.recv() => {}
        }
    })
}
