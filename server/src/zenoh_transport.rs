//! The esa contract over Zenoh (CONTRACT.md section 3): one queryable per RPC
//! under `<prefix>/<RpcName>`, a query's payload is the protobuf request, a
//! reply is the protobuf response, and a failure is a reply error whose
//! payload is a `StreamError` (gRPC code number plus message).
//!
//! A thin adapter: every query goes to the same [`EsaHandler`] the gRPC
//! service uses, so a session created over one transport is usable over the
//! other. When the server requires an auth token, a query carries it as its
//! attachment.

use std::sync::Arc;

use prost::Message as _;
use tokio::runtime::Handle;
use zenoh::bytes::Encoding;
use zenoh::query::{Query, Queryable};
use zenoh::{Config, Session};

use crate::error::{stream_error, StartError};
use crate::handler::EsaHandler;
use esa_proto::Rpc;

/// The key prefix of the contract when none is given.
pub const DEFAULT_PREFIX: &str = esa_proto::DEFAULT_ZENOH_PREFIX;

/// Where the default config listens: loopback, a free port.
pub const DEFAULT_LISTEN: &str = "tcp/127.0.0.1:0";

/// One process's part of a sharded deployment: shard `index` of `count`.
///
/// Clients route a session to shard `stable_hash(id) % count` (the hash is
/// documented in `deploy/README.md`); the server only serves its own key
/// space, `<prefix>/shard/<index>/<RpcName>`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    index: u32,
    count: u32,
}

impl Shard {
    /// Shard `index` of `count`; `index < count` is required.
    pub fn new(index: u32, count: u32) -> Result<Self, StartError> {
        if index >= count {
            return Err(StartError::Config(format!(
                "shard: expected i/N with 0 <= i < N, got {index}/{count}"
            )));
        }
        Ok(Self { index, count })
    }

    /// The shard's position, `0..count`.
    pub fn index(self) -> u32 {
        self.index
    }

    /// The number of shards.
    pub fn count(self) -> u32 {
        self.count
    }

    /// The key prefix this shard serves under `prefix`.
    pub fn prefix(self, prefix: &str) -> String {
        format!("{prefix}/shard/{}", self.index)
    }
}

impl std::str::FromStr for Shard {
    type Err = StartError;

    /// Parses `i/N`, e.g. `0/2`.
    fn from_str(text: &str) -> Result<Self, StartError> {
        let bad = || {
            StartError::Config(format!(
                "shard: expected i/N with 0 <= i < N (e.g. 0/2), got {text:?}"
            ))
        };
        let (index, count) = text.split_once('/').ok_or_else(bad)?;
        let index = index.trim().parse().map_err(|_| bad())?;
        let count = count.trim().parse().map_err(|_| bad())?;
        Shard::new(index, count)
    }
}

/// The default Zenoh config: a peer that listens on `listen` (loopback unless
/// told otherwise), connects to `connect`, and never discovers or announces
/// anything by itself (multicast scouting and gossip off), so no traffic
/// leaves the endpoints named here.
pub fn loopback_config(listen: &[String], connect: &[String]) -> Result<Config, StartError> {
    let listen = if listen.is_empty() {
        vec![DEFAULT_LISTEN.to_string()]
    } else {
        listen.to_vec()
    };
    let mut config = Config::default();
    for (key, value) in [
        ("mode", r#""peer""#.to_string()),
        ("listen/endpoints", json_strings(&listen)),
        ("connect/endpoints", json_strings(connect)),
        ("scouting/multicast/enabled", "false".to_string()),
        ("scouting/gossip/enabled", "false".to_string()),
    ] {
        config
            .insert_json5(key, &value)
            .map_err(|err| StartError::Zenoh(format!("config {key} = {value}: {err}")))?;
    }
    Ok(config)
}

/// A JSON5 list of strings (`Debug` quoting matches JSON for endpoints).
fn json_strings(items: &[String]) -> String {
    let quoted: Vec<String> = items.iter().map(|item| format!("{item:?}")).collect();
    format!("[{}]", quoted.join(","))
}

/// A Zenoh session answering the contract's queries until dropped or
/// [`ZenohService::close`]d.
pub struct ZenohService {
    session: Session,
    prefix: String,
    // Declared for as long as the service lives.
    _queryables: Vec<Queryable<()>>,
}

impl ZenohService {
    /// Opens a Zenoh session with `config` and declares one queryable per
    /// RPC under `prefix` (e.g. `esa/v1/ProbeBatch`), answered by `handler`.
    ///
    /// Must be called inside a multi-thread Tokio runtime (Zenoh refuses the
    /// current-thread one): queries are answered on it.
    pub async fn start(
        handler: Arc<EsaHandler>,
        config: Config,
        prefix: &str,
    ) -> Result<Self, StartError> {
        check_prefix(prefix)?;
        let session = zenoh::open(config)
            .await
            .map_err(|err| StartError::Zenoh(format!("cannot open a session: {err}")))?;
        let runtime = Handle::current();
        let mut queryables = Vec::with_capacity(Rpc::ALL.len());
        for rpc in Rpc::ALL {
            let key = format!("{prefix}/{}", rpc.name());
            let handler = Arc::clone(&handler);
            let runtime = runtime.clone();
            // Zenoh calls back on its own threads; answering on the Tokio
            // runtime lets queries (and big batches) run concurrently.
            // Complete: this server alone answers its keys, so a querier that targets complete
            // queryables (and routers doing the same) never mixes in another peer's reply.
            let queryable = session
                .declare_queryable(key.as_str())
                .complete(true)
                .callback(move |query| {
                    runtime.spawn(answer(Arc::clone(&handler), rpc, query));
                })
                .await
                .map_err(|err| {
                    StartError::Zenoh(format!("cannot declare queryable {key}: {err}"))
                })?;
            queryables.push(queryable);
        }
        tracing::info!(prefix, "zenoh queryables declared");
        Ok(Self {
            session,
            prefix: prefix.to_string(),
            _queryables: queryables,
        })
    }

    /// The key prefix the queryables live under.
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// The endpoints this session listens on (e.g. `tcp/127.0.0.1:41234`),
    /// for clients to connect to.
    pub async fn locators(&self) -> Vec<String> {
        let locators = self.session.info().locators().await;
        locators.iter().map(ToString::to_string).collect()
    }

    /// Undeclares the queryables and closes the session.
    pub async fn close(self) -> Result<(), StartError> {
        self.session
            .close()
            .await
            .map_err(|err| StartError::Zenoh(format!("cannot close the session: {err}")))
    }
}

/// A prefix is a literal key expression: wildcards would make the server
/// answer for keys of other deployments.
fn check_prefix(prefix: &str) -> Result<(), StartError> {
    let literal = !prefix.is_empty()
        && !prefix.starts_with('/')
        && !prefix.ends_with('/')
        && !prefix.contains("//")
        && !prefix.contains(['*', '$', '?', '#']);
    if literal {
        Ok(())
    } else {
        Err(StartError::Config(format!(
            "zenoh prefix: expected a key expression without wildcards or empty \
             chunks (e.g. esa/v1), got {prefix:?}"
        )))
    }
}

async fn answer(handler: Arc<EsaHandler>, rpc: Rpc, query: Query) {
    let request = query.payload().map(|p| p.to_bytes()).unwrap_or_default();
    let token = query.attachment().map(|a| a.to_bytes());
    let answer = handler
        .authorize(token.as_deref())
        .and_then(|()| handler.handle_encoded(rpc, &request));
    let sent = match answer {
        Ok(response) => {
            query
                .reply(query.key_expr().clone(), response)
                .encoding(Encoding::APPLICATION_PROTOBUF)
                .await
        }
        Err(err) => {
            query
                .reply_err(stream_error(err).encode_to_vec())
                .encoding(Encoding::APPLICATION_PROTOBUF)
                .await
        }
    };
    if let Err(err) = sent {
        // The querier gave up (timeout) or went away; nothing to tell it.
        tracing::debug!(rpc = rpc.name(), %err, "zenoh reply not sent");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_parse_and_need_index_below_count() {
        let shard: Shard = "1/3".parse().unwrap();
        assert_eq!((shard.index(), shard.count()), (1, 3));
        assert_eq!(shard.prefix("esa/v1"), "esa/v1/shard/1");
        for bad in ["3/3", "0/0", "1", "a/2", "-1/2", "1/2/3", ""] {
            assert!(bad.parse::<Shard>().is_err(), "{bad}");
        }
    }

    #[test]
    fn prefixes_must_be_literal_keys() {
        assert!(check_prefix("esa/v1").is_ok());
        assert!(check_prefix("lab/esa/v1").is_ok());
        for bad in [
            "", "/esa", "esa/", "esa//v1", "esa/*", "esa/**", "a$*", "e?",
        ] {
            assert!(check_prefix(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn default_config_is_a_quiet_loopback_peer() {
        let config = loopback_config(&[], &["tcp/127.0.0.1:7447".to_string()]).unwrap();
        let json = |key| config.get_json(key).unwrap();
        assert_eq!(json("mode"), r#""peer""#);
        assert!(json("listen/endpoints").contains("tcp/127.0.0.1:0"));
        assert!(json("connect/endpoints").contains("tcp/127.0.0.1:7447"));
        assert_eq!(json("scouting/multicast/enabled"), "false");
        assert_eq!(json("scouting/gossip/enabled"), "false");
        assert!(loopback_config(&["nonsense".to_string()], &[]).is_err());
    }
}
