//! The `esa-server` executable: flags, the `listening on` line, the metrics
//! flag, and clean shutdown on SIGTERM/SIGINT.

use std::io::{BufRead, BufReader};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

use crate::common::{config, create, get, Client};

const BIN: &str = env!("CARGO_BIN_EXE_esa-server");

fn launch(args: &[&str]) -> (Child, BufReader<ChildStdout>) {
    let mut child = Command::new(BIN)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("start esa-server");
    let stdout = BufReader::new(child.stdout.take().expect("piped stdout"));
    (child, stdout)
}

/// Reads stdout lines until one starts with `prefix`; returns the rest.
fn read_line_after(stdout: &mut BufReader<ChildStdout>, prefix: &str) -> String {
    let mut line = String::new();
    loop {
        line.clear();
        let n = stdout.read_line(&mut line).expect("read stdout");
        assert!(n > 0, "esa-server closed stdout before printing {prefix:?}");
        if let Some(rest) = line.trim_end().strip_prefix(prefix) {
            return rest.to_string();
        }
    }
}

fn signal(child: &Child, name: &str) {
    let status = Command::new("kill")
        .args([&format!("-{name}"), &child.id().to_string()])
        .status()
        .expect("run kill");
    assert!(status.success());
}

/// Waits for the child to exit and returns whether it succeeded. The servers
/// run with a shutdown grace far beyond this deadline, so exiting in time
/// means shutdown did not hang on connections. The wait is async so that
/// this runtime's client connections keep answering the server's goodbye.
async fn wait_exit(child: &mut Child) -> bool {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if let Some(status) = child.try_wait().expect("wait") {
            return status.success();
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("esa-server did not exit after the signal");
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[test]
fn help_documents_every_flag() {
    let output = Command::new(BIN).arg("--help").output().unwrap();
    assert!(output.status.success());
    let help = String::from_utf8(output.stdout).unwrap();
    for flag in [
        "--listen",
        "--uds",
        "--session-ttl",
        "--max-sessions",
        "--metrics-listen",
        "--max-message-bytes",
        "--shutdown-grace",
        "--log-format",
        "--zenoh",
        "--zenoh-prefix",
        "--zenoh-config",
        "--zenoh-listen",
        "--zenoh-connect",
        "--shard",
        "zenoh listening on",
        "--help",
        "--version",
        "RUST_LOG",
        "listening on",
    ] {
        assert!(help.contains(flag), "--help lacks {flag}:\n{help}");
    }
}

#[test]
fn bad_flags_are_rejected_with_a_message() {
    for args in [
        &["--session-ttl", "-1"][..],
        &["--session-ttl", "NaN"],
        &["--listen", "not-an-address"],
        &["--listen", "127.0.0.1:1", "--uds", "/tmp/x.sock"],
        &["--log-format", "xml"],
        &["--shard", "0/2"],
        &["--zenoh", "--shard", "2/2"],
        &["--zenoh", "--shard", "two"],
    ] {
        let output = Command::new(BIN).args(args).output().unwrap();
        assert_eq!(output.status.code(), Some(2), "{args:?}");
        assert!(!output.stderr.is_empty(), "{args:?}");
    }
}

#[tokio::test]
async fn serves_tcp_with_metrics_and_stops_on_sigterm() {
    let (mut child, mut stdout) = launch(&[
        "--listen",
        "127.0.0.1:0",
        "--metrics-listen",
        "127.0.0.1:0",
        "--session-ttl",
        "0.5",
        "--shutdown-grace",
        "600",
    ]);
    let metrics_url = read_line_after(&mut stdout, "metrics on ");
    let addr = read_line_after(&mut stdout, "listening on ");
    assert!(
        addr.starts_with("127.0.0.1:") && !addr.ends_with(":0"),
        "{addr}"
    );
    assert!(metrics_url.starts_with("http://127.0.0.1:") && metrics_url.ends_with("/metrics"));

    let mut client = Client::connect(format!("http://{addr}")).await.unwrap();
    create(&mut client, "bin", config(2)).await;
    assert!(get(&mut client, "bin").await.is_ok());

    let metrics_addr = metrics_url
        .trim_start_matches("http://")
        .trim_end_matches("/metrics")
        .to_string();
    let mut stream = tokio::net::TcpStream::connect(&metrics_addr).await.unwrap();
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    stream
        .write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        .await
        .unwrap();
    let mut page = String::new();
    stream.read_to_string(&mut page).await.unwrap();
    assert!(page.contains("esa_sessions_live 1"), "{page}");

    // The client stays connected: shutdown must not wait for it to leave.
    signal(&child, "TERM");
    assert!(
        wait_exit(&mut child).await,
        "esa-server exited with an error"
    );
    drop(client);
}

#[tokio::test]
async fn serves_a_unix_socket_and_removes_it_on_sigint() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bin.sock");
    let (mut child, mut stdout) =
        launch(&["--uds", path.to_str().unwrap(), "--shutdown-grace", "600"]);
    let addr = read_line_after(&mut stdout, "listening on ");
    assert_eq!(addr, format!("unix:{}", path.display()));
    assert!(path.exists());
    signal(&child, "INT");
    assert!(
        wait_exit(&mut child).await,
        "esa-server exited with an error"
    );
    assert!(!path.exists(), "socket file left behind");
}

// Zenoh needs a multi-thread Tokio runtime.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serves_a_zenoh_shard_beside_grpc() {
    use esa_server::pb;
    use prost::Message as _;

    let (mut child, mut stdout) = launch(&[
        "--listen",
        "127.0.0.1:0",
        "--zenoh",
        "--shard",
        "1/2",
        "--shutdown-grace",
        "600",
    ]);
    let locator = read_line_after(&mut stdout, "zenoh listening on ");
    assert!(locator.starts_with("tcp/127.0.0.1:"), "{locator}");
    let addr = read_line_after(&mut stdout, "listening on ");
    let mut client = Client::connect(format!("http://{addr}")).await.unwrap();
    create(&mut client, "sharded", config(2)).await;

    let mut peer_config =
        esa_server::zenoh_transport::loopback_config(&[], &[locator]).expect("peer config");
    peer_config.insert_json5("listen/endpoints", "[]").unwrap();
    let peer = zenoh::open(peer_config).await.expect("peer session");
    let request = pb::GetSessionRequest {
        session_id: "sharded".into(),
    };
    let replies = peer
        .get("esa/v1/shard/1/GetSession")
        .payload(request.encode_to_vec())
        .await
        .unwrap();
    let reply = replies.recv_async().await.expect("a reply");
    let sample = reply.result().expect("a response");
    let state = pb::GetSessionResponse::decode(&*sample.payload().to_bytes()).unwrap();
    assert_eq!(state, get(&mut client, "sharded").await.unwrap());
    peer.close().await.unwrap();

    signal(&child, "TERM");
    assert!(
        wait_exit(&mut child).await,
        "esa-server exited with an error"
    );
}

#[test]
fn a_bad_zenoh_config_stops_the_server_with_a_message() {
    let output = Command::new(BIN)
        .args([
            "--listen",
            "127.0.0.1:0",
            "--zenoh",
            "--zenoh-config",
            "/nonexistent.json5",
        ])
        .output()
        .unwrap();
    assert_eq!(output.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("/nonexistent.json5"), "{stderr}");
}
