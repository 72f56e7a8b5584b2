//! Requests of any shape: random, extreme and malformed values on every RPC
//! get a contract error code or succeed, and never take the server down.

use esa_server::pb;
use tonic::Code;

use crate::common::{config, create, get, start, Client};

/// splitmix64: a seeded, dependency-free source of hostile inputs.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }

    fn pick<T: Clone>(&mut self, items: &[T]) -> T {
        items[self.below(items.len() as u64) as usize].clone()
    }

    fn double(&mut self) -> f64 {
        let special = [
            0.0,
            -0.0,
            1.0,
            -1.0,
            1e308,
            -1e308,
            f64::MIN_POSITIVE,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        if self.below(4) == 0 {
            self.pick(&special)
        } else {
            f64::from_bits(self.next())
        }
    }

    fn doubles(&mut self) -> Vec<f64> {
        let len = self.pick(&[0, 1, 2, 3, 7, 100]);
        (0..len).map(|_| self.double()).collect()
    }

    fn step(&mut self) -> u64 {
        let any = self.next();
        self.pick(&[0, 1, 2, u64::MAX, u64::MAX - 1, any])
    }

    fn id(&mut self) -> String {
        let long = "x".repeat(129);
        self.pick(&["a", "b", "c", "", "ghost", long.as_str()])
            .to_string()
    }

    fn ids(&mut self) -> Vec<String> {
        let n = self.pick(&[0, 1, 2, 3, 4]);
        (0..n).map(|_| self.id()).collect()
    }

    fn config(&mut self) -> Option<pb::SessionConfig> {
        (self.below(8) != 0).then(|| pb::SessionConfig {
            action_dim: self.pick(&[0, 1, 2, 3, 4096, 4097, u32::MAX]),
            dt: self.double(),
            amplitude: self.doubles(),
            frequency: self.doubles(),
            learning_rate: self.doubles(),
            highpass_cutoff: (self.below(2) == 0).then(|| self.double()),
            disable_highpass: self.below(2) == 0,
            action_low: self.doubles(),
            action_high: self.doubles(),
            shift_limit: (self.below(2) == 0).then(|| self.double()),
            lr_decay: (self.below(2) == 0).then(|| self.double()),
            max_episodes: self.step(),
            normalize_response: self.below(2) == 0,
            response_rms_rate: (self.below(2) == 0).then(|| self.double()),
            response_clip: (self.below(2) == 0).then(|| self.double()),
            shift_leak: (self.below(2) == 0).then(|| self.double()),
            trust_region: (self.below(2) == 0).then(|| self.double()),
        })
    }
}

/// Codes the contract allows for a request the client got wrong.
const CONTRACT_CODES: [Code; 5] = [
    Code::InvalidArgument,
    Code::NotFound,
    Code::FailedPrecondition,
    Code::AlreadyExists,
    Code::ResourceExhausted,
];

async fn random_call(client: &mut Client, rng: &mut Rng) -> Result<(), tonic::Status> {
    match rng.below(8) {
        0 => {
            let request = pb::CreateSessionRequest {
                session_id: rng.id(),
                config: rng.config(),
                progress: None,
            };
            client.create_session(request).await.map(drop)
        }
        1 => {
            let request = pb::ProbeRequest {
                session_id: rng.id(),
                step: rng.step(),
                action: rng.doubles(),
                episode_start: rng.below(2) == 0,
                action_scale: rng.doubles(),
            };
            client.probe(request).await.map(drop)
        }
        2 => {
            let request = pb::ReportRequest {
                session_id: rng.id(),
                step: rng.step(),
                q_value: rng.double(),
                q_reference: (rng.below(2) == 0).then(|| rng.double()),
            };
            client.report(request).await.map(drop)
        }
        3 => {
            let session_id = rng.id();
            client
                .end_episode(pb::EndEpisodeRequest { session_id })
                .await
                .map(drop)
        }
        4 => get(client, &rng.id()).await.map(drop),
        5 => {
            let session_ids = rng.ids();
            let request = pb::ProbeBatchRequest {
                steps: (0..rng.below(5)).map(|_| rng.step()).collect(),
                actions: rng.doubles(),
                episode_starts: (0..rng.below(5)).map(|_| rng.below(2) == 0).collect(),
                action_scales: rng.doubles(),
                session_ids,
            };
            client.probe_batch(request).await.map(drop)
        }
        6 => {
            let session_ids = rng.ids();
            let request = pb::ReportBatchRequest {
                steps: (0..rng.below(5)).map(|_| rng.step()).collect(),
                q_values: rng.doubles(),
                q_references: rng.doubles(),
                session_ids,
            };
            client.report_batch(request).await.map(drop)
        }
        _ => {
            let session_id = rng.id();
            client
                .close_session(pb::CloseSessionRequest { session_id })
                .await
                .map(drop)
        }
    }
}

#[tokio::test]
async fn random_hostile_requests_get_contract_errors_and_the_server_keeps_serving() {
    let server = start().await;
    let mut client = server.client().await;
    let mut rng = Rng(7);
    let mut failures = 0;
    for i in 0..3000 {
        // Keep some valid sessions around so that deep paths are reached.
        if i % 100 == 0 {
            for (id, d) in [("a", 1), ("b", 2), ("c", 3)] {
                let _ = client
                    .create_session(pb::CreateSessionRequest {
                        session_id: id.into(),
                        config: Some(config(d)),
                        progress: None,
                    })
                    .await;
            }
        }
        if let Err(status) = random_call(&mut client, &mut rng).await {
            assert!(
                CONTRACT_CODES.contains(&status.code()),
                "call {i}: unexpected {status:?}"
            );
            failures += 1;
        }
    }
    assert!(failures > 0);
    // Still serving, and still correct.
    create(&mut client, "after", config(2)).await;
    assert_eq!(
        get(&mut client, "after").await.unwrap().shift,
        vec![0.0, 0.0]
    );
    server.stop().await;
}
