//! The flags of the Zenoh transport, compiled with the cargo feature `zenoh` only: a gRPC-only
//! build has no such flags (clap then refuses `--zenoh` as an unexpected argument).

use std::net::IpAddr;
use std::path::PathBuf;

use clap::Args;

use esa_server::zenoh_transport::{loopback_config, Shard, DEFAULT_PREFIX};
use esa_server::StartError;

/// `--zenoh` and the flags that only go with it.
#[derive(Debug, Args)]
#[command(next_help_heading = "Zenoh")]
pub struct ZenohFlags {
    /// Also serve the API over Zenoh, beside gRPC and on the same sessions:
    /// one queryable per RPC at PREFIX/<RpcName>. Prints `zenoh listening
    /// on LOCATOR` for each listen endpoint before `listening on`.
    #[arg(id = "zenoh", long = "zenoh")]
    pub enabled: bool,

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

impl ZenohFlags {
    /// The Zenoh config and key prefix these flags ask for; None without `--zenoh`.
    pub fn config(&self) -> Result<Option<(zenoh::Config, String)>, StartError> {
        if !self.enabled {
            return Ok(None);
        }
        let config = match &self.zenoh_config {
            Some(path) => zenoh::Config::from_file(path).map_err(|err| {
                StartError::Zenoh(format!("cannot load config {}: {err}", path.display()))
            })?,
            None => loopback_config(&self.zenoh_listen, &self.zenoh_connect)?,
        };
        let prefix = match self.shard {
            Some(shard) => shard.prefix(&self.zenoh_prefix),
            None => self.zenoh_prefix.clone(),
        };
        Ok(Some((config, prefix)))
    }

    /// A warning for each listen endpoint beyond loopback: the endpoints given here carry no
    /// certificates, so their queries (and the token) cross the network in clear text.
    pub fn exposure_warnings(&self, has_token: bool) -> Vec<String> {
        if !self.enabled {
            return Vec::new();
        }
        let advice = if has_token {
            "without TLS: the auth token and every query cross the network in clear \
             text. Use a --zenoh-config with mutual TLS (deploy/zenoh/mtls-*.json5)"
        } else {
            "with neither TLS nor access control: anyone who can reach it can read, \
             reset and close every session, or answer a trainer's queries. Use a \
             --zenoh-config with mutual TLS (deploy/zenoh/mtls-*.json5) and \
             --auth-token-file"
        };
        self.zenoh_listen
            .iter()
            .filter(|endpoint| !is_loopback_endpoint(endpoint))
            .map(|endpoint| format!("Zenoh on {endpoint} is reachable beyond this host {advice}"))
            .collect()
    }
}

/// Whether a Zenoh endpoint (`tcp/HOST:PORT`, `unixsock-stream/PATH`, ...) stays on this host.
fn is_loopback_endpoint(endpoint: &str) -> bool {
    let Some((protocol, address)) = endpoint.split_once('/') else {
        return false;
    };
    if protocol.starts_with("unixsock") {
        return true;
    }
    let address = address.split('#').next().unwrap_or(address);
    let host = address
        .rsplit_once(':')
        .map_or(address, |(host, _)| host)
        .trim_start_matches('[')
        .trim_end_matches(']');
    host == "localhost" || host.parse::<IpAddr>().is_ok_and(|ip| ip.is_loopback())
}

fn parse_shard(text: &str) -> Result<Shard, String> {
    text.parse().map_err(|err: StartError| err.to_string())
}
