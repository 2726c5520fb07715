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

/// A run started again from its first frame numbers round r's poses from
/// `r << ROUND_REVISION_BITS` (`v1::Pose::revision`): above every revision of the rounds
/// before (a frame is revised a few times, not 16 million), so that clients, which keep a
/// frame's highest revision, take the last round's.
pub const ROUND_REVISION_BITS: u32 = 24;

/// Whether a pose's `revision` is a frame's first pose in its round (the live pose).
pub fn first_of_round(revision: u32) -> bool {
    revision & ((1 << ROUND_REVISION_BITS) - 1) == 0
}

/// The encoded `FileDescriptorSet` of every egoslam `.proto` (public and internal).
pub const DESCRIPTORS: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/descriptors.bin"));

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rounds_first_pose_has_the_low_bits_zero() {
        assert!(first_of_round(0) && first_of_round(1 << 24) && first_of_round(3 << 24));
        assert!(!first_of_round(1) && !first_of_round((2 << 24) + 5));
    }
}
