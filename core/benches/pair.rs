//! One probe + report pair through the core (target: <= 100 ns at D = 6).
//!
//! Two laws, each its own group: `probe_report_pair` is section 1's law as before (no section 1b field),
//! `probe_report_pair_1b` has every field of CONTRACT.md section 1b on (`normalize_response`,
//! `shift_leak`, `trust_region`, an action scale sent with each probe, a `q_reference` with each
//! report) and also reads Algorithm 1's applied action after each probe, which the server does for
//! every `ProbeResponse` and which the reference is evaluated at.
//!
//! Each D is measured twice: in wall time (criterion's default) and in the benchmark thread's on-CPU
//! time. The box is shared by 2 cores and several engineers' jobs; wall time also counts the slices in
//! which other processes hold the CPU, on-CPU time is what the pair itself costs.

use std::hint::black_box;
use std::time::Duration;

use criterion::measurement::{Measurement, ValueFormatter, WallTime};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use esa_core::{Session, SessionConfig};

/// Steps per episode, as in the MuJoCo tasks: keeps `t` (and so the sine arguments) realistic.
const EPISODE_STEPS: u64 = 1000;

/// Which law a group measures.
#[derive(Clone, Copy)]
enum Law {
    /// Section 1: no section 1b field, no action scale, no reference.
    Section1,
    /// Every section 1b field on, an action scale per probe and a reference per report.
    Section1b,
}

fn pair<M: Measurement>(c: &mut Criterion<M>, group: &str, law: Law) {
    let mut group = c.benchmark_group(group);
    for dim in [1usize, 6, 17] {
        let frequency: Vec<f64> = (0..dim).map(|i| 40.0 + 5.0 * i as f64).collect();
        let section_1 = SessionConfig {
            action_low: vec![-1.0],
            action_high: vec![1.0],
            shift_limit: Some(0.5),
            ..SessionConfig::new(dim as u32, 0.01, vec![0.1], frequency, vec![0.25])
        };
        let config = match law {
            Law::Section1 => section_1,
            Law::Section1b => SessionConfig {
                normalize_response: true,
                shift_leak: Some(0.005),
                trust_region: Some(1.0),
                ..section_1
            },
        };
        let mut session = Session::new(config).expect("bench config is valid");
        let action: Vec<f64> = (0..dim).map(|i| 0.1 * i as f64 - 0.3).collect();
        // The policy's standard deviation, one per dimension (section 1b only).
        let scale: Vec<f64> = match law {
            Law::Section1 => Vec::new(),
            Law::Section1b => (0..dim).map(|i| 0.2 + 0.01 * i as f64).collect(),
        };
        let mut probe = Vec::with_capacity(dim);
        let mut applied = Vec::with_capacity(dim);
        let mut improved = Vec::with_capacity(dim);
        group.throughput(Throughput::Elements(1));
        group.bench_function(BenchmarkId::from_parameter(dim), |b| {
            b.iter(|| {
                if session.step() == EPISODE_STEPS {
                    session.end_episode();
                }
                let t = session.step();
                probe.clear();
                session
                    .probe(t, black_box(&action), black_box(&scale), false, &mut probe)
                    .expect("probe");
                let q = -probe.iter().map(|p| p * p).sum::<f64>();
                let q_reference = match law {
                    Law::Section1 => None,
                    Law::Section1b => {
                        applied.clear();
                        session.applied_action(&mut applied);
                        Some(-applied.iter().map(|a| a * a).sum::<f64>())
                    }
                };
                improved.clear();
                session
                    .report(t, black_box(q), black_box(q_reference), &mut improved)
                    .expect("report");
                black_box(&improved);
            })
        });
    }
    group.finish();
}

/// CPU time consumed by the calling thread (`CLOCK_THREAD_CPUTIME_ID`).
struct ThreadCpuTime {
    /// Values are durations, so criterion's own duration formatting applies.
    wall: WallTime,
}

fn thread_cpu_time() -> Duration {
    let mut now = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `now` is a valid, writable timespec; this clock id exists on every Linux since 2.6.12.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut now) };
    assert_eq!(rc, 0, "clock_gettime(CLOCK_THREAD_CPUTIME_ID) failed");
    Duration::new(now.tv_sec as u64, now.tv_nsec as u32)
}

impl Measurement for ThreadCpuTime {
    type Intermediate = Duration;
    type Value = Duration;

    fn start(&self) -> Duration {
        thread_cpu_time()
    }

    fn end(&self, start: Duration) -> Duration {
        thread_cpu_time().saturating_sub(start)
    }

    fn add(&self, a: &Duration, b: &Duration) -> Duration {
        *a + *b
    }

    fn zero(&self) -> Duration {
        Duration::ZERO
    }

    fn to_f64(&self, value: &Duration) -> f64 {
        value.as_nanos() as f64
    }

    fn formatter(&self) -> &dyn ValueFormatter {
        self.wall.formatter()
    }
}

fn pair_wall_time(c: &mut Criterion) {
    pair(c, "probe_report_pair/wall", Law::Section1);
    pair(c, "probe_report_pair_1b/wall", Law::Section1b);
}

fn pair_cpu_time(c: &mut Criterion<ThreadCpuTime>) {
    pair(c, "probe_report_pair/cpu", Law::Section1);
    pair(c, "probe_report_pair_1b/cpu", Law::Section1b);
}

criterion_group!(wall, pair_wall_time);
criterion_group! {
    name = cpu;
    config = Criterion::default().with_measurement(ThreadCpuTime { wall: WallTime });
    targets = pair_cpu_time
}
criterion_main!(wall, cpu);
