//! Command-line flags of the `esa-server` binary.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::{Parser, ValueEnum};

use esa_server::codec::MAX_REQUEST_BYTES;
use esa_server::{ServerBuilder, StartError, TlsSettings};

#[cfg(feature = "zenoh")]
mod zenoh_flags;
#[cfg(feature = "zenoh")]
use zenoh_flags::ZenohFlags;

/// Extremum-Seeking Action selection (ESA) as a gRPC service: keeps the
/// per-episode extremum-seeking state of many RL environments (sessions) and
/// turns the actions a policy samples into improved actions.
///
/// On start it prints `listening on ADDR` (after `metrics on URL` and
/// `zenoh listening on LOCATOR` lines when enabled) to stdout; logs go to stderr, filtered by RUST_LOG (default
/// info). SIGINT, SIGTERM or SIGHUP shut it down cleanly.
///
/// BYTES arguments take a plain number or a binary suffix: 512MiB, 2G (= 2GiB).
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

    /// Permission bits of the --uds socket file, in octal; connecting needs
    /// write permission, so the default lets only this user in.
    #[arg(long, value_name = "OCTAL", default_value = "600", requires = "uds", value_parser = parse_mode)]
    pub uds_mode: u32,

    /// Require this token (the file's content, surrounding whitespace
    /// removed) on every request: gRPC metadata `authorization: Bearer
    /// <token>`, or the Zenoh query attachment. Health checks are exempt.
    #[arg(long, value_name = "PATH")]
    pub auth_token_file: Option<PathBuf>,

    /// Serve gRPC over TLS with this PEM certificate (chain, server
    /// certificate first); needs --tls-key. Clients then connect with the CA
    /// that issued it. Not with --uds, whose file mode is its access control.
    #[arg(
        long,
        value_name = "PATH",
        requires = "tls_key",
        conflicts_with = "uds"
    )]
    pub tls_cert: Option<PathBuf>,

    /// The PEM private key (PKCS#8, SEC1 or PKCS#1) of --tls-cert.
    #[arg(long, value_name = "PATH", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,

    /// Mutual TLS: require every client to present a certificate issued by a
    /// CA in this PEM file; other clients fail the TLS handshake.
    #[arg(long, value_name = "PATH", requires = "tls_cert")]
    pub tls_client_ca: Option<PathBuf>,

    /// Seconds without a request after which a session expires and its id
    /// becomes NOT_FOUND; fractions allowed, 0 = never.
    #[arg(long, value_name = "SECONDS", default_value_t = 600.0, value_parser = parse_seconds)]
    pub session_ttl: f64,

    /// Most live sessions; creating one more fails with RESOURCE_EXHAUSTED.
    #[arg(long, value_name = "N", default_value_t = esa_store::DEFAULT_MAX_SESSIONS)]
    pub max_sessions: usize,

    /// Bytes the live sessions may cost together (a session of D action
    /// dimensions costs about 80 D + 500 bytes); creating one that does not
    /// fit fails with RESOURCE_EXHAUSTED. Default: half of the least of the
    /// machine's memory, the cgroup's limit and the address-space limit.
    #[arg(long, value_name = "BYTES", value_parser = parse_bytes)]
    pub max_session_memory: Option<usize>,

    /// Serve Prometheus metrics at http://ADDR/metrics (off unless given).
    #[arg(long, value_name = "ADDR")]
    pub metrics_listen: Option<SocketAddr>,

    /// Largest gRPC request message accepted; a bigger one fails with
    /// RESOURCE_EXHAUSTED before it is buffered. The default is the largest
    /// legal request (a StepStream step_linear_batch of 65,536 sessions with
    /// 128-byte ids, 1,048,576 action values, scales and critic gains).
    #[arg(long, value_name = "BYTES", default_value_t = MAX_REQUEST_BYTES, value_parser = parse_bytes)]
    pub max_message_bytes: usize,

    /// Bytes of request messages held at once over all calls (a message
    /// that does not fit fails with RESOURCE_EXHAUSTED). Default: four times
    /// --max-message-bytes.
    #[arg(long, value_name = "BYTES", value_parser = parse_bytes)]
    pub max_request_memory: Option<usize>,

    /// Seconds a unary call, or one StepStream message once begun, may take
    /// to arrive (and the call to be answered).
    #[arg(long, value_name = "SECONDS", default_value_t = 30.0, value_parser = parse_positive_seconds)]
    pub request_timeout: f64,

    /// Most gRPC connections held at once. At the limit a new connection
    /// replaces the one idle (no call in flight) the longest, and is refused
    /// only when every connection has a call in flight. Default: what the
    /// open-files limit allows (raised to its hard limit at start-up) less
    /// 64, at most 4096.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    pub max_connections: Option<u64>,

    /// Seconds a new connection may take to send the HTTP/2 preface.
    #[arg(long, value_name = "SECONDS", default_value_t = 10.0, value_parser = parse_positive_seconds)]
    pub handshake_timeout: f64,

    /// Most concurrent calls (HTTP/2 streams) per connection.
    #[arg(long, value_name = "N", default_value_t = 128, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_streams_per_connection: u32,

    /// Seconds between HTTP/2 pings on each connection; 0 = no pings.
    #[arg(long, value_name = "SECONDS", default_value_t = 30.0, value_parser = parse_seconds)]
    pub keepalive_interval: f64,

    /// Seconds to wait for a ping's answer before closing the connection.
    #[arg(long, value_name = "SECONDS", default_value_t = 10.0, value_parser = parse_positive_seconds)]
    pub keepalive_timeout: f64,

    /// Seconds that shutdown waits for calls in flight to finish (open
    /// StepStreams are ended at once with UNAVAILABLE).
    #[arg(long, value_name = "SECONDS", default_value_t = 5.0, value_parser = parse_seconds)]
    pub shutdown_grace: f64,

    /// Shut down (as on SIGTERM) once this process is no longer the server's
    /// parent, i.e. when the parent dies, whatever the signal. Launchers pass
    /// their own pid so that the server never outlives them.
    #[arg(long, value_name = "PID")]
    pub parent_pid: Option<u32>,

    /// Keep every session across a graceful stop: on SIGTERM (SIGINT, SIGHUP,
    /// or --parent-pid's exit) the server finishes the requests in flight and
    /// writes every live session's full state to this file (mode 0600,
    /// atomically); on start it restores the sessions the file holds (except
    /// those idle past --session-ttl) and removes it. A corrupt, truncated,
    /// foreign or newer-format file, or one that another user owns or others
    /// can write, stops the start. The file holds what clients sent: keep it
    /// private.
    #[arg(long, value_name = "PATH")]
    pub state_file: Option<PathBuf>,

    /// Remove this directory, with everything in it, when the server exits.
    /// Only the directory holding the --uds socket is accepted: it is meant
    /// for a launcher's private temporary directory.
    #[arg(long, value_name = "DIR", requires = "uds")]
    pub remove_dir_on_exit: Option<PathBuf>,

    /// Log line format on stderr.
    #[arg(long, value_enum, default_value_t = LogFormat::Text)]
    pub log_format: LogFormat,

    /// The Zenoh transport's flags (cargo feature `zenoh`, on by default).
    #[cfg(feature = "zenoh")]
    #[command(flatten)]
    pub zenoh: ZenohFlags,
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
    /// The TLS settings of --tls-cert, --tls-key and --tls-client-ca, their files read and
    /// checked; None without --tls-cert.
    pub fn tls(&self) -> Result<Option<TlsSettings>, StartError> {
        match (&self.tls_cert, &self.tls_key) {
            (Some(cert), Some(key)) => {
                TlsSettings::from_files(cert, key, self.tls_client_ca.as_deref()).map(Some)
            }
            _ => Ok(None),
        }
    }

    /// The server options these flags ask for, requiring `token` when given.
    pub fn server_builder(
        &self,
        token: Option<Vec<u8>>,
        tls: Option<TlsSettings>,
    ) -> ServerBuilder {
        let ttl = (self.session_ttl > 0.0).then(|| Duration::from_secs_f64(self.session_ttl));
        let keepalive = (self.keepalive_interval > 0.0).then(|| {
            (
                Duration::from_secs_f64(self.keepalive_interval),
                Duration::from_secs_f64(self.keepalive_timeout),
            )
        });
        let mut builder = ServerBuilder::default()
            .session_ttl(ttl)
            .max_sessions(self.max_sessions)
            .max_message_bytes(self.max_message_bytes)
            .request_timeout(Duration::from_secs_f64(self.request_timeout))
            .handshake_timeout(Duration::from_secs_f64(self.handshake_timeout))
            .max_streams_per_connection(self.max_streams_per_connection)
            .keepalive(keepalive)
            .shutdown_grace(Duration::from_secs_f64(self.shutdown_grace));
        if let Some(bytes) = self.max_session_memory {
            builder = builder.max_session_memory(bytes);
        }
        if let Some(bytes) = self.max_request_memory {
            builder = builder.max_request_memory(bytes);
        }
        if let Some(n) = self.max_connections {
            builder = builder.max_connections(usize::try_from(n).unwrap_or(usize::MAX));
        }
        if let Some(token) = token {
            builder = builder.auth_token(token);
        }
        if let Some(tls) = tls {
            builder = builder.tls(tls);
        }
        builder
    }

    /// The directory to remove on exit, checked to be the --uds socket's own.
    pub fn owned_dir(&self) -> Result<Option<&PathBuf>, StartError> {
        let Some(dir) = &self.remove_dir_on_exit else {
            return Ok(None);
        };
        let socket_dir = self.uds.as_deref().and_then(std::path::Path::parent);
        if socket_dir != Some(dir.as_path()) {
            return Err(StartError::Config(format!(
                "--remove-dir-on-exit: expected the directory of the --uds socket, got {}",
                dir.display()
            )));
        }
        Ok(Some(dir))
    }

    /// Warnings for listening beyond loopback without both TLS and access control (a token,
    /// or client certificates): without access control anyone who can reach the server can
    /// read, reset and close every session; without TLS the token and every request cross the
    /// network in clear text.
    pub fn exposure_warnings(&self, has_token: bool) -> Vec<String> {
        let mut warnings = Vec::new();
        if self.uds.is_none() && !self.listen.ip().is_loopback() {
            let encrypted = self.tls_cert.is_some();
            let controlled = has_token || self.tls_client_ca.is_some();
            let advice = match (encrypted, controlled) {
                (true, true) => None,
                (false, false) => Some(
                    "with neither TLS nor access control: anyone who can reach it can read, \
                     reset and close every session. Serve it with --tls-cert and --tls-key, \
                     and --auth-token-file (or --tls-client-ca)",
                ),
                (false, true) => Some(
                    "without TLS: the auth token and every request cross the network in \
                     clear text, where anyone on the path can read the token and reuse it. \
                     Add --tls-cert and --tls-key",
                ),
                (true, false) => Some(
                    "with TLS but no access control: anyone who can reach it can read, reset \
                     and close every session. Add --auth-token-file or --tls-client-ca",
                ),
            };
            if let Some(advice) = advice {
                warnings.push(format!(
                    "gRPC on {} is reachable beyond this host {advice}",
                    self.listen
                ));
            }
        }
        #[cfg(feature = "zenoh")]
        warnings.extend(self.zenoh.exposure_warnings(has_token));
        warnings
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

/// Seconds as for [`parse_seconds`], and more than zero.
fn parse_positive_seconds(text: &str) -> Result<f64, String> {
    parse_seconds(text).and_then(|seconds| {
        (seconds > 0.0)
            .then_some(seconds)
            .ok_or_else(|| format!("expected a number of seconds > 0, got {text}"))
    })
}

/// A byte count: a plain number, or one with a binary suffix (K, KiB, M, MiB, G, GiB, T, TiB).
fn parse_bytes(text: &str) -> Result<usize, String> {
    let bad = || format!("expected a number of bytes like 1073741824, 512MiB or 2G, got {text:?}");
    let digits = text.trim_end_matches(|c: char| c.is_ascii_alphabetic());
    let shift = match text[digits.len()..].to_ascii_lowercase().as_str() {
        "" | "b" => 0,
        "k" | "kib" => 10,
        "m" | "mib" => 20,
        "g" | "gib" => 30,
        "t" | "tib" => 40,
        _ => return Err(bad()),
    };
    let value: usize = digits.trim().parse().map_err(|_| bad())?;
    value.checked_mul(1 << shift).ok_or_else(bad)
}

/// Permission bits in octal, at most 0o777.
fn parse_mode(text: &str) -> Result<u32, String> {
    u32::from_str_radix(text, 8)
        .ok()
        .filter(|&mode| mode <= 0o777)
        .ok_or_else(|| format!("expected octal permission bits like 600 or 660, got {text:?}"))
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

    #[cfg(feature = "zenoh")]
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
        assert!(parse(&[]).unwrap().zenoh.config().unwrap().is_none());
        let cli = parse(&["--zenoh", "--shard", "1/2", "--zenoh-prefix", "lab/esa"]).unwrap();
        let (_, prefix) = cli.zenoh.config().unwrap().unwrap();
        assert_eq!(prefix, "lab/esa/shard/1");
        let (_, prefix) = parse(&["--zenoh"])
            .unwrap()
            .zenoh
            .config()
            .unwrap()
            .unwrap();
        assert_eq!(prefix, "esa/v1");
    }

    #[test]
    fn byte_counts_take_binary_suffixes() {
        assert_eq!(parse_bytes("1024"), Ok(1024));
        assert_eq!(parse_bytes("512MiB"), Ok(512 << 20));
        assert_eq!(parse_bytes("2G"), Ok(2 << 30));
        assert_eq!(parse_bytes("3kib"), Ok(3 << 10));
        for bad in ["", "-1", "1.5G", "12 parsecs", "GiB"] {
            assert!(parse_bytes(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn modes_are_octal() {
        assert_eq!(parse_mode("600"), Ok(0o600));
        assert_eq!(parse_mode("0660"), Ok(0o660));
        assert!(parse_mode("800").is_err());
        assert!(parse_mode("1777").is_err());
    }

    /// No address is bound here: the warnings depend only on the flags.
    #[test]
    fn listening_beyond_loopback_without_tls_and_a_token_is_warned_about() {
        let parse = |args: &[&str]| Cli::try_parse_from([&["esa-server"], args].concat()).unwrap();
        assert!(parse(&[]).exposure_warnings(false).is_empty());
        assert!(parse(&["--uds", "/tmp/x.sock"])
            .exposure_warnings(false)
            .is_empty());
        let wide = ["--listen", "192.0.2.1:50051"];
        let tls = ["--tls-cert", "c.pem", "--tls-key", "k.pem"];
        let mutual = [&tls[..], &["--tls-client-ca", "ca.pem"]].concat();
        for (args, token, needles) in [
            (
                &[][..],
                false,
                &[
                    "neither TLS nor access control",
                    "--tls-cert",
                    "--auth-token-file",
                ][..],
            ),
            (&[], true, &["without TLS", "clear text", "--tls-cert"]),
            (
                &tls,
                false,
                &["no access control", "--auth-token-file", "--tls-client-ca"],
            ),
        ] {
            let warnings = parse(&[&wide[..], args].concat()).exposure_warnings(token);
            assert_eq!(warnings.len(), 1, "{warnings:?}");
            assert!(warnings[0].contains("192.0.2.1:50051"), "{warnings:?}");
            for needle in needles {
                assert!(warnings[0].contains(needle), "{needle}: {warnings:?}");
            }
        }
        assert!(parse(&[&wide[..], &tls].concat())
            .exposure_warnings(true)
            .is_empty());
        assert!(parse(&[&wide[..], &mutual].concat())
            .exposure_warnings(false)
            .is_empty());
    }

    /// The endpoints given on the command line carry no TLS, so every one beyond loopback is
    /// warned about, with or without a token.
    #[cfg(feature = "zenoh")]
    #[test]
    fn zenoh_listening_beyond_loopback_is_warned_about() {
        let parse = |args: &[&str]| Cli::try_parse_from([&["esa-server"], args].concat()).unwrap();
        let zenoh = parse(&[
            "--zenoh",
            "--zenoh-listen",
            "tcp/127.0.0.1:7447",
            "--zenoh-listen",
            "tcp/[::1]:7448",
            "--zenoh-listen",
            "tcp/192.0.2.1:7447",
        ]);
        for token in [false, true] {
            let warnings = zenoh.exposure_warnings(token);
            assert_eq!(warnings.len(), 1, "{warnings:?}");
            assert!(warnings[0].contains("tcp/192.0.2.1:7447"), "{warnings:?}");
            assert!(warnings[0].contains("mutual TLS"), "{warnings:?}");
        }
    }

    #[test]
    fn tls_flags_come_together_and_not_with_a_unix_socket() {
        let parse = |args: &[&str]| Cli::try_parse_from([&["esa-server"], args].concat());
        assert!(parse(&["--tls-cert", "c.pem"]).is_err());
        assert!(parse(&["--tls-key", "k.pem"]).is_err());
        assert!(parse(&["--tls-client-ca", "ca.pem"]).is_err());
        assert!(parse(&[
            "--tls-cert",
            "c.pem",
            "--tls-key",
            "k.pem",
            "--uds",
            "/tmp/x.sock"
        ])
        .is_err());
        assert!(parse(&["--tls-cert", "c.pem", "--tls-key", "k.pem"]).is_ok());
        assert!(parse(&[]).unwrap().tls().unwrap().is_none());
    }

    #[test]
    fn only_the_sockets_own_directory_may_be_removed_on_exit() {
        let parse = |args: &[&str]| Cli::try_parse_from([&["esa-server"], args].concat());
        assert!(parse(&["--remove-dir-on-exit", "/tmp/esa"]).is_err());
        let ok = parse(&[
            "--uds",
            "/tmp/esa-1/esa.sock",
            "--remove-dir-on-exit",
            "/tmp/esa-1",
        ]);
        assert!(ok.unwrap().owned_dir().unwrap().is_some());
        let other = parse(&[
            "--uds",
            "/tmp/esa-1/esa.sock",
            "--remove-dir-on-exit",
            "/tmp",
        ]);
        assert!(other.unwrap().owned_dir().is_err());
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
