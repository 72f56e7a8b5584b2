//! Every error case of the CONTRACT.md table, each with its code, a message
//! that names what to fix, and no change to the session involved.

use esa_server::pb;
use tonic::Code;

use crate::common::{
    assert_error, close, config, create, end_episode, get, probe, report, start, Client,
};

async fn create_result(
    client: &mut Client,
    id: &str,
    config: Option<pb::SessionConfig>,
) -> Result<tonic::Response<pb::CreateSessionResponse>, tonic::Status> {
    client
        .create_session(pb::CreateSessionRequest {
            session_id: id.into(),
            config,
            progress: None,
        })
        .await
}

#[tokio::test]
async fn unknown_session_is_not_found_on_every_rpc() {
    let server = start().await;
    let mut client = server.client().await;
    let id = "no-such-session";
    assert_error(
        probe(&mut client, id, 0, &[0.0], false).await,
        Code::NotFound,
        &[id],
    );
    assert_error(report(&mut client, id, 0, 0.0).await, Code::NotFound, &[id]);
    assert_error(get(&mut client, id).await, Code::NotFound, &[id]);
    assert_error(end_episode(&mut client, id).await, Code::NotFound, &[id]);
    assert_error(close(&mut client, id).await, Code::NotFound, &[id]);
    assert_error(
        client
            .probe_batch(pb::ProbeBatchRequest {
                session_ids: vec![id.into()],
                steps: vec![0],
                actions: vec![0.0],
                episode_starts: vec![],
                ..Default::default()
            })
            .await,
        Code::NotFound,
        &["item 0", id],
    );
    assert_error(
        client
            .report_batch(pb::ReportBatchRequest {
                session_ids: vec![id.into()],
                steps: vec![0],
                q_values: vec![0.0],
                ..Default::default()
            })
            .await,
        Code::NotFound,
        &["item 0", id],
    );
    server.stop().await;
}

#[tokio::test]
async fn bad_configs_are_invalid_argument_and_create_nothing() {
    let server = start().await;
    let mut client = server.client().await;
    let cases: Vec<(pb::SessionConfig, &str)> = vec![
        (
            pb::SessionConfig {
                action_dim: 0,
                ..config(1)
            },
            "action_dim",
        ),
        (
            pb::SessionConfig {
                action_dim: 4097,
                ..config(1)
            },
            "action_dim",
        ),
        (
            pb::SessionConfig {
                dt: 0.0,
                ..config(1)
            },
            "dt",
        ),
        (
            pb::SessionConfig {
                dt: f64::NAN,
                ..config(1)
            },
            "dt",
        ),
        (
            pb::SessionConfig {
                dt: f64::INFINITY,
                ..config(1)
            },
            "dt",
        ),
        (
            pb::SessionConfig {
                amplitude: vec![],
                ..config(1)
            },
            "amplitude",
        ),
        (
            pb::SessionConfig {
                amplitude: vec![-0.1],
                ..config(1)
            },
            "amplitude",
        ),
        (
            pb::SessionConfig {
                amplitude: vec![f64::NAN],
                ..config(1)
            },
            "amplitude",
        ),
        (
            pb::SessionConfig {
                amplitude: vec![0.1, 0.2, 0.3],
                ..config(2)
            },
            "amplitude",
        ),
        (
            pb::SessionConfig {
                frequency: vec![400.0],
                ..config(1)
            },
            "Nyquist",
        ),
        (
            pb::SessionConfig {
                frequency: vec![f64::INFINITY],
                ..config(1)
            },
            "frequency",
        ),
        (
            pb::SessionConfig {
                frequency: vec![0.0],
                ..config(1)
            },
            "frequency",
        ),
        (
            pb::SessionConfig {
                learning_rate: vec![f64::NAN],
                ..config(1)
            },
            "learning_rate",
        ),
        (
            pb::SessionConfig {
                highpass_cutoff: Some(f64::NAN),
                ..config(1)
            },
            "highpass_cutoff",
        ),
        (
            pb::SessionConfig {
                highpass_cutoff: Some(0.0),
                ..config(1)
            },
            "highpass_cutoff",
        ),
        (
            pb::SessionConfig {
                action_low: vec![1.0],
                action_high: vec![1.0],
                ..config(1)
            },
            "action_low",
        ),
        (
            pb::SessionConfig {
                action_low: vec![f64::NAN],
                ..config(1)
            },
            "action_low",
        ),
        (
            pb::SessionConfig {
                action_low: vec![f64::INFINITY],
                ..config(1)
            },
            "action_low",
        ),
        (
            pb::SessionConfig {
                action_high: vec![f64::NEG_INFINITY],
                ..config(1)
            },
            "action_high",
        ),
        // CONTRACT: inf anywhere in a request is INVALID_ARGUMENT, even on a bound's open side.
        (
            pb::SessionConfig {
                action_low: vec![f64::NEG_INFINITY],
                ..config(1)
            },
            "action_low",
        ),
        (
            pb::SessionConfig {
                action_high: vec![f64::INFINITY],
                ..config(1)
            },
            "action_high",
        ),
        (
            pb::SessionConfig {
                shift_limit: Some(f64::INFINITY),
                ..config(1)
            },
            "shift_limit",
        ),
        (
            pb::SessionConfig {
                shift_limit: Some(-1.0),
                ..config(1)
            },
            "shift_limit",
        ),
        (
            pb::SessionConfig {
                lr_decay: Some(f64::NAN),
                ..config(1)
            },
            "lr_decay",
        ),
        (
            pb::SessionConfig {
                lr_decay: Some(1.5),
                ..config(1)
            },
            "lr_decay",
        ),
        (
            pb::SessionConfig {
                lr_decay: Some(0.0),
                ..config(1)
            },
            "lr_decay",
        ),
    ];
    for (i, (cfg, field)) in cases.into_iter().enumerate() {
        let id = format!("bad-{i}");
        assert_error(
            create_result(&mut client, &id, Some(cfg)).await,
            Code::InvalidArgument,
            &[field],
        );
        assert_error(get(&mut client, &id).await, Code::NotFound, &[]);
    }
    assert_error(
        create_result(&mut client, "no-config", None).await,
        Code::InvalidArgument,
        &["config"],
    );
    assert_eq!(server.handler.store().live(), 0);
    server.stop().await;
}

#[tokio::test]
async fn session_ids_must_be_1_to_128_bytes() {
    let server = start().await;
    let mut client = server.client().await;
    let longest = "x".repeat(128);
    assert_eq!(create(&mut client, &longest, config(1)).await, longest);
    let too_long = "y".repeat(129);
    assert_error(
        create_result(&mut client, &too_long, Some(config(1))).await,
        Code::InvalidArgument,
        &["session_id", "128", "129"],
    );
    // Multi-byte characters count in bytes: 43 x 3 = 129.
    assert_error(
        create_result(&mut client, &"€".repeat(43), Some(config(1))).await,
        Code::InvalidArgument,
        &["session_id"],
    );
    assert_error(
        probe(&mut client, &too_long, 0, &[0.0], false).await,
        Code::InvalidArgument,
        &["session_id"],
    );
    assert_error(
        probe(&mut client, "", 0, &[0.0], false).await,
        Code::InvalidArgument,
        &["session_id", "got 0"],
    );
    assert_error(
        get(&mut client, "").await,
        Code::InvalidArgument,
        &["session_id"],
    );
    assert_error(
        close(&mut client, "").await,
        Code::InvalidArgument,
        &["session_id"],
    );
    assert_error(
        client
            .probe_batch(pb::ProbeBatchRequest {
                session_ids: vec![longest.clone(), String::new()],
                steps: vec![0, 0],
                actions: vec![0.0, 0.0],
                episode_starts: vec![],
                ..Default::default()
            })
            .await,
        Code::InvalidArgument,
        &["item 1", "session_id"],
    );
    server.stop().await;
}

#[tokio::test]
async fn bad_step_requests_fail_and_change_nothing() {
    let server = start().await;
    let mut client = server.client().await;
    create(&mut client, "s", config(2)).await;
    probe(&mut client, "s", 0, &[0.1, 0.2], false)
        .await
        .unwrap();
    report(&mut client, "s", 0, 1.0).await.unwrap();
    let before = get(&mut client, "s").await.unwrap();

    // FAILED_PRECONDITION: the message names the expected step.
    assert_error(
        probe(&mut client, "s", 5, &[0.1, 0.2], false).await,
        Code::FailedPrecondition,
        &["expected step 1", "got 5"],
    );
    assert_error(
        report(&mut client, "s", 1, 1.0).await,
        Code::FailedPrecondition,
        &["Probe before Report"],
    );
    // INVALID_ARGUMENT: wrong length, NaN or infinity anywhere.
    assert_error(
        probe(&mut client, "s", 1, &[0.1], false).await,
        Code::InvalidArgument,
        &["action", "2"],
    );
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        assert_error(
            probe(&mut client, "s", 1, &[0.1, bad], false).await,
            Code::InvalidArgument,
            &["action"],
        );
    }
    assert_eq!(get(&mut client, "s").await.unwrap(), before);

    probe(&mut client, "s", 1, &[0.1, 0.2], false)
        .await
        .unwrap();
    let pending = get(&mut client, "s").await.unwrap();
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        assert_error(
            report(&mut client, "s", 1, bad).await,
            Code::InvalidArgument,
            &["q_value"],
        );
    }
    assert_error(
        report(&mut client, "s", 2, 1.0).await,
        Code::FailedPrecondition,
        &["expected step 1"],
    );
    assert_eq!(get(&mut client, "s").await.unwrap(), pending);
    report(&mut client, "s", 1, 1.0).await.unwrap();
    server.stop().await;
}

#[tokio::test]
async fn malformed_batches_are_invalid_argument_naming_the_field() {
    let server = start().await;
    let mut client = server.client().await;
    create(&mut client, "a", config(1)).await;
    create(&mut client, "b", config(2)).await;
    let ids = || vec!["a".to_string(), "b".to_string()];

    let probe_batch =
        |steps: Vec<u64>, actions: Vec<f64>, starts: Vec<bool>| pb::ProbeBatchRequest {
            session_ids: ids(),
            steps,
            actions,
            episode_starts: starts,
            ..Default::default()
        };
    let cases = [
        (
            probe_batch(vec![0], vec![0.0; 3], vec![]),
            vec!["steps", "expected 2", "got 1"],
        ),
        (
            probe_batch(vec![0, 0], vec![0.0; 2], vec![]),
            vec!["actions", "expected 3", "got 2"],
        ),
        (
            probe_batch(vec![0, 0], vec![0.0; 4], vec![]),
            vec!["actions", "expected 3", "got 4"],
        ),
        (
            probe_batch(vec![0, 0], vec![0.0; 3], vec![true]),
            vec!["episode_starts", "got 1"],
        ),
        (
            probe_batch(vec![0, 0], vec![0.0, 0.0, f64::NAN], vec![]),
            vec!["item 1", "action"],
        ),
        (
            pb::ProbeBatchRequest::default(),
            vec!["session_ids", "1 to 65536", "got 0"],
        ),
    ];
    for (request, needles) in cases {
        assert_error(
            client.probe_batch(request).await,
            Code::InvalidArgument,
            &needles,
        );
    }

    let report_batch = |steps: Vec<u64>, q_values: Vec<f64>| pb::ReportBatchRequest {
        session_ids: ids(),
        steps,
        q_values,
        ..Default::default()
    };
    assert_error(
        client
            .report_batch(report_batch(vec![0, 0], vec![1.0]))
            .await,
        Code::InvalidArgument,
        &["q_values", "expected 2", "got 1"],
    );
    assert_error(
        client
            .report_batch(report_batch(vec![0], vec![1.0, 1.0]))
            .await,
        Code::InvalidArgument,
        &["steps"],
    );
    assert_error(
        client.report_batch(pb::ReportBatchRequest::default()).await,
        Code::InvalidArgument,
        &["session_ids"],
    );
    server.stop().await;
}

#[tokio::test]
async fn batches_over_65536_items_are_invalid_argument() {
    let server = start().await;
    let mut client = server.client().await;
    let n = 65_537;
    let ids: Vec<String> = (0..n).map(|i| format!("s{i}")).collect();
    assert_error(
        client
            .probe_batch(pb::ProbeBatchRequest {
                session_ids: ids.clone(),
                steps: vec![0; n],
                actions: vec![0.0; n],
                episode_starts: vec![],
                ..Default::default()
            })
            .await,
        Code::InvalidArgument,
        &["65536", "65537"],
    );
    assert_error(
        client
            .report_batch(pb::ReportBatchRequest {
                session_ids: ids,
                steps: vec![0; n],
                q_values: vec![0.0; n],
                ..Default::default()
            })
            .await,
        Code::InvalidArgument,
        &["65536", "65537"],
    );
    server.stop().await;
}

#[tokio::test]
async fn a_bad_request_does_not_disturb_other_sessions() {
    let server = start().await;
    let mut client = server.client().await;
    create(&mut client, "good", config(1)).await;
    create(&mut client, "other", config(1)).await;
    probe(&mut client, "good", 0, &[0.5], false).await.unwrap();
    let before = get(&mut client, "good").await.unwrap();
    let _ = probe(&mut client, "other", 3, &[f64::NAN], false).await;
    let _ = report(&mut client, "other", 0, f64::NAN).await;
    let _ = create_result(&mut client, "other", Some(config(2))).await;
    assert_eq!(get(&mut client, "good").await.unwrap(), before);
    report(&mut client, "good", 0, 1.0).await.unwrap();
    server.stop().await;
}
