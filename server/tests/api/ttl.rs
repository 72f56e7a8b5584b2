//! Idle-session expiry. These tests must let real time pass (the TTL is what
//! is under test), so they use short TTLs; every wait is bounded.

use std::time::{Duration, Instant};

use esa_server::pb;
use esa_server::EsaServer;
use tonic::Code;

use crate::common::{assert_error, config, create, get, probe, start_with};

#[tokio::test]
async fn an_idle_session_expires_and_its_id_can_be_reused() {
    let server = start_with(
        EsaServer::builder()
            .session_ttl(Some(Duration::from_millis(300)))
            .sweep_interval(Duration::from_secs(3600)),
    )
    .await;
    let mut client = server.client().await;
    create(&mut client, "idle", config(1)).await;
    tokio::time::sleep(Duration::from_millis(600)).await;

    // Expiry is exact on lookup, independent of the (here: never) sweep.
    assert_error(
        probe(&mut client, "idle", 0, &[0.0], false).await,
        Code::NotFound,
        &["idle", "expired"],
    );
    assert_eq!(server.handler.store().live(), 0);
    assert_eq!(server.handler.store().expired_total(), 1);

    // The id is free again, even for a different config.
    let other = pb::SessionConfig {
        action_dim: 3,
        ..config(1)
    };
    assert_eq!(create(&mut client, "idle", other).await, "idle");
    assert_eq!(get(&mut client, "idle").await.unwrap().shift.len(), 3);
    server.stop().await;
}

#[tokio::test]
async fn requests_keep_a_session_alive() {
    let ttl = Duration::from_millis(1000);
    let server = start_with(EsaServer::builder().session_ttl(Some(ttl))).await;
    let mut client = server.client().await;
    create(&mut client, "busy", config(1)).await;
    let start = Instant::now();
    while start.elapsed() < 2 * ttl {
        tokio::time::sleep(ttl / 4).await;
        get(&mut client, "busy")
            .await
            .expect("a session in use does not expire");
    }
    server.stop().await;
}

#[tokio::test]
async fn the_sweeper_frees_sessions_nobody_asks_for() {
    let server = start_with(
        EsaServer::builder()
            .session_ttl(Some(Duration::from_millis(200)))
            .sweep_interval(Duration::from_millis(50)),
    )
    .await;
    let mut client = server.client().await;
    for i in 0..5 {
        create(&mut client, &format!("s{i}"), config(1)).await;
    }
    assert_eq!(server.handler.store().live(), 5);
    let deadline = Instant::now() + Duration::from_secs(10);
    while server.handler.store().live() > 0 {
        assert!(Instant::now() < deadline, "sessions were not swept");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(server.handler.store().expired_total(), 5);
    server.stop().await;
}
