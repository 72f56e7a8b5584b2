//! Connection hygiene: silent and unresponsive
//! connections are closed, a full server makes room for a new client, and
//! floods of idle connections neither lock real clients out nor spin the
//! CPU. Floods are a few hundred loopback connections, each test bounded in
//! time.

use std::time::{Duration, Instant};

use esa_server::pb;
use esa_server::EsaServer;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tonic::Code;

use crate::common::{config, cpu_time, create, get, launch_tcp, start_with, Client, TestServer};
use crate::stream::Stream;

/// Reads until the server closes the connection; returns how long that took.
async fn closed_within(stream: &mut TcpStream, limit: Duration) -> Option<Duration> {
    let started = Instant::now();
    let mut buf = [0u8; 4096];
    let closed = tokio::time::timeout(limit, async {
        loop {
            match stream.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(_) => {}
            }
        }
    })
    .await;
    closed.ok().map(|()| started.elapsed())
}

#[tokio::test]
async fn a_connection_that_sends_nothing_is_closed_after_the_handshake_timeout() {
    let server =
        start_with(EsaServer::builder().handshake_timeout(Duration::from_millis(300))).await;
    let mut silent = TcpStream::connect(server.addr).await.unwrap();
    let took = closed_within(&mut silent, Duration::from_secs(5)).await;
    assert!(took.is_some(), "the silent connection was never closed");
    // Real clients are unaffected.
    let mut client = server.client().await;
    create(&mut client, "real", config(1)).await;
    server.stop().await;
}

/// The HTTP/2 client preface and an empty SETTINGS frame: a handshake that
/// then never answers anything, pings included.
const PREFACE_AND_SETTINGS: &[u8] =
    b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n\x00\x00\x00\x04\x00\x00\x00\x00\x00";

#[tokio::test]
async fn a_connection_that_stops_answering_pings_is_closed() {
    let server = start_with(EsaServer::builder().keepalive(Some((
        Duration::from_millis(200),
        Duration::from_millis(200),
    ))))
    .await;
    let mut mute = TcpStream::connect(server.addr).await.unwrap();
    mute.write_all(PREFACE_AND_SETTINGS).await.unwrap();
    let took = closed_within(&mut mute, Duration::from_secs(5)).await;
    assert!(
        took.is_some(),
        "the unresponsive connection was never closed"
    );
    server.stop().await;
}

async fn metric(server: &TestServer, name: &str) -> u64 {
    let text = server.handler.render_metrics();
    text.lines()
        .find_map(|line| line.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or_else(|| panic!("no {name} in\n{text}"))
}

#[tokio::test]
async fn at_the_limit_the_longest_idle_connection_makes_room() {
    let server = start_with(EsaServer::builder().max_connections(3)).await;
    let mut idle = Vec::new();
    for i in 0..3 {
        let mut client = server.client().await;
        create(&mut client, &format!("idle{i}"), config(1)).await;
        idle.push(client);
    }
    assert_eq!(metric(&server, "esa_connections_open").await, 3);
    let mut newcomer = server.client().await;
    create(&mut newcomer, "new", config(1)).await;
    assert_eq!(metric(&server, "esa_connections_evicted_total").await, 1);
    assert!(metric(&server, "esa_connections_open").await <= 3);
    server.stop().await;
}

#[tokio::test]
async fn at_the_limit_with_every_connection_busy_a_newcomer_is_refused() {
    let server = start_with(EsaServer::builder().max_connections(2)).await;
    let mut busy = Vec::new();
    for _ in 0..2 {
        let mut client = server.client().await;
        // An open StepStream is a call in flight for as long as it lasts.
        busy.push(Stream::open(&mut client).await);
    }
    let newcomer = Client::connect(server.url()).await;
    let refused = match newcomer {
        Err(_) => true,
        Ok(mut client) => get(&mut client, "x").await.is_err_and(|s| {
            matches!(
                s.code(),
                Code::Unavailable | Code::Unknown | Code::Cancelled
            )
        }),
    };
    assert!(refused, "a third connection was served");
    assert!(metric(&server, "esa_connections_refused_total").await >= 1);
    drop(busy);
    server.stop().await;
}

/// Opens `n` loopback connections that never send a byte.
async fn silent_flood(addr: &str, n: usize) -> Vec<TcpStream> {
    let mut flood = Vec::with_capacity(n);
    for _ in 0..n {
        match TcpStream::connect(addr).await {
            Ok(stream) => flood.push(stream),
            // The backlog is full: the flood is as big as it gets.
            Err(_) => break,
        }
    }
    flood
}

/// A server with 128 file descriptors (a common default is 1,024; the
/// server cannot raise it past the hard limit set here): 300 silent
/// connections and 40 idle HTTP/2 clients, then a real client must be
/// served within seconds, with the server using little CPU meanwhile.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_idle_connections_does_not_lock_out_a_real_client() {
    let (mut child, url) = launch_tcp("ulimit -n 128", &[]).await;
    let address = url.trim_start_matches("http://").to_string();
    let flood = silent_flood(&address, 300).await;
    let mut idle = Vec::new();
    for i in 0..40 {
        let mut client = Client::connect(url.clone()).await.unwrap();
        create(&mut client, &format!("idle{i}"), config(1)).await;
        idle.push(client);
    }
    let cpu_before = cpu_time(child.id());
    let started = Instant::now();
    let mut real = tokio::time::timeout(Duration::from_secs(5), Client::connect(url.clone()))
        .await
        .expect("connected in time")
        .unwrap();
    let served = tokio::time::timeout(
        Duration::from_secs(5),
        real.create_session(pb::CreateSessionRequest {
            session_id: "real".into(),
            config: Some(config(2)),
            progress: None,
        }),
    )
    .await;
    assert!(matches!(served, Ok(Ok(_))), "{served:?}");
    tokio::time::sleep(Duration::from_secs(2).saturating_sub(started.elapsed())).await;
    let cpu = cpu_time(child.id()) - cpu_before;
    assert!(
        cpu < Duration::from_millis(600),
        "the server used {cpu:?} of CPU in 2 s"
    );
    let fds = std::fs::read_dir(format!("/proc/{}/fd", child.id()))
        .unwrap()
        .count();
    assert!(fds <= 128, "{fds}");
    drop((flood, idle));
    child.kill().unwrap();
    child.wait().unwrap();
}

/// With --max-connections above what the descriptors allow, accept fails
/// with EMFILE: the server pauses instead of retrying in a busy loop, and
/// serves again once the handshake timeout has closed the silent connections.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn out_of_file_descriptors_the_server_backs_off_instead_of_spinning() {
    let (mut child, url) = launch_tcp(
        "ulimit -n 64",
        &["--max-connections", "1000", "--handshake-timeout", "1"],
    )
    .await;
    let address = url.trim_start_matches("http://").to_string();
    let flood = silent_flood(&address, 80).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let cpu_before = cpu_time(child.id());
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let cpu = cpu_time(child.id()) - cpu_before;
    assert!(
        cpu < Duration::from_millis(400),
        "the server used {cpu:?} of CPU in 1.5 s"
    );
    let served = tokio::time::timeout(Duration::from_secs(15), async {
        let mut client = Client::connect(url.clone()).await?;
        Ok::<_, Box<dyn std::error::Error>>(
            client
                .create_session(pb::CreateSessionRequest {
                    session_id: "real".into(),
                    config: Some(config(1)),
                    progress: None,
                })
                .await?,
        )
    })
    .await;
    assert!(matches!(served, Ok(Ok(_))), "{served:?}");
    drop(flood);
    child.kill().unwrap();
    child.wait().unwrap();
}
