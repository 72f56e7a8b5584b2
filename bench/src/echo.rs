//! The floor every gRPC latency row stands beside: a bare tonic server that answers each
//! unary call, and each message of a stream, with the bytes it was sent (no decoding, no
//! session, no update law), on the same kind of loopback socket, timed with the same loop;
//! a StepStream row stands beside the stream, for it pays no call set-up per message. A row's ratio to it says what
//! esa-server adds to the host's cheapest round trip, and holds across hosts where the
//! microseconds do not.

use std::convert::Infallible;

use bytes::{Buf, BufMut, Bytes};
use http::uri::PathAndQuery;
use tempfile::TempDir;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::body::Body;
use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
use tonic::transport::server::TcpIncoming;
use tonic::transport::{Channel, Server};
use tonic::{Request, Response, Status, Streaming};

use crate::driver::{channel, Api};
use crate::error::{Error, Result};
use crate::measure::Pair;
use crate::server_process::{Address, Socket};

const ECHO: &str = "/esa.bench.Echo/Echo";
const STREAM: &str = "/esa.bench.Echo/Stream";

/// Messages as the bytes on the wire: nothing is decoded or encoded.
#[derive(Clone, Copy, Debug, Default)]
struct RawCodec;

#[derive(Debug)]
struct RawBytes;

impl Encoder for RawBytes {
    type Item = Bytes;
    type Error = Status;

    fn encode(&mut self, item: Bytes, dst: &mut EncodeBuf<'_>) -> Result<(), Status> {
        dst.put(item);
        Ok(())
    }
}

impl Decoder for RawBytes {
    type Item = Bytes;
    type Error = Status;

    fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<Bytes>, Status> {
        Ok(Some(src.copy_to_bytes(src.remaining())))
    }
}

impl Codec for RawCodec {
    type Encode = Bytes;
    type Decode = Bytes;
    type Encoder = RawBytes;
    type Decoder = RawBytes;

    fn encoder(&mut self) -> RawBytes {
        RawBytes
    }

    fn decoder(&mut self) -> RawBytes {
        RawBytes
    }
}

/// An echo server on a runtime of its own (esa-server has a process of its own), so that
/// it does not share the load generator's threads; it stops when dropped.
pub struct EchoServer {
    address: Address,
    runtime: Option<tokio::runtime::Runtime>,
    _dir: Option<TempDir>,
}

impl EchoServer {
    /// Serves on `127.0.0.1:0` ([`Socket::Tcp`]) or a Unix socket in a temporary directory
    /// ([`Socket::Uds`]).
    pub fn start(socket: Socket) -> Result<Self> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()?;
        let _context = runtime.enter();
        let service = tower::service_fn(|request: http::Request<Body>| async move {
            let mut grpc = tonic::server::Grpc::new(RawCodec);
            Ok::<_, Infallible>(if request.uri().path() == STREAM {
                let echo = tower::service_fn(|call: Request<Streaming<Bytes>>| async move {
                    Ok::<_, Status>(Response::new(call.into_inner()))
                });
                grpc.streaming(echo, request).await
            } else {
                let echo = tower::service_fn(|call: Request<Bytes>| async move {
                    Ok::<_, Status>(Response::new(call.into_inner()))
                });
                grpc.unary(echo, request).await
            })
        });
        let (address, dir) = match socket {
            Socket::Tcp => {
                let incoming = TcpIncoming::bind(
                    "127.0.0.1:0"
                        .parse()
                        .map_err(|err| Error::Protocol(format!("loopback address: {err}")))?,
                )?
                .with_nodelay(Some(true));
                let address = Address::Tcp(incoming.local_addr()?);
                runtime.spawn(Server::builder().serve_with_incoming(service, incoming));
                (address, None)
            }
            Socket::Uds => {
                let dir = tempfile::tempdir()?;
                let path = dir.path().join("echo.sock");
                let listener = tokio::net::UnixListener::bind(&path)?;
                let incoming = tokio_stream::wrappers::UnixListenerStream::new(listener);
                runtime.spawn(Server::builder().serve_with_incoming(service, incoming));
                (Address::Unix(path), Some(dir))
            }
            Socket::Zenoh => {
                return Err(Error::Protocol("no gRPC echo over Zenoh".into()));
            }
        };
        Ok(Self {
            address,
            runtime: Some(runtime),
            _dir: dir,
        })
    }

    /// Where it listens.
    pub fn address(&self) -> &Address {
        &self.address
    }
}

impl Drop for EchoServer {
    fn drop(&mut self) {
        // Inside the load generator's runtime a blocking shutdown would panic.
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_background();
        }
    }
}

/// Two echoes in turn, carrying a row's probe and report requests' sizes: two unary calls,
/// or two messages on one stream for a StepStream row.
pub struct EchoPair {
    grpc: tonic::client::Grpc<Channel>,
    requests: [Bytes; 2],
    stream: Option<(mpsc::Sender<Bytes>, Streaming<Bytes>)>,
}

impl EchoPair {
    /// A new connection to `server` for requests of `sizes` bytes, as `api` sends them.
    pub async fn connect(server: &EchoServer, sizes: (usize, usize), api: Api) -> Result<Self> {
        let mut grpc = tonic::client::Grpc::new(channel(server.address()).await?);
        let requests = [sizes.0, sizes.1].map(|size| Bytes::from(vec![0x2a; size]));
        let mut stream = None;
        if api == Api::Stream {
            // One message in flight at a time, as the StepStream rows send theirs.
            let (sender, receiver) = mpsc::channel(1);
            ready(&mut grpc).await?;
            let path = PathAndQuery::from_static(STREAM);
            let request = Request::new(ReceiverStream::new(receiver));
            let answers = grpc.streaming(request, path, RawCodec).await?.into_inner();
            stream = Some((sender, answers));
        }
        Ok(Self {
            grpc,
            requests,
            stream,
        })
    }
}

async fn ready(grpc: &mut tonic::client::Grpc<Channel>) -> Result<()> {
    grpc.ready()
        .await
        .map_err(|err| Error::Protocol(format!("echo channel: {err}")))
}

impl Pair for EchoPair {
    async fn pair(&mut self) -> Result<()> {
        for request in &self.requests {
            let answer = match &mut self.stream {
                Some((sender, answers)) => {
                    let closed = || Error::Protocol("echo stream closed".into());
                    sender.send(request.clone()).await.map_err(|_| closed())?;
                    answers.message().await?.ok_or_else(closed)?
                }
                None => {
                    ready(&mut self.grpc).await?;
                    let path = PathAndQuery::from_static(ECHO);
                    let call = Request::new(request.clone());
                    self.grpc.unary(call, path, RawCodec).await?.into_inner()
                }
            };
            if answer.len() != request.len() {
                return Err(Error::Protocol("the echo changed the message".into()));
            }
        }
        Ok(())
    }
}
