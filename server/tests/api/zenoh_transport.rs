//! The contract over Zenoh (CONTRACT.md section 3), beside gRPC on the same
//! handler: queries from a loopback Zenoh peer get the same answers as gRPC
//! calls, and errors come back as reply errors carrying a `StreamError`.
//! Zenoh needs a multi-thread Tokio runtime, hence the test flavor.

use std::time::Duration;

use esa_server::pb;
use esa_server::zenoh_transport::{loopback_config, ZenohService};
use prost::Message;
use tonic::Code;
use zenoh::bytes::Encoding;
use zenoh::Session;

use crate::common::{self, config, create, get, probe, q_of, report, TestServer};

/// A gRPC server and a Zenoh service on one handler, and a peer connected to it.
pub(crate) struct Both {
    pub(crate) grpc: TestServer,
    zenoh: ZenohService,
    pub(crate) peer: Session,
}

pub(crate) async fn start_both(prefix: &str) -> Both {
    let grpc = common::start().await;
    let zenoh = ZenohService::start(
        grpc.handler.clone(),
        loopback_config(&[], &[]).expect("default config"),
        prefix,
    )
    .await
    .expect("zenoh service");
    let locators = zenoh.locators().await;
    assert!(
        !locators.is_empty() && locators.iter().all(|l| l.starts_with("tcp/127.0.0.1:")),
        "{locators:?}"
    );
    // The same quiet loopback peer, connecting instead of listening. Opening
    // waits for the service's declarations, so its queryables are known.
    let mut peer_config = loopback_config(&[], &locators).expect("peer config");
    peer_config
        .insert_json5("listen/endpoints", "[]")
        .expect("no listener");
    let peer = zenoh::open(peer_config).await.expect("peer session");
    Both { grpc, zenoh, peer }
}

impl Both {
    pub(crate) async fn stop(self) {
        self.peer.close().await.expect("close peer");
        self.zenoh.close().await.expect("close service");
        self.grpc.stop().await;
    }
}

/// Sends one query; `Ok` is the decoded response, `Err` the decoded `StreamError`.
pub(crate) async fn query<R: Message + Default>(
    peer: &Session,
    key: &str,
    request: &impl Message,
) -> Result<R, pb::StreamError> {
    let replies = peer
        .get(key)
        .payload(request.encode_to_vec())
        .timeout(Duration::from_secs(10))
        .await
        .expect("query sent");
    let reply = replies.recv_async().await.expect("one reply");
    match reply.result() {
        Ok(sample) => {
            assert_eq!(sample.encoding(), &Encoding::APPLICATION_PROTOBUF);
            Ok(R::decode(&*sample.payload().to_bytes()).expect("a response message"))
        }
        Err(err) => {
            assert_eq!(err.encoding(), &Encoding::APPLICATION_PROTOBUF);
            Err(pb::StreamError::decode(&*err.payload().to_bytes()).expect("a StreamError"))
        }
    }
}

fn probe_request(id: &str, step: u64, action: &[f64], start: bool) -> pb::ProbeRequest {
    pb::ProbeRequest {
        session_id: id.into(),
        step,
        action: action.to_vec(),
        episode_start: start,
        ..Default::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn identical_calls_give_identical_answers() {
    let both = start_both("esa/v1").await;
    let mut grpc = both.grpc.client().await;
    create(&mut grpc, "over-grpc", config(2)).await;
    let created: pb::CreateSessionResponse = query(
        &both.peer,
        "esa/v1/CreateSession",
        &pb::CreateSessionRequest {
            session_id: "over-zenoh".into(),
            config: Some(config(2)),
            progress: None,
        },
    )
    .await
    .unwrap();
    assert_eq!(created.session_id, "over-zenoh");

    let mut action = [0.0, 0.0];
    for step in 0..40 {
        let start = step == 0;
        let by_grpc = probe(&mut grpc, "over-grpc", step, &action, start)
            .await
            .unwrap();
        let request = probe_request("over-zenoh", step, &action, start);
        let by_zenoh: pb::ProbeResponse =
            query(&both.peer, "esa/v1/Probe", &request).await.unwrap();
        assert_eq!(by_grpc, by_zenoh);
        let q = q_of(&by_grpc.probe);
        let by_grpc = report(&mut grpc, "over-grpc", step, q).await.unwrap();
        let request = pb::ReportRequest {
            session_id: "over-zenoh".into(),
            step,
            q_value: q,
            ..Default::default()
        };
        let by_zenoh: pb::ReportResponse =
            query(&both.peer, "esa/v1/Report", &request).await.unwrap();
        assert_eq!(by_grpc, by_zenoh);
        action.copy_from_slice(&by_grpc.action);
    }
    let by_zenoh: pb::GetSessionResponse = query(
        &both.peer,
        "esa/v1/GetSession",
        &pb::GetSessionRequest {
            session_id: "over-zenoh".into(),
        },
    )
    .await
    .unwrap();
    assert_eq!(get(&mut grpc, "over-grpc").await.unwrap(), by_zenoh);
    both.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_created_over_grpc_is_usable_over_zenoh_and_stepstream() {
    let both = start_both("esa/v1").await;
    let mut grpc = both.grpc.client().await;
    create(&mut grpc, "shared", config(1)).await;
    let request = pb::StepStreamRequest {
        kind: Some(pb::step_stream_request::Kind::ProbeBatch(
            pb::ProbeBatchRequest {
                session_ids: vec!["shared".into()],
                steps: vec![0],
                actions: vec![0.3],
                episode_starts: vec![true],
                ..Default::default()
            },
        )),
    };
    let answer: pb::StepStreamResponse = query(&both.peer, "esa/v1/StepStream", &request)
        .await
        .unwrap();
    let Some(pb::step_stream_response::Kind::ProbeBatch(probes)) = answer.kind else {
        panic!("expected probes, got {answer:?}");
    };
    assert_eq!(probes.probes.len(), 1);
    assert!(get(&mut grpc, "shared").await.unwrap().probe_pending);
    // As on the gRPC stream, a failing StepStream message is answered in-band.
    let request = pb::StepStreamRequest {
        kind: Some(pb::step_stream_request::Kind::ReportBatch(
            pb::ReportBatchRequest {
                session_ids: vec!["shared".into()],
                steps: vec![7],
                q_values: vec![1.0],
                ..Default::default()
            },
        )),
    };
    let answer: pb::StepStreamResponse = query(&both.peer, "esa/v1/StepStream", &request)
        .await
        .unwrap();
    let Some(pb::step_stream_response::Kind::Error(error)) = answer.kind else {
        panic!("expected an in-band error, got {answer:?}");
    };
    assert_eq!(error.code, Code::FailedPrecondition as i32);
    both.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn errors_are_reply_errors_with_the_grpc_code_and_message() {
    let both = start_both("esa/v1").await;
    let mut grpc = both.grpc.client().await;
    let missing = pb::GetSessionRequest {
        session_id: "missing".into(),
    };
    let by_zenoh = query::<pb::GetSessionResponse>(&both.peer, "esa/v1/GetSession", &missing)
        .await
        .unwrap_err();
    let by_grpc = get(&mut grpc, "missing").await.unwrap_err();
    assert_eq!(by_zenoh.code, Code::NotFound as i32);
    assert_eq!(by_zenoh.message, by_grpc.message());

    create(&mut grpc, "strict", config(2)).await;
    let cases = [
        (
            probe_request("strict", 0, &[f64::NAN, 0.0], true),
            Code::InvalidArgument,
        ),
        (
            probe_request("strict", 0, &[0.0], true),
            Code::InvalidArgument,
        ),
        (
            probe_request("strict", 5, &[0.0, 0.0], false),
            Code::FailedPrecondition,
        ),
    ];
    for (request, code) in cases {
        let error = query::<pb::ProbeResponse>(&both.peer, "esa/v1/Probe", &request)
            .await
            .unwrap_err();
        assert_eq!(error.code, code as i32, "{}", error.message);
        assert!(!error.message.is_empty());
    }
    // Bytes that are no ProbeRequest at all.
    let replies = both
        .peer
        .get("esa/v1/Probe")
        .payload(vec![0xff, 0xff, 0xff])
        .await
        .unwrap();
    let reply = replies.recv_async().await.unwrap();
    let error =
        pb::StreamError::decode(&*reply.result().unwrap_err().payload().to_bytes()).unwrap();
    assert_eq!(error.code, Code::InvalidArgument as i32);
    // Nothing changed.
    assert!(!get(&mut grpc, "strict").await.unwrap().probe_pending);
    both.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_shard_prefix_moves_every_queryable() {
    let both = start_both("esa/v1/shard/1").await;
    let request = pb::GetSessionRequest {
        session_id: "x".into(),
    };
    let error = query::<pb::GetSessionResponse>(&both.peer, "esa/v1/shard/1/GetSession", &request)
        .await
        .unwrap_err();
    assert_eq!(error.code, Code::NotFound as i32);
    // Nobody serves the unsharded key: the query ends without a reply.
    let replies = both
        .peer
        .get("esa/v1/GetSession")
        .payload(request.encode_to_vec())
        .await
        .unwrap();
    assert!(replies.recv_async().await.is_err());
    both.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wildcard_prefixes_are_refused() {
    let handler = esa_server::EsaServer::builder().build().handler();
    let config = loopback_config(&[], &[]).unwrap();
    let refused = ZenohService::start(handler, config, "esa/*").await;
    assert!(refused.is_err_and(
        |err| matches!(err, esa_server::StartError::Config(message) if message.contains("prefix"))
    ));
}

/// Complete queryables: a query that only wants answers from servers
/// holding the whole key space (as routers and careful clients ask) still
/// reaches this one, so clients can ignore replies from incomplete peers.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn queryables_are_declared_complete() {
    let both = start_both("complete/esa/v1").await;
    let request = pb::GetSessionRequest {
        session_id: "none".into(),
    };
    let replies = both
        .peer
        .get("complete/esa/v1/GetSession")
        .payload(request.encode_to_vec())
        .target(zenoh::query::QueryTarget::AllComplete)
        .timeout(Duration::from_secs(5))
        .await
        .unwrap();
    let reply = replies
        .recv_async()
        .await
        .expect("a complete queryable answers");
    let error =
        pb::StreamError::decode(&*reply.result().expect_err("unknown id").payload().to_bytes())
            .unwrap();
    assert_eq!(error.code, Code::NotFound as i32);
    both.stop().await;
}
