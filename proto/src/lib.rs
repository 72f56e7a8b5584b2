//! esa-proto: the esa.v1 wire contract (`proto/esa/v1/esa.proto`, semantics in
//! `docs/CONTRACT.md`) for Rust programs: the generated prost messages and
//! tonic client ([`v1`]), the RPC names ([`Rpc`]) and the structured error
//! details every transport carries ([`details`]). The server, the load
//! generator and any Rust client share these types; the server's side of the
//! service is generated in esa-server.

pub mod convert;
pub mod details;
mod rpc;

pub use rpc::Rpc;

/// The key prefix of the Zenoh transport when none is configured:
/// `esa/v1/<RpcName>` (CONTRACT.md section 3).
pub const DEFAULT_ZENOH_PREFIX: &str = "esa/v1";

/// Types generated from `proto/esa/v1/esa.proto`: the messages and the
/// `esa_service_client` module.
#[allow(missing_docs, clippy::all)]
pub mod v1 {
    tonic::include_proto!("esa.v1");

    /// Encoded descriptors of esa.v1, for server reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("esa_descriptor");
}
