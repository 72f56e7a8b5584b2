//! Listeners and the services around EsaService: Unix sockets, health,
//! reflection, the metrics endpoint, and the encoded-message entry point
//! that non-gRPC transports use.

use std::net::SocketAddr;

use esa_server::error::{grpc_code, stream_error};
use esa_server::metrics_endpoint::serve_metrics;
use esa_server::pb;
use esa_server::{EsaServer, Listener, Rpc};
use hyper_util::rt::TokioIo;
use prost::Message;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tonic::transport::{Channel, Endpoint};
use tonic::Code;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;
use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
use tonic_reflection::pb::v1::ServerReflectionRequest;

use crate::common::{config, create, get, probe, report, spawn, start, Client, TestServer};

#[tokio::test]
async fn serves_on_a_unix_socket_and_removes_it_on_shutdown() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("esa.sock");
    let listener = Listener::unix(&path).unwrap();
    assert_eq!(
        listener.address().unwrap(),
        format!("unix:{}", path.display())
    );
    let (_handler, stop, task) = spawn(EsaServer::builder(), listener);

    // A second server on a live socket is refused.
    assert!(Listener::unix(&path).is_err());

    let socket = path.clone();
    let channel = Endpoint::from_static("http://localhost")
        .connect_with_connector(tower::service_fn(move |_| {
            let socket = socket.clone();
            async move {
                Ok::<_, std::io::Error>(TokioIo::new(
                    tokio::net::UnixStream::connect(socket).await?,
                ))
            }
        }))
        .await
        .unwrap();
    let mut client = Client::new(channel);
    create(&mut client, "uds", config(1)).await;
    let p = probe(&mut client, "uds", 0, &[0.5], true).await.unwrap();
    report(&mut client, "uds", 0, -p.probe[0]).await.unwrap();
    assert_eq!(get(&mut client, "uds").await.unwrap().step, 1);

    stop.send(()).unwrap();
    task.await.unwrap().unwrap();
    assert!(!path.exists(), "socket file left behind");
}

#[tokio::test]
async fn listen_errors_name_the_address_and_never_delete_files() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("precious.txt");
    std::fs::write(&file, "keep me").unwrap();
    let err = Listener::unix(&file).err().expect("not a socket");
    assert!(err.to_string().contains("not a socket"), "{err}");
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "keep me");

    let taken = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = taken.local_addr().unwrap();
    let err = Listener::tcp(addr).await.err().expect("address in use");
    assert!(err.to_string().contains(&addr.to_string()), "{err}");
}

#[tokio::test]
async fn a_stale_socket_file_is_replaced() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("stale.sock");
    // A listener that is dropped without cleanup leaves its file behind.
    drop(std::os::unix::net::UnixListener::bind(&path).unwrap());
    assert!(path.exists());
    assert!(Listener::unix(&path).is_ok());
}

async fn channel(server: &TestServer) -> Channel {
    Endpoint::from_shared(server.url())
        .unwrap()
        .connect()
        .await
        .unwrap()
}

#[tokio::test]
async fn health_reports_serving() {
    let server = start().await;
    let mut health = HealthClient::new(channel(&server).await);
    for service in ["", "esa.v1.EsaService"] {
        let status = health
            .check(HealthCheckRequest {
                service: service.into(),
            })
            .await
            .unwrap()
            .into_inner()
            .status;
        assert_eq!(status, ServingStatus::Serving as i32, "service {service:?}");
    }
    server.stop().await;
}

#[tokio::test]
async fn reflection_lists_and_describes_the_service() {
    let server = start().await;
    let mut reflection = ServerReflectionClient::new(channel(&server).await);
    let ask = |request: MessageRequest| ServerReflectionRequest {
        host: String::new(),
        message_request: Some(request),
    };
    let requests = tokio_stream::iter(vec![
        ask(MessageRequest::ListServices(String::new())),
        ask(MessageRequest::FileContainingSymbol(
            "esa.v1.EsaService".into(),
        )),
    ]);
    let mut responses = reflection
        .server_reflection_info(requests)
        .await
        .unwrap()
        .into_inner();

    let listed = responses.message().await.unwrap().unwrap().message_response;
    let Some(MessageResponse::ListServicesResponse(list)) = listed else {
        panic!("expected a service list, got {listed:?}");
    };
    let names: Vec<_> = list.service.iter().map(|s| s.name.as_str()).collect();
    assert!(names.contains(&"esa.v1.EsaService"), "{names:?}");
    assert!(names.contains(&"grpc.health.v1.Health"), "{names:?}");

    let described = responses.message().await.unwrap().unwrap().message_response;
    let Some(MessageResponse::FileDescriptorResponse(files)) = described else {
        panic!("expected a file descriptor, got {described:?}");
    };
    let file = prost_types::FileDescriptorProto::decode(files.file_descriptor_proto[0].as_slice())
        .unwrap();
    assert_eq!(file.package(), "esa.v1");
    assert!(file.service.iter().any(|s| s.name() == "EsaService"));
    server.stop().await;
}

/// Sends one HTTP/1.1 GET and returns the whole response.
async fn http_get(addr: SocketAddr, path: &str) -> String {
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    stream
        .write_all(
            format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").as_bytes(),
        )
        .await
        .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).await.unwrap();
    response
}

#[tokio::test]
async fn metrics_endpoint_serves_prometheus_text() {
    let server = start().await;
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let metrics_addr = listener.local_addr().unwrap();
    let metrics = tokio::spawn(serve_metrics(listener, server.handler.clone()));

    let mut client = server.client().await;
    create(&mut client, "m", config(1)).await;
    probe(&mut client, "m", 0, &[0.0], false).await.unwrap();
    probe(&mut client, "m", 9, &[0.0], false).await.unwrap_err();
    get(&mut client, "ghost").await.unwrap_err();

    let response = http_get(metrics_addr, "/metrics").await;
    assert!(response.starts_with("HTTP/1.1 200"), "{response}");
    assert!(
        response.contains("application/openmetrics-text"),
        "{response}"
    );
    for line in [
        "esa_sessions_live 1\n",
        "esa_requests_total{rpc=\"CreateSession\",code=\"OK\"} 1\n",
        "esa_requests_total{rpc=\"Probe\",code=\"OK\"} 1\n",
        "esa_requests_total{rpc=\"Probe\",code=\"FAILED_PRECONDITION\"} 1\n",
        "esa_requests_total{rpc=\"GetSession\",code=\"NOT_FOUND\"} 1\n",
        "# TYPE esa_request_duration_seconds histogram\n",
        "esa_request_duration_seconds_bucket{le=\"+Inf\",rpc=\"Probe\"} 2\n",
        "esa_request_duration_seconds_count{rpc=\"Probe\"} 2\n",
        "esa_request_duration_seconds_sum{rpc=\"Probe\"} ",
    ] {
        assert!(response.contains(line), "missing {line:?} in:\n{response}");
    }
    assert!(http_get(metrics_addr, "/other")
        .await
        .starts_with("HTTP/1.1 404"));
    metrics.abort();
    server.stop().await;
}

#[tokio::test]
async fn encoded_messages_reach_the_same_sessions() {
    let server = start().await;
    let handler = &server.handler;
    let created = handler
        .handle_encoded(
            Rpc::CreateSession,
            &pb::CreateSessionRequest {
                session_id: "z".into(),
                config: Some(config(1)),
                progress: None,
            }
            .encode_to_vec(),
        )
        .unwrap();
    assert_eq!(
        pb::CreateSessionResponse::decode(created.as_slice())
            .unwrap()
            .session_id,
        "z"
    );
    // A session created one way is visible the other way.
    let mut client = server.client().await;
    let p = probe(&mut client, "z", 0, &[0.25], false).await.unwrap();
    let reported = handler
        .handle_encoded(
            Rpc::Report,
            &pb::ReportRequest {
                session_id: "z".into(),
                step: 0,
                q_value: 1.0,
                ..Default::default()
            }
            .encode_to_vec(),
        )
        .unwrap();
    assert_eq!(
        pb::ReportResponse::decode(reported.as_slice())
            .unwrap()
            .action
            .len(),
        1
    );
    assert!(p.probe.len() == 1);

    let err = handler
        .handle_encoded(Rpc::Probe, b"\xff\xff\xff")
        .unwrap_err();
    assert_eq!(grpc_code(&err), Code::InvalidArgument);
    let err = handler
        .handle_encoded(
            Rpc::GetSession,
            &pb::GetSessionRequest {
                session_id: "nope".into(),
            }
            .encode_to_vec(),
        )
        .unwrap_err();
    assert_eq!(grpc_code(&err), Code::NotFound);
    assert_eq!(stream_error(err).code, Code::NotFound as i32);

    // StepStream messages answer errors in-band, as on the gRPC stream.
    let answer = handler
        .handle_encoded(
            Rpc::StepStream,
            &pb::StepStreamRequest { kind: None }.encode_to_vec(),
        )
        .unwrap();
    let answer = pb::StepStreamResponse::decode(answer.as_slice()).unwrap();
    assert!(matches!(
        answer.kind,
        Some(pb::step_stream_response::Kind::Error(pb::StreamError {
            code: 3,
            ..
        }))
    ));
    server.stop().await;
}
