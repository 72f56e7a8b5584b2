//! StepStream: one response per request, in order; errors in-band; the
//! stream stays open after an error.

use esa_server::pb;
use esa_server::pb::step_stream_request::Kind as Req;
use esa_server::pb::step_stream_response::Kind as Resp;
use esa_server::EsaServer;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Code, Streaming};

use crate::common::{config, create, get, start, start_with, Client};

pub(crate) struct Stream {
    requests: mpsc::Sender<pb::StepStreamRequest>,
    pub(crate) responses: Streaming<pb::StepStreamResponse>,
}

impl Stream {
    pub(crate) async fn open(client: &mut Client) -> Self {
        let (requests, rx) = mpsc::channel(16);
        let responses = client
            .step_stream(ReceiverStream::new(rx))
            .await
            .expect("open StepStream")
            .into_inner();
        Stream {
            requests,
            responses,
        }
    }

    pub(crate) async fn send(&self, kind: Option<Req>) {
        self.requests
            .send(pb::StepStreamRequest { kind })
            .await
            .expect("stream open");
    }

    pub(crate) async fn next(&mut self) -> Resp {
        self.responses
            .message()
            .await
            .expect("no transport error")
            .expect("a response")
            .kind
            .expect("a kind")
    }
}

fn probe_batch(ids: &[&str], step: u64, actions: Vec<f64>) -> Option<Req> {
    Some(Req::ProbeBatch(pb::ProbeBatchRequest {
        session_ids: ids.iter().map(|s| s.to_string()).collect(),
        steps: vec![step; ids.len()],
        actions,
        episode_starts: vec![],
        ..Default::default()
    }))
}

fn report_batch(ids: &[&str], steps: Vec<u64>, q_values: Vec<f64>) -> Option<Req> {
    Some(Req::ReportBatch(pb::ReportBatchRequest {
        session_ids: ids.iter().map(|s| s.to_string()).collect(),
        steps,
        q_values,
        ..Default::default()
    }))
}

#[tokio::test]
async fn stream_matches_the_batch_rpcs_and_survives_errors() {
    let server = start().await;
    let mut client = server.client().await;
    for id in ["s1", "s2", "u1", "u2"] {
        create(&mut client, id, config(2)).await;
    }
    let mut stream = Stream::open(&mut client).await;
    for step in 0..10 {
        let actions = vec![0.1, 0.2, 0.3 + step as f64 * 0.01, 0.4];
        stream
            .send(probe_batch(&["s1", "s2"], step, actions.clone()))
            .await;
        let Resp::ProbeBatch(streamed) = stream.next().await else {
            panic!("expected a probe_batch response");
        };
        let Some(Req::ProbeBatch(unary_request)) = probe_batch(&["u1", "u2"], step, actions) else {
            unreachable!()
        };
        let unary = client
            .probe_batch(unary_request)
            .await
            .unwrap()
            .into_inner();
        assert_eq!(streamed, unary);

        // A bad step first: answered in-band, nothing changes, stream stays open.
        stream
            .send(report_batch(
                &["s1", "s2"],
                vec![step, step + 1],
                vec![1.0, 2.0],
            ))
            .await;
        let Resp::Error(error) = stream.next().await else {
            panic!("expected an error response");
        };
        assert_eq!(error.code, Code::FailedPrecondition as i32);
        assert!(error.message.contains("item 1"), "{}", error.message);
        assert_eq!(error.item, Some(pb::BatchItem { index: 1 }));
        assert!(get(&mut client, "s1").await.unwrap().probe_pending);

        stream
            .send(report_batch(
                &["s1", "s2"],
                vec![step, step],
                vec![1.0, 2.0],
            ))
            .await;
        let Resp::ReportBatch(streamed) = stream.next().await else {
            panic!("expected a report_batch response");
        };
        let Some(Req::ReportBatch(unary_request)) =
            report_batch(&["u1", "u2"], vec![step, step], vec![1.0, 2.0])
        else {
            unreachable!()
        };
        let unary = client
            .report_batch(unary_request)
            .await
            .unwrap()
            .into_inner();
        assert_eq!(streamed, unary);
    }
    server.stop().await;
}

#[tokio::test]
async fn pipelined_requests_are_answered_in_order() {
    let server = start().await;
    let mut client = server.client().await;
    create(&mut client, "s", config(1)).await;
    let mut stream = Stream::open(&mut client).await;
    // Everything is sent before any response is read.
    stream.send(probe_batch(&["s"], 0, vec![0.5])).await;
    stream.send(None).await;
    stream.send(probe_batch(&["ghost"], 0, vec![0.5])).await;
    stream.send(report_batch(&["s"], vec![0], vec![1.0])).await;
    stream.send(probe_batch(&["s"], 1, vec![f64::NAN])).await;
    stream.send(probe_batch(&["s"], 1, vec![0.5])).await;

    assert!(matches!(stream.next().await, Resp::ProbeBatch(p) if p.probes.len() == 1));
    let Resp::Error(empty) = stream.next().await else {
        panic!("expected an error for an empty request");
    };
    assert_eq!(empty.code, Code::InvalidArgument as i32);
    assert!(empty.message.contains("kind"), "{}", empty.message);
    let Resp::Error(ghost) = stream.next().await else {
        panic!("expected NOT_FOUND");
    };
    assert_eq!(ghost.code, Code::NotFound as i32);
    assert!(ghost.message.contains("ghost"), "{}", ghost.message);
    assert!(matches!(stream.next().await, Resp::ReportBatch(r) if r.actions.len() == 1));
    let Resp::Error(nan) = stream.next().await else {
        panic!("expected INVALID_ARGUMENT");
    };
    assert_eq!(nan.code, Code::InvalidArgument as i32);
    assert!(matches!(stream.next().await, Resp::ProbeBatch(_)));

    // Closing the request side ends the response stream cleanly.
    drop(stream.requests);
    assert!(stream.responses.message().await.unwrap().is_none());
    server.stop().await;
}

#[tokio::test]
async fn shutdown_ends_open_streams_with_unavailable() {
    // A grace time far beyond the timeout below: only ending the stream
    // lets shutdown finish in time.
    let server =
        start_with(EsaServer::builder().shutdown_grace(std::time::Duration::from_secs(600))).await;
    let mut client = server.client().await;
    create(&mut client, "s", config(1)).await;
    let mut stream = Stream::open(&mut client).await;
    stream.send(probe_batch(&["s"], 0, vec![0.5])).await;
    assert!(matches!(stream.next().await, Resp::ProbeBatch(_)));

    let stopping = tokio::spawn(server.stop());
    let status = stream
        .responses
        .message()
        .await
        .expect_err("the stream ends with an error status");
    assert_eq!(status.code(), Code::Unavailable, "{status:?}");
    tokio::time::timeout(std::time::Duration::from_secs(30), stopping)
        .await
        .expect("shutdown finished without waiting for the grace time")
        .unwrap();
}
