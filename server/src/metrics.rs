//! Request, connection, store and process metrics in a `prometheus-client`
//! registry, encoded in the OpenMetrics text format (served by
//! [`crate::metrics_endpoint`]).
//!
//! The store's figures and the process's (CPU, memory, file descriptors,
//! threads, start time, read from `/proc/self` on Linux) are sampled when the
//! registry is encoded; everything else is counted as it happens.

use std::sync::atomic::AtomicU64;
use std::time::Duration;

use esa_proto::Rpc;
use parking_lot::Mutex;
use prometheus_client::encoding::text::encode;
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::Histogram;
use prometheus_client::metrics::info::Info;
use prometheus_client::registry::{Registry, Unit};
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

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RequestLabels {
    rpc: &'static str,
    code: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RpcLabels {
    rpc: &'static str,
}

type FloatCounter = Counter<f64, AtomicU64>;
type FloatGauge = Gauge<f64, AtomicU64>;

/// The metrics of one server.
pub struct Metrics {
    registry: Registry,
    requests: Family<RequestLabels, Counter>,
    latency: Family<RpcLabels, Histogram>,
    nonfinite_skipped: Counter,
    connections_open: Gauge,
    connections_evicted: Counter,
    connections_refused: Counter,
    sampled: Sampled,
    /// One encoder at a time: sampling sets gauges and advances counters.
    render_lock: Mutex<()>,
}

/// Figures sampled at encoding time.
#[derive(Default)]
struct Sampled {
    sessions_live: Gauge,
    sessions_expired: Counter,
    session_memory_bytes: Gauge,
    cpu_seconds: FloatCounter,
    resident_memory_bytes: Gauge,
    virtual_memory_bytes: Gauge,
    open_fds: Gauge,
    max_fds: Gauge,
    threads: Gauge,
    start_time_seconds: FloatGauge,
}

/// The store's figures at the time of rendering.
pub struct StoreGauges {
    pub sessions_live: usize,
    pub sessions_expired: u64,
    pub session_memory_bytes: usize,
}

impl Default for Metrics {
    fn default() -> Self {
        let mut registry = Registry::default();
        let requests = Family::<RequestLabels, Counter>::default();
        let latency = Family::<RpcLabels, Histogram>::new_with_constructor(
            (|| Histogram::new(BUCKETS)) as fn() -> Histogram,
        );
        let nonfinite_skipped = Counter::default();
        let connections_open = Gauge::default();
        let connections_evicted = Counter::default();
        let connections_refused = Counter::default();
        let sampled = Sampled::default();

        registry.register(
            "esa_build",
            "The esa-server build: its version",
            Info::new(vec![("version", env!("CARGO_PKG_VERSION"))]),
        );
        registry.register(
            "esa_sessions_live",
            "Sessions currently held by the server",
            sampled.sessions_live.clone(),
        );
        registry.register(
            "esa_sessions_expired",
            "Sessions removed after being idle longer than the TTL",
            sampled.sessions_expired.clone(),
        );
        registry.register(
            "esa_session_memory_bytes",
            "Bytes the live sessions cost, as charged to --max-session-memory",
            sampled.session_memory_bytes.clone(),
        );
        registry.register(
            "esa_connections_open",
            "gRPC connections currently held",
            connections_open.clone(),
        );
        registry.register(
            "esa_connections_evicted",
            "Idle gRPC connections closed to make room for new ones at --max-connections",
            connections_evicted.clone(),
        );
        registry.register(
            "esa_connections_refused",
            "gRPC connections refused at --max-connections because every held one had a call in flight",
            connections_refused.clone(),
        );
        registry.register(
            "esa_nonfinite_updates_skipped",
            "Reports whose shift update would have been non-finite and was skipped",
            nonfinite_skipped.clone(),
        );
        registry.register(
            "esa_requests",
            "Requests handled, by RPC and gRPC status code (StepStream counts each stream message)",
            requests.clone(),
        );
        registry.register(
            "esa_request_duration_seconds",
            "Time spent handling a request inside the server, excluding the transport",
            latency.clone(),
        );
        // The process metrics every Prometheus client library exports, same names.
        registry.register_with_unit(
            "process_cpu",
            "Total user and system CPU time spent",
            Unit::Seconds,
            sampled.cpu_seconds.clone(),
        );
        registry.register_with_unit(
            "process_resident_memory",
            "Resident memory size",
            Unit::Bytes,
            sampled.resident_memory_bytes.clone(),
        );
        registry.register_with_unit(
            "process_virtual_memory",
            "Virtual memory size",
            Unit::Bytes,
            sampled.virtual_memory_bytes.clone(),
        );
        registry.register(
            "process_open_fds",
            "Open file descriptors",
            sampled.open_fds.clone(),
        );
        registry.register(
            "process_max_fds",
            "Maximum number of open file descriptors (the soft limit)",
            sampled.max_fds.clone(),
        );
        registry.register(
            "process_threads",
            "OS threads of the process",
            sampled.threads.clone(),
        );
        registry.register_with_unit(
            "process_start_time",
            "Start time of the process since the Unix epoch",
            Unit::Seconds,
            sampled.start_time_seconds.clone(),
        );

        Self {
            registry,
            requests,
            latency,
            nonfinite_skipped,
            connections_open,
            connections_evicted,
            connections_refused,
            sampled,
            render_lock: Mutex::new(()),
        }
    }
}

impl Metrics {
    /// Records one handled request.
    pub fn observe(&self, rpc: Rpc, code: Code, elapsed: Duration) {
        let rpc = rpc.name();
        let code = CODE_NAMES.get(code as usize).copied().unwrap_or("UNKNOWN");
        self.requests
            .get_or_create(&RequestLabels { rpc, code })
            .inc();
        self.latency
            .get_or_create(&RpcLabels { rpc })
            .observe(elapsed.as_secs_f64());
    }

    /// Records reports whose shift update was skipped as non-finite.
    pub fn add_nonfinite_skipped(&self, n: u64) {
        self.nonfinite_skipped.inc_by(n);
    }

    pub fn connection_opened(&self) {
        self.connections_open.inc();
    }

    pub fn connection_closed(&self) {
        self.connections_open.dec();
    }

    /// Records an idle connection closed to make room for a new one.
    pub fn connection_evicted(&self) {
        self.connections_evicted.inc();
    }

    /// Records a connection refused because every held one had a call in flight.
    pub fn connection_refused(&self) {
        self.connections_refused.inc();
    }

    /// The OpenMetrics text exposition of all metrics.
    pub fn render(&self, store: &StoreGauges) -> String {
        let _one_at_a_time = self.render_lock.lock();
        let sampled = &self.sampled;
        sampled
            .sessions_live
            .set(i64::try_from(store.sessions_live).unwrap_or(i64::MAX));
        advance_to(&sampled.sessions_expired, store.sessions_expired);
        sampled
            .session_memory_bytes
            .set(i64::try_from(store.session_memory_bytes).unwrap_or(i64::MAX));
        if let Some(process) = process::sample() {
            let cpu = &sampled.cpu_seconds;
            let delta = process.cpu_seconds - cpu.get();
            if delta > 0.0 {
                cpu.inc_by(delta);
            }
            sampled.resident_memory_bytes.set(process.resident_bytes);
            sampled.virtual_memory_bytes.set(process.virtual_bytes);
            sampled.open_fds.set(process.open_fds);
            sampled.max_fds.set(process.max_fds);
            sampled.threads.set(process.threads);
            sampled.start_time_seconds.set(process.start_time_seconds);
        }
        let mut out = String::with_capacity(8192);
        // Writing to a String cannot fail.
        let _ = encode(&mut out, &self.registry);
        out
    }
}

/// Raises a counter that mirrors a monotonic total kept elsewhere.
fn advance_to(counter: &Counter, total: u64) {
    let current = counter.get();
    if total > current {
        counter.inc_by(total - current);
    }
}

/// This process's figures from `/proc/self` (Linux); `None` elsewhere.
mod process {
    pub struct Process {
        pub cpu_seconds: f64,
        pub resident_bytes: i64,
        pub virtual_bytes: i64,
        pub open_fds: i64,
        pub max_fds: i64,
        pub threads: i64,
        pub start_time_seconds: f64,
    }

    pub fn sample() -> Option<Process> {
        let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
        // Fields after the parenthesised command name, which may hold spaces.
        let fields: Vec<&str> = stat.get(stat.rfind(')')? + 2..)?.split(' ').collect();
        // `man 5 proc`: field n (1-based) is fields[n - 3] here.
        let field = |n: usize| -> Option<f64> { fields.get(n - 3)?.parse().ok() };
        // SAFETY: sysconf only reads configuration values.
        let ticks = unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64;
        // SAFETY: as above.
        let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) } as f64;
        if ticks <= 0.0 || page <= 0.0 {
            return None;
        }
        let boot_time: f64 = std::fs::read_to_string("/proc/stat")
            .ok()?
            .lines()
            .find_map(|line| line.strip_prefix("btime ")?.trim().parse().ok())?;
        let open_fds = std::fs::read_dir("/proc/self/fd").ok()?.count() as i64;
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit writes into the struct it is given.
        let max_fds = if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } == 0 {
            i64::try_from(limit.rlim_cur).unwrap_or(i64::MAX)
        } else {
            -1
        };
        Some(Process {
            cpu_seconds: (field(14)? + field(15)?) / ticks,
            threads: field(20)? as i64,
            start_time_seconds: boot_time + field(22)? / ticks,
            virtual_bytes: field(23)? as i64,
            resident_bytes: (field(24)? * page) as i64,
            open_fds,
            max_fds,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exposition_has_counters_cumulative_buckets_build_and_process_metrics() {
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
        for line in [
            "esa_sessions_live 4\n",
            "esa_sessions_expired_total 1\n",
            "esa_session_memory_bytes 3000\n",
            "# TYPE esa_connections_open gauge\nesa_connections_open 1\n",
            "esa_requests_total{rpc=\"Probe\",code=\"OK\"} 2\n",
            "esa_requests_total{rpc=\"Probe\",code=\"NOT_FOUND\"} 1\n",
            "esa_request_duration_seconds_bucket{le=\"0.000005\",rpc=\"Probe\"} 1\n",
            "esa_request_duration_seconds_bucket{le=\"0.005\",rpc=\"Probe\"} 2\n",
            "esa_request_duration_seconds_bucket{le=\"1.0\",rpc=\"Probe\"} 2\n",
            "esa_request_duration_seconds_bucket{le=\"+Inf\",rpc=\"Probe\"} 3\n",
            "esa_request_duration_seconds_count{rpc=\"Probe\"} 3\n",
            &format!(
                "esa_build_info{{version=\"{}\"}} 1\n",
                env!("CARGO_PKG_VERSION")
            ),
            "# TYPE process_cpu_seconds counter\n",
            "# TYPE process_resident_memory_bytes gauge\n",
            "# EOF\n",
        ] {
            assert!(text.contains(line), "missing {line:?} in:\n{text}");
        }
        assert!(!text.contains("rpc=\"Report\""));
        // A total kept elsewhere only moves the counter forward.
        let text = metrics.render(&StoreGauges {
            sessions_live: 0,
            sessions_expired: 3,
            session_memory_bytes: 0,
        });
        assert!(text.contains("esa_sessions_expired_total 3\n"), "{text}");
        assert!(text.contains("process_open_fds "), "{text}");
    }
}
