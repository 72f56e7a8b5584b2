//! The update law over the wire equals `esa_core` run directly, on random
//! configs and inputs, to the bit (doubles travel losslessly in protobuf),
//! including CONTRACT.md section 1b (applied action, action scale, paired
//! reference, normalization, leak, trust region).

use esa_core::Session;
use esa_server::convert::config_from_proto;
use esa_server::pb;

use crate::common::{create, get, start, Client};

async fn probe(
    client: &mut Client,
    id: &str,
    step: u64,
    action: &[f64],
    action_scale: &[f64],
    episode_start: bool,
) -> pb::ProbeResponse {
    client
        .probe(pb::ProbeRequest {
            session_id: id.into(),
            step,
            action: action.to_vec(),
            episode_start,
            action_scale: action_scale.to_vec(),
        })
        .await
        .expect("probe")
        .into_inner()
}

async fn report(
    client: &mut Client,
    id: &str,
    step: u64,
    q_value: f64,
    q_reference: Option<f64>,
) -> pb::ReportResponse {
    client
        .report(pb::ReportRequest {
            session_id: id.into(),
            step,
            q_value,
            q_reference,
        })
        .await
        .expect("report")
        .into_inner()
}

/// xorshift64*: a dependency-free, seeded source of test inputs.
struct Rng(u64);

impl Rng {
    fn next_f64(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }

    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next_f64()
    }

    fn below(&mut self, n: u64) -> u64 {
        (self.next_f64() * n as f64) as u64
    }

    /// Length 1 (broadcast) or `d` values in [lo, hi).
    fn vector(&mut self, d: u32, lo: f64, hi: f64) -> Vec<f64> {
        let len = if self.below(2) == 0 { 1 } else { d };
        (0..len).map(|_| self.uniform(lo, hi)).collect()
    }
}

fn random_config(rng: &mut Rng) -> pb::SessionConfig {
    let d = 1 + rng.below(6) as u32;
    let dt = rng.uniform(0.001, 0.05);
    let bounded = rng.below(2) == 0;
    pb::SessionConfig {
        action_dim: d,
        dt,
        amplitude: rng.vector(d, 0.0, 0.5),
        // Strictly below Nyquist: w * dt < pi.
        frequency: rng.vector(d, 0.5 / dt, 3.0 / dt),
        learning_rate: rng.vector(d, 0.0, 2.0),
        highpass_cutoff: (rng.below(2) == 0).then(|| rng.uniform(0.1, 10.0)),
        disable_highpass: rng.below(3) == 0,
        action_low: if bounded { vec![-1.0] } else { vec![] },
        action_high: if bounded {
            rng.vector(d, 0.5, 2.0)
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
                let wire = probe(&mut client, &id, step, &action, &scale, start).await;
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

                let wire = report(&mut client, &id, step, q, reference).await;
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
