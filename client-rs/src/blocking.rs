//! The client for synchronous code (and for the Python extension, which releases the GIL
//! around each call): [`crate::Client`] on a private single-threaded runtime.
//!
//! The runtime is driven by the calling thread itself ([`Client::block_on`]), so a round trip
//! costs no hand-off between threads: the request is written, and the answer read, by the
//! thread that asked. Between calls nothing would answer the server's HTTP/2 pings, so a keeper
//! thread drives the runtime for a moment every few seconds (a connection left unanswered for
//! the server's keepalive timeout would be dropped and reopened by the next call).
//!
//! [`StreamThread`] is the other way round, for a caller that does not wait for its answers:
//! a StepStream driven by a thread of its own, so its work overlaps the caller's.

use std::future::Future;
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::Arc;
use std::thread;
use std::time::Duration;

use tokio::runtime::Runtime;
use tonic::Code;

use crate::{pb, Answer, Error, Options, Result, Step, StepStream};

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
    /// Where and how it connects, for [`Client::stream_thread`]'s own connection.
    address: String,
    options: Options,
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
            crate::Client::connect_lazy(address, options.clone())?
        };
        Ok(Self {
            client,
            _keeper: keeper(Arc::clone(&runtime)),
            runtime,
            address: address.to_string(),
            options,
        })
    }

    /// A StepStream on a thread and connection of its own ([`StreamThread`]).
    pub fn stream_thread(&self) -> Result<StreamThread> {
        StreamThread::spawn(&self.address, self.options.clone())
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

    /// CreateSession resuming a lost session's progress ([`crate::Client::resume_session`]).
    pub fn resume_session(
        &self,
        session_id: String,
        config: pb::SessionConfig,
        progress: pb::SessionProgress,
    ) -> Result<String> {
        self.block_on(self.client.resume_session(session_id, config, progress))
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

/// A StepStream on a thread of its own, with its own connection and runtime: [`send`] queues a
/// request and returns at once, the thread writes it, reads its answer and keeps it for
/// [`answer`]. So the calling thread does none of the stream's work (HTTP/2 framing, the
/// socket's system calls, decoding) and never waits for the wire unless it asks for an answer
/// that has not arrived. For a caller that sends a step and reads its answer one step later
/// (the pipelined step for a linear critic): the round trip and the stream's work then overlap
/// the caller's own.
///
/// Requests are answered in the order sent. A failure of the wire fails that request's answer
/// and drops the stream; the next request opens a new one. Dropping this ends the thread.
///
/// [`send`]: StreamThread::send
/// [`answer`]: StreamThread::answer
#[derive(Debug)]
pub struct StreamThread {
    requests: tokio::sync::mpsc::UnboundedSender<Step>,
    answers: mpsc::Receiver<Result<Answer>>,
    /// How long [`StreamThread::answer`] waits at most: the thread's own calls have the
    /// options' deadline, so this only guards against a thread that stopped answering.
    patience: Duration,
}

impl StreamThread {
    /// Starts the thread, which connects lazily to `address` (as [`crate::Client::connect_lazy`]).
    pub fn spawn(address: &str, options: Options) -> Result<Self> {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|err| Error::new(Code::Internal, format!("the stream's runtime: {err}")))?;
        let client = {
            let _context = runtime.enter();
            crate::Client::connect_lazy(address, options.clone())?
        };
        let (requests, mut queued) = tokio::sync::mpsc::unbounded_channel::<Step>();
        let (answered, answers) = mpsc::channel();
        thread::Builder::new()
            .name("esa-grpc-stream".into())
            .spawn(move || {
                runtime.block_on(async move {
                    let mut stream: Option<StepStream> = None;
                    while let Some(step) = queued.recv().await {
                        let answer = exchange(&client, &mut stream, step).await;
                        if answer.as_ref().is_err_and(Error::is_retryable) {
                            stream = None;
                        }
                        if answered.send(answer).is_err() {
                            break;
                        }
                    }
                });
            })
            .map_err(|err| Error::new(Code::Internal, format!("the stream's thread: {err}")))?;
        Ok(Self {
            requests,
            answers,
            // Opening the stream and the exchange itself each have the deadline.
            patience: options.timeout.saturating_mul(3),
        })
    }

    /// Queues a request; its answer comes from a later [`StreamThread::answer`].
    pub fn send(&self, step: Step) -> Result<()> {
        self.requests.send(step).map_err(|_| gone())
    }

    /// The answer to the oldest request not yet answered, waiting for it if need be.
    pub fn answer(&mut self) -> Result<Answer> {
        match self.answers.recv_timeout(self.patience) {
            Ok(answer) => answer,
            Err(RecvTimeoutError::Timeout) => Err(Error::deadline(self.patience)),
            Err(RecvTimeoutError::Disconnected) => Err(gone()),
        }
    }
}

/// One request on `stream` (opened first when there is none) and its answer.
async fn exchange(
    client: &crate::Client,
    stream: &mut Option<StepStream>,
    step: Step,
) -> Result<Answer> {
    let stream = match stream {
        Some(stream) => stream,
        None => stream.insert(client.step_stream().await?),
    };
    stream.send(step).await?;
    stream.next().await
}

fn gone() -> Error {
    Error::new(Code::Unavailable, "the step stream's thread has stopped")
}
