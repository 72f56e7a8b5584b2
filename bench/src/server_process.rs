//! The real `esa-server` binary as a child process: start it on loopback TCP,
//! a Unix socket or Zenoh, learn its address from the `listening on` (and
//! `zenoh listening on`) lines, read its resident memory, kill it on drop.

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use tempfile::TempDir;

use crate::error::{Error, Result};

/// How long a starting server may take to print its `listening on` line.
const STARTUP_TIMEOUT: Duration = Duration::from_secs(30);

/// Where a server listens.
#[derive(Clone, Debug)]
pub enum Address {
    /// gRPC over loopback TCP.
    Tcp(SocketAddr),
    /// gRPC over a Unix domain socket.
    Unix(PathBuf),
    /// Zenoh queries under the default prefix, to these locators.
    Zenoh(Vec<String>),
}

/// Which kind of socket to start a server on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Socket {
    /// `--listen 127.0.0.1:0`.
    Tcp,
    /// `--uds <tempdir>/esa.sock`.
    Uds,
    /// `--zenoh` on its default loopback listener (`tcp/127.0.0.1:0`),
    /// gRPC on `--listen 127.0.0.1:0` beside it (unused).
    Zenoh,
}

/// A running esa-server child; killed when dropped.
pub struct ServerProcess {
    child: Child,
    address: Address,
    metrics: Option<String>,
    // Holds the Unix socket's directory until the server is gone.
    _dir: Option<TempDir>,
}

impl ServerProcess {
    /// Starts `binary` on `socket` with sessions that never expire (a bench
    /// may pause between phases) and room for `max_sessions`.
    pub fn start(binary: &Path, socket: Socket, max_sessions: usize) -> Result<Self> {
        let mut command = Command::new(binary);
        command
            .args(["--session-ttl", "0", "--max-sessions"])
            .arg(max_sessions.to_string());
        let dir = match socket {
            Socket::Tcp => {
                command.args(["--listen", "127.0.0.1:0"]);
                None
            }
            Socket::Zenoh => {
                command.args(["--listen", "127.0.0.1:0", "--zenoh"]);
                None
            }
            Socket::Uds => {
                let dir = tempfile::tempdir()?;
                command.arg("--uds").arg(dir.path().join("esa.sock"));
                Some(dir)
            }
        };
        Self::spawn(command, binary, socket, dir)
    }

    /// Starts `binary` with `args` (which choose a TCP `--listen` address)
    /// under an open-files limit of `open_files`, as on a machine with that
    /// limit: the server cannot raise it, and its defaults derive from it.
    pub fn start_tcp_limited(binary: &Path, args: &[String], open_files: u64) -> Result<Self> {
        let mut command = Command::new("bash");
        command
            .arg("-c")
            .arg(format!("ulimit -n {open_files} && exec \"$0\" \"$@\""))
            .arg(binary)
            .args(args);
        Self::spawn(command, binary, Socket::Tcp, None)
    }

    fn spawn(
        mut command: Command,
        binary: &Path,
        socket: Socket,
        dir: Option<TempDir>,
    ) -> Result<Self> {
        command
            // Per-request logging would be measured too; keep only problems.
            .env("RUST_LOG", "warn")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit());
        let mut child = command
            .spawn()
            .map_err(|err| Error::Server(format!("cannot run {}: {err}", binary.display())))?;
        let announced = match child.stdout.take().map(|out| wait_for_address(out, socket)) {
            Some(Ok(announced)) => announced,
            Some(Err(err)) => {
                let _ = child.kill();
                let _ = child.wait();
                return Err(err);
            }
            None => return Err(Error::Server("no stdout pipe".into())),
        };
        Ok(Self {
            child,
            address: announced.address,
            metrics: announced.metrics,
            _dir: dir,
        })
    }

    /// The address the server announced.
    pub fn address(&self) -> &Address {
        &self.address
    }

    /// The metrics URL the server announced (with `--metrics-listen`).
    pub fn metrics(&self) -> Option<&str> {
        self.metrics.as_deref()
    }

    /// The server's process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The server's resident set size in KiB (`VmRSS` of /proc/PID/status).
    pub fn rss_kib(&self) -> Result<u64> {
        rss_kib(self.pid())
    }
}

/// The resident set size of process `pid` in KiB (`VmRSS` of /proc/PID/status).
pub fn rss_kib(pid: u32) -> Result<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))?;
    status
        .lines()
        .find_map(|line| line.strip_prefix("VmRSS:"))
        .and_then(|rest| rest.trim().trim_end_matches("kB").trim().parse().ok())
        .ok_or_else(|| Error::Server("no VmRSS line in /proc/PID/status".into()))
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// What a starting server printed.
struct Announced {
    address: Address,
    metrics: Option<String>,
}

/// Reads the child's stdout until `listening on ADDR` (which comes after any
/// `metrics on URL` and `zenoh listening on LOCATOR` lines), then keeps
/// draining it in the background so the child never blocks on a full pipe.
/// For [`Socket::Zenoh`] the address is the announced locators.
fn wait_for_address(stdout: std::process::ChildStdout, socket: Socket) -> Result<Announced> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut locators = Vec::new();
        let mut metrics = None;
        let mut sent = false;
        for line in BufReader::new(stdout).lines().map_while(|line| line.ok()) {
            if sent {
                continue;
            }
            if let Some(locator) = line.strip_prefix("zenoh listening on ") {
                locators.push(locator.to_owned());
            } else if let Some(url) = line.strip_prefix("metrics on ") {
                metrics = Some(url.to_owned());
            } else if let Some(address) = line.strip_prefix("listening on ") {
                let announced = (
                    address.to_owned(),
                    std::mem::take(&mut locators),
                    metrics.take(),
                );
                sent = tx.send(announced).is_ok();
            }
        }
    });
    let (line, locators, metrics) = rx
        .recv_timeout(STARTUP_TIMEOUT)
        .map_err(|_| Error::Server("no `listening on` line (did it exit?)".into()))?;
    let address = if socket == Socket::Zenoh {
        if locators.is_empty() {
            return Err(Error::Server("no `zenoh listening on` line".into()));
        }
        Address::Zenoh(locators)
    } else {
        match line.strip_prefix("unix:") {
            Some(path) => Address::Unix(PathBuf::from(path)),
            None => line
                .parse()
                .map(Address::Tcp)
                .map_err(|_| Error::Server(format!("cannot parse address {line:?}")))?,
        }
    };
    Ok(Announced { address, metrics })
}
