//! The client for synchronous code (and for the Python extension, which releases the GIL
//! around each call): [`crate::Client`] on a private single-threaded runtime.
//!
//! The runtime is driven by the calling thread itself ([`Client::block_on`]), so a round trip
//! costs no hand-off between threads: the request is written, and the answer read, by the
//! thread that asked. Between calls nothing would answer the server's HTTP/2 pings, so a keeper
//! thread drives the runtime for a moment every few seconds (a connection left unanswered for
//! the server's keepalive timeout would be dropped and reopened by the next call).

use std::future::Future;
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::Arc;
use std::thread;
use std::time::Duration;

use tokio::runtime::Runtime;
use tonic::Code;

use crate::{pb, Error, Options, Result};

/// How often the keeper thread answers what arrived while no call was waiting; well within the
/// server's keepalive timeout (10 s by default).
const KEEPER_INTERVAL: Duration = Duration::from_secs(2);
/// How long the keeper drives the runtime each time.
const KEEPER_DRIVE: Duration = Duration::from_millis(1);

/// A connection to one esa-server, with blocking calls. Connects lazily: a server not up yet
/// fails the calls, not the client ([`Client::healthy`] waits for one).
#[derive(Debug)]
pub struct Client {
    client: crate::Client,
    runtime: Arc<Runtime>,
    /// Dropped with the client: ends the keeper thread.
    _keeper: mpsc::Sender<()>,
}

impl Client {
    /// A client of the server at `address` (`host:port`, `unix:/path`, `https://host:port`).
    pub fn connect(address: &str, options: Options) -> Result<Self> {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|err| Error::new(Code::Internal, format!("the client's runtime: {err}")))?;
        let runtime = Arc::new(runtime);
        let client = {
            let _context = runtime.enter();
            crate::Client::connect_lazy(address, options)?
        };
        Ok(Self {
            client,
            _keeper: keeper(Arc::clone(&runtime)),
            runtime,
        })
    }

    /// The async client this one drives (for calls not wrapped here, e.g. a StepStream).
    pub fn client(&self) -> &crate::Client {
        &self.client
    }

    /// Runs `future` (a call of [`Client::client`]) to completion on this client's runtime.
    pub fn block_on<F: Future>(&self, future: F) -> F::Output {
        self.runtime.block_on(future)
    }

    /// CreateSession; returns the id.
    pub fn create_session(&self, session_id: String, config: pb::SessionConfig) -> Result<String> {
        self.block_on(self.client.create_session(session_id, config))
    }

    /// GetSession.
    pub fn get_session(&self, session_id: String) -> Result<pb::GetSessionResponse> {
        self.block_on(self.client.get_session(session_id))
    }

    /// CloseSession.
    pub fn close_session(&self, session_id: String) -> Result<()> {
        self.block_on(self.client.close_session(session_id))
    }

    /// EndEpisode; returns the episodes completed.
    pub fn end_episode(&self, session_id: String) -> Result<u64> {
        self.block_on(self.client.end_episode(session_id))
    }

    /// Probe of one session.
    pub fn probe(&self, request: pb::ProbeRequest) -> Result<pb::ProbeResponse> {
        self.block_on(self.client.probe(request))
    }

    /// Report of one session.
    pub fn report(&self, request: pb::ReportRequest) -> Result<pb::ReportResponse> {
        self.block_on(self.client.report(request))
    }

    /// ProbeBatch.
    pub fn probe_batch(&self, request: pb::ProbeBatchRequest) -> Result<pb::ProbeBatchResponse> {
        self.block_on(self.client.probe_batch(request))
    }

    /// ReportBatch.
    pub fn report_batch(&self, request: pb::ReportBatchRequest) -> Result<pb::ReportBatchResponse> {
        self.block_on(self.client.report_batch(request))
    }

    /// Whether the server's health check answers SERVING within `timeout`.
    pub fn healthy(&self, timeout: Duration, wait_for_ready: bool) -> bool {
        self.block_on(self.client.healthy(timeout, wait_for_ready))
    }
}

/// Drives `runtime` for a moment every `KEEPER_INTERVAL` until `stop`'s sender is dropped.
fn keeper(runtime: Arc<Runtime>) -> mpsc::Sender<()> {
    let (stop, stopped) = mpsc::channel::<()>();
    let _detached = thread::Builder::new()
        .name("esa-grpc-keeper".into())
        .spawn(move || {
            while let Err(RecvTimeoutError::Timeout) = stopped.recv_timeout(KEEPER_INTERVAL) {
                runtime.block_on(async { tokio::time::sleep(KEEPER_DRIVE).await });
            }
        });
    stop
}
