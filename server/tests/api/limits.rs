//! The session limit and concurrent use of the store.

use std::collections::HashSet;

use esa_server::pb;
use esa_server::EsaServer;
use tonic::Code;

use crate::common::{assert_error, close, config, create, start, start_with};

#[tokio::test]
async fn max_sessions_is_resource_exhausted() {
    let server = start_with(EsaServer::builder().max_sessions(3)).await;
    let mut client = server.client().await;
    for id in ["a", "b", "c"] {
        create(&mut client, id, config(1)).await;
    }
    let fourth = client
        .create_session(pb::CreateSessionRequest {
            session_id: "d".into(),
            config: Some(config(1)),
            progress: None,
        })
        .await;
    assert_error(fourth, Code::ResourceExhausted, &["3", "--max-sessions"]);
    // Re-creating an existing session at the limit is still fine.
    assert_eq!(create(&mut client, "a", config(1)).await, "a");

    close(&mut client, "b").await.unwrap();
    assert_eq!(create(&mut client, "d", config(1)).await, "d");
    assert_eq!(server.handler.store().live(), 3);
    server.stop().await;
}

/// Many clients stepping overlapping batches in opposite orders at once: no
/// deadlock, and every session ends exactly where its own steps put it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_overlapping_batches_neither_deadlock_nor_interfere() {
    let server = start().await;
    let mut client = server.client().await;
    let ids: Vec<String> = (0..8).map(|i| format!("s{i}")).collect();
    for id in &ids {
        create(&mut client, id, config(1)).await;
    }
    let steps = 40u64;
    let mut tasks = Vec::new();
    for worker in 0..4 {
        let mut client = server.client().await;
        // Workers 0/1 and 2/3 share no session; each pair uses opposite orders.
        let mut mine: Vec<String> = ids[(worker / 2) * 4..(worker / 2) * 4 + 4].to_vec();
        if worker % 2 == 1 {
            mine.reverse();
        }
        tasks.push(tokio::spawn(async move {
            let mut applied = 0;
            for _ in 0..steps {
                // Both workers of a pair race for the same sessions; a
                // FAILED_PRECONDITION loser simply retries from the new state.
                let state = client
                    .get_session(pb::GetSessionRequest {
                        session_id: mine[0].clone(),
                    })
                    .await
                    .unwrap()
                    .into_inner();
                let step = state.step;
                let probe = client
                    .probe_batch(pb::ProbeBatchRequest {
                        session_ids: mine.clone(),
                        steps: vec![step; mine.len()],
                        actions: vec![0.1; mine.len()],
                        episode_starts: vec![],
                        ..Default::default()
                    })
                    .await;
                if probe.is_err() {
                    continue;
                }
                let report = client
                    .report_batch(pb::ReportBatchRequest {
                        session_ids: mine.clone(),
                        steps: vec![step; mine.len()],
                        q_values: vec![1.0; mine.len()],
                        ..Default::default()
                    })
                    .await;
                match report {
                    Ok(_) => applied += 1,
                    Err(status) => assert!(
                        matches!(status.code(), Code::FailedPrecondition),
                        "{status:?}"
                    ),
                }
            }
            applied
        }));
    }
    let mut applied = 0;
    for task in tasks {
        applied += task.await.unwrap();
    }
    assert!(applied > 0);
    // All sessions of a pair moved together: batches are atomic.
    for group in ids.chunks(4) {
        let mut steps_seen = HashSet::new();
        for id in group {
            let s = client
                .get_session(pb::GetSessionRequest {
                    session_id: id.clone(),
                })
                .await
                .unwrap()
                .into_inner();
            steps_seen.insert((s.step, s.probe_pending));
        }
        assert_eq!(
            steps_seen.len(),
            1,
            "sessions of one group diverged: {steps_seen:?}"
        );
    }
    server.stop().await;
}
