//! The egoslam messages, compiled with prost from `proto/`.
//!
//! `v1` (package `egoslam.v1`, `proto/egoslam/v1/`) is the contract with clients in other
//! languages: what goes out over zenoh. Its fields are only ever added, never renumbered
//! (tests/public_contract.rs). `internal::v1` (package `egoslam.internal.v1`) holds the
//! messages between egoslam's own processes and its state formats (checkpoint, saved map):
//! clients never depend on them.

/// Version 1 of the client contract.
pub mod v1 {
    include!(concat!(env!("OUT_DIR"), "/egoslam.v1.rs"));
}

/// Messages between the processes (iceoryx2) and the formats of the merger's checkpoint and
/// of saved maps; each file format carries its own version.
pub mod internal {
    pub mod v1 {
        include!(concat!(env!("OUT_DIR"), "/egoslam.internal.v1.rs"));
    }
}

/// The encoded `FileDescriptorSet` of every egoslam `.proto` (public and internal).
pub const DESCRIPTORS: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/descriptors.bin"));
