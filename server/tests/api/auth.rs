//! Access control: the optional shared-secret token
//! over gRPC and Zenoh, the private Unix socket, and complete queryables.

use std::os::unix::fs::PermissionsExt as _;

use esa_server::pb;
use esa_server::pb::esa_service_client::EsaServiceClient;
#[cfg(feature = "zenoh")]
use esa_server::zenoh_transport::{loopback_config, ZenohService};
use esa_server::{EsaServer, Listener};
use tonic::metadata::MetadataValue;
use tonic::service::Interceptor;
use tonic::transport::Channel;
use tonic::{Code, Request, Status};
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

use crate::common::{assert_error, config, start_with};

const TOKEN: &str = "0123456789abcdef-s3cret";

#[derive(Clone)]
struct Bearer(Option<&'static str>);

impl Interceptor for Bearer {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(token) = self.0 {
            let value = MetadataValue::try_from(format!("Bearer {token}")).expect("ascii");
            request.metadata_mut().insert("authorization", value);
        }
        Ok(request)
    }
}

async fn client_with(
    url: String,
    token: Option<&'static str>,
) -> EsaServiceClient<tonic::service::interceptor::InterceptedService<Channel, Bearer>> {
    let channel = Channel::from_shared(url).unwrap().connect().await.unwrap();
    EsaServiceClient::with_interceptor(channel, Bearer(token))
}

fn create_request(id: &str) -> pb::CreateSessionRequest {
    pb::CreateSessionRequest {
        session_id: id.into(),
        config: Some(config(1)),
        progress: None,
    }
}

#[tokio::test]
async fn with_a_token_only_requests_that_present_it_are_served() {
    let server = start_with(EsaServer::builder().auth_token(TOKEN)).await;
    for (token, needle) in [
        (None, "requires an auth token"),
        (Some("wrong"), "does not match"),
    ] {
        let mut stranger = client_with(server.url(), token).await;
        assert_error(
            stranger.create_session(create_request("s")).await,
            Code::Unauthenticated,
            &[needle],
        );
        assert!(stranger.step_stream(tokio_stream::empty()).await.is_err());
    }
    let mut owner = client_with(server.url(), Some(TOKEN)).await;
    owner.create_session(create_request("s")).await.unwrap();
    let probe = pb::StepStreamRequest {
        kind: Some(pb::step_stream_request::Kind::ProbeBatch(
            pb::ProbeBatchRequest {
                session_ids: vec!["s".into()],
                steps: vec![0],
                actions: vec![0.5],
                ..Default::default()
            },
        )),
    };
    let mut responses = owner
        .step_stream(tokio_stream::iter([probe]))
        .await
        .unwrap()
        .into_inner();
    let answer = responses.message().await.unwrap().and_then(|r| r.kind);
    assert!(
        matches!(answer, Some(pb::step_stream_response::Kind::ProbeBatch(_))),
        "{answer:?}"
    );

    // Health stays open, so launchers can wait for the server without the token.
    let channel = Channel::from_shared(server.url())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let health = HealthClient::new(channel)
        .check(HealthCheckRequest::default())
        .await;
    assert!(health.is_ok(), "{health:?}");
    server.stop().await;
}

#[cfg(feature = "zenoh")]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn over_zenoh_the_token_is_the_query_attachment() {
    use prost::Message as _;
    use std::time::Duration;

    let server = start_with(EsaServer::builder().auth_token(TOKEN)).await;
    let zenoh = ZenohService::start(
        server.handler.clone(),
        loopback_config(&[], &[]).unwrap(),
        "auth/esa/v1",
    )
    .await
    .unwrap();
    let mut peer_config = loopback_config(&[], &zenoh.locators().await).unwrap();
    peer_config.insert_json5("listen/endpoints", "[]").unwrap();
    let peer = zenoh::open(peer_config).await.unwrap();
    let request = create_request("z").encode_to_vec();
    for attachment in [None, Some("wrong"), Some(TOKEN)] {
        let mut get = peer
            .get("auth/esa/v1/CreateSession")
            .payload(request.clone())
            .timeout(Duration::from_secs(5));
        if let Some(token) = attachment {
            get = get.attachment(token);
        }
        let reply = get.await.unwrap().recv_async().await.expect("a reply");
        match (attachment, reply.result()) {
            (Some(TOKEN), Ok(sample)) => {
                let created =
                    pb::CreateSessionResponse::decode(&*sample.payload().to_bytes()).unwrap();
                assert_eq!(created.session_id, "z");
            }
            (Some(TOKEN), Err(err)) => panic!("refused with the token: {err:?}"),
            (_, Ok(_)) => panic!("served without the token ({attachment:?})"),
            (_, Err(err)) => {
                let error = pb::StreamError::decode(&*err.payload().to_bytes()).unwrap();
                assert_eq!(error.code, Code::Unauthenticated as i32, "{error:?}");
            }
        }
    }
    peer.close().await.unwrap();
    zenoh.close().await.unwrap();
    server.stop().await;
}

#[tokio::test]
async fn the_unix_socket_is_private_unless_told_otherwise() {
    let dir = tempfile::tempdir().unwrap();
    let mode =
        |path: &std::path::Path| std::fs::metadata(path).unwrap().permissions().mode() & 0o777;
    let private = dir.path().join("private.sock");
    let _listener = Listener::unix(&private).unwrap();
    assert_eq!(mode(&private), 0o600);
    let shared = dir.path().join("group.sock");
    let _listener = Listener::unix_with_mode(&shared, 0o660).unwrap();
    assert_eq!(mode(&shared), 0o660);
}
