//! The egoslam wire format: protobuf messages of package `egoslam.v1`, compiled with prost.
//!
//! The `.proto` files in `proto/egoslam/v1/` are the contract with clients in other languages;
//! this crate only re-exports what prost generated from them.

/// Version 1 of the wire format. Fields are only ever added, never renumbered.
pub mod v1 {
    include!(concat!(env!("OUT_DIR"), "/egoslam.v1.rs"));
}
