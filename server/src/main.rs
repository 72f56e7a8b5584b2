//! The `esa-server` binary: parses flags, sets up logging, serves until
//! SIGINT/SIGTERM/SIGHUP or until its launcher dies (`--parent-pid`).

mod cli;

use std::io::{IsTerminal as _, Write as _};
use std::os::unix::fs::PermissionsExt as _;
use std::path::Path;
use std::process::ExitCode;
use std::time::Duration;

use clap::Parser;
use esa_server::error::io_context;
use esa_server::metrics_endpoint::serve_metrics;
use esa_server::resources;
use esa_server::state_file::StateFile;
#[cfg(feature = "zenoh")]
use esa_server::zenoh_transport::ZenohService;
use esa_server::{Listener, StartError};
use tracing_subscriber::EnvFilter;

use crate::cli::{Cli, LogFormat};

#[tokio::main]
async fn main() -> ExitCode {
    let cli = Cli::parse();
    init_tracing(cli.log_format);
    let result = run(&cli).await;
    // Also after a failed start: a launcher that handed over its directory may be gone.
    if let Ok(Some(dir)) = cli.owned_dir() {
        match std::fs::remove_dir_all(dir) {
            Ok(()) => {}
            Err(err) if err.kind() == std::io::ErrorKind::NotFound => {}
            Err(err) => tracing::warn!(dir = %dir.display(), %err, "cannot remove the directory"),
        }
    }
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            tracing::error!(%err, "esa-server failed");
            ExitCode::FAILURE
        }
    }
}

async fn run(cli: &Cli) -> Result<(), StartError> {
    cli.owned_dir()?;
    // Before the defaults that derive from it (the connection limit) are computed.
    match resources::raise_open_files_limit() {
        Ok(files) => tracing::debug!(files, "open-files limit"),
        Err(err) => tracing::warn!(%err, "cannot raise the open-files limit"),
    }
    let token = cli.auth_token_file.as_deref().map(read_token).transpose()?;
    let tls = cli.tls()?;
    for warning in cli.exposure_warnings(token.is_some()) {
        tracing::warn!("{warning}");
    }
    let state_file = cli.state_file.as_deref().map(StateFile::open).transpose()?;
    let loaded = match &state_file {
        Some(file) => file.load()?,
        None => None,
    };
    let server = cli.server_builder(token, tls).build();
    let handler = server.handler();
    if let Some(loaded) = loaded {
        let written_by = loaded.written_by.clone();
        let restored = loaded.restore_into(handler.store())?;
        tracing::info!(
            sessions = restored.sessions,
            expired = restored.expired,
            written_by,
            "restored the sessions of the state file"
        );
    }
    let listener = match &cli.uds {
        Some(path) => Listener::unix_with_mode(path, cli.uds_mode)?,
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
    #[cfg(feature = "zenoh")]
    let zenoh = start_zenoh(cli, &server).await?;
    let shutdown = shutdown_signal(cli.parent_pid)?;
    // Its sessions live in this process now: a crash must not bring back a state that clients
    // have moved past.
    if let Some(file) = &state_file {
        file.remove()?;
    }
    // The line launchers (tests, the Python client) wait for; it comes after
    // binding, so connecting as soon as it is read succeeds.
    announce(&format!("listening on {}", listener.address()?));
    let served = server.serve(listener, shutdown).await;
    #[cfg(feature = "zenoh")]
    let closed = match zenoh {
        Some(service) => service.close().await,
        None => Ok(()),
    };
    // Written whatever stopped the transports: the sessions are intact either way.
    let saved = match &state_file {
        Some(file) => save_state(file, &handler),
        None => Ok(()),
    };
    served?;
    #[cfg(feature = "zenoh")]
    closed?;
    saved?;
    tracing::info!("stopped");
    Ok(())
}

/// Lets the requests in flight finish, refuses later ones, and writes every live session to
/// `file` (nothing is left half-written if that fails).
fn save_state(file: &StateFile, handler: &esa_server::EsaHandler) -> Result<(), StartError> {
    handler.store().freeze();
    let (sessions, bytes) = file.save(handler.store().export())?;
    tracing::info!(
        sessions,
        bytes,
        path = %file.path().display(),
        "wrote the state file"
    );
    Ok(())
}

/// Starts the Zenoh service `--zenoh` asks for, on `server`'s sessions, and announces where it
/// listens; None without `--zenoh`.
#[cfg(feature = "zenoh")]
async fn start_zenoh(
    cli: &Cli,
    server: &esa_server::EsaServer,
) -> Result<Option<ZenohService>, StartError> {
    let Some((config, prefix)) = cli.zenoh.config()? else {
        return Ok(None);
    };
    let service = ZenohService::start(server.handler(), config, &prefix).await?;
    for locator in service.locators().await {
        announce(&format!("zenoh listening on {locator}"));
    }
    Ok(Some(service))
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

/// The token in `path`, without surrounding whitespace (a trailing newline).
fn read_token(path: &Path) -> Result<Vec<u8>, StartError> {
    let context = || format!("cannot read the auth token from {}", path.display());
    let text = std::fs::read(path).map_err(|err| io_context(err, context()))?;
    let token = text.trim_ascii();
    if token.is_empty() {
        return Err(StartError::Config(format!(
            "--auth-token-file: expected a token in {}, got an empty file",
            path.display()
        )));
    }
    let mode = std::fs::metadata(path).map_err(|err| io_context(err, context()))?;
    if mode.permissions().mode() & 0o077 != 0 {
        tracing::warn!(
            path = %path.display(),
            "the auth token file is readable by other users; chmod 600 it"
        );
    }
    Ok(token.to_vec())
}

/// How often the server checks that its launcher (`--parent-pid`) is alive.
const PARENT_CHECK: Duration = Duration::from_millis(200);

/// Installs SIGINT, SIGTERM and SIGHUP handlers now (so a signal that
/// arrives right after the `listening on` line is not lost) and returns a
/// future that completes on the first of them, or once this process is no
/// longer the child of `parent` (it died, whatever killed it: the kernel
/// hands orphans to another process).
fn shutdown_signal(
    parent: Option<u32>,
) -> Result<impl std::future::Future<Output = ()>, StartError> {
    use tokio::signal::unix::{signal, SignalKind};
    let mut interrupt = signal(SignalKind::interrupt())?;
    let mut terminate = signal(SignalKind::terminate())?;
    let mut hangup = signal(SignalKind::hangup())?;
    Ok(async move {
        let orphaned = async {
            let Some(parent) = parent else {
                return std::future::pending().await;
            };
            let mut ticks = tokio::time::interval(PARENT_CHECK);
            while std::os::unix::process::parent_id() == parent {
                ticks.tick().await;
            }
            tracing::info!(parent, "the parent process is gone");
        };
        tokio::select! {
            _ = interrupt.recv() => {}
            _ = terminate.recv() => {}
            _ = hangup.recv() => {}
            () = orphaned => {}
        }
    })
}
