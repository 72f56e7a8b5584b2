//! Command-line flags of the `esa-server` binary.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::{Parser, ValueEnum};

use esa_server::ServerBuilder;

/// Extremum-Seeking Action selection (ESA) as a gRPC service: keeps the
/// per-episode extremum-seeking state of many RL environments (sessions) and
/// turns the actions a policy samples into improved actions.
///
/// On start it prints `listening on ADDR` (and `metrics on URL` when
/// enabled) to stdout; logs go to stderr, filtered by RUST_LOG (default
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
    fn seconds_must_be_finite_and_non_negative() {
        assert_eq!(parse_seconds("0.25"), Ok(0.25));
        assert!(parse_seconds("-1").is_err());
        assert!(parse_seconds("inf").is_err());
        assert!(parse_seconds("NaN").is_err());
        assert!(parse_seconds("soon").is_err());
    }
}
