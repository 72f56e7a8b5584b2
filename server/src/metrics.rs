//! Request metrics kept in lock-free counters, rendered in the Prometheus text
//! exposition format (served by [`crate::metrics_endpoint`]).

use std::fmt::Write as _;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use esa_proto::Rpc;
use tonic::Code;

/// Upper bounds of the latency histogram buckets, in seconds. Handler time of
/// one step is microseconds; large batches reach milliseconds.
const BUCKETS: [f64; 12] = [
    1e-6, 5e-6, 1e-5, 2.5e-5, 5e-5, 1e-4, 2.5e-4, 1e-3, 5e-3, 2.5e-2, 0.1, 1.0,
];

/// gRPC status code names, indexed by code number.
const CODE_NAMES: [&str; 17] = [
    "OK",
    "CANCELLED",
    "UNKNOWN",
    "INVALID_ARGUMENT",
    "DEADLINE_EXCEEDED",
    "NOT_FOUND",
    "ALREADY_EXISTS",
    "PERMISSION_DENIED",
    "RESOURCE_EXHAUSTED",
    "FAILED_PRECONDITION",
    "ABORTED",
    "OUT_OF_RANGE",
    "UNIMPLEMENTED",
    "INTERNAL",
    "UNAVAILABLE",
    "DATA_LOSS",
    "UNAUTHENTICATED",
];

/// Counters of one server.
pub struct Metrics {
    requests: [[AtomicU64; CODE_NAMES.len()]; Rpc::ALL.len()],
    latency: [Histogram; Rpc::ALL.len()],
    nonfinite_skipped: AtomicU64,
    connections_open: AtomicU64,
    connections_evicted: AtomicU64,
    connections_refused: AtomicU64,
}

/// The store's figures at the time of rendering.
pub struct StoreGauges {
    pub sessions_live: usize,
    pub sessions_expired: u64,
    pub session_memory_bytes: usize,
}

#[derive(Default)]
struct Histogram {
    buckets: [AtomicU64; BUCKETS.len()],
    sum_nanos: AtomicU64,
    count: AtomicU64,
}

impl Default for Metrics {
    fn default() -> Self {
        Self {
            requests: std::array::from_fn(|_| std::array::from_fn(|_| AtomicU64::new(0))),
            latency: std::array::from_fn(|_| Histogram::default()),
            nonfinite_skipped: AtomicU64::new(0),
            connections_open: AtomicU64::new(0),
            connections_evicted: AtomicU64::new(0),
            connections_refused: AtomicU64::new(0),
        }
    }
}

impl Metrics {
    /// Records one handled request.
    pub fn observe(&self, rpc: Rpc, code: Code, elapsed: Duration) {
        if let Some(counter) = self
            .requests
            .get(rpc as usize)
            .and_then(|by_code| by_code.get(code as usize))
        {
            counter.fetch_add(1, Ordering::Relaxed);
        }
        if let Some(histogram) = self.latency.get(rpc as usize) {
            histogram.observe(elapsed);
        }
    }

    /// Records reports whose shift update was skipped as non-finite.
    pub fn add_nonfinite_skipped(&self, n: u64) {
        self.nonfinite_skipped.fetch_add(n, Ordering::Relaxed);
    }

    pub fn connection_opened(&self) {
        self.connections_open.fetch_add(1, Ordering::Relaxed);
    }

    pub fn connection_closed(&self) {
        self.connections_open.fetch_sub(1, Ordering::Relaxed);
    }

    /// Records an idle connection closed to make room for a new one.
    pub fn connection_evicted(&self) {
        self.connections_evicted.fetch_add(1, Ordering::Relaxed);
    }

    /// Records a connection refused because every held one had a call in flight.
    pub fn connection_refused(&self) {
        self.connections_refused.fetch_add(1, Ordering::Relaxed);
    }

    /// The Prometheus text exposition of all metrics.
    pub fn render(&self, store: &StoreGauges) -> String {
        let mut out = String::with_capacity(4096);
        // Writing to a String cannot fail.
        let _ = self.write_to(&mut out, store);
        out
    }

    fn write_to(&self, out: &mut String, store: &StoreGauges) -> std::fmt::Result {
        let gauges = [
            ("esa_sessions_live", "gauge", "Sessions currently held by the server.", store.sessions_live as u64),
            ("esa_sessions_expired_total", "counter", "Sessions removed after being idle longer than the TTL.", store.sessions_expired),
            ("esa_session_memory_bytes", "gauge", "Bytes the live sessions cost, as charged to --max-session-memory.", store.session_memory_bytes as u64),
            ("esa_connections_open", "gauge", "gRPC connections currently held.", self.connections_open.load(Ordering::Relaxed)),
            ("esa_connections_evicted_total", "counter", "Idle gRPC connections closed to make room for new ones at --max-connections.", self.connections_evicted.load(Ordering::Relaxed)),
            ("esa_connections_refused_total", "counter", "gRPC connections refused at --max-connections because every held one had a call in flight.", self.connections_refused.load(Ordering::Relaxed)),
        ];
        for (name, kind, help, value) in gauges {
            writeln!(out, "# HELP {name} {help}")?;
            writeln!(out, "# TYPE {name} {kind}")?;
            writeln!(out, "{name} {value}")?;
        }
        writeln!(
            out,
            "# HELP esa_nonfinite_updates_skipped_total Reports whose shift update would have been non-finite and was skipped."
        )?;
        writeln!(out, "# TYPE esa_nonfinite_updates_skipped_total counter")?;
        writeln!(
            out,
            "esa_nonfinite_updates_skipped_total {}",
            self.nonfinite_skipped.load(Ordering::Relaxed)
        )?;

        writeln!(out, "# HELP esa_requests_total Requests handled, by RPC and gRPC status code (StepStream counts each stream message).")?;
        writeln!(out, "# TYPE esa_requests_total counter")?;
        for (rpc, by_code) in Rpc::ALL.iter().zip(&self.requests) {
            for (code, counter) in CODE_NAMES.iter().zip(by_code) {
                let n = counter.load(Ordering::Relaxed);
                if n > 0 {
                    writeln!(
                        out,
                        "esa_requests_total{{rpc=\"{}\",code=\"{code}\"}} {n}",
                        rpc.name()
                    )?;
                }
            }
        }

        writeln!(out, "# HELP esa_request_duration_seconds Time spent handling a request inside the server, excluding the transport.")?;
        writeln!(out, "# TYPE esa_request_duration_seconds histogram")?;
        for (rpc, histogram) in Rpc::ALL.iter().zip(&self.latency) {
            let count = histogram.count.load(Ordering::Relaxed);
            if count == 0 {
                continue;
            }
            let rpc = rpc.name();
            let mut cumulative = 0;
            for (bound, bucket) in BUCKETS.iter().zip(&histogram.buckets) {
                cumulative += bucket.load(Ordering::Relaxed);
                writeln!(
                    out,
                    "esa_request_duration_seconds_bucket{{rpc=\"{rpc}\",le=\"{bound:e}\"}} {cumulative}"
                )?;
            }
            writeln!(
                out,
                "esa_request_duration_seconds_bucket{{rpc=\"{rpc}\",le=\"+Inf\"}} {count}"
            )?;
            let sum = histogram.sum_nanos.load(Ordering::Relaxed) as f64 * 1e-9;
            writeln!(
                out,
                "esa_request_duration_seconds_sum{{rpc=\"{rpc}\"}} {sum:e}"
            )?;
            writeln!(
                out,
                "esa_request_duration_seconds_count{{rpc=\"{rpc}\"}} {count}"
            )?;
        }
        Ok(())
    }
}

impl Histogram {
    fn observe(&self, elapsed: Duration) {
        let seconds = elapsed.as_secs_f64();
        // Buckets hold non-cumulative counts; the exposition accumulates them.
        if let Some(bucket) = BUCKETS
            .iter()
            .zip(&self.buckets)
            .find_map(|(bound, bucket)| (seconds <= *bound).then_some(bucket))
        {
            bucket.fetch_add(1, Ordering::Relaxed);
        }
        let nanos = u64::try_from(elapsed.as_nanos()).unwrap_or(u64::MAX);
        self.sum_nanos.fetch_add(nanos, Ordering::Relaxed);
        self.count.fetch_add(1, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exposition_has_counters_and_cumulative_buckets() {
        let metrics = Metrics::default();
        metrics.observe(Rpc::Probe, Code::Ok, Duration::from_micros(3));
        metrics.observe(Rpc::Probe, Code::Ok, Duration::from_millis(2));
        metrics.observe(Rpc::Probe, Code::NotFound, Duration::from_secs(5));
        metrics.connection_opened();
        let text = metrics.render(&StoreGauges {
            sessions_live: 4,
            sessions_expired: 1,
            session_memory_bytes: 3000,
        });
        assert!(text.contains("esa_sessions_live 4\n"));
        assert!(text.contains("esa_sessions_expired_total 1\n"));
        assert!(text.contains("esa_session_memory_bytes 3000\n"));
        assert!(text.contains("# TYPE esa_connections_open gauge\nesa_connections_open 1\n"));
        assert!(text.contains("esa_requests_total{rpc=\"Probe\",code=\"OK\"} 2\n"));
        assert!(text.contains("esa_requests_total{rpc=\"Probe\",code=\"NOT_FOUND\"} 1\n"));
        assert!(text.contains("esa_request_duration_seconds_bucket{rpc=\"Probe\",le=\"5e-6\"} 1\n"));
        assert!(text.contains("esa_request_duration_seconds_bucket{rpc=\"Probe\",le=\"5e-3\"} 2\n"));
        assert!(text.contains("esa_request_duration_seconds_bucket{rpc=\"Probe\",le=\"1e0\"} 2\n"));
        assert!(text.contains("esa_request_duration_seconds_bucket{rpc=\"Probe\",le=\"+Inf\"} 3\n"));
        assert!(text.contains("esa_request_duration_seconds_count{rpc=\"Probe\"} 3\n"));
        assert!(!text.contains("rpc=\"Report\""));
    }
}
