//! ProbeBatch / ReportBatch: equal to the unary path, all-or-nothing.

use esa_server::pb;
use tonic::Code;

use crate::common::{assert_error, config, create, get, probe, q_of, report, start, Client};

/// Sessions of dimensions 1, 2 and 3 (actions are concatenated per item).
const DIMS: [u32; 3] = [1, 2, 3];

fn batch_ids(prefix: &str) -> Vec<String> {
    DIMS.iter().map(|d| format!("{prefix}-{d}")).collect()
}

fn actions_at(step: u64) -> Vec<f64> {
    let total: u32 = DIMS.iter().sum();
    (0..total)
        .map(|i| 0.1 * f64::from(i) - 0.02 * step as f64)
        .collect()
}

async fn create_all(client: &mut Client, ids: &[String]) {
    for (id, d) in ids.iter().zip(DIMS) {
        create(client, id, config(d)).await;
    }
}

/// Probes every session of `ids` at `step` with [`actions_at`].
async fn probe_all(client: &mut Client, ids: &[String], step: u64) {
    client
        .probe_batch(pb::ProbeBatchRequest {
            session_ids: ids.to_vec(),
            steps: vec![step; ids.len()],
            actions: actions_at(step),
            episode_starts: vec![],
            ..Default::default()
        })
        .await
        .unwrap();
}

async fn snapshot(client: &mut Client, ids: &[String]) -> Vec<pb::GetSessionResponse> {
    let mut out = Vec::new();
    for id in ids {
        out.push(get(client, id).await.unwrap());
    }
    out
}

#[tokio::test]
async fn batches_give_the_same_results_as_unary_calls() {
    let server = start().await;
    let mut client = server.client().await;
    let batched = batch_ids("batch");
    let unary = batch_ids("unary");
    for (id, d) in batched.iter().chain(&unary).zip(DIMS.iter().cycle()) {
        create(&mut client, id, config(*d)).await;
    }
    for step in 0..30 {
        let actions = actions_at(step);
        let probes = client
            .probe_batch(pb::ProbeBatchRequest {
                session_ids: batched.clone(),
                steps: vec![step; DIMS.len()],
                actions: actions.clone(),
                episode_starts: if step == 0 {
                    vec![true; DIMS.len()]
                } else {
                    vec![]
                },
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner()
            .probes;

        let mut expected_probes = Vec::new();
        let mut rest = actions.as_slice();
        for (id, d) in unary.iter().zip(DIMS) {
            let (action, tail) = rest.split_at(d as usize);
            rest = tail;
            let p = probe(&mut client, id, step, action, step == 0)
                .await
                .unwrap();
            expected_probes.extend(p.probe);
        }
        assert_eq!(probes, expected_probes, "probes at step {step}");

        let mut q_values = Vec::new();
        let mut rest = probes.as_slice();
        for d in DIMS {
            let (p, tail) = rest.split_at(d as usize);
            rest = tail;
            q_values.push(q_of(p));
        }
        let actions = client
            .report_batch(pb::ReportBatchRequest {
                session_ids: batched.clone(),
                steps: vec![step; DIMS.len()],
                q_values: q_values.clone(),
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner()
            .actions;
        let mut expected_actions = Vec::new();
        for (id, q) in unary.iter().zip(&q_values) {
            expected_actions.extend(report(&mut client, id, step, *q).await.unwrap().action);
        }
        assert_eq!(actions, expected_actions, "actions at step {step}");
    }
    for (b, u) in snapshot(&mut client, &batched)
        .await
        .iter()
        .zip(snapshot(&mut client, &unary).await)
    {
        assert_eq!((b.step, &b.shift), (u.step, &u.shift));
    }
    server.stop().await;
}

#[tokio::test]
async fn a_batch_with_one_bad_item_changes_no_session() {
    let server = start().await;
    let mut client = server.client().await;
    let ids = batch_ids("s");
    create_all(&mut client, &ids).await;
    // Every session at step 2 with a pending probe, except the last at step 2
    // without one.
    for step in 0..2 {
        probe_all(&mut client, &ids, step).await;
        client
            .report_batch(pb::ReportBatchRequest {
                session_ids: ids.clone(),
                steps: vec![step; 3],
                q_values: vec![1.0, -2.0, 0.5],
                ..Default::default()
            })
            .await
            .unwrap();
    }
    for (id, d) in ids.iter().zip(DIMS).take(2) {
        probe(&mut client, id, 2, &vec![0.3; d as usize], false)
            .await
            .unwrap();
    }
    let before = snapshot(&mut client, &ids).await;
    let with_ids =
        |session_ids: Vec<String>, steps: Vec<u64>, actions: Vec<f64>| pb::ProbeBatchRequest {
            session_ids,
            steps,
            actions,
            episode_starts: vec![],
            ..Default::default()
        };

    let bad_probes = [
        // A step mismatch in the middle.
        (
            with_ids(ids.clone(), vec![2, 7, 2], actions_at(2)),
            Code::FailedPrecondition,
            "item 1",
        ),
        // A NaN in the last item's action.
        (
            with_ids(ids.clone(), vec![2, 2, 2], {
                let mut a = actions_at(2);
                a[5] = f64::NAN;
                a
            }),
            Code::InvalidArgument,
            "item 2",
        ),
        // An unknown session last.
        (
            with_ids(
                vec![ids[0].clone(), ids[1].clone(), "ghost".into()],
                vec![2, 2, 2],
                vec![0.0; 4],
            ),
            Code::NotFound,
            "item 2",
        ),
        // episode_start with a non-zero step on the first item.
        (
            pb::ProbeBatchRequest {
                episode_starts: vec![true, false, false],
                ..with_ids(ids.clone(), vec![2, 2, 2], actions_at(2))
            },
            Code::FailedPrecondition,
            "item 0",
        ),
    ];
    for (request, code, needle) in bad_probes {
        assert_error(client.probe_batch(request).await, code, &[needle]);
        assert_eq!(snapshot(&mut client, &ids).await, before, "after {needle}");
    }

    let bad_reports = [
        // The last session has no pending probe.
        (
            vec![2, 2, 2],
            vec![1.0, 1.0, 1.0],
            Code::FailedPrecondition,
            "item 2",
        ),
        // Infinite Q on the second item.
        (
            vec![2, 2, 2],
            vec![1.0, f64::INFINITY, 1.0],
            Code::InvalidArgument,
            "item 1",
        ),
        (
            vec![2, 3, 2],
            vec![1.0, 1.0, 1.0],
            Code::FailedPrecondition,
            "item 1",
        ),
    ];
    for (steps, q_values, code, needle) in bad_reports {
        assert_error(
            client
                .report_batch(pb::ReportBatchRequest {
                    session_ids: ids.clone(),
                    steps,
                    q_values,
                    ..Default::default()
                })
                .await,
            code,
            &[needle],
        );
        assert_eq!(snapshot(&mut client, &ids).await, before, "after {needle}");
    }
    server.stop().await;
}

#[tokio::test]
async fn a_session_may_appear_only_once_per_batch() {
    let server = start().await;
    let mut client = server.client().await;
    create(&mut client, "a", config(1)).await;
    create(&mut client, "b", config(1)).await;
    let before = snapshot(&mut client, &["a".into(), "b".into()]).await;
    assert_error(
        client
            .probe_batch(pb::ProbeBatchRequest {
                session_ids: vec!["a".into(), "b".into(), "a".into()],
                steps: vec![0; 3],
                actions: vec![0.0; 3],
                episode_starts: vec![],
                ..Default::default()
            })
            .await,
        Code::InvalidArgument,
        &["item 2", "\"a\"", "item 0", "at most once"],
    );
    assert_error(
        client
            .report_batch(pb::ReportBatchRequest {
                session_ids: vec!["b".into(), "b".into()],
                steps: vec![0; 2],
                q_values: vec![0.0; 2],
                ..Default::default()
            })
            .await,
        Code::InvalidArgument,
        &["item 1", "\"b\"", "item 0"],
    );
    assert_eq!(
        snapshot(&mut client, &["a".into(), "b".into()]).await,
        before
    );
    server.stop().await;
}

#[tokio::test]
async fn the_failing_item_travels_as_data_in_the_status_details() {
    let server = start().await;
    let mut client = server.client().await;
    let ids = batch_ids("d");
    create_all(&mut client, &ids).await;
    let mut actions = actions_at(0);
    actions[1] = f64::NAN; // item 1's first value
    let status = client
        .probe_batch(pb::ProbeBatchRequest {
            session_ids: ids.clone(),
            steps: vec![0; 3],
            actions,
            ..Default::default()
        })
        .await
        .expect_err("a NaN action");
    assert_eq!(status.code(), Code::InvalidArgument);
    assert_eq!(esa_proto::details::batch_item(status.details()), Some(1));
    let status = client
        .report_batch(pb::ReportBatchRequest {
            session_ids: ids.clone(),
            steps: vec![0; 3],
            q_values: vec![1.0; 3],
            ..Default::default()
        })
        .await
        .expect_err("nothing was probed");
    assert_eq!(status.code(), Code::FailedPrecondition);
    assert_eq!(esa_proto::details::batch_item(status.details()), Some(0));
    // An error of the whole request names no item.
    let status = client
        .report_batch(pb::ReportBatchRequest {
            session_ids: ids.clone(),
            steps: vec![0; 2],
            q_values: vec![1.0; 3],
            ..Default::default()
        })
        .await
        .expect_err("one step too few");
    assert_eq!(status.code(), Code::InvalidArgument);
    assert_eq!(esa_proto::details::batch_item(status.details()), None);
    server.stop().await;
}

#[tokio::test]
async fn report_batch_retry_replays_the_same_actions() {
    let server = start().await;
    let mut client = server.client().await;
    let ids = batch_ids("r");
    create_all(&mut client, &ids).await;
    for step in 0..3 {
        probe_all(&mut client, &ids, step).await;
        let request = pb::ReportBatchRequest {
            session_ids: ids.clone(),
            steps: vec![step; 3],
            q_values: vec![0.5, 1.5, -1.0],
            ..Default::default()
        };
        let first = client
            .report_batch(request.clone())
            .await
            .unwrap()
            .into_inner();
        let state = snapshot(&mut client, &ids).await;
        let retry = client.report_batch(request).await.unwrap().into_inner();
        assert_eq!(first, retry);
        assert_eq!(snapshot(&mut client, &ids).await, state);
    }
    server.stop().await;
}
