//! Compiles esa/v1/esa.proto with the pure-Rust `protox` compiler (no system
//! protoc) into the prost messages and the tonic client, and writes the
//! encoded descriptor set to OUT_DIR for server reflection. The server's side
//! of the service is generated in esa-server, which decodes requests with its
//! own bounded codec.

use std::path::PathBuf;

use prost::Message;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let proto_root = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR")?);
    let proto_file = proto_root.join("esa/v1/esa.proto");
    println!("cargo:rerun-if-changed={}", proto_file.display());

    let descriptors = protox::compile([&proto_file], [&proto_root])?;
    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(
        out_dir.join("esa_descriptor.bin"),
        descriptors.encode_to_vec(),
    )?;

    tonic_prost_build::configure()
        .build_client(true)
        .build_server(false)
        .compile_fds(descriptors)?;
    Ok(())
}
