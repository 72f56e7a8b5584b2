//! esa-server: Extremum-Seeking Action selection as a service.
//!
//! Layers, each a thin wrapper over the next: transports ([`grpc`],
//! [`zenoh_transport`], and any other adapter) call the
//! transport-independent [`handler::EsaHandler`], which validates requests
//! and runs them against the [`store::SessionStore`] of `esa_core::Session`s.
//! [`server::EsaServer`] assembles the gRPC server.

pub mod codec;
pub mod connections;
pub mod convert;
pub mod error;
pub mod grpc;
pub mod guard;
pub mod handler;
pub mod metrics;
pub mod resources;
pub mod rpc;
pub mod server;
pub mod store;
pub mod throttle;
pub mod zenoh_transport;

pub use error::Error;
pub use handler::EsaHandler;
pub use rpc::Rpc;
pub use server::{EsaServer, Listener, ServerBuilder};

/// Types generated from `proto/esa/v1/esa.proto`.
#[allow(missing_docs, clippy::all)]
pub mod pb {
    tonic::include_proto!("esa.v1");

    /// Encoded descriptors of esa.v1, served by reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("esa_descriptor");
}
