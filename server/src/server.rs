//! Assembling and running the gRPC server: the builder that tests and the
//! binary use, the listeners (TCP or Unix socket) and graceful shutdown.

use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::os::unix::fs::{FileTypeExt, PermissionsExt};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::{TcpListener, UnixListener};
use tokio::sync::watch;
use tokio_stream::Stream;
use tonic::transport::server::{Connected, Router};
use tonic_health::server::HealthReporter;

use crate::codec::MAX_REQUEST_BYTES;
use crate::connections::{ConnectionLimits, Incoming, Registry};
use crate::error::{io_context, StartError};
use crate::grpc::{stopped, GrpcService};
use crate::guard::{GuardLayer, RequestLimits};
use crate::handler::EsaHandler;
use crate::pb;
use crate::pb::esa_service_server::EsaServiceServer;
use crate::resources;
use crate::store::SessionStore;
use crate::throttle::WARNING_PERIOD;
use crate::tls::TlsSettings;

/// Options of an [`EsaServer`]; defaults match the binary's flag defaults.
#[derive(Clone, Debug)]
pub struct ServerBuilder {
    session_ttl: Option<Duration>,
    sweep_interval: Option<Duration>,
    max_sessions: usize,
    max_session_memory: usize,
    max_message_bytes: usize,
    max_request_memory: Option<usize>,
    request_timeout: Duration,
    connections: ConnectionLimits,
    max_streams_per_connection: u32,
    keepalive: Option<(Duration, Duration)>,
    auth_token: Option<Vec<u8>>,
    tls: Option<TlsSettings>,
    shutdown_grace: Duration,
}

impl Default for ServerBuilder {
    fn default() -> Self {
        Self {
            session_ttl: Some(Duration::from_secs(600)),
            sweep_interval: None,
            max_sessions: esa_store::DEFAULT_MAX_SESSIONS,
            max_session_memory: resources::default_session_memory(),
            max_message_bytes: MAX_REQUEST_BYTES,
            max_request_memory: None,
            request_timeout: Duration::from_secs(30),
            connections: ConnectionLimits {
                max: resources::default_max_connections(),
                handshake_timeout: Duration::from_secs(10),
            },
            max_streams_per_connection: 128,
            keepalive: Some((Duration::from_secs(30), Duration::from_secs(10))),
            auth_token: None,
            tls: None,
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

    /// Bytes the sessions held at once may cost (`store::session_cost`);
    /// creating one that does not fit is RESOURCE_EXHAUSTED. Default: half
    /// of the memory this process may use (`resources::memory_limit`).
    pub fn max_session_memory(mut self, bytes: usize) -> Self {
        self.max_session_memory = bytes;
        self
    }

    /// Largest gRPC request message accepted, in bytes (default: the largest
    /// legal request, `codec::MAX_REQUEST_BYTES`); a bigger one is
    /// RESOURCE_EXHAUSTED from its header on, before it is buffered.
    pub fn max_message_bytes(mut self, bytes: usize) -> Self {
        self.max_message_bytes = bytes;
        self
    }

    /// Bytes of request messages held at once over all calls (default: four
    /// largest messages); a message that does not fit is RESOURCE_EXHAUSTED.
    pub fn max_request_memory(mut self, bytes: usize) -> Self {
        self.max_request_memory = Some(bytes);
        self
    }

    /// How long a unary call, or one message of a stream once begun, may
    /// take to arrive and be answered (default 30 s).
    pub fn request_timeout(mut self, timeout: Duration) -> Self {
        self.request_timeout = timeout;
        self
    }

    /// Most connections held at once (default: what the open-files limit
    /// allows, at most 4096); see `connections` for what happens at the limit.
    pub fn max_connections(mut self, n: usize) -> Self {
        self.connections.max = n;
        self
    }

    /// How long a new connection may take to send the HTTP/2 preface (default 10 s).
    pub fn handshake_timeout(mut self, timeout: Duration) -> Self {
        self.connections.handshake_timeout = timeout;
        self
    }

    /// Most concurrent calls (HTTP/2 streams) per connection (default 128).
    pub fn max_streams_per_connection(mut self, n: u32) -> Self {
        self.max_streams_per_connection = n;
        self
    }

    /// HTTP/2 pings every `interval` on each connection; one not answered
    /// within `timeout` closes the connection (default 30 s and 10 s; `None`
    /// sends none).
    pub fn keepalive(mut self, interval_and_timeout: Option<(Duration, Duration)>) -> Self {
        self.keepalive = interval_and_timeout;
        self
    }

    /// Requires every request to present `token` (gRPC metadata
    /// `authorization: Bearer <token>`, or the Zenoh query attachment);
    /// health checks are exempt.
    pub fn auth_token(mut self, token: impl Into<Vec<u8>>) -> Self {
        self.auth_token = Some(token.into());
        self
    }

    /// Serves gRPC over TLS (mutual TLS when the settings name a client CA). Each TLS
    /// handshake must finish within the handshake timeout.
    pub fn tls(mut self, settings: TlsSettings) -> Self {
        self.tls = Some(settings);
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
        let store = SessionStore::new(self.session_ttl, self.max_sessions, self.max_session_memory);
        let handler = match self.auth_token {
            Some(token) => EsaHandler::new(store).with_auth_token(token),
            None => EsaHandler::new(store),
        };
        EsaServer {
            handler: Arc::new(handler),
            sweep_interval,
            requests: RequestLimits {
                max_message_bytes: self.max_message_bytes,
                max_request_memory: self
                    .max_request_memory
                    .unwrap_or(self.max_message_bytes.saturating_mul(4)),
                message_timeout: self.request_timeout,
            },
            connections: self.connections,
            max_streams_per_connection: self.max_streams_per_connection,
            keepalive: self.keepalive,
            tls: self.tls,
            shutdown_grace: self.shutdown_grace,
        }
    }
}

/// A configured server, ready to serve on a [`Listener`].
pub struct EsaServer {
    handler: Arc<EsaHandler>,
    sweep_interval: Option<Duration>,
    requests: RequestLimits,
    connections: ConnectionLimits,
    max_streams_per_connection: u32,
    keepalive: Option<(Duration, Duration)>,
    tls: Option<TlsSettings>,
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
    pub async fn tcp(addr: SocketAddr) -> Result<Self, StartError> {
        let listener = TcpListener::bind(addr)
            .await
            .map_err(|err| io_context(err, format!("cannot listen on {addr}")))?;
        Ok(Listener::Tcp(listener))
    }

    /// Binds a Unix domain socket at `path` that only this user can connect
    /// to (mode 0600). A socket file left behind by a server that died is
    /// replaced; a live socket or any other file is an error (and never
    /// deleted).
    pub fn unix(path: &Path) -> Result<Self, StartError> {
        Self::unix_with_mode(path, 0o600)
    }

    /// [`Listener::unix`] with the socket file's permission bits `mode`
    /// (connecting needs write permission, so 0660 lets the file's group in).
    pub fn unix_with_mode(path: &Path, mode: u32) -> Result<Self, StartError> {
        let context = || format!("cannot listen on unix:{}", path.display());
        if let Ok(meta) = std::fs::symlink_metadata(path) {
            let is_socket = meta.file_type().is_socket();
            if !is_socket || UnixStream::connect(path).is_ok() {
                let why = if is_socket {
                    "another server is listening there"
                } else {
                    "the path exists and is not a socket"
                };
                return Err(StartError::Io(io::Error::new(
                    io::ErrorKind::AddrInUse,
                    format!("{}: {why}", context()),
                )));
            }
            std::fs::remove_file(path).map_err(|err| io_context(err, context()))?;
        }
        let listener = UnixListener::bind(path).map_err(|err| io_context(err, context()))?;
        // Until this runs the file has the umask's mode; the serve loop only starts after it.
        std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode))
            .map_err(|err| io_context(err, context()))?;
        Ok(Listener::Unix(listener, path.to_path_buf()))
    }

    /// The bound address: `127.0.0.1:50051`, or `unix:/path` for a socket.
    pub fn address(&self) -> Result<String, StartError> {
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
    ) -> Result<(), StartError> {
        let _sweeper = self
            .sweep_interval
            .map(|every| AbortOnDrop(spawn_sweeper(self.handler(), every)));
        let _summaries = AbortOnDrop(spawn_warning_summaries(self.handler()));

        let (stop_tx, stop_rx) = watch::channel(false);
        let (health, health_service) = tonic_health::server::health_reporter();
        health.set_serving::<EsaServiceServer<GrpcService>>().await;
        let esa = EsaServiceServer::new(GrpcService::new(self.handler(), stop_rx))
            .max_decoding_message_size(self.requests.max_message_bytes);
        let (keepalive_interval, keepalive_timeout) = self.keepalive.unzip();
        let mut server = tonic::transport::Server::builder();
        if let Some(tls) = &self.tls {
            // The registry's preface deadline is met by the ClientHello; this one bounds the
            // rest of the TLS handshake.
            server = server.tls_config(tls.server_config(self.connections.handshake_timeout))?;
        }
        let router = server
            .timeout(self.requests.message_timeout)
            .max_concurrent_streams(self.max_streams_per_connection)
            .http2_keepalive_interval(keepalive_interval)
            .http2_keepalive_timeout(keepalive_timeout)
            .layer(GuardLayer::new(self.handler(), self.requests))
            .add_service(health_service)
            .add_service(reflection().build_v1()?)
            .add_service(reflection().build_v1alpha()?)
            .add_service(esa);
        let registry = Registry::new(self.connections, self.handler.metrics());
        match listener {
            Listener::Tcp(listener) => {
                let incoming = Incoming::new(listener, registry);
                self.run(router, incoming, shutdown, health, stop_tx).await
            }
            Listener::Unix(listener, path) => {
                let _remove_socket = RemoveOnDrop(path);
                let incoming = Incoming::new(listener, registry);
                self.run(router, incoming, shutdown, health, stop_tx).await
            }
        }
    }

    async fn run<I, IO, IE>(
        &self,
        router: Router<tower::layer::util::Stack<GuardLayer, tower::layer::util::Identity>>,
        incoming: I,
        shutdown: impl Future<Output = ()>,
        health: HealthReporter,
        stop_tx: watch::Sender<bool>,
    ) -> Result<(), StartError>
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

/// Logs, once per period, what throttled warnings held back.
fn spawn_warning_summaries(handler: Arc<EsaHandler>) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let mut ticks = tokio::time::interval(WARNING_PERIOD);
        loop {
            ticks.tick().await;
            handler.log_suppressed_warnings();
        }
    })
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
