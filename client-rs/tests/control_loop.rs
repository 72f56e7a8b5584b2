//! The control-loop example against a spawned esa-server, and the client's typed errors.

#[allow(dead_code)]
#[path = "../examples/control_loop.rs"]
mod example;

use esa_client::{pb, Client, Kind, Options};

fn server() -> Option<example::Server> {
    if example::server_binary().is_none() {
        eprintln!("skipped: no esa-server (set ESA_SERVER_BIN or build target/release)");
        return None;
    }
    Some(example::Server::spawn().expect("esa-server starts"))
}

/// A session of one action dimension.
fn one_dim_config() -> pb::SessionConfig {
    pb::SessionConfig {
        action_dim: 1,
        dt: 0.04,
        amplitude: vec![0.2],
        frequency: vec![31.4],
        learning_rate: vec![0.5],
        ..Default::default()
    }
}

#[tokio::test]
async fn the_example_moves_the_action_toward_the_critics_best() {
    let Some(server) = server() else { return };
    let mean = example::run(&server.address, 300).await.unwrap();
    assert!(
        mean > 0.2,
        "ESA executed {mean}, expected a shift toward 0.7"
    );
}

#[tokio::test]
async fn errors_are_typed_with_the_batch_item() {
    let Some(server) = server() else { return };
    let client = Client::connect(&server.address, Options::default())
        .await
        .unwrap();
    assert!(
        client
            .healthy(std::time::Duration::from_secs(5), true)
            .await
    );
    let err = client.end_episode("nobody").await.unwrap_err();
    assert_eq!(err.kind(), Kind::SessionNotFound);

    let config = one_dim_config();
    let id = client.create_session("mine", config.clone()).await.unwrap();
    // The same id and config again is a safe retry; another config is a conflict.
    assert_eq!(
        client.create_session("mine", config.clone()).await.unwrap(),
        id
    );
    let changed = pb::SessionConfig {
        amplitude: vec![0.3],
        ..config.clone()
    };
    let err = client.create_session("mine", changed).await.unwrap_err();
    assert_eq!(err.kind(), Kind::SessionAlreadyExists);
    let other = client.create_session("", config).await.unwrap();

    // The second item names no session: the whole batch is refused for item 1.
    let request = pb::ProbeBatchRequest {
        session_ids: vec![id.clone(), "nobody".into()],
        steps: vec![0, 0],
        actions: vec![0.0, 0.0],
        episode_starts: vec![true, true],
        action_scales: vec![],
    };
    let err = client.probe_batch(request.clone()).await.unwrap_err();
    assert_eq!(err.kind(), Kind::SessionNotFound, "{err}");
    assert_eq!(err.index(), Some(1), "{err}");
    // The same on a StepStream, which stays open after the refusal.
    let mut stream = client.step_stream().await.unwrap();
    let streamed = stream.probe_batch(request).await.unwrap_err();
    assert_eq!(streamed.kind(), Kind::SessionNotFound);
    assert_eq!(streamed.index(), Some(1));
    // A batch-level error names no item.
    let short = pb::ProbeBatchRequest {
        session_ids: vec![id.clone(), other.clone()],
        steps: vec![0, 0],
        actions: vec![0.0, 0.0, 0.0],
        episode_starts: vec![true, true],
        action_scales: vec![],
    };
    let err = client.probe_batch(short).await.unwrap_err();
    assert_eq!(err.kind(), Kind::InvalidArgument);
    assert_eq!(err.index(), None);
    let ok = pb::ProbeBatchRequest {
        session_ids: vec![id.clone(), other],
        steps: vec![0, 0],
        actions: vec![0.0, 0.0],
        episode_starts: vec![true, true],
        action_scales: vec![],
    };
    assert_eq!(stream.probe_batch(ok).await.unwrap().probes.len(), 2);

    // A report for the wrong step: FAILED_PRECONDITION.
    let err = client
        .report(pb::ReportRequest {
            session_id: id,
            step: 5,
            q_value: 0.0,
            q_reference: None,
        })
        .await
        .unwrap_err();
    assert_eq!(err.kind(), Kind::StepMismatch);
}

#[tokio::test]
async fn no_server_is_unavailable_and_retryable() {
    let client = Client::connect_lazy("127.0.0.1:9", Options::default()).unwrap();
    let err = client.end_episode("x").await.unwrap_err();
    assert_eq!(err.kind(), Kind::ServerUnavailable, "{err}");
    assert!(err.is_retryable());
}

#[test]
fn the_blocking_client_makes_the_same_calls() {
    let Some(server) = server() else { return };
    let client =
        esa_client::blocking::Client::connect(&server.address, Options::default()).unwrap();
    assert!(client.healthy(std::time::Duration::from_secs(5), true));
    let err = client.close_session("nobody".into()).unwrap_err();
    assert_eq!(err.kind(), Kind::SessionNotFound);
}

#[tokio::test]
async fn a_pipelined_pair_fails_with_its_report_and_the_stream_stays_in_step() {
    let Some(server) = server() else { return };
    let client = Client::connect(&server.address, Options::default())
        .await
        .unwrap();
    let config = one_dim_config();
    let ids = vec![
        client.create_session("", config.clone()).await.unwrap(),
        client.create_session("", config).await.unwrap(),
    ];
    let probe = |step: u64| pb::ProbeBatchRequest {
        session_ids: ids.clone(),
        steps: vec![step; 2],
        actions: vec![0.1, -0.1],
        episode_starts: vec![step == 0; 2],
        action_scales: vec![],
    };
    let report = |q_values: Vec<f64>| pb::ReportBatchRequest {
        session_ids: ids.clone(),
        steps: vec![0, 0],
        q_values,
        q_references: vec![],
    };
    let mut stream = client.step_stream().await.unwrap();
    stream.probe_batch(probe(0)).await.unwrap();
    // Item 1's Q is not finite: the report is refused, and so the probe of step 1, which
    // would need it; the report's error is the pair's.
    let err = stream
        .report_then_probe(report(vec![1.0, f64::NAN]), probe(1))
        .await
        .unwrap_err();
    assert_eq!(err.kind(), Kind::InvalidArgument, "{err}");
    assert_eq!(err.index(), Some(1), "{err}");
    assert_eq!(stream.pending(), 0);
    // Both answers were read: the same stream carries the repaired pair.
    let answer = stream
        .report_then_probe(report(vec![1.0, 2.0]), probe(1))
        .await
        .unwrap();
    assert_eq!(answer.probes.len(), 2);
    let state = client.get_session(ids[1].clone()).await.unwrap();
    assert_eq!(state.step, 1, "{state:?}");
}

#[tokio::test]
async fn whole_steps_answer_with_shifts_and_a_refused_one_changes_nothing() {
    let Some(server) = server() else { return };
    let client = Client::connect(&server.address, Options::default())
        .await
        .unwrap();
    let id = client.create_session("", one_dim_config()).await.unwrap();
    let probe = |step: u64| pb::ProbeBatchRequest {
        session_ids: vec![id.clone()],
        steps: vec![step],
        actions: vec![0.1],
        episode_starts: vec![step == 0],
        action_scales: vec![],
    };
    let mut stream = client.step_stream().await.unwrap();
    let linear = stream
        .step_linear_batch(pb::StepLinearBatchRequest {
            probe: Some(probe(0)),
            critic_gains: vec![1.0],
            critic_offsets: vec![0.0],
            paired: false,
        })
        .await
        .unwrap();
    assert_eq!((linear.probes.len(), linear.shifts.len()), (1, 1));
    let given = |q_values: Vec<f64>| pb::StepBatchRequest {
        probe: Some(probe(1)),
        q_values,
        q_references: vec![],
    };
    let err = stream.step_batch(given(vec![f64::NAN])).await.unwrap_err();
    assert_eq!(err.kind(), Kind::InvalidArgument, "{err}");
    assert_eq!(err.index(), Some(0), "{err}");
    let state = client.get_session(id.clone()).await.unwrap();
    assert_eq!((state.step, state.shift), (1, linear.shifts));
    let answer = stream.step_batch(given(vec![0.5])).await.unwrap();
    assert_eq!(answer.shifts, client.get_session(id).await.unwrap().shift);
}
