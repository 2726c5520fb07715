//! Compiles proto/egoslam/v1/*.proto with prost (protoc from Debian's protobuf-compiler).
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../proto");
    let files: Vec<_> = ["geometry", "frontend", "map", "checkpoint", "saved_map"]
        .iter()
        .map(|f| root.join(format!("egoslam/v1/{f}.proto")))
        .collect();
    for f in &files {
        println!("cargo:rerun-if-changed={}", f.display());
    }
    prost_build::Config::new().compile_protos(&files, &[root])?;
    Ok(())
}
