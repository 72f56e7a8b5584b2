//! Memory bounds: request messages are
//! limited in size, in what they decode to, in the memory they hold while
//! arriving and in how long they may take; sessions are budgeted in bytes.
//! Every size here is bounded, and every server is on loopback.

use std::time::{Duration, Instant};

use bytes::Bytes;
use esa_server::codec::{MAX_BATCH_ITEMS, MAX_REQUEST_BYTES};
use esa_server::pb;
use esa_server::store::session_cost;
use esa_server::EsaServer;
use prost::Message;
use tonic::Code;

use crate::common::{
    assert_error, call_raw, close, config, create, launch_tcp, proc_status_bytes, start_with,
    Client,
};
use crate::stream::Stream;

fn probe_batch_of(bytes: usize) -> pb::ProbeBatchRequest {
    pb::ProbeBatchRequest {
        session_ids: vec!["s".into()],
        steps: vec![0],
        actions: vec![0.0; bytes / 8],
        ..Default::default()
    }
}

#[tokio::test]
async fn an_oversize_message_is_resource_exhausted_on_every_rpc_kind() {
    let server = start_with(EsaServer::builder().max_message_bytes(64 << 10)).await;
    let mut client = server.client().await;
    let oversize = client.probe_batch(probe_batch_of(100 << 10)).await;
    assert_error(
        oversize,
        Code::ResourceExhausted,
        &["65536 bytes", "--max-message-bytes"],
    );

    let mut stream = Stream::open(&mut client).await;
    stream
        .send(Some(pb::step_stream_request::Kind::ProbeBatch(
            probe_batch_of(100 << 10),
        )))
        .await;
    let status = stream.responses.message().await.expect_err("stream ends");
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");

    // The server is unharmed: a legal request right after is served.
    create(&mut client, "after", config(1)).await;
    server.stop().await;
}

#[tokio::test]
async fn undecodable_requests_are_invalid_argument() {
    let server = start_with(EsaServer::builder()).await;
    for method in ["ProbeBatch", "Probe", "CreateSession", "StepStream"] {
        let answer = call_raw(&server.url(), method, b"\xff\xff\xff".to_vec()).await;
        assert_error(answer, Code::InvalidArgument, &["expected an encoded"]);
    }
    server.stop().await;
}

/// The default limit is the largest legal request; a ProbeBatch of that size
/// made of one-byte ids (about 8 million) is refused before it is decoded,
/// so the server's memory peaks near the message's size, not twenty times it.
#[tokio::test]
async fn a_batch_of_tiny_ids_is_refused_without_decoding_it() {
    let (mut child, url) = launch_tcp("", &[]).await;
    let id = pb::ProbeBatchRequest {
        session_ids: vec!["a".into()],
        ..Default::default()
    }
    .encode_to_vec();
    let hostile = id.repeat(MAX_REQUEST_BYTES / id.len());
    assert!(hostile.len() / id.len() > 100 * MAX_BATCH_ITEMS);

    let before = proc_status_bytes(child.id(), "VmRSS");
    let answer = call_raw(&url, "ProbeBatch", hostile).await;
    assert_error(answer, Code::InvalidArgument, &["session_ids", "65536"]);
    let peak = proc_status_bytes(child.id(), "VmHWM");
    let grown = peak.saturating_sub(before);
    assert!(
        grown < 4 * MAX_REQUEST_BYTES as u64,
        "peak RSS grew by {grown} bytes for a {MAX_REQUEST_BYTES}-byte request"
    );

    let over = call_raw(&url, "ProbeBatch", vec![0; MAX_REQUEST_BYTES + 1]).await;
    assert_error(over, Code::ResourceExhausted, &["--max-message-bytes"]);
    child.kill().unwrap();
    child.wait().unwrap();
}

/// A raw HTTP/2 client: gRPC clients never send half a message.
async fn h2_connect(url: &str) -> h2::client::SendRequest<Bytes> {
    let addr = url.trim_start_matches("http://");
    let tcp = tokio::net::TcpStream::connect(addr).await.expect("connect");
    let (client, connection) = h2::client::handshake(tcp).await.expect("h2 handshake");
    tokio::spawn(connection);
    client
}

/// Opens a StepStream and sends the first `sent` bytes of a message that
/// announces `announced` bytes; the returned stream must be kept to keep the
/// call open.
async fn start_half_message(
    client: &mut h2::client::SendRequest<Bytes>,
    announced: u32,
    sent: usize,
) -> (h2::client::ResponseFuture, h2::SendStream<Bytes>) {
    let request = http::Request::post("http://localhost/esa.v1.EsaService/StepStream")
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .body(())
        .unwrap();
    let mut ready = client.clone().ready().await.expect("ready");
    let (response, mut body) = ready.send_request(request, false).expect("send");
    let mut message = vec![0u8; 5 + sent];
    message[1..5].copy_from_slice(&announced.to_be_bytes());
    body.send_data(message.into(), false).expect("data");
    (response, body)
}

/// The gRPC status a call ended with (from its headers, or its trailers).
async fn grpc_code(response: h2::client::ResponseFuture) -> Code {
    let response = response.await.expect("response");
    let code = |headers: &http::HeaderMap| {
        headers
            .get("grpc-status")
            .map(|v| Code::from_bytes(v.as_bytes()))
    };
    if let Some(code) = code(response.headers()) {
        return code;
    }
    let mut body = response.into_body();
    while let Some(data) = body.data().await {
        let data = data.expect("data");
        let _ = body.flow_control().release_capacity(data.len());
    }
    let trailers = body.trailers().await.expect("trailers").expect("some");
    code(&trailers).expect("grpc-status")
}

/// Four StepStreams that each announce a 20 MB message and send a fifth of
/// it: three fit the request memory, the fourth is refused at once, and the
/// three end when their message is not complete within the request timeout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unfinished_messages_are_bounded_in_memory_and_in_time() {
    let (mut child, url) = launch_tcp(
        "",
        &["--request-timeout", "1", "--max-request-memory", "64MiB"],
    )
    .await;
    let mut client = h2_connect(&url).await;
    let before = proc_status_bytes(child.id(), "VmRSS");
    let started = Instant::now();
    let mut calls = Vec::new();
    for _ in 0..4 {
        calls.push(start_half_message(&mut client, 20_000_000, 4_000_000).await);
    }
    let mut codes = Vec::new();
    for (response, _body) in calls {
        let code = tokio::time::timeout(Duration::from_secs(10), grpc_code(response))
            .await
            .expect("the call ends");
        codes.push(code);
    }
    codes.sort_by_key(|code| *code as i32);
    assert_eq!(
        codes,
        [
            Code::DeadlineExceeded,
            Code::DeadlineExceeded,
            Code::DeadlineExceeded,
            Code::ResourceExhausted
        ]
    );
    assert!(started.elapsed() < Duration::from_secs(5));
    let grown = proc_status_bytes(child.id(), "VmHWM").saturating_sub(before);
    assert!(grown < 200 << 20, "peak RSS grew by {grown} bytes");

    // Memory was given back to the budget: a whole message now fits.
    let mut grpc = Client::connect(url).await.unwrap();
    create(&mut grpc, "after", config(1)).await;
    child.kill().unwrap();
    child.wait().unwrap();
}

#[tokio::test]
async fn the_session_memory_budget_is_resource_exhausted_and_freed_by_close() {
    let cost = session_cost("big-0", 4096);
    let server = start_with(EsaServer::builder().max_session_memory(3 * cost)).await;
    let mut client = server.client().await;
    for id in ["big-0", "big-1", "big-2"] {
        create(&mut client, id, config(4096)).await;
    }
    let fourth = client
        .create_session(pb::CreateSessionRequest {
            session_id: "big-3".into(),
            config: Some(config(4096)),
            progress: None,
        })
        .await;
    assert_error(
        fourth,
        Code::ResourceExhausted,
        &["--max-session-memory", &cost.to_string()],
    );
    // A small session still fits in what is left.
    assert!(session_cost("small", 1) < cost);
    close(&mut client, "big-0").await.unwrap();
    create(&mut client, "big-3", config(4096)).await;
    assert_eq!(server.handler.store().memory(), 3 * cost);
    server.stop().await;
}

/// Under a 1.5 GiB address-space limit, D = 4096 sessions are created until
/// the server answers RESOURCE_EXHAUSTED rather than abort (which would lose
/// every session); the server keeps serving, and its memory stays within the
/// limit.
#[tokio::test]
async fn big_sessions_under_a_memory_limit_end_in_resource_exhausted_not_an_abort() {
    let limit_kib = 1_536 * 1024;
    let (mut child, url) =
        launch_tcp(&format!("ulimit -v {limit_kib}"), &["--session-ttl", "0"]).await;
    let mut client = Client::connect(url).await.unwrap();
    let mut created = 0;
    let refused = loop {
        assert!(
            created < 10_000,
            "no limit reached after {created} sessions"
        );
        let answer = client
            .create_session(pb::CreateSessionRequest {
                session_id: format!("s{created}"),
                config: Some(config(4096)),
                progress: None,
            })
            .await;
        match answer {
            Ok(_) => created += 1,
            Err(status) => break status,
        }
    };
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(
        refused.message().contains("--max-session-memory"),
        "{refused:?}"
    );
    assert!(created > 1_000, "only {created} sessions fit");
    assert!(child.try_wait().unwrap().is_none(), "the server died");
    for id in ["s0", &format!("s{}", created - 1)] {
        assert!(crate::common::get(&mut client, id).await.is_ok());
    }
    let rss = proc_status_bytes(child.id(), "VmRSS");
    assert!(rss < limit_kib * 1024, "{rss}");
    // Every session is charged at least what it really takes.
    let charged = created as u64 * session_cost("s1000", 4096) as u64;
    assert!(rss < charged + (256 << 20), "RSS {rss}, charged {charged}");
    child.kill().unwrap();
    child.wait().unwrap();
}
