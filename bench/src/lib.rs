//! Load generation against the real `esa-server` binary, shared by two
//! programs: `esa-bench` (latency, throughput and memory per session)
//! and `esa-soak` (minutes of load with floods and faults).
//! Everything stays on loopback.

pub mod driver;
pub mod error;
pub mod measure;
pub mod memory;
pub mod server_process;
pub mod soak;
pub mod zenoh_client;
