//! Zenoh over mutual TLS, as deploy/zenoh/*-tls.json5 set it up, on loopback:
//! a router that only admits certificates of the deployment's CA, the esa
//! server and a trainer connected to it over TLS. Peers without such a
//! certificate (none, one from another CA, plain TCP) cannot connect, so they
//! see none of the trainer's queries and cannot answer them; a peer with a
//! valid certificate (the control) does see them, which shows the probe would
//! notice a leak.

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use esa_server::pb;
use esa_server::zenoh_transport::ZenohService;
use prost::Message as _;
use zenoh::query::{ConsolidationMode, QueryTarget};
use zenoh::{Config, Session};

use crate::common::{config, start};
use crate::tls::{Leaf, Pki};

const PREFIX: &str = "mtls/esa/v1";
const QUERIES: usize = 5;

/// Files of one party's TLS settings.
struct Files {
    ca: String,
    cert: Option<String>,
    key: Option<String>,
}

fn write(dir: &Path, name: &str, text: &str) -> String {
    let path = dir.join(name);
    std::fs::write(&path, text).expect("write test file");
    path.to_str().expect("utf-8 path").to_string()
}

fn files(dir: &Path, name: &str, ca_pem: &str, leaf: Option<&Leaf>) -> Files {
    Files {
        ca: write(dir, &format!("{name}-ca.pem"), ca_pem),
        cert: leaf.map(|leaf| write(dir, &format!("{name}.pem"), &leaf.cert)),
        key: leaf.map(|leaf| write(dir, &format!("{name}-key.pem"), &leaf.key)),
    }
}

fn set(config: &mut Config, key: &str, value: &str) {
    config
        .insert_json5(key, value)
        .unwrap_or_else(|err| panic!("{key} = {value}: {err}"));
}

/// A quiet config (no scouting, no gossip) of `mode`, listening on and connecting to exactly
/// the endpoints given.
fn quiet(mode: &str, listen: &[&str], connect: &[&str]) -> Config {
    let mut config = Config::default();
    set(&mut config, "mode", &format!("{mode:?}"));
    set(&mut config, "listen/endpoints", &format!("{listen:?}"));
    set(&mut config, "connect/endpoints", &format!("{connect:?}"));
    set(&mut config, "scouting/multicast/enabled", "false");
    set(&mut config, "scouting/gossip/enabled", "false");
    config
}

/// The router: listens on TLS only and requires a client certificate from the CA.
fn router_config(tls: &Files) -> Config {
    let mut config = quiet("router", &["tls/127.0.0.1:0"], &[]);
    let (Some(cert), Some(key)) = (&tls.cert, &tls.key) else {
        panic!("the router needs a certificate");
    };
    set(
        &mut config,
        "transport/link/tls",
        &format!(
            "{{ root_ca_certificate: {:?}, listen_certificate: {cert:?}, \
             listen_private_key: {key:?}, enable_mtls: true }}",
            tls.ca
        ),
    );
    config
}

/// A party connecting to `endpoint` with `tls`; `patient` parties wait for the router,
/// others try once and carry on unconnected.
fn connecting_config(mode: &str, endpoint: &str, tls: &Files, patient: bool) -> Config {
    let mut config = quiet(mode, &[], &[endpoint]);
    let identity = match (&tls.cert, &tls.key) {
        (Some(cert), Some(key)) => {
            format!(
                "connect_certificate: {cert:?}, connect_private_key: {key:?}, enable_mtls: true,"
            )
        }
        _ => String::new(),
    };
    set(
        &mut config,
        "transport/link/tls",
        &format!("{{ root_ca_certificate: {:?}, {identity} }}", tls.ca),
    );
    let timeout = if patient { "10000" } else { "0" };
    set(&mut config, "connect/timeout_ms", timeout);
    set(&mut config, "connect/exit_on_failure", &patient.to_string());
    config
}

/// A peer that answers every query under the prefix with a forged session, counting them.
struct Impostor {
    session: Session,
    queries: Arc<AtomicUsize>,
}

async fn impostor(config: Config) -> Impostor {
    let session = zenoh::open(config).await.expect("impostor session");
    let queries = Arc::new(AtomicUsize::new(0));
    let seen = Arc::clone(&queries);
    let key = format!("{PREFIX}/**");
    let runtime = tokio::runtime::Handle::current();
    session
        .declare_queryable(&key)
        .complete(true)
        .callback(move |query| {
            seen.fetch_add(1, Ordering::SeqCst);
            let forged = pb::CreateSessionResponse {
                session_id: "forged".into(),
            };
            // Zenoh calls back on its own threads; the reply is sent from the test's runtime.
            runtime.spawn(async move {
                let key = query.key_expr().clone();
                let _ = query.reply(key, forged.encode_to_vec()).await;
            });
        })
        .background()
        .await
        .expect("impostor queryable");
    Impostor { session, queries }
}

/// Sends one CreateSession to every queryable of its key and returns the session ids replied.
async fn ask(trainer: &Session, id: &str) -> Vec<String> {
    let request = pb::CreateSessionRequest {
        session_id: id.into(),
        config: Some(config(1)),
        progress: None,
    };
    let replies = trainer
        .get(format!("{PREFIX}/CreateSession"))
        .payload(request.encode_to_vec())
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::None)
        .timeout(Duration::from_secs(3))
        .await
        .expect("query sent");
    let mut ids = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            let created = pb::CreateSessionResponse::decode(&*sample.payload().to_bytes())
                .expect("a CreateSessionResponse");
            ids.push(created.session_id);
        }
    }
    ids
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_a_certificate_from_the_ca_a_peer_sees_and_answers_no_query() {
    tokio::time::timeout(Duration::from_secs(120), scenario())
        .await
        .expect("the scenario finished in time");
}

async fn scenario() {
    let dir = tempfile::tempdir().expect("temp dir");
    let dir = dir.path();
    let pki = Pki::new("deployment CA");
    let ca = pki.ca_pem();
    let router_tls = files(dir, "router", &ca, Some(&pki.leaf("router")));
    let router = zenoh::open(router_config(&router_tls))
        .await
        .expect("router");
    let locator = router
        .info()
        .locators()
        .await
        .into_iter()
        .map(|locator| locator.to_string())
        .find(|locator| locator.starts_with("tls/127.0.0.1:"))
        .expect("the router's TLS locator");
    let port = locator.rsplit_once(':').expect("a port").1.to_string();

    let grpc = start().await;
    let server_tls = files(dir, "server", &ca, Some(&pki.leaf("esa-server")));
    let zenoh = ZenohService::start(
        grpc.handler.clone(),
        connecting_config("client", &locator, &server_tls, true),
        PREFIX,
    )
    .await
    .expect("the server connects over mTLS");
    let trainer_tls = files(dir, "trainer", &ca, Some(&pki.leaf("esa-trainer")));
    let trainer = zenoh::open(connecting_config("client", &locator, &trainer_tls, true))
        .await
        .expect("the trainer connects over mTLS");

    let other_pki = Pki::new("another CA");
    let outsiders = [
        // Trusts the router, but has no certificate to show.
        (
            "no certificate",
            connecting_config("peer", &locator, &files(dir, "bare", &ca, None), false),
        ),
        // A certificate, but from a CA the router does not trust.
        (
            "another CA's certificate",
            connecting_config(
                "peer",
                &locator,
                &files(dir, "other", &ca, Some(&other_pki.leaf("esa-trainer"))),
                false,
            ),
        ),
        // Plain TCP to the TLS port.
        (
            "plain TCP",
            quiet("peer", &[], &[&format!("tcp/127.0.0.1:{port}")]),
        ),
    ];
    let mut impostors = Vec::new();
    for (name, config) in outsiders {
        impostors.push((name, impostor(config).await));
    }
    for (name, outsider) in &impostors {
        let info = outsider.session.info();
        let links = info.routers_zid().await.count() + info.peers_zid().await.count();
        assert_eq!(links, 0, "{name} got connected");
    }

    for i in 0..QUERIES {
        let id = format!("mtls-{i}");
        assert_eq!(ask(&trainer, &id).await, [id], "query {i}");
    }
    for (name, outsider) in &impostors {
        assert_eq!(
            outsider.queries.load(Ordering::SeqCst),
            0,
            "{name} saw trainer queries"
        );
    }

    // The control: a peer with the CA's certificate is let in, sees the queries and can
    // answer them (the routers' access control in deploy/ is what then stops it).
    let insider_tls = files(dir, "insider", &ca, Some(&pki.leaf("insider")));
    let insider = impostor(connecting_config("client", &locator, &insider_tls, true)).await;
    let mut answers = Vec::new();
    for attempt in 0..20 {
        // The router learns the insider's queryable shortly after it connects.
        answers = ask(&trainer, &format!("control-{attempt}")).await;
        if answers.len() > 1 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(answers.contains(&"forged".to_string()), "{answers:?}");
    assert!(insider.queries.load(Ordering::SeqCst) > 0);

    insider.session.close().await.expect("close insider");
    for (_, outsider) in impostors {
        outsider.session.close().await.expect("close outsider");
    }
    trainer.close().await.expect("close trainer");
    zenoh.close().await.expect("close service");
    router.close().await.expect("close router");
    grpc.stop().await;
}
