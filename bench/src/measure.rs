//! Bounded measurement loops: the latency distribution of one client's
//! pairs, and the session-steps per second of several clients at once.

use std::time::{Duration, Instant};

use hdrhistogram::Histogram;
use serde::Serialize;
use tokio::sync::Barrier;

use crate::driver::{connect, create_sessions, Api, Stepper};
use crate::error::Result;
use crate::server_process::Address;

/// Every loop stops at whichever bound it reaches first.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Bounds {
    /// Unmeasured pairs before measuring (connections, caches, allocator).
    pub warmup: Duration,
    /// Longest measured window.
    pub window: Duration,
    /// Most measured pairs per client.
    pub max_pairs: u64,
}

/// What to step: over which API, how many sessions of which dimension.
#[derive(Clone, Copy, Debug)]
pub struct Workload {
    /// How the pairs travel.
    pub api: Api,
    /// Sessions stepped per pair.
    pub batch: usize,
    /// Action dimension D.
    pub dim: usize,
}

/// Latency of one pair (probe + report round trips) as one client sees it.
#[derive(Clone, Debug, Serialize)]
pub struct Latency {
    /// Measured pairs.
    pub pairs: u64,
    /// Median, microseconds.
    pub p50_us: f64,
    /// 90th percentile, microseconds.
    pub p90_us: f64,
    /// 99th percentile, microseconds.
    pub p99_us: f64,
    /// Mean, microseconds.
    pub mean_us: f64,
    /// Slowest pair, microseconds.
    pub max_us: f64,
}

/// Session-steps per second of `concurrency` clients stepping their own
/// sessions at the same time, each with one pair in flight.
#[derive(Clone, Debug, Serialize)]
pub struct Throughput {
    /// Clients (connections), each with one request in flight.
    pub concurrency: usize,
    /// Pairs completed by all clients.
    pub pairs: u64,
    /// From the common start to the last client's end.
    pub seconds: f64,
    /// `pairs * batch / seconds`.
    pub session_steps_per_s: f64,
}

/// What a latency row times: one pair of round trips.
pub trait Pair {
    /// Runs one pair.
    fn pair(&mut self) -> impl std::future::Future<Output = Result<()>> + Send;
}

impl Pair for Stepper {
    async fn pair(&mut self) -> Result<()> {
        Stepper::pair(self).await
    }
}

/// Runs pairs on `stepper` for `bounds.warmup`, then measures each pair.
pub async fn latency(stepper: &mut impl Pair, bounds: Bounds) -> Result<Latency> {
    run_for(stepper, bounds.warmup, bounds.max_pairs).await?;
    // 1 ns .. 60 s at 3 significant digits.
    let mut histogram = Histogram::<u64>::new_with_bounds(1, 60_000_000_000, 3)
        .expect("constant histogram bounds are valid");
    let end = Instant::now() + bounds.window;
    while histogram.len() < bounds.max_pairs && Instant::now() < end {
        let start = Instant::now();
        stepper.pair().await?;
        histogram.record(start.elapsed().as_nanos().max(1) as u64)?;
    }
    Ok(Latency::of(&histogram))
}

impl Latency {
    /// The summary of a histogram of pair times in nanoseconds.
    pub fn of(histogram: &Histogram<u64>) -> Self {
        let us = |ns: u64| ns as f64 / 1e3;
        Latency {
            pairs: histogram.len(),
            p50_us: us(histogram.value_at_quantile(0.50)),
            p90_us: us(histogram.value_at_quantile(0.90)),
            p99_us: us(histogram.value_at_quantile(0.99)),
            mean_us: histogram.mean() / 1e3,
            max_us: us(histogram.max()),
        }
    }
}

/// Runs pairs until `duration` has passed or `max_pairs` are done; returns
/// the number of pairs.
async fn run_for(stepper: &mut impl Pair, duration: Duration, max_pairs: u64) -> Result<u64> {
    let end = Instant::now() + duration;
    let mut pairs = 0;
    while pairs < max_pairs && Instant::now() < end {
        stepper.pair().await?;
        pairs += 1;
    }
    Ok(pairs)
}

/// `concurrency` clients, each on its own connection with its own
/// `workload.batch` sessions (`<prefix>-<client>-<i>`), warm up, start
/// together and step until the window closes. The sessions are closed
/// afterwards.
pub async fn throughput(
    address: &Address,
    workload: Workload,
    concurrency: usize,
    bounds: Bounds,
    prefix: &str,
) -> Result<Throughput> {
    let mut steppers = Vec::with_capacity(concurrency);
    for client in 0..concurrency {
        let mut connection = connect(address).await?;
        let prefix = format!("{prefix}-{client}");
        let ids = create_sessions(&mut connection, &prefix, workload.batch, workload.dim).await?;
        steppers.push(Stepper::new(connection, workload.api, ids, workload.dim).await?);
    }
    let barrier = std::sync::Arc::new(Barrier::new(concurrency));
    let tasks: Vec<_> = steppers
        .into_iter()
        .map(|mut stepper| {
            let barrier = barrier.clone();
            tokio::spawn(async move {
                run_for(&mut stepper, bounds.warmup, bounds.max_pairs).await?;
                barrier.wait().await;
                let start = Instant::now();
                let pairs = run_for(&mut stepper, bounds.window, bounds.max_pairs).await?;
                let end = Instant::now();
                stepper.close().await?;
                Ok::<_, crate::error::Error>((pairs, start, end))
            })
        })
        .collect();
    let mut pairs = 0;
    let mut first_start: Option<Instant> = None;
    let mut last_end: Option<Instant> = None;
    for task in tasks {
        let (n, start, end) = task
            .await
            .map_err(|err| crate::error::Error::Protocol(format!("client task failed: {err}")))??;
        pairs += n;
        first_start = Some(first_start.map_or(start, |s| s.min(start)));
        last_end = Some(last_end.map_or(end, |e| e.max(end)));
    }
    let seconds = match (first_start, last_end) {
        (Some(start), Some(end)) => (end - start).as_secs_f64(),
        _ => 0.0,
    };
    Ok(Throughput {
        concurrency,
        pairs,
        seconds,
        session_steps_per_s: if seconds > 0.0 {
            (pairs * workload.batch as u64) as f64 / seconds
        } else {
            0.0
        },
    })
}
