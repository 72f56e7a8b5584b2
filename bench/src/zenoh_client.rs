//! The contract over Zenoh (CONTRACT.md section 3) from the load generator's
//! side: a loopback peer that connects to the server's announced locators and
//! sends one query per call to `<prefix>/<RpcName>`, the protobuf request as
//! payload, as the server's own Zenoh tests do.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use esa_proto::v1 as pb;
use esa_proto::Rpc;
use esa_proto::DEFAULT_ZENOH_PREFIX;
use prost::Message;
use zenoh::bytes::Encoding;
use zenoh::query::{ConsolidationMode, Querier};
use zenoh::Session;

use crate::error::{Error, Result};

/// Longest wait for one reply; a loaded 2-core machine answering a batch of
/// 1024 can take far longer than Zenoh's 10 s default would ever need, but a
/// lost server must still end the run.
const QUERY_TIMEOUT: Duration = Duration::from_secs(30);

/// One Zenoh session with a querier per RPC; clones share them.
#[derive(Clone)]
pub struct ZenohClient {
    inner: Arc<Inner>,
}

struct Inner {
    // Declared before `session` so they are undeclared before it closes.
    queriers: HashMap<Rpc, Querier<'static>>,
    _session: Session,
}

impl ZenohClient {
    /// Opens a peer session that connects to `locators` only (no listener,
    /// no scouting) and declares one querier per RPC under the default prefix.
    pub async fn connect(locators: &[String]) -> Result<Self> {
        let zenoh_err =
            |what: &str, err: &dyn std::fmt::Display| Error::Zenoh(format!("{what}: {err}"));
        let endpoints = serde_json::to_string(locators)?;
        let config = zenoh::Config::from_json5(&format!(
            "{{mode: 'peer', connect: {{endpoints: {endpoints}}}, listen: {{endpoints: []}}, \
             scouting: {{multicast: {{enabled: false}}, gossip: {{enabled: false}}}}}}"
        ))
        .map_err(|err| zenoh_err("peer config", &err))?;
        // Opening waits for the server's declarations, so its queryables are
        // known before the first query.
        let session = zenoh::open(config)
            .await
            .map_err(|err| zenoh_err("cannot open a session", &err))?;
        let mut queriers = HashMap::with_capacity(Rpc::ALL.len());
        for rpc in Rpc::ALL {
            let key = format!("{DEFAULT_ZENOH_PREFIX}/{}", rpc.name());
            let querier = session
                .declare_querier(key.clone())
                // One server answers each key: hand its reply over at once
                // instead of holding it until the query is finalized (as the
                // Python client does).
                .consolidation(ConsolidationMode::None)
                .timeout(QUERY_TIMEOUT)
                .await
                .map_err(|err| zenoh_err(&format!("cannot declare querier {key}"), &err))?;
            queriers.insert(rpc, querier);
        }
        Ok(Self {
            inner: Arc::new(Inner {
                queriers,
                _session: session,
            }),
        })
    }

    /// Sends `request` to `rpc`'s key; a reply error is the server's
    /// `StreamError`, returned as [`Error::Stream`].
    pub async fn call<R: Message + Default>(&self, rpc: Rpc, request: &impl Message) -> Result<R> {
        let querier = self
            .inner
            .queriers
            .get(&rpc)
            .ok_or_else(|| Error::Zenoh(format!("no querier for {}", rpc.name())))?;
        let replies = querier
            .get()
            .payload(request.encode_to_vec())
            .encoding(Encoding::APPLICATION_PROTOBUF)
            .await
            .map_err(|err| Error::Zenoh(format!("{}: cannot send: {err}", rpc.name())))?;
        // The channel ends without a reply when the query times out with no
        // server answering.
        let reply = replies
            .recv_async()
            .await
            .map_err(|_| Error::Zenoh(format!("{}: no reply", rpc.name())))?;
        let decode = |what: &str, err: prost::DecodeError| {
            Error::Protocol(format!("{} answered with a bad {what}: {err}", rpc.name()))
        };
        match reply.result() {
            Ok(sample) => {
                R::decode(&*sample.payload().to_bytes()).map_err(|err| decode("response", err))
            }
            Err(err) if err.encoding() == &Encoding::APPLICATION_PROTOBUF => {
                let err = pb::StreamError::decode(&*err.payload().to_bytes())
                    .map_err(|err| decode("StreamError", err))?;
                Err(Error::Stream {
                    code: err.code,
                    message: err.message,
                })
            }
            // Zenoh's own errors (e.g. its query timeout) are plain text.
            Err(err) => Err(Error::Zenoh(format!(
                "{}: {}",
                rpc.name(),
                err.payload().try_to_string().unwrap_or_default()
            ))),
        }
    }
}
