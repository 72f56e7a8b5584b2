//! The tower layer in front of every gRPC call: the auth token, the memory held by request
//! messages, and a deadline for each request message once begun.
//!
//! tonic buffers a request message whole before decoding it, and reserves its announced length
//! up front, so a client that announces big messages and never finishes them holds that memory
//! for as long as its calls stay open. Here each call's body is watched as it arrives: a message
//! over `max_message_bytes` is refused from its 5-byte gRPC header (RESOURCE_EXHAUSTED, before any
//! of it is buffered), the bytes the server may hold for requests across all calls are budgeted,
//! and a message must arrive completely within `message_timeout` once begun.

use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use bytes::Bytes;
use http_body::{Frame, SizeHint};
use http_body_util::BodyExt as _;
use tokio::time::Sleep;
use tonic::body::Body;
use tonic::Status;
use tower::{Layer, Service};

use crate::connections::Connection;
use crate::error::{status, Error};
use crate::handler::EsaHandler;

/// A gRPC message header: a compression flag and a big-endian 4-byte length.
const HEADER_BYTES: usize = 5;

/// Calls to these services need no token: health says nothing about sessions, and launchers
/// probe it before they have a client configured.
const OPEN_PREFIX: &str = "/grpc.health.v1.Health/";

/// Limits on request messages; see the module documentation.
#[derive(Clone, Copy, Debug)]
pub struct RequestLimits {
    /// Largest request message.
    pub max_message_bytes: usize,
    /// Bytes of request messages held at once over all calls.
    pub max_request_memory: usize,
    /// How long one message may take to arrive once its first byte did.
    pub message_timeout: Duration,
}

/// Adds [`Guard`] around the gRPC services.
#[derive(Clone)]
pub struct GuardLayer(Arc<Shared>);

struct Shared {
    handler: Arc<EsaHandler>,
    limits: RequestLimits,
    /// Bytes currently reserved by request bodies.
    held: AtomicUsize,
}

impl GuardLayer {
    pub fn new(handler: Arc<EsaHandler>, limits: RequestLimits) -> Self {
        Self(Arc::new(Shared {
            handler,
            limits,
            held: AtomicUsize::new(0),
        }))
    }
}

impl<S> Layer<S> for GuardLayer {
    type Service = Guard<S>;

    fn layer(&self, inner: S) -> Guard<S> {
        Guard {
            inner,
            shared: Arc::clone(&self.0),
        }
    }
}

/// See the module documentation.
#[derive(Clone)]
pub struct Guard<S> {
    inner: S,
    shared: Arc<Shared>,
}

type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

impl<S, B> Service<http::Request<Body>> for Guard<S>
where
    S: Service<http::Request<Body>, Response = http::Response<B>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
    B: http_body::Body<Data = Bytes> + Send + 'static,
    B::Error: Into<tonic::codegen::StdError>,
{
    type Response = http::Response<Body>;
    type Error = S::Error;
    type Future = BoxFuture<Result<Self::Response, S::Error>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<Body>) -> Self::Future {
        if let Err(err) = self.shared.authorize(&request) {
            return Box::pin(std::future::ready(Ok(status(err).into_http())));
        }
        let call = request
            .extensions()
            .get::<Connection>()
            .map(Connection::call_started);
        let shared = Arc::clone(&self.shared);
        let response = self
            .inner
            .call(request.map(|body| Body::new(RequestBody::new(body, shared))));
        Box::pin(async move {
            let response = response.await?;
            // The call counts as in flight until its response body is dropped (a StepStream
            // lives in its response body).
            Ok(response.map(|body| {
                Body::new(body.map_frame(move |frame| {
                    let _in_flight = &call;
                    frame
                }))
            }))
        })
    }
}

impl Shared {
    fn authorize(&self, request: &http::Request<Body>) -> Result<(), Error> {
        if request.uri().path().starts_with(OPEN_PREFIX) {
            return Ok(());
        }
        let presented = request
            .headers()
            .get(http::header::AUTHORIZATION)
            .map(|value| {
                let value = value.as_bytes();
                value.strip_prefix(b"Bearer ").unwrap_or(value)
            });
        self.handler.authorize(presented)
    }

    fn reserve(&self, bytes: usize) -> Result<(), Error> {
        let max = self.limits.max_request_memory;
        self.held
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |held| {
                held.checked_add(bytes).filter(|&total| total <= max)
            })
            .map(drop)
            .map_err(|held| {
                Error::ResourceExhausted(format!(
                    "the server holds {held} bytes of request messages and this one needs \
                     {bytes} more (--max-request-memory {max}); retry shortly"
                ))
            })
    }

    fn release(&self, bytes: usize) {
        self.held.fetch_sub(bytes, Ordering::AcqRel);
    }
}

/// A call's request body, watched as it arrives (see the module documentation).
struct RequestBody {
    inner: Body,
    shared: Arc<Shared>,
    /// Bytes reserved for this call: the largest message announced on it so far, since tonic
    /// keeps a buffer that large until the call ends.
    held: usize,
    header: [u8; HEADER_BYTES],
    header_len: usize,
    /// Bytes of the current message still to come.
    remaining: usize,
    /// Armed while a message is incomplete.
    deadline: Option<Pin<Box<Sleep>>>,
}

impl RequestBody {
    fn new(inner: Body, shared: Arc<Shared>) -> Self {
        Self {
            inner,
            shared,
            held: 0,
            header: [0; HEADER_BYTES],
            header_len: 0,
            remaining: 0,
            deadline: None,
        }
    }

    /// Follows the gRPC framing through `data`, admitting each message from its header.
    fn track(&mut self, mut data: &[u8]) -> Result<(), Error> {
        let mut completed = false;
        while !data.is_empty() {
            if self.remaining > 0 {
                let n = self.remaining.min(data.len());
                self.remaining -= n;
                data = data.get(n..).unwrap_or_default();
            } else {
                let n = (HEADER_BYTES - self.header_len).min(data.len());
                if let (Some(to), Some(from)) = (
                    self.header.get_mut(self.header_len..self.header_len + n),
                    data.get(..n),
                ) {
                    to.copy_from_slice(from);
                }
                self.header_len += n;
                data = data.get(n..).unwrap_or_default();
                if self.header_len == HEADER_BYTES {
                    self.header_len = 0;
                    let [_, length @ ..] = self.header;
                    self.remaining = u32::from_be_bytes(length) as usize;
                    self.admit(self.remaining)?;
                }
            }
            completed |= self.remaining == 0 && self.header_len == 0;
        }
        // The deadline runs from a message's first byte: a message completed here ends its own,
        // and one begun here starts a new one.
        let incomplete = self.remaining > 0 || self.header_len > 0;
        if completed || !incomplete {
            self.deadline = None;
        }
        if incomplete && self.deadline.is_none() {
            let timeout = self.shared.limits.message_timeout;
            self.deadline = Some(Box::pin(tokio::time::sleep(timeout)));
        }
        Ok(())
    }

    fn admit(&mut self, len: usize) -> Result<(), Error> {
        let max = self.shared.limits.max_message_bytes;
        if len > max {
            return Err(Error::ResourceExhausted(format!(
                "request message of {len} bytes is over the server's limit of {max} bytes \
                 (--max-message-bytes)"
            )));
        }
        if len > self.held {
            self.shared.reserve(len - self.held)?;
            self.held = len;
        }
        Ok(())
    }
}

impl Drop for RequestBody {
    fn drop(&mut self) {
        self.shared.release(self.held);
    }
}

impl http_body::Body for RequestBody {
    type Data = Bytes;
    type Error = Status;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        let this = self.get_mut();
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(data) = frame.data_ref() {
                    if let Err(err) = this.track(data) {
                        return Poll::Ready(Some(Err(status(err))));
                    }
                }
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Pending => {
                let late = this
                    .deadline
                    .as_mut()
                    .is_some_and(|deadline| deadline.as_mut().poll(cx).is_ready());
                if !late {
                    return Poll::Pending;
                }
                let timeout = this.shared.limits.message_timeout;
                Poll::Ready(Some(Err(status(Error::DeadlineExceeded(format!(
                    "a request message was begun but not completed within {timeout:?}"
                ))))))
            }
            done => done,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}
