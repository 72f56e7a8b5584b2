//! One session through its whole life, and the retry semantics of CONTRACT.md.

use esa_core::Session;
use esa_server::pb;
use tonic::Code;

use crate::common::{
    assert_error, close, config, create, end_episode, get, probe, q_of, report, start,
};

#[tokio::test]
async fn full_lifecycle() {
    let server = start().await;
    let mut client = server.client().await;
    let cfg = pb::SessionConfig {
        action_low: vec![-1.0],
        action_high: vec![1.0, 2.0],
        shift_limit: Some(0.5),
        ..config(2)
    };
    assert_eq!(create(&mut client, "env-0", cfg.clone()).await, "env-0");

    let fresh = get(&mut client, "env-0").await.unwrap();
    assert_eq!(fresh.config, Some(cfg));
    assert_eq!(
        (fresh.step, fresh.episodes_completed, fresh.probe_pending),
        (0, 0, false)
    );
    assert_eq!(fresh.shift, vec![0.0, 0.0]);

    for step in 0..5 {
        let p = probe(&mut client, "env-0", step, &[0.5, 0.5], step == 0)
            .await
            .unwrap();
        assert_eq!((p.probe.len(), p.step), (2, step));
        assert!(get(&mut client, "env-0").await.unwrap().probe_pending);
        let r = report(&mut client, "env-0", step, q_of(&p.probe))
            .await
            .unwrap();
        assert_eq!((r.action.len(), r.step), (2, step));
        let snapshot = get(&mut client, "env-0").await.unwrap();
        assert_eq!((snapshot.step, snapshot.probe_pending), (step + 1, false));
    }
    assert!(get(&mut client, "env-0").await.unwrap().shift != vec![0.0, 0.0]);

    let ended = end_episode(&mut client, "env-0").await.unwrap();
    assert_eq!(ended.episodes_completed, 1);
    let after = get(&mut client, "env-0").await.unwrap();
    assert_eq!((after.step, after.episodes_completed), (0, 1));
    assert_eq!(after.shift, vec![0.0, 0.0]);

    close(&mut client, "env-0").await.unwrap();
    assert_error(get(&mut client, "env-0").await, Code::NotFound, &["env-0"]);
    assert_error(
        close(&mut client, "env-0").await,
        Code::NotFound,
        &["env-0"],
    );
    server.stop().await;
}

#[tokio::test]
async fn empty_id_gets_a_fresh_uuid() {
    let server = start().await;
    let mut client = server.client().await;
    let a = create(&mut client, "", config(1)).await;
    let b = create(&mut client, "", config(1)).await;
    assert!(uuid::Uuid::parse_str(&a).is_ok(), "{a} is not a UUID");
    assert_ne!(a, b);
    assert!(get(&mut client, &a).await.is_ok());
    server.stop().await;
}

#[tokio::test]
async fn create_is_idempotent_for_the_same_config_and_already_exists_otherwise() {
    let server = start().await;
    let mut client = server.client().await;
    create(&mut client, "s", config(2)).await;
    let p = probe(&mut client, "s", 0, &[0.0, 0.0], true).await.unwrap();
    report(&mut client, "s", 0, q_of(&p.probe)).await.unwrap();
    let before = get(&mut client, "s").await.unwrap();

    // Same id, same config: the existing session, untouched.
    assert_eq!(create(&mut client, "s", config(2)).await, "s");
    assert_eq!(get(&mut client, "s").await.unwrap(), before);

    let different = pb::SessionConfig {
        learning_rate: vec![0.5],
        ..config(2)
    };
    assert_error(
        client
            .create_session(pb::CreateSessionRequest {
                session_id: "s".into(),
                config: Some(different),
                progress: None,
            })
            .await,
        Code::AlreadyExists,
        &["\"s\"", "different config"],
    );
    assert_eq!(get(&mut client, "s").await.unwrap(), before);
    server.stop().await;
}

#[tokio::test]
async fn probe_retry_replaces_the_pending_action() {
    let server = start().await;
    let mut client = server.client().await;
    create(&mut client, "s", config(2)).await;
    // Step 0 has sin(0) = 0, so walk to step 3 where the probe differs from the action.
    for step in 0..3 {
        let p = probe(&mut client, "s", step, &[0.1, 0.2], false)
            .await
            .unwrap();
        report(&mut client, "s", step, q_of(&p.probe))
            .await
            .unwrap();
    }
    let first = probe(&mut client, "s", 3, &[0.9, 0.9], false)
        .await
        .unwrap();
    let again = probe(&mut client, "s", 3, &[0.9, 0.9], false)
        .await
        .unwrap();
    assert_eq!(first, again, "the same probe twice is deterministic");
    let replaced = probe(&mut client, "s", 3, &[0.3, 0.4], false)
        .await
        .unwrap();

    // A twin session that only ever saw the second action at step 3.
    let mut twin =
        Session::new(esa_server::convert::config_from_proto(Some(config(2))).unwrap()).unwrap();
    let mut out = Vec::new();
    for step in 0..3 {
        out.clear();
        twin.probe(step, &[0.1, 0.2], &[], false, &mut out).unwrap();
        let q = q_of(&out);
        out.clear();
        twin.report(step, q, None, &mut out).unwrap();
    }
    out.clear();
    twin.probe(3, &[0.3, 0.4], &[], false, &mut out).unwrap();
    assert_eq!(replaced.probe, out);

    let r = report(&mut client, "s", 3, 1.5).await.unwrap();
    out.clear();
    twin.report(3, 1.5, None, &mut out).unwrap();
    assert_eq!(r.action, out, "the report uses the replacing action");
    server.stop().await;
}

#[tokio::test]
async fn report_retry_returns_the_same_action_and_updates_nothing() {
    let server = start().await;
    let mut client = server.client().await;
    create(&mut client, "s", config(1)).await;
    for step in 0..4 {
        let p = probe(&mut client, "s", step, &[0.7], false).await.unwrap();
        report(&mut client, "s", step, q_of(&p.probe))
            .await
            .unwrap();
    }
    let p = probe(&mut client, "s", 4, &[0.7], false).await.unwrap();
    let applied = report(&mut client, "s", 4, q_of(&p.probe)).await.unwrap();
    let state = get(&mut client, "s").await.unwrap();

    let retried = report(&mut client, "s", 4, 123.0).await.unwrap();
    assert_eq!(retried, applied);
    assert_eq!(get(&mut client, "s").await.unwrap(), state);

    // Once the next probe arrives the old report is no longer replayable.
    probe(&mut client, "s", 5, &[0.7], false).await.unwrap();
    assert_error(
        report(&mut client, "s", 4, 1.0).await,
        Code::FailedPrecondition,
        &["expected step 5"],
    );
    server.stop().await;
}

#[tokio::test]
async fn episode_start_ends_a_running_episode_and_is_a_no_op_on_a_fresh_one() {
    let server = start().await;
    let mut client = server.client().await;
    create(&mut client, "s", config(1)).await;

    probe(&mut client, "s", 0, &[0.0], true).await.unwrap();
    let fresh = get(&mut client, "s").await.unwrap();
    assert_eq!((fresh.episodes_completed, fresh.probe_pending), (0, true));

    report(&mut client, "s", 0, 1.0).await.unwrap();
    probe(&mut client, "s", 1, &[0.0], false).await.unwrap();
    report(&mut client, "s", 1, 2.0).await.unwrap();

    // episode_start with a step other than 0 is refused and changes nothing.
    let before = get(&mut client, "s").await.unwrap();
    assert_error(
        probe(&mut client, "s", 2, &[0.0], true).await,
        Code::FailedPrecondition,
        &["expected step 0", "got 2"],
    );
    assert_eq!(get(&mut client, "s").await.unwrap(), before);

    probe(&mut client, "s", 0, &[0.0], true).await.unwrap();
    let restarted = get(&mut client, "s").await.unwrap();
    assert_eq!(
        (
            restarted.episodes_completed,
            restarted.step,
            restarted.probe_pending
        ),
        (1, 0, true)
    );
    assert_eq!(restarted.shift, vec![0.0]);

    // A pending probe alone also counts as a running episode.
    probe(&mut client, "s", 0, &[0.0], true).await.unwrap();
    assert_eq!(get(&mut client, "s").await.unwrap().episodes_completed, 2);
    server.stop().await;
}
