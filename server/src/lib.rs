//! esa-server: Extremum-Seeking Action selection as a service.
//!
//! Layers, each a thin wrapper over the next: transports ([`grpc`],
//! `zenoh_transport` with the cargo feature `zenoh`, on by default, and any other
//! adapter) and the HTTP metrics endpoint
//! ([`metrics_endpoint`]) call the transport-independent
//! [`handler::EsaHandler`], which validates requests and runs them against the
//! [`store::SessionStore`] of `esa_core::Session`s (concurrency, TTL and
//! memory budget over esa-store's sessions by id, whose [`Error`] every
//! transport reports), counting them in [`metrics::Metrics`]. [`server::EsaServer`] assembles the gRPC server. The
//! wire types come from the esa-proto crate ([`pb`]).

pub mod codec;
pub mod connections;
pub mod convert;
pub mod error;
pub mod grpc;
pub mod guard;
pub mod handler;
pub mod metrics;
pub mod metrics_endpoint;
pub mod resources;
pub mod server;
pub mod state_file;
pub mod store;
pub mod throttle;
pub mod tls;
#[cfg(feature = "zenoh")]
pub mod zenoh_transport;

pub use error::{Error, StartError};
pub use esa_proto::Rpc;
pub use handler::EsaHandler;
pub use server::{EsaServer, Listener, ServerBuilder};
pub use tls::TlsSettings;

/// The esa.v1 types: esa-proto's messages, client and descriptor set, and the
/// server side of the service generated here with the bounded codec.
#[allow(missing_docs, clippy::all)]
pub mod pb {
    pub use esa_proto::v1::*;

    tonic::include_proto!("esa.v1");
}
