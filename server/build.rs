//! Generates the server side of `esa.v1.EsaService` (proto/esa/v1/esa.proto,
//! compiled with the pure-Rust `protox`, no system protoc) with the server's
//! own codec (`src/codec.rs`). The messages, the client and the descriptor
//! set come from the esa-proto crate, which this code refers to.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let manifest_dir = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR")?);
    let proto_root = manifest_dir.join("../proto");
    let proto_file = proto_root.join("esa/v1/esa.proto");
    println!("cargo:rerun-if-changed={}", proto_file.display());

    let descriptors = protox::compile([&proto_file], [&proto_root])?;
    tonic_prost_build::configure()
        .build_client(false)
        .build_server(true)
        .extern_path(".esa.v1", "::esa_proto::v1")
        // Bounds what a batch decodes to and answers undecodable bytes with INVALID_ARGUMENT.
        .codec_path("crate::codec::BoundedCodec")
        .compile_fds(descriptors)?;
    Ok(())
}
