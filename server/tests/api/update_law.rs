//! The update law over the wire equals `esa_core` run directly, on random
//! configs and inputs, to the bit (doubles travel losslessly in protobuf),
//! including CONTRACT.md section 1b (applied action, action scale, paired
//! reference, normalization, leak, trust region).

use esa_core::Session;
use esa_server::convert::config_from_proto;
use esa_server::pb;

use crate::common::{create, get, probe_scaled, report_paired, start, Rng};

/// Length 1 (broadcast) or `d` values in [lo, hi).
fn vector(rng: &mut Rng, d: u32, lo: f64, hi: f64) -> Vec<f64> {
    let len = if rng.below(2) == 0 { 1 } else { d };
    (0..len).map(|_| rng.uniform(lo, hi)).collect()
}

fn random_config(rng: &mut Rng) -> pb::SessionConfig {
    let d = 1 + rng.below(6) as u32;
    let dt = rng.uniform(0.001, 0.05);
    let bounded = rng.below(2) == 0;
    pb::SessionConfig {
        action_dim: d,
        dt,
        amplitude: vector(rng, d, 0.0, 0.5),
        // Strictly below Nyquist: w * dt < pi.
        frequency: vector(rng, d, 0.5 / dt, 3.0 / dt),
        learning_rate: vector(rng, d, 0.0, 2.0),
        highpass_cutoff: (rng.below(2) == 0).then(|| rng.uniform(0.1, 10.0)),
        disable_highpass: rng.below(3) == 0,
        action_low: if bounded { vec![-1.0] } else { vec![] },
        action_high: if bounded {
            vector(rng, d, 0.5, 2.0)
        } else {
            vec![]
        },
        shift_limit: (rng.below(2) == 0).then(|| rng.uniform(0.05, 1.0)),
        lr_decay: (rng.below(2) == 0).then(|| rng.uniform(0.5, 1.0)),
        max_episodes: rng.below(3),
        normalize_response: rng.below(2) == 0,
        response_rms_rate: (rng.below(2) == 0).then(|| rng.uniform(0.01, 1.0)),
        response_clip: (rng.below(2) == 0).then(|| rng.uniform(0.5, 5.0)),
        shift_leak: (rng.below(2) == 0).then(|| rng.uniform(0.0, 0.2)),
        trust_region: (rng.below(2) == 0).then(|| rng.uniform(0.1, 3.0)),
    }
}

#[tokio::test]
async fn wire_results_equal_the_core_on_random_configs() {
    let server = start().await;
    let mut client = server.client().await;
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    for case in 0..48 {
        let cfg = random_config(&mut rng);
        let id = format!("case-{case}");
        create(&mut client, &id, cfg.clone()).await;
        let mut core = Session::new(config_from_proto(Some(cfg.clone())).unwrap()).unwrap();
        let d = cfg.action_dim as usize;
        let target: Vec<f64> = (0..d).map(|_| rng.uniform(-1.0, 1.0)).collect();
        // Bounded so that a diverging random config still yields finite Q.
        let q_at = |u: &[f64]| {
            -u.iter()
                .zip(&target)
                .map(|(p, t)| (p - t).powi(2) / (1.0 + (p - t).powi(2)))
                .sum::<f64>()
        };
        let mut out = Vec::new();
        for episode in 0..3 {
            let steps = 20 + rng.below(20);
            for step in 0..steps {
                let action: Vec<f64> = (0..d).map(|_| rng.uniform(-1.5, 1.5)).collect();
                let scale: Vec<f64> = match rng.below(3) {
                    0 => Vec::new(),
                    1 => vec![rng.uniform(0.05, 2.0)],
                    _ => (0..d).map(|_| rng.uniform(0.05, 2.0)).collect(),
                };
                let start = step == 0 && episode > 0;
                let wire = probe_scaled(&mut client, &id, step, &action, &scale, start)
                    .await
                    .expect("probe");
                out.clear();
                core.probe(step, &action, &scale, start, &mut out).unwrap();
                assert_eq!(
                    wire.probe, out,
                    "case {case} episode {episode} step {step} probe"
                );
                let q = q_at(&out);
                out.clear();
                core.applied_action(&mut out);
                assert_eq!(
                    wire.action, out,
                    "case {case} episode {episode} step {step} applied action"
                );
                let reference = (rng.below(2) == 0).then(|| q_at(&out));

                let wire = report_paired(&mut client, &id, step, q, reference)
                    .await
                    .expect("report");
                out.clear();
                core.report(step, q, reference, &mut out).unwrap();
                assert_eq!(
                    wire.action, out,
                    "case {case} episode {episode} step {step} action"
                );
            }
            let state = get(&mut client, &id).await.unwrap();
            assert_eq!(
                state.shift,
                core.shift(),
                "case {case} episode {episode} shift"
            );
            assert_eq!(state.episodes_completed, core.episodes_completed());
            assert_eq!(state.response_mean_square, core.response_mean_square());
            assert_eq!(
                state.config,
                Some(cfg.clone()),
                "GetSession returns the 1b fields as set"
            );
        }
    }
    server.stop().await;
}
