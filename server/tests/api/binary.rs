//! The `esa-server` executable: flags, the `listening on` line, the metrics
//! flag, and clean shutdown on SIGTERM/SIGINT.

use std::process::{Command, Stdio};
use std::time::Duration;

use crate::common::{
    config, create, eventually, exited, get, launch, read_line_after, signal, signal_pid,
    wait_exit, Client, BIN,
};

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
        "--max-session-memory",
        "--metrics-listen",
        "--max-message-bytes",
        "--max-request-memory",
        "--request-timeout",
        "--max-connections",
        "--handshake-timeout",
        "--max-streams-per-connection",
        "--keepalive-interval",
        "--keepalive-timeout",
        "--auth-token-file",
        "--uds-mode",
        "--parent-pid",
        "--remove-dir-on-exit",
        "--shutdown-grace",
        "--state-file",
        "--log-format",
        "--help",
        "--version",
        "RUST_LOG",
        "listening on",
    ] {
        assert!(help.contains(flag), "--help lacks {flag}:\n{help}");
    }
    let zenoh_flags = [
        "--zenoh",
        "--zenoh-prefix",
        "--zenoh-config",
        "--zenoh-listen",
        "--zenoh-connect",
        "--shard",
    ];
    for flag in zenoh_flags {
        assert_eq!(
            help.contains(flag),
            cfg!(feature = "zenoh"),
            "{flag}:\n{help}"
        );
    }
}

/// A gRPC-only build (`--no-default-features`) refuses the Zenoh flags by name.
#[cfg(not(feature = "zenoh"))]
#[test]
fn without_the_zenoh_feature_its_flags_are_refused() {
    let output = Command::new(BIN).arg("--zenoh").output().unwrap();
    assert_eq!(output.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("unexpected argument '--zenoh'"), "{stderr}");
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
        &["--max-session-memory", "lots"],
        &["--request-timeout", "0"],
        &["--uds-mode", "999", "--uds", "/tmp/x.sock"],
        &["--remove-dir-on-exit", "/tmp"],
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
#[cfg(feature = "zenoh")]
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

#[cfg(feature = "zenoh")]
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

/// A launcher (here a shell) passes `--parent-pid $$`: whatever kills the
/// launcher, the server notices it is orphaned, shuts down and removes its
/// directory (no orphans after SIGKILL, SIGTERM or SIGHUP).
#[tokio::test]
async fn the_server_exits_with_its_parent_whatever_kills_it() {
    for (signal_name, number) in [("KILL", 9), ("TERM", 15), ("HUP", 1)] {
        if ignored_here(number) {
            // An ignored signal stays ignored in every child (nohup ignores SIGHUP), so
            // the launcher could not die of it: nothing to test.
            eprintln!("SIG{signal_name} is ignored by this test process: not tested");
            continue;
        }
        let dir = tempfile::tempdir().unwrap();
        let script = r#""$0" --uds "$1/esa.sock" --remove-dir-on-exit "$1" --parent-pid $$ \
            >/dev/null 2>&1 </dev/null & echo $!; wait"#;
        let mut parent = Command::new("bash")
            .args(["-c", script, BIN, dir.path().to_str().unwrap()])
            .stdout(Stdio::piped())
            .spawn()
            .unwrap();
        let mut pid = String::new();
        std::io::BufRead::read_line(
            &mut std::io::BufReader::new(parent.stdout.take().unwrap()),
            &mut pid,
        )
        .unwrap();
        let server: u32 = pid.trim().parse().unwrap();
        let socket = dir.path().join("esa.sock");
        assert!(
            eventually(Duration::from_secs(10), || socket.exists()).await,
            "the server did not start"
        );
        signal(&parent, signal_name);
        parent.wait().unwrap();
        let gone = eventually(Duration::from_secs(5), || exited(server)).await;
        if !gone {
            signal_pid(server, "KILL");
        }
        assert!(gone, "the server outlived its parent's SIG{signal_name}");
        assert!(
            !dir.path().exists(),
            "SIG{signal_name}: directory left behind"
        );
    }
}

/// Whether this process ignores signal `number` (`SigIgn` of /proc/self/status).
fn ignored_here(number: u32) -> bool {
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    let mask = status
        .lines()
        .find_map(|line| line.strip_prefix("SigIgn:"))
        .map(|hex| u64::from_str_radix(hex.trim(), 16).unwrap())
        .unwrap();
    mask & (1 << (number - 1)) != 0
}

#[test]
fn an_auth_token_file_must_hold_a_token() {
    let dir = tempfile::tempdir().unwrap();
    let empty = dir.path().join("empty");
    std::fs::write(&empty, "\n").unwrap();
    for path in [empty.as_path(), &dir.path().join("missing")] {
        let output = Command::new(BIN)
            .args(["--listen", "127.0.0.1:0", "--auth-token-file"])
            .arg(path)
            .output()
            .unwrap();
        assert_eq!(output.status.code(), Some(1));
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(stderr.contains(path.to_str().unwrap()), "{stderr}");
    }
}
