//! The update law over the wire equals `esa_core` run directly, on random
//! configs and inputs, to the bit (doubles travel losslessly in protobuf).

use esa_core::Session;
use esa_server::convert::config_from_proto;
use esa_server::pb;

use crate::common::{create, get, probe, report, start};

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
    }
}

#[tokio::test]
async fn wire_results_equal_the_core_on_random_configs() {
    let server = start().await;
    let mut client = server.client().await;
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    for case in 0..24 {
        let cfg = random_config(&mut rng);
        let id = format!("case-{case}");
        create(&mut client, &id, cfg.clone()).await;
        let mut core = Session::new(config_from_proto(Some(cfg.clone())).unwrap()).unwrap();
        let d = cfg.action_dim as usize;
        let target: Vec<f64> = (0..d).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let mut out = Vec::new();
        for episode in 0..3 {
            let steps = 20 + rng.below(20);
            for step in 0..steps {
                let action: Vec<f64> = (0..d).map(|_| rng.uniform(-1.5, 1.5)).collect();
                let start = step == 0 && episode > 0;
                let wire = probe(&mut client, &id, step, &action, start).await.unwrap();
                out.clear();
                core.probe(step, &action, start, &mut out).unwrap();
                assert_eq!(
                    wire.probe, out,
                    "case {case} episode {episode} step {step} probe"
                );

                // Bounded so that a diverging random config still yields finite Q.
                let q = -out
                    .iter()
                    .zip(&target)
                    .map(|(p, t)| (p - t).powi(2) / (1.0 + (p - t).powi(2)))
                    .sum::<f64>();
                let wire = report(&mut client, &id, step, q).await.unwrap();
                out.clear();
                core.report(step, q, &mut out).unwrap();
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
        }
    }
    server.stop().await;
}
