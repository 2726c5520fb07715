//! Compiles proto/egoslam/v1/*.proto (the client contract) and proto/egoslam/internal/v1/
//! (messages between the processes, the checkpoint and the saved map) with prost (protoc
//! from Debian's protobuf-compiler), and writes the descriptor set of both for the check
//! that the public package changes only compatibly (tests/public_contract.rs).
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../proto");
    let files: Vec<_> = [
        "v1/geometry",
        "v1/map",
        "internal/v1/frontend",
        "internal/v1/window",
        "internal/v1/checkpoint",
        "internal/v1/saved_map",
    ]
    .iter()
    .map(|f| root.join(format!("egoslam/{f}.proto")))
    .collect();
    for f in &files {
        println!("cargo:rerun-if-changed={}", f.display());
    }
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    prost_build::Config::new()
        .file_descriptor_set_path(out.join("descriptors.bin"))
        .compile_protos(&files, &[root])?;
    Ok(())
}
