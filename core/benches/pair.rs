//! One probe + report pair through the core (issue 7, deliverable 2; target <= 100 ns at D = 6).

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use esa_core::{Session, SessionConfig};

/// Steps per episode, as in the MuJoCo tasks: keeps `t` (and so the sine arguments) realistic.
const EPISODE_STEPS: u64 = 1000;

fn pair(c: &mut Criterion) {
    let mut group = c.benchmark_group("probe_report_pair");
    for dim in [1usize, 6, 17] {
        let frequency: Vec<f64> = (0..dim).map(|i| 40.0 + 5.0 * i as f64).collect();
        let config = SessionConfig {
            action_low: vec![-1.0],
            action_high: vec![1.0],
            shift_limit: Some(0.5),
            ..SessionConfig::new(dim as u32, 0.01, vec![0.1], frequency, vec![0.25])
        };
        let mut session = Session::new(config).expect("bench config is valid");
        let action: Vec<f64> = (0..dim).map(|i| 0.1 * i as f64 - 0.3).collect();
        let mut probe = Vec::with_capacity(dim);
        let mut improved = Vec::with_capacity(dim);
        group.throughput(Throughput::Elements(1));
        group.bench_function(BenchmarkId::from_parameter(dim), |b| {
            b.iter(|| {
                let t = session.step();
                if t == EPISODE_STEPS {
                    session.end_episode();
                }
                let t = session.step();
                probe.clear();
                session
                    .probe(t, black_box(&action), false, &mut probe)
                    .expect("probe");
                let q = -probe.iter().map(|p| p * p).sum::<f64>();
                improved.clear();
                session
                    .report(t, black_box(q), &mut improved)
                    .expect("report");
                black_box(&improved);
            })
        });
    }
    group.finish();
}

criterion_group!(benches, pair);
criterion_main!(benches);
