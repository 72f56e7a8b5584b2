//! Command-line flags of the `esa-server` binary.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::{Parser, ValueEnum};

use esa_server::zenoh_transport::{loopback_config, Shard, DEFAULT_PREFIX};
use esa_server::{Error, ServerBuilder};

/// Extremum-Seeking Action selection (ESA) as a gRPC service: keeps the
/// per-episode extremum-seeking state of many RL environments (sessions) and
/// turns the actions a policy samples into improved actions.
///
/// On start it prints `listening on ADDR` (after `metrics on URL` and
/// `zenoh listening on LOCATOR` lines when enabled) to stdout; logs go to stderr, filtered by RUST_LOG (default
/// info). SIGINT or SIGTERM shut it down cleanly.
#[derive(Debug, Parser)]
#[command(name = "esa-server", version)]
pub struct Cli {
    /// TCP address for gRPC. Keep it on loopback unless the network is
    /// trusted; port 0 picks a free port (see the `listening on` line).
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:50051")]
    pub listen: SocketAddr,

    /// Serve gRPC on this Unix domain socket instead of TCP. A stale socket
    /// file is replaced; the file is removed on exit.
    #[arg(long, value_name = "PATH", conflicts_with = "listen")]
    pub uds: Option<PathBuf>,

    /// Seconds without a request after which a session expires and its id
    /// becomes NOT_FOUND; fractions allowed, 0 = never.
    #[arg(long, value_name = "SECONDS", default_value_t = 600.0, value_parser = parse_seconds)]
    pub session_ttl: f64,

    /// Most live sessions; creating one more fails with RESOURCE_EXHAUSTED.
    #[arg(long, value_name = "N", default_value_t = 100_000)]
    pub max_sessions: usize,

    /// Serve Prometheus metrics at http://ADDR/metrics (off unless given).
    #[arg(long, value_name = "ADDR")]
    pub metrics_listen: Option<SocketAddr>,

    /// Largest gRPC request accepted, in bytes; big batches need more than
    /// gRPC's usual 4 MiB.
    #[arg(long, value_name = "BYTES", default_value_t = 64 << 20)]
    pub max_message_bytes: usize,

    /// Seconds that shutdown waits for calls in flight to finish (open
    /// StepStreams are ended at once with UNAVAILABLE).
    #[arg(long, value_name = "SECONDS", default_value_t = 5.0, value_parser = parse_seconds)]
    pub shutdown_grace: f64,

    /// Log line format on stderr.
    #[arg(long, value_enum, default_value_t = LogFormat::Text)]
    pub log_format: LogFormat,

    /// Also serve the API over Zenoh, beside gRPC and on the same sessions:
    /// one queryable per RPC at PREFIX/<RpcName>. Prints `zenoh listening
    /// on LOCATOR` for each listen endpoint before `listening on`.
    #[arg(long)]
    pub zenoh: bool,

    /// Zenoh key prefix of the queryables.
    #[arg(long, value_name = "PREFIX", default_value = DEFAULT_PREFIX, requires = "zenoh")]
    pub zenoh_prefix: String,

    /// A Zenoh json5 config file (any mode and endpoints) instead of the
    /// default: a peer listening on tcp/127.0.0.1:0, with multicast scouting
    /// and gossip off.
    #[arg(long, value_name = "FILE", requires = "zenoh")]
    pub zenoh_config: Option<PathBuf>,

    /// Zenoh endpoint to listen on instead of tcp/127.0.0.1:0 (repeatable).
    #[arg(
        long,
        value_name = "ENDPOINT",
        requires = "zenoh",
        conflicts_with = "zenoh_config"
    )]
    pub zenoh_listen: Vec<String>,

    /// Zenoh endpoint to connect to, e.g. a zenohd router (repeatable).
    #[arg(
        long,
        value_name = "ENDPOINT",
        requires = "zenoh",
        conflicts_with = "zenoh_config"
    )]
    pub zenoh_connect: Vec<String>,

    /// Serve shard i of N (0 <= i < N): the queryables move to
    /// PREFIX/shard/<i>/<RpcName>; clients pick a session's shard by a
    /// stable hash of its id (deploy/README.md).
    #[arg(long, value_name = "i/N", requires = "zenoh", value_parser = parse_shard)]
    pub shard: Option<Shard>,
}

/// How log lines are written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines.
    Text,
    /// One JSON object per line.
    Json,
}

impl Cli {
    /// The server options these flags ask for.
    pub fn server_builder(&self) -> ServerBuilder {
        let ttl = (self.session_ttl > 0.0).then(|| Duration::from_secs_f64(self.session_ttl));
        ServerBuilder::default()
            .session_ttl(ttl)
            .max_sessions(self.max_sessions)
            .max_message_bytes(self.max_message_bytes)
            .shutdown_grace(Duration::from_secs_f64(self.shutdown_grace))
    }

    /// The Zenoh config and key prefix these flags ask for; None without `--zenoh`.
    pub fn zenoh(&self) -> Result<Option<(zenoh::Config, String)>, Error> {
        if !self.zenoh {
            return Ok(None);
        }
        let config = match &self.zenoh_config {
            Some(path) => zenoh::Config::from_file(path).map_err(|err| {
                Error::Zenoh(format!("cannot load config {}: {err}", path.display()))
            })?,
            None => loopback_config(&self.zenoh_listen, &self.zenoh_connect)?,
        };
        let prefix = match self.shard {
            Some(shard) => shard.prefix(&self.zenoh_prefix),
            None => self.zenoh_prefix.clone(),
        };
        Ok(Some((config, prefix)))
    }
}

fn parse_shard(text: &str) -> Result<Shard, String> {
    text.parse().map_err(|err: Error| err.to_string())
}

/// A finite, non-negative number of seconds that fits a `Duration`.
fn parse_seconds(text: &str) -> Result<f64, String> {
    let seconds: f64 = text
        .parse()
        .map_err(|_| format!("expected a number of seconds, got {text:?}"))?;
    Duration::try_from_secs_f64(seconds)
        .map(|_| seconds)
        .map_err(|_| format!("expected a finite number of seconds >= 0, got {text}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn flags_are_consistent() {
        Cli::command().debug_assert();
    }

    #[test]
    fn listen_and_uds_conflict_but_defaults_do_not() {
        assert!(Cli::try_parse_from(["esa-server", "--uds", "/tmp/x.sock"]).is_ok());
        assert!(
            Cli::try_parse_from(["esa-server", "--uds", "/tmp/x", "--listen", "127.0.0.1:1"])
                .is_err()
        );
    }

    #[test]
    fn zenoh_flags_need_zenoh_and_shift_the_prefix_per_shard() {
        let parse = |args: &[&str]| Cli::try_parse_from([&["esa-server"], args].concat());
        assert!(parse(&["--shard", "0/2"]).is_err());
        assert!(parse(&["--zenoh-prefix", "x"]).is_err());
        assert!(parse(&["--zenoh", "--shard", "2/2"]).is_err());
        assert!(parse(&[
            "--zenoh",
            "--zenoh-config",
            "z.json5",
            "--zenoh-connect",
            "tcp/127.0.0.1:1"
        ])
        .is_err());
        assert!(parse(&[]).unwrap().zenoh().unwrap().is_none());
        let cli = parse(&["--zenoh", "--shard", "1/2", "--zenoh-prefix", "lab/esa"]).unwrap();
        let (_, prefix) = cli.zenoh().unwrap().unwrap();
        assert_eq!(prefix, "lab/esa/shard/1");
        let (_, prefix) = parse(&["--zenoh"]).unwrap().zenoh().unwrap().unwrap();
        assert_eq!(prefix, "esa/v1");
    }

    #[test]
    fn seconds_must_be_finite_and_non_negative() {
        assert_eq!(parse_seconds("0.25"), Ok(0.25));
        assert!(parse_seconds("-1").is_err());
        assert!(parse_seconds("inf").is_err());
        assert!(parse_seconds("NaN").is_err());
        assert!(parse_seconds("soon").is_err());
    }
}
