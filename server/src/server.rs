//! Assembling and running the gRPC server: the builder that tests and the
//! binary use, the listeners (TCP or Unix socket) and graceful shutdown.

use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::os::unix::fs::FileTypeExt;
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::{TcpListener, UnixListener};
use tokio::sync::watch;
use tokio_stream::wrappers::UnixListenerStream;
use tokio_stream::Stream;
use tonic::transport::server::{Connected, Router, TcpIncoming};
use tonic_health::server::HealthReporter;

use crate::error::Error;
use crate::grpc::{stopped, GrpcService};
use crate::handler::EsaHandler;
use crate::pb;
use crate::pb::esa_service_server::EsaServiceServer;
use crate::store::SessionStore;

/// Options of an [`EsaServer`]; defaults match the binary's flag defaults.
#[derive(Clone, Debug)]
pub struct ServerBuilder {
    session_ttl: Option<Duration>,
    sweep_interval: Option<Duration>,
    max_sessions: usize,
    max_message_bytes: usize,
    shutdown_grace: Duration,
}

impl Default for ServerBuilder {
    fn default() -> Self {
        Self {
            session_ttl: Some(Duration::from_secs(600)),
            sweep_interval: None,
            max_sessions: 100_000,
            max_message_bytes: 64 << 20,
            shutdown_grace: Duration::from_secs(5),
        }
    }
}

impl ServerBuilder {
    /// Idle time after which a session expires; `None` = never.
    pub fn session_ttl(mut self, ttl: Option<Duration>) -> Self {
        self.session_ttl = ttl;
        self
    }

    /// How often expired sessions are swept from memory (default: a quarter
    /// of the TTL, between 100 ms and 60 s). Lookups see expiry exactly
    /// either way; the sweep only frees sessions nobody asks for.
    pub fn sweep_interval(mut self, every: Duration) -> Self {
        self.sweep_interval = Some(every);
        self
    }

    /// Most sessions held at once; creating one more is RESOURCE_EXHAUSTED.
    pub fn max_sessions(mut self, n: usize) -> Self {
        self.max_sessions = n;
        self
    }

    /// Largest gRPC message accepted, in bytes (large batches need more than
    /// gRPC's usual 4 MiB).
    pub fn max_message_bytes(mut self, bytes: usize) -> Self {
        self.max_message_bytes = bytes;
        self
    }

    /// How long shutdown waits for open calls (such as a StepStream a client
    /// keeps open) before closing them.
    pub fn shutdown_grace(mut self, grace: Duration) -> Self {
        self.shutdown_grace = grace;
        self
    }

    pub fn build(self) -> EsaServer {
        let sweep_interval = self.session_ttl.map(|ttl| {
            self.sweep_interval.unwrap_or_else(|| {
                (ttl / 4).clamp(Duration::from_millis(100), Duration::from_secs(60))
            })
        });
        EsaServer {
            handler: Arc::new(EsaHandler::new(SessionStore::new(
                self.session_ttl,
                self.max_sessions,
            ))),
            sweep_interval,
            max_message_bytes: self.max_message_bytes,
            shutdown_grace: self.shutdown_grace,
        }
    }
}

/// A configured server, ready to serve on a [`Listener`].
pub struct EsaServer {
    handler: Arc<EsaHandler>,
    sweep_interval: Option<Duration>,
    max_message_bytes: usize,
    shutdown_grace: Duration,
}

/// Where the gRPC server accepts connections.
pub enum Listener {
    Tcp(TcpListener),
    /// A Unix domain socket; its file is removed when serving ends.
    Unix(UnixListener, PathBuf),
}

impl Listener {
    /// Binds a TCP listener (port 0 picks a free port).
    pub async fn tcp(addr: SocketAddr) -> Result<Self, Error> {
        let listener = TcpListener::bind(addr)
            .await
            .map_err(|err| io_context(err, format!("cannot listen on {addr}")))?;
        Ok(Listener::Tcp(listener))
    }

    /// Binds a Unix domain socket at `path`. A socket file left behind by a
    /// server that died is replaced; a live socket or any other file is an
    /// error (and never deleted).
    pub fn unix(path: &Path) -> Result<Self, Error> {
        let context = || format!("cannot listen on unix:{}", path.display());
        if let Ok(meta) = std::fs::symlink_metadata(path) {
            let is_socket = meta.file_type().is_socket();
            if !is_socket || UnixStream::connect(path).is_ok() {
                let why = if is_socket {
                    "another server is listening there"
                } else {
                    "the path exists and is not a socket"
                };
                return Err(Error::Io(io::Error::new(
                    io::ErrorKind::AddrInUse,
                    format!("{}: {why}", context()),
                )));
            }
            std::fs::remove_file(path).map_err(|err| io_context(err, context()))?;
        }
        let listener = UnixListener::bind(path).map_err(|err| io_context(err, context()))?;
        Ok(Listener::Unix(listener, path.to_path_buf()))
    }

    /// The bound address: `127.0.0.1:50051`, or `unix:/path` for a socket.
    pub fn address(&self) -> Result<String, Error> {
        Ok(match self {
            Listener::Tcp(listener) => listener.local_addr()?.to_string(),
            Listener::Unix(_, path) => format!("unix:{}", path.display()),
        })
    }
}

impl EsaServer {
    pub fn builder() -> ServerBuilder {
        ServerBuilder::default()
    }

    /// The handler behind the gRPC service; other transports serve the same
    /// sessions through it.
    pub fn handler(&self) -> Arc<EsaHandler> {
        Arc::clone(&self.handler)
    }

    /// Serves EsaService, health and reflection on `listener` until
    /// `shutdown` completes. Then open StepStreams end with UNAVAILABLE and
    /// other calls in flight get the grace time to finish.
    pub async fn serve(
        self,
        listener: Listener,
        shutdown: impl Future<Output = ()>,
    ) -> Result<(), Error> {
        let _sweeper = self
            .sweep_interval
            .map(|every| AbortOnDrop(spawn_sweeper(self.handler(), every)));

        let (stop_tx, stop_rx) = watch::channel(false);
        let (health, health_service) = tonic_health::server::health_reporter();
        health.set_serving::<EsaServiceServer<GrpcService>>().await;
        let esa = EsaServiceServer::new(GrpcService::new(self.handler(), stop_rx))
            .max_decoding_message_size(self.max_message_bytes);
        let router = tonic::transport::Server::builder()
            .add_service(health_service)
            .add_service(reflection().build_v1()?)
            .add_service(reflection().build_v1alpha()?)
            .add_service(esa);
        match listener {
            Listener::Tcp(listener) => {
                let incoming = TcpIncoming::from(listener).with_nodelay(Some(true));
                self.run(router, incoming, shutdown, health, stop_tx).await
            }
            Listener::Unix(listener, path) => {
                let _remove_socket = RemoveOnDrop(path);
                let incoming = UnixListenerStream::new(listener);
                self.run(router, incoming, shutdown, health, stop_tx).await
            }
        }
    }

    async fn run<I, IO, IE>(
        &self,
        router: Router,
        incoming: I,
        shutdown: impl Future<Output = ()>,
        health: HealthReporter,
        stop_tx: watch::Sender<bool>,
    ) -> Result<(), Error>
    where
        I: Stream<Item = Result<IO, IE>>,
        IO: AsyncRead + AsyncWrite + Connected + Unpin + Send + 'static,
        IE: Into<Box<dyn std::error::Error + Send + Sync>>,
    {
        let serving = router.serve_with_incoming_shutdown(incoming, stopped(stop_tx.subscribe()));
        tokio::pin!(serving);
        let result = tokio::select! {
            result = &mut serving => result,
            () = shutdown => {
                tracing::info!("shutting down");
                health.set_not_serving::<EsaServiceServer<GrpcService>>().await;
                // Ends open StepStreams too, which would otherwise hold
                // shutdown for the whole grace time.
                let _ = stop_tx.send(true);
                match tokio::time::timeout(self.shutdown_grace, &mut serving).await {
                    Ok(result) => result,
                    Err(_) => {
                        tracing::warn!(
                            grace = ?self.shutdown_grace,
                            "open calls did not finish in time; closing them"
                        );
                        Ok(())
                    }
                }
            }
        };
        Ok(result?)
    }
}

/// Reflection over esa.v1 and grpc.health.v1 (the builder is not Clone, and
/// v1 and v1alpha each need one).
fn reflection() -> tonic_reflection::server::Builder<'static> {
    tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
}

fn spawn_sweeper(handler: Arc<EsaHandler>, every: Duration) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let mut ticks = tokio::time::interval(every);
        ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            ticks.tick().await;
            let removed = handler.store().sweep();
            if removed > 0 {
                tracing::debug!(
                    removed,
                    live = handler.store().live(),
                    "expired idle sessions"
                );
            }
        }
    })
}

/// `err` with `context` in front of its message (the kind is kept).
pub fn io_context(err: io::Error, context: String) -> io::Error {
    io::Error::new(err.kind(), format!("{context}: {err}"))
}

struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

struct RemoveOnDrop(PathBuf);

impl Drop for RemoveOnDrop {
    fn drop(&mut self) {
        if let Err(err) = std::fs::remove_file(&self.0) {
            tracing::warn!(path = %self.0.display(), %err, "could not remove the socket file");
        }
    }
}
