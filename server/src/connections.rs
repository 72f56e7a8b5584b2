//! Accepting connections so that a flood of them cannot lock real clients out or spin the CPU.
//!
//! - At most `max` connections are held, fewer than the file-descriptor limit allows, so accept
//!   does not run out of descriptors. At the limit a new connection replaces the one that has been
//!   idle (no call in flight) the longest; it is refused only when every connection has a call in
//!   flight. A client whose idle connection is replaced reconnects on its next call.
//! - A connection must send the 24-byte HTTP/2 preface within the handshake timeout, so silent
//!   and half-open connections do not hold a slot for long.
//! - When accept fails for want of descriptors or memory, the loop backs off, with a throttled
//!   warning, instead of retrying at once (which spins a core while the error lasts).

use std::collections::HashMap;
use std::future::Future as _;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use futures_util::task::AtomicWaker;
use parking_lot::Mutex;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream, UnixListener, UnixStream};
use tokio::time::Sleep;
use tokio_stream::Stream;
use tonic::transport::server::Connected;

use crate::metrics::Metrics;
use crate::throttle::{Throttle, WARNING_PERIOD};

/// The HTTP/2 client preface (`PRI * HTTP/2.0...`), the first bytes of every connection.
const PREFACE_BYTES: usize = 24;

/// First and longest pause after accept failed for want of resources.
const BACKOFF: (Duration, Duration) = (Duration::from_millis(10), Duration::from_secs(1));

/// What the server holds, and for how long, per connection.
#[derive(Clone, Copy, Debug)]
pub struct ConnectionLimits {
    /// Most connections held at once.
    pub max: usize,
    /// How long a new connection may take to send the HTTP/2 preface.
    pub handshake_timeout: Duration,
}

/// The connections of one listener.
pub struct Registry {
    held: Mutex<HashMap<u64, Arc<Conn>>>,
    next_id: AtomicU64,
    limits: ConnectionLimits,
    epoch: Instant,
    metrics: Arc<Metrics>,
    refusals: Throttle,
}

/// One held connection, shared between its I/O and the calls it carries.
struct Conn {
    id: u64,
    calls: AtomicUsize,
    /// Nanoseconds since the registry's epoch at which the last call ended (or the connection
    /// opened).
    idle_since: AtomicU64,
    epoch: Instant,
    evicted: AtomicBool,
    /// Wakes the connection's reader so that it notices eviction.
    reader: AtomicWaker,
}

impl Registry {
    pub fn new(limits: ConnectionLimits, metrics: Arc<Metrics>) -> Arc<Self> {
        Arc::new(Self {
            held: Mutex::new(HashMap::new()),
            next_id: AtomicU64::new(0),
            limits,
            epoch: Instant::now(),
            metrics,
            refusals: Throttle::new(WARNING_PERIOD),
        })
    }

    /// Holds `io` as a new connection, replacing the longest idle one at the limit; `None` (and
    /// `io` is closed) when every held connection has a call in flight.
    fn admit<IO>(self: &Arc<Self>, io: IO) -> Option<ConnIo<IO>> {
        let mut held = self.held.lock();
        if held.len() >= self.limits.max {
            let idlest = held
                .values()
                .filter(|conn| conn.calls.load(Ordering::Acquire) == 0)
                .min_by_key(|conn| conn.idle_since.load(Ordering::Relaxed))
                .map(|conn| conn.id);
            let Some(evicted) = idlest.and_then(|id| held.remove(&id)) else {
                drop(held);
                self.metrics.connection_refused();
                if let Some(suppressed) = self.refusals.admit() {
                    tracing::warn!(
                        max = self.limits.max,
                        suppressed,
                        "connection refused: every held connection has a call in flight \
                         (--max-connections)"
                    );
                }
                return None;
            };
            evicted.evicted.store(true, Ordering::Release);
            evicted.reader.wake();
            self.metrics.connection_evicted();
        }
        let conn = Arc::new(Conn {
            id: self.next_id.fetch_add(1, Ordering::Relaxed),
            calls: AtomicUsize::new(0),
            idle_since: AtomicU64::new(nanos_since(self.epoch)),
            epoch: self.epoch,
            evicted: AtomicBool::new(false),
            reader: AtomicWaker::new(),
        });
        held.insert(conn.id, Arc::clone(&conn));
        drop(held);
        self.metrics.connection_opened();
        Some(ConnIo {
            io,
            conn,
            registry: Arc::clone(self),
            handshake: Some(Handshake {
                deadline: Box::pin(tokio::time::sleep(self.limits.handshake_timeout)),
                remaining: PREFACE_BYTES,
            }),
        })
    }
}

fn nanos_since(epoch: Instant) -> u64 {
    u64::try_from(epoch.elapsed().as_nanos()).unwrap_or(u64::MAX)
}

/// The connection a request came on (tonic puts it in the request's extensions).
#[derive(Clone)]
pub struct Connection(Arc<Conn>);

impl Connection {
    /// Counts a call in flight on this connection (so that it is not evicted as idle) until the
    /// returned guard is dropped.
    pub fn call_started(&self) -> CallInFlight {
        self.0.calls.fetch_add(1, Ordering::AcqRel);
        CallInFlight(Arc::clone(&self.0))
    }
}

/// A call in flight; see [`Connection::call_started`].
pub struct CallInFlight(Arc<Conn>);

impl Drop for CallInFlight {
    fn drop(&mut self) {
        self.0
            .idle_since
            .store(nanos_since(self.0.epoch), Ordering::Relaxed);
        self.0.calls.fetch_sub(1, Ordering::AcqRel);
    }
}

struct Handshake {
    deadline: Pin<Box<Sleep>>,
    /// Preface bytes still to come.
    remaining: usize,
}

/// A held connection's I/O: ends when evicted, or when the preface is late.
pub struct ConnIo<IO> {
    io: IO,
    conn: Arc<Conn>,
    registry: Arc<Registry>,
    handshake: Option<Handshake>,
}

impl<IO> Drop for ConnIo<IO> {
    fn drop(&mut self) {
        self.registry.held.lock().remove(&self.conn.id);
        self.registry.metrics.connection_closed();
    }
}

impl<IO> Connected for ConnIo<IO> {
    type ConnectInfo = Connection;

    fn connect_info(&self) -> Connection {
        Connection(Arc::clone(&self.conn))
    }
}

impl<IO: AsyncRead + Unpin> AsyncRead for ConnIo<IO> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        this.conn.reader.register(cx.waker());
        if this.conn.evicted.load(Ordering::Acquire) {
            return Poll::Ready(Err(io::Error::new(
                io::ErrorKind::ConnectionAborted,
                "closed to make room: the connection limit was reached and this connection \
                 had been idle the longest",
            )));
        }
        let before = buf.filled().len();
        let read = Pin::new(&mut this.io).poll_read(cx, buf);
        if let Some(handshake) = &mut this.handshake {
            match read {
                Poll::Ready(Ok(())) => {
                    let got = buf.filled().len() - before;
                    handshake.remaining = handshake.remaining.saturating_sub(got);
                    if handshake.remaining == 0 {
                        this.handshake = None;
                    }
                }
                Poll::Pending if handshake.deadline.as_mut().poll(cx).is_ready() => {
                    return Poll::Ready(Err(io::Error::new(
                        io::ErrorKind::TimedOut,
                        format!(
                            "no HTTP/2 preface within {:?}",
                            this.registry.limits.handshake_timeout
                        ),
                    )));
                }
                _ => {}
            }
        }
        read
    }
}

impl<IO: AsyncWrite + Unpin> AsyncWrite for ConnIo<IO> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_shutdown(cx)
    }
}

/// A listening socket the server accepts from.
pub trait Accept: Unpin {
    type Io: AsyncRead + AsyncWrite + Unpin + Send + 'static;

    fn poll_accept(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<Self::Io>>;
}

impl Accept for TcpListener {
    type Io = TcpStream;

    fn poll_accept(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<TcpStream>> {
        TcpListener::poll_accept(self, cx).map_ok(|(stream, _)| {
            // Steps are small messages answered at once: never wait to coalesce them.
            if let Err(err) = stream.set_nodelay(true) {
                tracing::debug!(%err, "cannot set TCP_NODELAY");
            }
            stream
        })
    }
}

impl Accept for UnixListener {
    type Io = UnixStream;

    fn poll_accept(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<UnixStream>> {
        UnixListener::poll_accept(self, cx).map_ok(|(stream, _)| stream)
    }
}

/// The connections accepted from a listener, as the stream tonic serves. It never yields an
/// error: failures are handled (and logged) here.
pub struct Incoming<L> {
    listener: L,
    registry: Arc<Registry>,
    pause: Option<Pin<Box<Sleep>>>,
    next_pause: Duration,
    failures: Throttle,
}

impl<L: Accept> Incoming<L> {
    pub fn new(listener: L, registry: Arc<Registry>) -> Self {
        Self {
            listener,
            registry,
            pause: None,
            next_pause: BACKOFF.0,
            failures: Throttle::new(WARNING_PERIOD),
        }
    }
}

impl<L: Accept> Stream for Incoming<L> {
    type Item = io::Result<ConnIo<L::Io>>;

    fn poll_next(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        let this = self.get_mut();
        loop {
            if let Some(pause) = &mut this.pause {
                std::task::ready!(pause.as_mut().poll(cx));
                this.pause = None;
            }
            match std::task::ready!(this.listener.poll_accept(cx)) {
                Ok(io) => {
                    this.next_pause = BACKOFF.0;
                    if let Some(conn) = this.registry.admit(io) {
                        return Poll::Ready(Some(Ok(conn)));
                    }
                }
                Err(err) if out_of_resources(&err) => {
                    let pause = this.next_pause;
                    this.next_pause = (pause * 2).min(BACKOFF.1);
                    this.pause = Some(Box::pin(tokio::time::sleep(pause)));
                    if let Some(suppressed) = this.failures.admit() {
                        tracing::warn!(
                            %err,
                            ?pause,
                            suppressed,
                            "cannot accept connections; pausing. Raise the open-files limit \
                             (ulimit -n) or lower --max-connections"
                        );
                    }
                }
                // The client's failure (it reset the connection before accept, ...): next one.
                Err(err) => tracing::debug!(%err, "accept failed"),
            }
        }
    }
}

fn out_of_resources(err: &io::Error) -> bool {
    matches!(
        err.raw_os_error(),
        Some(libc::EMFILE | libc::ENFILE | libc::ENOBUFS | libc::ENOMEM)
    )
}
