//! StepStream's `step_linear_batch` and `step_batch`: the same bits as a ProbeBatch and the
//! ReportBatch of the critic at its probes, shifts from which a client computes the next probes
//! and actions ahead with esa-core's functions, and bad critics answered in-band with nothing
//! changed.

use esa_core::fused_step;
use esa_core::Session;
use esa_proto::convert::config_from_proto;
use esa_server::pb;
use esa_server::pb::step_stream_request::Kind as Req;
use esa_server::pb::step_stream_response::Kind as Resp;
use tonic::Code;

use crate::common::{create, get, start, Client};
use crate::stream::Stream;

const IDS: [&str; 2] = ["fused-0", "fused-1"];
const TWINS: [&str; 2] = ["twin-0", "twin-1"];
const GIVEN: [&str; 2] = ["given-0", "given-1"];

/// Section 1b in full: bounds, a limit, a trust region, the normalization and a leak.
fn config() -> pb::SessionConfig {
    pb::SessionConfig {
        action_dim: 2,
        dt: 0.02,
        amplitude: vec![0.3],
        frequency: vec![40.0, 25.0],
        learning_rate: vec![0.5],
        action_low: vec![-1.0],
        action_high: vec![1.0],
        shift_limit: Some(0.4),
        normalize_response: true,
        shift_leak: Some(0.01),
        trust_region: Some(1.5),
        ..Default::default()
    }
}

fn probe(
    ids: &[&str],
    steps: &[u64],
    actions: &[f64],
    starts: &[bool],
    scales: &[f64],
) -> pb::ProbeBatchRequest {
    pb::ProbeBatchRequest {
        session_ids: ids.iter().map(|id| id.to_string()).collect(),
        steps: steps.to_vec(),
        actions: actions.to_vec(),
        episode_starts: starts.to_vec(),
        action_scales: scales.to_vec(),
    }
}

fn linear(gains: &[f64], offsets: &[f64], points: &[f64]) -> Vec<f64> {
    gains
        .chunks(2)
        .zip(points.chunks(2))
        .zip(offsets)
        .map(|((g, a), c)| g.iter().zip(a).map(|(g, a)| g * a).sum::<f64>() + c)
        .collect()
}

async fn shifts(client: &mut Client, ids: &[&str]) -> Vec<f64> {
    let mut all = Vec::new();
    for id in ids {
        all.extend(get(client, id).await.expect("session").shift);
    }
    all
}

#[tokio::test]
async fn a_fused_step_is_the_probe_and_the_critics_report_and_its_shifts_predict_the_next_action() {
    let server = start().await;
    let mut client = server.client().await;
    for id in IDS.iter().chain(&TWINS).chain(&GIVEN) {
        create(&mut client, id, config()).await;
    }
    let mut stream = Stream::open(&mut client).await;
    // What a client of the pipelined step holds: fresh sessions of the configs.
    let local = vec![Session::new(config_from_proto(config())).expect("valid"); 2];
    let mut ahead = vec![0.0; 4];
    let mut steps = [0u64; 2];
    for t in 0..60u64 {
        let x = t as f64;
        let actions = [0.9 * (0.3 * x).sin(), -0.4, 0.2 * (0.1 * x).cos(), 1.3];
        let scales = [0.5 + 0.4 * (0.2 * x).sin(), 0.3, 0.05 + 0.01 * x, 0.8];
        let gains = [1.0 + 0.1 * x, -2.0, 0.5, 3.0 * (0.05 * x).cos()];
        let offsets = [x, -1.0];
        // Session 1's episodes end every 17 steps, session 0's at t = 30 only.
        let starts = [t == 0 || t == 30, t % 17 == 0];
        for (step, start) in steps.iter_mut().zip(starts) {
            if start {
                *step = 0;
            }
        }
        stream
            .send(Some(Req::StepLinearBatch(pb::StepLinearBatchRequest {
                probe: Some(probe(&IDS, &steps, &actions, &starts, &scales)),
                critic_gains: gains.to_vec(),
                critic_offsets: offsets.to_vec(),
                paired: true,
            })))
            .await;
        let Resp::StepLinearBatch(fused) = stream.next().await else {
            panic!("expected a step_linear_batch answer");
        };

        // The client's own probes and actions, from the previous answer's shifts; the critic
        // evaluated there goes with the step.
        for (i, start) in starts.iter().enumerate() {
            if *start {
                ahead[2 * i..2 * i + 2].fill(0.0);
            }
        }
        let (mut ahead_probes, mut ahead_actions) = (Vec::new(), Vec::new());
        fused_step::probes_ahead(
            &local,
            &ahead,
            &steps,
            &actions,
            &scales,
            &mut ahead_probes,
            &mut ahead_actions,
        )
        .expect("valid");
        stream
            .send(Some(Req::StepBatch(pb::StepBatchRequest {
                probe: Some(probe(&GIVEN, &steps, &actions, &starts, &scales)),
                q_values: linear(&gains, &offsets, &ahead_probes),
                q_references: linear(&gains, &offsets, &ahead_actions),
            })))
            .await;
        let Resp::StepBatch(given) = stream.next().await else {
            panic!("expected a step_batch answer");
        };

        stream
            .send(Some(Req::ProbeBatch(probe(
                &TWINS, &steps, &actions, &starts, &scales,
            ))))
            .await;
        let Resp::ProbeBatch(probed) = stream.next().await else {
            panic!("expected a probe_batch answer");
        };
        stream
            .send(Some(Req::ReportBatch(pb::ReportBatchRequest {
                session_ids: TWINS.iter().map(|id| id.to_string()).collect(),
                steps: steps.to_vec(),
                q_values: linear(&gains, &offsets, &probed.probes),
                q_references: linear(&gains, &offsets, &probed.actions),
            })))
            .await;
        assert!(matches!(stream.next().await, Resp::ReportBatch(_)));

        assert_eq!(fused.probes, probed.probes, "t = {t}");
        assert_eq!(fused.actions, probed.actions, "t = {t}");
        assert_eq!(fused.shifts, shifts(&mut client, &TWINS).await, "t = {t}");
        assert_eq!(fused.shifts, shifts(&mut client, &IDS).await, "t = {t}");
        let mut predicted = Vec::new();
        fused_step::applied_ahead(&local, &ahead, &actions, &scales, &mut predicted)
            .expect("valid");
        assert_eq!(predicted, fused.actions, "t = {t}");
        assert_eq!(
            (&ahead_probes, &ahead_actions),
            (&fused.probes, &fused.actions),
            "t = {t}"
        );
        assert_eq!(given, fused, "t = {t}");
        ahead = fused.shifts;
        steps = steps.map(|s| s + 1);
    }
    for id in IDS.iter().chain(&GIVEN) {
        let state = get(&mut client, id).await.expect("session");
        assert!(!state.probe_pending, "a fused step leaves no probe pending");
    }
    server.stop().await;
}

#[tokio::test]
async fn bad_fused_steps_are_answered_in_band_and_change_nothing() {
    let server = start().await;
    let mut client = server.client().await;
    create(&mut client, "s", config()).await;
    let mut stream = Stream::open(&mut client).await;
    let good = |gains: Vec<f64>, offsets: Vec<f64>| {
        Some(Req::StepLinearBatch(pb::StepLinearBatchRequest {
            probe: Some(probe(&["s"], &[0], &[0.1, 0.2], &[], &[])),
            critic_gains: gains,
            critic_offsets: offsets,
            paired: false,
        }))
    };
    let given = |q_values: Vec<f64>, q_references: Vec<f64>| {
        Some(Req::StepBatch(pb::StepBatchRequest {
            probe: Some(probe(&["s"], &[0], &[0.1, 0.2], &[], &[])),
            q_values,
            q_references,
        }))
    };
    let cases = [
        (
            good(vec![1.0], vec![0.0]),
            Code::InvalidArgument,
            "critic_gains: expected 2 values, got 1",
        ),
        (
            good(vec![1.0, f64::NAN], vec![0.0]),
            Code::InvalidArgument,
            "critic_gains: expected finite",
        ),
        (
            good(vec![1.0, 1.0], vec![]),
            Code::InvalidArgument,
            "critic_offsets: expected 1 values, got 0",
        ),
        (
            good(vec![1.0, 1.0], vec![f64::INFINITY]),
            Code::InvalidArgument,
            "critic_offsets: expected finite",
        ),
        (
            Some(Req::StepLinearBatch(pb::StepLinearBatchRequest {
                probe: None,
                critic_gains: vec![1.0, 1.0],
                critic_offsets: vec![0.0],
                paired: false,
            })),
            Code::InvalidArgument,
            "probe: expected",
        ),
        (
            Some(Req::StepLinearBatch(pb::StepLinearBatchRequest {
                probe: Some(probe(&["s"], &[3], &[0.1, 0.2], &[], &[])),
                critic_gains: vec![1.0, 1.0],
                critic_offsets: vec![0.0],
                paired: false,
            })),
            Code::FailedPrecondition,
            "item 0",
        ),
        (
            Some(Req::StepLinearBatch(pb::StepLinearBatchRequest {
                probe: Some(probe(&["ghost"], &[0], &[0.1, 0.2], &[], &[])),
                critic_gains: vec![1.0, 1.0],
                critic_offsets: vec![0.0],
                paired: false,
            })),
            Code::NotFound,
            "ghost",
        ),
        (
            given(vec![], vec![]),
            Code::InvalidArgument,
            "q_values: expected 1 values",
        ),
        (
            given(vec![1.0], vec![1.0, 2.0]),
            Code::InvalidArgument,
            "q_references: expected 1 values",
        ),
        (
            given(vec![f64::NAN], vec![]),
            Code::InvalidArgument,
            "q_value: expected a finite number",
        ),
        (
            given(vec![1.0], vec![f64::NEG_INFINITY]),
            Code::InvalidArgument,
            "q_reference: expected a finite number",
        ),
        (
            Some(Req::StepBatch(pb::StepBatchRequest {
                probe: None,
                q_values: vec![1.0],
                q_references: vec![],
            })),
            Code::InvalidArgument,
            "probe: expected",
        ),
    ];
    let before = get(&mut client, "s").await.expect("session");
    for (request, code, needle) in cases {
        stream.send(request).await;
        let Resp::Error(error) = stream.next().await else {
            panic!("expected an error for {needle}");
        };
        assert_eq!(error.code, code as i32, "{}", error.message);
        assert!(
            error.message.contains(needle),
            "{} lacks {needle}",
            error.message
        );
        assert_eq!(get(&mut client, "s").await.expect("session"), before);
    }
    // The stream stays open, and a good step goes through.
    stream.send(good(vec![1.0, 1.0], vec![0.0])).await;
    assert!(matches!(stream.next().await, Resp::StepLinearBatch(r) if r.shifts.len() == 2));
    assert_eq!(get(&mut client, "s").await.expect("session").step, 1);
    stream
        .send(Some(Req::StepBatch(pb::StepBatchRequest {
            probe: Some(probe(&["s"], &[1], &[0.1, 0.2], &[], &[])),
            q_values: vec![0.5],
            q_references: vec![],
        })))
        .await;
    assert!(matches!(stream.next().await, Resp::StepBatch(r) if r.shifts.len() == 2));
    assert_eq!(get(&mut client, "s").await.expect("session").step, 2);
    server.stop().await;
}
