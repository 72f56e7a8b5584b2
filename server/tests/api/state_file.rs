//! `--state-file`: a server stopped with SIGTERM and started again continues every session bit for
//! bit (a retried report is still a replay); a file that is truncated, corrupt, foreign, of a
//! newer format or writable by others stops the start and stays where it is; sessions idle past
//! the TTL stay dead. And CreateSession's `progress`, with the progress batch answers carry.

use std::os::unix::fs::PermissionsExt as _;
use std::path::Path;
use std::process::{Child, Command};

use esa_core::Session;
use esa_server::pb;
use tonic::Code;

use crate::common::{
    assert_error, config, create, get, launch, probe, read_line_after, report, signal, start,
    wait_exit, Client, BIN,
};

/// Section 1b's law with every field that carries state across reports and episodes.
fn stateful_config() -> pb::SessionConfig {
    pb::SessionConfig {
        action_dim: 2,
        dt: 0.05,
        amplitude: vec![0.2],
        frequency: vec![20.0, 9.0],
        learning_rate: vec![0.3],
        lr_decay: Some(0.8),
        normalize_response: true,
        shift_leak: Some(0.01),
        trust_region: Some(1.5),
        ..Default::default()
    }
}

async fn serve(state: &Path, extra: &[&str]) -> (Child, Client) {
    let (child, mut stdout) = launch(
        &[
            &[
                "--listen",
                "127.0.0.1:0",
                "--state-file",
                state.to_str().unwrap(),
            ],
            extra,
        ]
        .concat(),
    );
    let addr = read_line_after(&mut stdout, "listening on ");
    let client = Client::connect(format!("http://{addr}")).await.unwrap();
    (child, client)
}

async fn stop(mut child: Child, client: Client) {
    signal(&child, "TERM");
    assert!(
        wait_exit(&mut child).await,
        "esa-server exited with an error"
    );
    drop(client);
}

fn action(t: u64) -> [f64; 2] {
    [0.4 * (t as f64 * 0.3).sin(), -0.1]
}

fn q(t: u64) -> f64 {
    (t as f64 * 0.7).cos() * 10.0
}

/// One probe and report at `t` (an episode start at 0) on the server and on a local session;
/// asserts that they answer the same bits.
async fn step_both(client: &mut Client, local: &mut Session, id: &str, t: u64) {
    let mut expected = Vec::new();
    local
        .probe(t, &action(t), &[], t == 0, &mut expected)
        .unwrap();
    let probed = probe(client, id, t, &action(t), t == 0).await.unwrap();
    assert_eq!(bits(&probed.probe), bits(&expected), "probe of step {t}");
    expected.clear();
    local.report(t, q(t), None, &mut expected).unwrap();
    let reported = report(client, id, t, q(t)).await.unwrap();
    assert_eq!(
        bits(&reported.action),
        bits(&expected),
        "report of step {t}"
    );
}

fn bits(values: &[f64]) -> Vec<u64> {
    values.iter().map(|x| x.to_bits()).collect()
}

#[tokio::test]
async fn a_sigterm_and_a_restart_continue_every_session_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    let (child, mut client) = serve(&state, &[]).await;
    assert!(!state.exists(), "nothing to load, nothing written yet");
    let stateful = stateful_config();
    let mut local = Session::new(esa_proto::convert::config_from_proto(stateful.clone())).unwrap();
    create(&mut client, "a", stateful).await;
    create(&mut client, "pending", config(1)).await;
    for t in [0, 1, 2, 3, 0, 1, 2, 0, 1, 2, 3, 4] {
        step_both(&mut client, &mut local, "a", t).await;
    }
    probe(&mut client, "pending", 0, &[0.5], true)
        .await
        .unwrap();
    let before = [
        get(&mut client, "a").await.unwrap(),
        get(&mut client, "pending").await.unwrap(),
    ];
    assert_eq!(before[0].episodes_completed, 2);
    assert!(before[0].response_mean_square.is_some() && before[1].probe_pending);
    stop(child, client).await;

    let mode = std::fs::metadata(&state).unwrap().permissions().mode();
    assert_eq!(mode & 0o777, 0o600, "the state file is private");
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|entry| entry.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, [".state.lock", "state"], "no temporary file is left");

    let (child, mut client) = serve(&state, &[]).await;
    assert!(!state.exists(), "a loaded state file is removed");
    let after = [
        get(&mut client, "a").await.unwrap(),
        get(&mut client, "pending").await.unwrap(),
    ];
    assert_eq!(after, before);
    // The report of step 4 was applied before the stop: sent again, it is a replay.
    let replayed = report(&mut client, "a", 4, 123.0).await.unwrap();
    let mut expected = Vec::new();
    local.report(4, 123.0, None, &mut expected).unwrap();
    assert_eq!(bits(&replayed.action), bits(&expected));
    for t in [5, 6, 0, 1, 2] {
        step_both(&mut client, &mut local, "a", t).await;
    }
    let reported = report(&mut client, "pending", 0, 1.0).await.unwrap();
    assert_eq!(reported.step, 0);
    stop(child, client).await;
    // And again: a restored session is saved like any other.
    let (child, mut client) = serve(&state, &[]).await;
    for t in [3, 4] {
        step_both(&mut client, &mut local, "a", t).await;
    }
    stop(child, client).await;
}

/// The fixture of format 1, written by esa-server 0.1.0 (`write_the_format_1_fixture`): every
/// later version must keep reading it, so that an upgrade continues the sessions.
const FORMAT_1: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/state-format-1");

/// What the fixture's server was asked, replayed on `client` and on local sessions.
async fn fixture_requests(client: &mut Client) -> Session {
    let stateful = stateful_config();
    let mut local = Session::new(esa_proto::convert::config_from_proto(stateful.clone())).unwrap();
    create(client, "golden", stateful).await;
    for t in [0, 1, 2, 3, 0, 1, 2] {
        step_both(client, &mut local, "golden", t).await;
    }
    create(client, "golden-pending", config(1)).await;
    probe(client, "golden-pending", 0, &[0.5], true)
        .await
        .unwrap();
    local
}

/// Writes the format 1 fixture (`cargo test -p esa-server --test api -- --ignored
/// write_the_format_1_fixture`): only when the format's first release is cut.
#[tokio::test]
#[ignore = "writes tests/data/state-format-1"]
async fn write_the_format_1_fixture() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    let (child, mut client) = serve(&state, &[]).await;
    fixture_requests(&mut client).await;
    stop(child, client).await;
    std::fs::copy(&state, FORMAT_1).unwrap();
}

#[tokio::test]
async fn a_state_file_of_an_earlier_version_continues_its_sessions() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    write_private(&state, &std::fs::read(FORMAT_1).unwrap());
    // The fixture was written long ago: its sessions live only without a TTL.
    let (child, mut old) = serve(&state, &["--session-ttl", "0"]).await;
    let (fresh, mut client) = serve(&dir.path().join("fresh"), &[]).await;
    let mut local = fixture_requests(&mut client).await;
    for id in ["golden", "golden-pending"] {
        assert_eq!(
            get(&mut old, id).await.unwrap(),
            get(&mut client, id).await.unwrap(),
            "{id}"
        );
    }
    for t in [3, 4, 0, 1] {
        step_both(&mut old, &mut local, "golden", t).await;
    }
    stop(child, old).await;
    stop(fresh, client).await;
}

#[tokio::test]
async fn a_second_server_on_the_same_state_file_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    let (child, client) = serve(&state, &[]).await;
    refuses(&state, &["another esa-server uses it"]);
    stop(child, client).await;
}

#[tokio::test]
async fn sessions_idle_past_the_ttl_of_the_new_server_are_not_restored() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    let (child, mut client) = serve(&state, &[]).await;
    create(&mut client, "idle", config(1)).await;
    stop(child, client).await;
    // The session has been idle at least for the restart, longer than a microsecond.
    let (child, mut client) = serve(&state, &["--session-ttl", "0.000001"]).await;
    assert_error(get(&mut client, "idle").await, Code::NotFound, &["idle"]);
    stop(child, client).await;
}

/// Starts the executable on `state` and expects it to refuse, with `needles` in its message.
fn refuses(state: &Path, needles: &[&str]) {
    let output = Command::new(BIN)
        .args(["--listen", "127.0.0.1:0", "--state-file"])
        .arg(state)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(!String::from_utf8_lossy(&output.stdout).contains("listening on"));
    for needle in needles {
        assert!(stderr.contains(needle), "{needle:?} not in {stderr}");
    }
}

/// A valid state file holding one session, as bytes.
async fn valid_file(dir: &Path) -> Vec<u8> {
    let state = dir.join("valid");
    let (child, mut client) = serve(&state, &[]).await;
    create(&mut client, "s", stateful_config()).await;
    stop(child, client).await;
    let bytes = std::fs::read(&state).unwrap();
    std::fs::remove_file(&state).unwrap();
    bytes
}

fn write_private(path: &Path, bytes: &[u8]) {
    let _ = std::fs::remove_file(path);
    std::fs::write(path, bytes).unwrap();
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o600)).unwrap();
}

#[tokio::test]
async fn a_bad_state_file_stops_the_start_and_stays() {
    let dir = tempfile::tempdir().unwrap();
    let good = valid_file(dir.path()).await;
    let text = String::from_utf8(good.clone()).unwrap();
    let header_end = text.find('\n').unwrap();
    let flip = header_end + 1 + (good.len() - header_end) / 2;
    let mut corrupt = good.clone();
    corrupt[flip] ^= 0x01;
    let newer = text.replacen("format 1,", "format 2,", 1);
    let mut extra = good.clone();
    extra.extend_from_slice(b"{}");
    let cases: [(&str, Vec<u8>, &[&str]); 7] = [
        ("empty", Vec::new(), &["not an esa-server state file"]),
        (
            "truncated",
            good[..good.len() - 10].to_vec(),
            &["truncated"],
        ),
        ("corrupt", corrupt, &["corrupt", "checksum"]),
        ("extra", extra, &["2 bytes after its end"]),
        (
            "foreign",
            b"[sessions]\nid = 1\n".to_vec(),
            &["not an esa-server state file"],
        ),
        ("newer", newer.into_bytes(), &["format 2", "reads format 1"]),
        (
            "binary",
            vec![0xff; 4096],
            &["not an esa-server state file"],
        ),
    ];
    for (name, bytes, needles) in cases {
        let path = dir.path().join(name);
        write_private(&path, &bytes);
        refuses(&path, needles);
        assert_eq!(
            std::fs::read(&path).unwrap(),
            bytes,
            "{name} is left as it was"
        );
    }
}

#[tokio::test]
async fn a_state_file_with_an_impossible_session_stops_the_start() {
    let dir = tempfile::tempdir().unwrap();
    let good = String::from_utf8(valid_file(dir.path()).await).unwrap();
    let (header, body) = good.split_once('\n').unwrap();
    assert!(header.starts_with("esa-server state file, format 1, "));
    // A valid checksum over a session no client could have made: NaN has no JSON, a negative
    // mean square no session.
    let spoiled = body.replacen(
        "\"response_mean_square\":null",
        "\"response_mean_square\":-4.0",
        1,
    );
    assert_ne!(spoiled, body);
    let header = format!(
        "esa-server state file, format 1, {} bytes, crc32 {:08x}",
        spoiled.len(),
        crc32fast::hash(spoiled.as_bytes())
    );
    let path = dir.path().join("impossible");
    write_private(&path, format!("{header}\n{spoiled}").as_bytes());
    refuses(
        &path,
        &["session \"s\" is not valid", "response_mean_square"],
    );
}

#[tokio::test]
async fn a_state_file_others_can_write_or_a_link_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let good = valid_file(dir.path()).await;
    for mode in [0o620, 0o602, 0o666] {
        let path = dir.path().join(format!("mode{mode:o}"));
        write_private(&path, &good);
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(mode)).unwrap();
        refuses(&path, &["refused", "others can write it", "chmod 600"]);
        assert!(path.exists());
    }
    let target = dir.path().join("target");
    write_private(&target, &good);
    let link = dir.path().join("link");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    refuses(&link, &["refused", "symbolic link"]);
    let directory = dir.path().join("directory");
    std::fs::create_dir(&directory).unwrap();
    refuses(&directory, &["refused", "not a regular file"]);
    refuses(
        &dir.path().join("missing-dir").join("state"),
        &["--state-file: cannot write state file"],
    );
}

#[tokio::test]
async fn create_session_resumes_a_lost_sessions_progress() {
    let server = start().await;
    let mut client = server.client().await;
    let resume = |id: &str, config: pb::SessionConfig, progress| pb::CreateSessionRequest {
        session_id: id.into(),
        config: Some(config),
        progress: Some(progress),
    };
    let progress = pb::SessionProgress {
        episodes_completed: 3,
        response_mean_square: Some(2.5),
    };
    client
        .create_session(resume("r", stateful_config(), progress))
        .await
        .unwrap();
    let state = get(&mut client, "r").await.unwrap();
    assert_eq!(
        (
            state.step,
            state.episodes_completed,
            state.response_mean_square
        ),
        (0, 3, Some(2.5))
    );
    // It steps as a session that lived through three episodes with that mean square.
    let core_config = esa_proto::convert::config_from_proto(stateful_config());
    let mut local = Session::resume(core_config, 3, Some(2.5)).unwrap();
    for t in 0..5 {
        step_both(&mut client, &mut local, "r", t).await;
    }
    // An existing session is newer than what the client saw: it stays as it is.
    client
        .create_session(resume(
            "r",
            stateful_config(),
            pb::SessionProgress::default(),
        ))
        .await
        .unwrap();
    assert_eq!(get(&mut client, "r").await.unwrap().step, 5);
    for (config, m, needle) in [
        (
            config(1),
            Some(1.0),
            "expected none without normalize_response",
        ),
        (
            stateful_config(),
            Some(-1.0),
            "expected a finite number >= 0",
        ),
        (
            stateful_config(),
            Some(f64::NAN),
            "expected a finite number >= 0",
        ),
    ] {
        let progress = pb::SessionProgress {
            episodes_completed: 0,
            response_mean_square: m,
        };
        assert_error(
            client
                .create_session(resume("bad", config, progress))
                .await
                .map(tonic::Response::into_inner),
            Code::InvalidArgument,
            &["response_mean_square", needle],
        );
    }
    assert_error(get(&mut client, "bad").await, Code::NotFound, &["bad"]);
    server.stop().await;
}

#[tokio::test]
async fn batch_answers_carry_each_sessions_progress() {
    let server = start().await;
    let mut client = server.client().await;
    create(&mut client, "n", stateful_config()).await;
    create(&mut client, "p", config(2)).await;
    let ids = vec!["n".to_string(), "p".to_string()];
    let probe_batch = |steps: Vec<u64>, starts: Vec<bool>| pb::ProbeBatchRequest {
        session_ids: ids.clone(),
        steps,
        actions: vec![0.1; 4],
        episode_starts: starts,
        action_scales: Vec::new(),
    };
    let answer = client
        .probe_batch(probe_batch(vec![0, 0], vec![true, true]))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.episodes_completed, [0, 0]);
    assert_eq!(answer.response_mean_squares, [-1.0, -1.0], "m unset: -1");
    client
        .report_batch(pb::ReportBatchRequest {
            session_ids: ids.clone(),
            steps: vec![0, 0],
            q_values: vec![1.0, 1.0],
            q_references: vec![0.0, 0.0],
        })
        .await
        .unwrap();
    let mut stream_requests = Vec::new();
    for (t, q) in [(1, 3.0), (2, -2.0)] {
        stream_requests.push(pb::StepStreamRequest {
            kind: Some(pb::step_stream_request::Kind::StepBatch(
                pb::StepBatchRequest {
                    probe: Some(probe_batch(vec![t, t], Vec::new())),
                    q_values: vec![q, q],
                    q_references: Vec::new(),
                },
            )),
        });
    }
    stream_requests.push(pb::StepStreamRequest {
        kind: Some(pb::step_stream_request::Kind::ProbeBatch(probe_batch(
            vec![0, 0],
            vec![true, true],
        ))),
    });
    let mut answers = client
        .step_stream(tokio_stream::iter(stream_requests))
        .await
        .unwrap()
        .into_inner();
    use pb::step_stream_response::Kind;
    let mut last_m = 0.0;
    for _ in 0..2 {
        let Some(Kind::StepBatch(step)) = answers.message().await.unwrap().unwrap().kind else {
            panic!("expected a step answer");
        };
        assert_eq!(step.episodes_completed, [0, 0]);
        let [m, unset] = step.response_mean_squares[..] else {
            panic!(
                "expected two mean squares, got {:?}",
                step.response_mean_squares
            );
        };
        assert_eq!(unset, -1.0, "a session without normalize_response: -1");
        assert!(m > 0.0 && m != last_m, "{m}");
        last_m = m;
    }
    let Some(Kind::ProbeBatch(start)) = answers.message().await.unwrap().unwrap().kind else {
        panic!("expected a probe answer");
    };
    assert_eq!(start.episodes_completed, [1, 1]);
    assert_eq!(
        start.response_mean_squares[0], last_m,
        "a probe does not move m"
    );
    let state = get(&mut client, "n").await.unwrap();
    assert_eq!(state.response_mean_square, Some(last_m));
    // No session of the batch normalizes: no mean squares at all.
    let plain = client
        .probe_batch(pb::ProbeBatchRequest {
            session_ids: vec!["p".into()],
            steps: vec![0],
            actions: vec![0.0; 2],
            episode_starts: vec![true],
            action_scales: Vec::new(),
        })
        .await
        .unwrap()
        .into_inner();
    assert!(plain.response_mean_squares.is_empty());
    // Its pending probe of step 0 ends a second episode.
    assert_eq!(plain.episodes_completed, [2]);
    server.stop().await;
}
