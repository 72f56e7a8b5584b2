//! Load generation against the real `esa-server` binary: `esa-bench`
//! (latency, throughput and memory per session, beside a bare tonic echo),
//! and the soak test's clients (`tests/soak`). Everything stays on loopback.

pub mod driver;
pub mod echo;
pub mod error;
pub mod measure;
pub mod memory;
pub mod server_process;
pub mod zenoh_client;
