//! The bounded, scale-free law (CONTRACT.md section 1b: Algorithm 1's applied
//! action, action scales, paired references, the trust region) over every
//! transport: gRPC unary (Probe/Report per session), gRPC batch
//! (ProbeBatch/ReportBatch), the StepStream and Zenoh queries. On each: the
//! answers equal `esa_core` run directly (the oracle) on random configs,
//! normalized sessions give the same actions for Q and c1 * Q + c0, v never
//! leaves the trust region whatever Q reports, and every bad value is
//! INVALID_ARGUMENT with nothing changed.

use esa_core::Session;
use esa_server::convert::config_from_proto;
use esa_server::pb;
use esa_server::pb::step_stream_request::Kind as Req;
use esa_server::pb::step_stream_response::Kind as Resp;
use tonic::Code;

use crate::common::{get, Client, Rng};
use crate::stream::Stream;
use crate::zenoh_transport::{query, start_both, Both};

type Failure = (Code, String);

/// One way of carrying batch probes and reports to the server.
enum Wire<'a> {
    /// Probe and Report, one call per session.
    Unary(Client),
    Batch(Client),
    Stream(Stream),
    Zenoh(&'a zenoh::Session),
}

const PREFIX: &str = "esa/v1b";

impl Wire<'_> {
    fn name(&self) -> &'static str {
        match self {
            Wire::Unary(_) => "unary",
            Wire::Batch(_) => "batch",
            Wire::Stream(_) => "stream",
            Wire::Zenoh(_) => "zenoh",
        }
    }

    /// How many sessions a batch may hold here: unary calls are not all-or-nothing
    /// across sessions, so the bad-value checks give them one session.
    fn sessions(&self) -> usize {
        if matches!(self, Wire::Unary(_)) {
            1
        } else {
            3
        }
    }

    async fn create(&mut self, id: &str, config: &pb::SessionConfig) -> Result<(), Failure> {
        let request = pb::CreateSessionRequest {
            session_id: id.into(),
            config: Some(config.clone()),
            progress: None,
        };
        match self {
            Wire::Zenoh(peer) => {
                query::<pb::CreateSessionResponse>(peer, &key("CreateSession"), &request)
                    .await
                    .map(drop)
                    .map_err(stream_failure)
            }
            Wire::Unary(client) | Wire::Batch(client) => client
                .create_session(request)
                .await
                .map(drop)
                .map_err(status_failure),
            // The stream carries only batches; sessions are created beside it.
            Wire::Stream(_) => unreachable!("create stream sessions over gRPC"),
        }
    }

    async fn probe(
        &mut self,
        request: pb::ProbeBatchRequest,
    ) -> Result<pb::ProbeBatchResponse, Failure> {
        match self {
            Wire::Unary(client) => {
                let n = request.session_ids.len();
                let d = request.actions.len() / n;
                // One session sends its vectors whole (so a wrong length reaches the server).
                let part = |values: &[f64], i: usize| {
                    if n == 1 || values.is_empty() {
                        values.to_vec()
                    } else {
                        values[i * d..(i + 1) * d].to_vec()
                    }
                };
                let mut out = pb::ProbeBatchResponse::default();
                for (i, id) in request.session_ids.iter().enumerate() {
                    let scale = part(&request.action_scales, i);
                    let response = client
                        .probe(pb::ProbeRequest {
                            session_id: id.clone(),
                            step: request.steps[i],
                            action: part(&request.actions, i),
                            episode_start: request.episode_starts.get(i).copied().unwrap_or(false),
                            action_scale: scale,
                        })
                        .await
                        .map_err(status_failure)?
                        .into_inner();
                    out.probes.extend(response.probe);
                    out.actions.extend(response.action);
                }
                Ok(out)
            }
            Wire::Batch(client) => client
                .probe_batch(request)
                .await
                .map(tonic::Response::into_inner)
                .map_err(status_failure),
            Wire::Stream(stream) => {
                stream.send(Some(Req::ProbeBatch(request))).await;
                match stream.next().await {
                    Resp::ProbeBatch(response) => Ok(response),
                    Resp::Error(err) => Err(stream_failure(err)),
                    other => panic!("unexpected answer {other:?}"),
                }
            }
            Wire::Zenoh(peer) => query(peer, &key("ProbeBatch"), &request)
                .await
                .map_err(stream_failure),
        }
    }

    async fn report(
        &mut self,
        request: pb::ReportBatchRequest,
    ) -> Result<pb::ReportBatchResponse, Failure> {
        match self {
            Wire::Unary(client) => {
                let mut out = pb::ReportBatchResponse::default();
                for (i, id) in request.session_ids.iter().enumerate() {
                    let response = client
                        .report(pb::ReportRequest {
                            session_id: id.clone(),
                            step: request.steps[i],
                            q_value: request.q_values[i],
                            q_reference: request.q_references.get(i).copied(),
                        })
                        .await
                        .map_err(status_failure)?
                        .into_inner();
                    out.actions.extend(response.action);
                }
                Ok(out)
            }
            Wire::Batch(client) => client
                .report_batch(request)
                .await
                .map(tonic::Response::into_inner)
                .map_err(status_failure),
            Wire::Stream(stream) => {
                stream.send(Some(Req::ReportBatch(request))).await;
                match stream.next().await {
                    Resp::ReportBatch(response) => Ok(response),
                    Resp::Error(err) => Err(stream_failure(err)),
                    other => panic!("unexpected answer {other:?}"),
                }
            }
            Wire::Zenoh(peer) => query(peer, &key("ReportBatch"), &request)
                .await
                .map_err(stream_failure),
        }
    }
}

fn key(rpc: &str) -> String {
    format!("{PREFIX}/{rpc}")
}

fn status_failure(status: tonic::Status) -> Failure {
    (status.code(), status.message().to_owned())
}

fn stream_failure(err: pb::StreamError) -> Failure {
    (Code::from(err.code), err.message)
}

/// A gRPC + Zenoh server on one handler, and the four wires to it.
async fn wires(both: &Both) -> Vec<Wire<'_>> {
    let mut stream_client = both.grpc.client().await;
    vec![
        Wire::Unary(both.grpc.client().await),
        Wire::Batch(both.grpc.client().await),
        Wire::Stream(Stream::open(&mut stream_client).await),
        Wire::Zenoh(&both.peer),
    ]
}

/// An optional value in [lo, hi), present half the time.
fn maybe(rng: &mut Rng, lo: f64, hi: f64) -> Option<f64> {
    rng.coin().then(|| rng.uniform(lo, hi))
}

fn random_config(rng: &mut Rng, d: u32) -> pb::SessionConfig {
    let dt = rng.uniform(0.002, 0.05);
    let bounded = rng.coin();
    pb::SessionConfig {
        action_dim: d,
        dt,
        amplitude: vec![rng.uniform(0.0, 0.5)],
        frequency: (0..d).map(|_| rng.uniform(0.3, 2.9) / dt).collect(),
        learning_rate: vec![rng.uniform(0.0, 1.0)],
        highpass_cutoff: maybe(rng, 0.1, 10.0),
        disable_highpass: rng.coin(),
        action_low: if bounded { vec![-1.5] } else { vec![] },
        action_high: if bounded { vec![1.5] } else { vec![] },
        shift_limit: maybe(rng, 0.05, 2.0),
        lr_decay: maybe(rng, 0.5, 1.0),
        max_episodes: 0,
        normalize_response: rng.coin(),
        response_rms_rate: maybe(rng, 0.01, 1.0),
        response_clip: maybe(rng, 0.5, 5.0),
        shift_leak: maybe(rng, 0.0, 0.2),
        trust_region: maybe(rng, 0.1, 3.0),
    }
}

/// The N sessions' part of one step: sampled actions, scales and the episode-start flags.
struct StepInput {
    actions: Vec<f64>,
    scales: Vec<f64>,
    starts: Vec<bool>,
}

fn step_input(rng: &mut Rng, n: usize, d: usize, t: u64) -> StepInput {
    let scaled = rng.coin();
    StepInput {
        actions: (0..n * d).map(|_| rng.uniform(-1.2, 1.2)).collect(),
        scales: if scaled {
            (0..n * d).map(|_| rng.uniform(0.05, 2.0)).collect()
        } else {
            Vec::new()
        },
        starts: vec![t == 0; n],
    }
}

/// Smooth and bounded in u, with a state-driven level that changes every step.
fn landscape(u: &[f64], level: f64) -> f64 {
    level
        - u.iter()
            .enumerate()
            .map(|(i, x)| (x - 0.2 * i as f64).powi(2) / (1.0 + (x - 0.2 * i as f64).powi(2)))
            .sum::<f64>()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bounded_law_matches_the_core_over_every_transport() {
    let both = start_both(PREFIX).await;
    let mut grpc = both.grpc.client().await;
    let mut rng = Rng(0x51b_2024_cafe_f00d);
    for (w, mut wire) in wires(&both).await.into_iter().enumerate() {
        for case in 0..8 {
            let (n, d) = (1 + case % 3, 1 + (case % 4) as u32);
            let configs: Vec<_> = (0..n).map(|_| random_config(&mut rng, d)).collect();
            let ids: Vec<String> = (0..n).map(|i| format!("oracle-{w}-{case}-{i}")).collect();
            for (id, config) in ids.iter().zip(&configs) {
                create_on(&mut wire, &mut grpc, id, config).await;
            }
            let mut oracle: Vec<Session> = configs
                .iter()
                .map(|c| Session::new(config_from_proto(Some(c.clone())).unwrap()).unwrap())
                .collect();
            let d = d as usize;
            let mut steps = vec![0u64; n];
            for t in 0..60u64 {
                let episode_end = t > 0 && t % 25 == 0;
                let input = step_input(&mut rng, n, d, if episode_end { 0 } else { t });
                if episode_end {
                    steps.fill(0);
                }
                let starts: Vec<bool> = input.starts.iter().map(|s| *s || episode_end).collect();
                let wire_probe = wire
                    .probe(pb::ProbeBatchRequest {
                        session_ids: ids.clone(),
                        steps: steps.clone(),
                        actions: input.actions.clone(),
                        episode_starts: starts.clone(),
                        action_scales: input.scales.clone(),
                    })
                    .await
                    .unwrap_or_else(|e| panic!("{} probe: {e:?}", wire.name()));
                let (mut probes, mut applied) = (Vec::new(), Vec::new());
                for (i, session) in oracle.iter_mut().enumerate() {
                    let scale = if input.scales.is_empty() {
                        &[][..]
                    } else {
                        &input.scales[i * d..(i + 1) * d]
                    };
                    session
                        .probe(
                            steps[i],
                            &input.actions[i * d..(i + 1) * d],
                            scale,
                            starts[i],
                            &mut probes,
                        )
                        .unwrap();
                    session.applied_action(&mut applied);
                }
                assert_eq!(
                    wire_probe.probes,
                    probes,
                    "{} case {case} t {t} probes",
                    wire.name()
                );
                assert_eq!(
                    wire_probe.actions,
                    applied,
                    "{} case {case} t {t} applied",
                    wire.name()
                );
                let level = rng.uniform(-3.0, 3.0);
                let q: Vec<f64> = probes.chunks(d).map(|p| landscape(p, level)).collect();
                let references: Vec<f64> = if rng.coin() {
                    applied.chunks(d).map(|a| landscape(a, level)).collect()
                } else {
                    Vec::new()
                };
                let wire_report = wire
                    .report(pb::ReportBatchRequest {
                        session_ids: ids.clone(),
                        steps: steps.clone(),
                        q_values: q.clone(),
                        q_references: references.clone(),
                    })
                    .await
                    .unwrap_or_else(|e| panic!("{} report: {e:?}", wire.name()));
                let mut improved = Vec::new();
                for (i, session) in oracle.iter_mut().enumerate() {
                    session
                        .report(steps[i], q[i], references.get(i).copied(), &mut improved)
                        .unwrap();
                }
                assert_eq!(
                    wire_report.actions,
                    improved,
                    "{} case {case} t {t} actions",
                    wire.name()
                );
                steps.iter_mut().for_each(|s| *s += 1);
            }
            for (id, session) in ids.iter().zip(&oracle) {
                let state = get(&mut grpc, id).await.unwrap();
                assert_eq!(state.shift, session.shift());
                assert_eq!(state.response_mean_square, session.response_mean_square());
            }
        }
    }
    both.stop().await;
}

async fn create_on(wire: &mut Wire<'_>, grpc: &mut Client, id: &str, config: &pb::SessionConfig) {
    match wire {
        Wire::Stream(_) => {
            let request = pb::CreateSessionRequest {
                session_id: id.into(),
                config: Some(config.clone()),
                progress: None,
            };
            grpc.create_session(request).await.expect("create");
        }
        _ => wire.create(id, config).await.expect("create"),
    }
}

/// Runs one scripted episode sequence through `wire` with Q scaled by `c1` and shifted by `c0`;
/// returns every applied and improved action.
async fn scaled_run(
    wire: &mut Wire<'_>,
    grpc: &mut Client,
    id: &str,
    c1: f64,
    c0: f64,
    paired: bool,
) -> Vec<f64> {
    let config = pb::SessionConfig {
        action_dim: 2,
        dt: 0.008,
        amplitude: vec![0.1],
        frequency: vec![31.4, 23.6],
        learning_rate: vec![0.02],
        normalize_response: true,
        shift_leak: Some(0.005),
        trust_region: Some(1.0),
        ..Default::default()
    };
    create_on(wire, grpc, id, &config).await;
    let mut rng = Rng(7);
    let mut out = Vec::new();
    for t in 0..400u64 {
        let step = t % 200;
        let actions = vec![rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)];
        let sigma = rng.uniform(0.2, 1.0);
        let probe = wire
            .probe(pb::ProbeBatchRequest {
                session_ids: vec![id.into()],
                steps: vec![step],
                actions,
                episode_starts: vec![step == 0],
                action_scales: vec![sigma, sigma],
            })
            .await
            .expect("probe");
        let level = (t as f64 * 0.05).sin() * 5.0;
        let q = c1 * landscape(&probe.probes, level) + c0;
        let reference = paired.then(|| c1 * landscape(&probe.actions, level) + c0);
        let report = wire
            .report(pb::ReportBatchRequest {
                session_ids: vec![id.into()],
                steps: vec![step],
                q_values: vec![q],
                q_references: reference.into_iter().collect(),
            })
            .await
            .expect("report");
        out.extend(probe.actions);
        out.extend(report.actions);
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn normalized_actions_do_not_depend_on_the_scale_of_q_over_every_transport() {
    let both = start_both(PREFIX).await;
    let mut grpc = both.grpc.client().await;
    for (w, mut wire) in wires(&both).await.into_iter().enumerate() {
        for paired in [false, true] {
            let base = scaled_run(
                &mut wire,
                &mut grpc,
                &format!("scale-{w}-{paired}-base"),
                1.0,
                0.0,
                paired,
            )
            .await;
            // Scales at which h^2 stays far above the contract's 1e-12 guard (below it, the
            // invariance holds only up to the guard, as CONTRACT.md says).
            for (c1, c0) in [(0.25, 0.0), (1e3, 0.0), (250.0, -4e3), (30.0, 77.0)] {
                let id = format!("scale-{w}-{paired}-{c1}-{c0}");
                let scaled = scaled_run(&mut wire, &mut grpc, &id, c1, c0, paired).await;
                let worst = base
                    .iter()
                    .zip(&scaled)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                assert!(
                    worst < 1e-6,
                    "{} paired={paired} c1={c1} c0={c0}: max |diff| {worst}",
                    wire.name()
                );
                let moved = base
                    .chunks(4)
                    .any(|pair| pair[0] != pair[2] || pair[1] != pair[3]);
                assert!(
                    moved || worst == 0.0,
                    "the run must move v for the check to mean anything"
                );
            }
        }
    }
    both.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn v_stays_in_the_trust_region_whatever_q_reports_over_every_transport() {
    let both = start_both(PREFIX).await;
    let mut grpc = both.grpc.client().await;
    let mut rng = Rng(99);
    for (w, mut wire) in wires(&both).await.into_iter().enumerate() {
        for normalize_response in [false, true] {
            let id = format!("trust-{w}-{normalize_response}");
            let kappa = 0.5;
            let config = pb::SessionConfig {
                action_dim: 3,
                dt: 0.01,
                amplitude: vec![0.2],
                frequency: vec![60.0, 50.0, 40.0],
                learning_rate: vec![1e3],
                normalize_response,
                trust_region: Some(kappa),
                ..Default::default()
            };
            create_on(&mut wire, &mut grpc, &id, &config).await;
            for t in 0..150u64 {
                let sigma: Vec<f64> = (0..3).map(|_| rng.uniform(0.01, 3.0)).collect();
                let actions: Vec<f64> = (0..3).map(|_| rng.uniform(-1.0, 1.0)).collect();
                let probe = wire
                    .probe(pb::ProbeBatchRequest {
                        session_ids: vec![id.clone()],
                        steps: vec![t],
                        actions: actions.clone(),
                        episode_starts: vec![],
                        action_scales: sigma.clone(),
                    })
                    .await
                    .expect("probe");
                // Adversarial: huge, sign-flipping values that an untrained critic might report.
                let q = rng.uniform(-1.0, 1.0) * 10f64.powf(rng.uniform(-3.0, 300.0));
                wire.report(pb::ReportBatchRequest {
                    session_ids: vec![id.clone()],
                    steps: vec![t],
                    q_values: vec![q],
                    q_references: vec![],
                })
                .await
                .expect("report");
                let state = get(&mut grpc, &id).await.unwrap();
                for ((v, s), (applied, a)) in state
                    .shift
                    .iter()
                    .zip(&sigma)
                    .zip(probe.actions.iter().zip(&actions))
                {
                    assert!(
                        v.abs() <= kappa * s,
                        "{} t {t}: |v| = {} > kappa sigma = {}",
                        wire.name(),
                        v.abs(),
                        kappa * s
                    );
                    assert!(v.is_finite() && applied.is_finite() && a.is_finite());
                }
            }
        }
    }
    both.stop().await;
}

/// One bad request and the field its message must name.
struct Bad {
    what: &'static str,
    field: &'static str,
    /// A wrong count of per-item values, which a unary call cannot express.
    batch_only: bool,
    probe: Option<pb::ProbeBatchRequest>,
    report: Option<pb::ReportBatchRequest>,
}

fn bad_requests(ids: &[String], d: usize) -> Vec<Bad> {
    let n = ids.len();
    let base_probe = pb::ProbeBatchRequest {
        session_ids: ids.to_vec(),
        steps: vec![1; n],
        actions: vec![0.1; n * d],
        episode_starts: vec![],
        action_scales: vec![0.5; n * d],
    };
    let base_report = pb::ReportBatchRequest {
        session_ids: ids.to_vec(),
        steps: vec![0; n],
        q_values: vec![1.0; n],
        q_references: vec![0.5; n],
    };
    let last = n * d - 1;
    let mut bad = Vec::new();
    for (what, value) in [
        ("NaN", f64::NAN),
        ("inf", f64::INFINITY),
        ("-inf", f64::NEG_INFINITY),
        ("zero", 0.0),
        ("negative", -1.0),
    ] {
        let mut probe = base_probe.clone();
        probe.action_scales[last] = value;
        bad.push(Bad {
            what,
            field: "action_scale",
            batch_only: false,
            probe: Some(probe),
            report: None,
        });
    }
    let mut long = base_probe.clone();
    long.action_scales.push(0.5);
    bad.push(Bad {
        what: "action_scales one too many",
        field: "action_scale",
        batch_only: false,
        probe: Some(long),
        report: None,
    });
    for (what, value) in [
        ("NaN", f64::NAN),
        ("inf", f64::INFINITY),
        ("-inf", f64::NEG_INFINITY),
    ] {
        let mut report = base_report.clone();
        report.q_references[n - 1] = value;
        bad.push(Bad {
            what,
            field: "q_reference",
            batch_only: false,
            probe: None,
            report: Some(report),
        });
    }
    let mut long = base_report;
    long.q_references.push(0.0);
    bad.push(Bad {
        what: "q_references one too many",
        field: "q_reference",
        batch_only: true,
        probe: None,
        report: Some(long),
    });
    bad
}

fn bad_configs() -> Vec<(&'static str, pb::SessionConfig)> {
    let good = pb::SessionConfig {
        action_dim: 2,
        dt: 0.01,
        amplitude: vec![0.2],
        frequency: vec![60.0],
        learning_rate: vec![0.25],
        ..Default::default()
    };
    let mut out = Vec::new();
    for rate in [0.0, -0.1, 1.5, f64::NAN, f64::INFINITY] {
        out.push((
            "response_rms_rate",
            pb::SessionConfig {
                response_rms_rate: Some(rate),
                ..good.clone()
            },
        ));
    }
    for leak in [-0.1, 1.0, f64::NAN, f64::INFINITY] {
        out.push((
            "shift_leak",
            pb::SessionConfig {
                shift_leak: Some(leak),
                ..good.clone()
            },
        ));
    }
    for x in [0.0, -2.0, f64::NAN, f64::INFINITY] {
        out.push((
            "response_clip",
            pb::SessionConfig {
                response_clip: Some(x),
                ..good.clone()
            },
        ));
        out.push((
            "trust_region",
            pb::SessionConfig {
                trust_region: Some(x),
                ..good.clone()
            },
        ));
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_bad_value_is_invalid_argument_and_changes_nothing_over_every_transport() {
    let both = start_both(PREFIX).await;
    let mut grpc = both.grpc.client().await;
    for (w, mut wire) in wires(&both).await.into_iter().enumerate() {
        // Bad configs: refused, and no session is created.
        if !matches!(wire, Wire::Stream(_)) {
            for (c, (field, config)) in bad_configs().into_iter().enumerate() {
                let id = format!("bad-config-{w}-{c}");
                let (code, message) = wire.create(&id, &config).await.expect_err("bad config");
                assert_eq!(
                    code,
                    Code::InvalidArgument,
                    "{} {field}: {message}",
                    wire.name()
                );
                assert!(
                    message.contains(field),
                    "{} message {message:?} names {field}",
                    wire.name()
                );
                assert_eq!(
                    get(&mut grpc, &id).await.unwrap_err().code(),
                    Code::NotFound
                );
            }
        }
        // Bad probe and report fields: refused with every session as it was.
        let d = 2;
        let ids: Vec<String> = (0..wire.sessions())
            .map(|i| format!("bad-{w}-{i}"))
            .collect();
        let config = pb::SessionConfig {
            action_dim: d as u32,
            dt: 0.01,
            amplitude: vec![0.2],
            frequency: vec![60.0],
            learning_rate: vec![0.25],
            normalize_response: true,
            trust_region: Some(1.0),
            ..Default::default()
        };
        for id in &ids {
            create_on(&mut wire, &mut grpc, id, &config).await;
        }
        // Step 0 done and step 1 probed, so both a probe of step 1 and a report of step 1 are valid.
        let n = ids.len();
        for step in 0..2u64 {
            wire.probe(pb::ProbeBatchRequest {
                session_ids: ids.clone(),
                steps: vec![step; n],
                actions: vec![0.3; n * d],
                episode_starts: vec![],
                action_scales: vec![],
            })
            .await
            .expect("probe");
            if step == 0 {
                wire.report(pb::ReportBatchRequest {
                    session_ids: ids.clone(),
                    steps: vec![0; n],
                    q_values: vec![2.0; n],
                    q_references: vec![],
                })
                .await
                .expect("report");
            }
        }
        for bad in bad_requests(&ids, d) {
            if bad.batch_only && matches!(wire, Wire::Unary(_)) {
                continue;
            }
            let mut before = Vec::new();
            for id in &ids {
                before.push(get(&mut grpc, id).await.unwrap());
            }
            let result = match (bad.probe, bad.report) {
                (Some(probe), _) => wire.probe(probe).await.map(drop),
                (_, Some(mut report)) => {
                    report.steps = vec![1; n];
                    wire.report(report).await.map(drop)
                }
                _ => unreachable!(),
            };
            let (code, message) = result.expect_err(bad.what);
            assert_eq!(
                code,
                Code::InvalidArgument,
                "{} {}: {message}",
                wire.name(),
                bad.what
            );
            assert!(
                message.contains(bad.field),
                "{} {}: {message:?} names {}",
                wire.name(),
                bad.what,
                bad.field
            );
            for (id, was) in ids.iter().zip(&before) {
                assert_eq!(
                    &get(&mut grpc, id).await.unwrap(),
                    was,
                    "{} {}: session changed",
                    wire.name(),
                    bad.what
                );
            }
        }
    }
    both.stop().await;
}
