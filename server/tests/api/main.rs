//! Integration tests: each starts a real server in-process on 127.0.0.1:0
//! (or a Unix socket) and calls it through the generated gRPC client, except
//! `binary`, which runs the `esa-server` executable itself.

mod auth;
mod batch;
mod binary;
// The bounded law (CONTRACT.md section 1b) over every wire, Zenoh among them.
#[cfg(feature = "zenoh")]
mod bounded_law;
mod common;
mod errors;
mod fused_step;
mod hygiene;
mod lifecycle;
mod limits;
mod memory;
mod robustness;
mod state_file;
mod stream;
mod tls;
mod transport;
mod ttl;
mod update_law;
mod warnings;
#[cfg(feature = "zenoh")]
mod zenoh_tls;
#[cfg(feature = "zenoh")]
mod zenoh_transport;
