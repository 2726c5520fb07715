//! Relocalization (paper, section 5 "Relocalization"; issue 7): ORB descriptors on keyframes
//! at the tracked corners, a vocabulary tree with an inverted index over keyframes, PnP from
//! scratch for frames without a tracking prior, and the saved-map file that lets another
//! run localize in a map built earlier.
//!
//! No I/O here: callers read and write files; everything is testable on bytes and images.

pub mod absolute_pose;
pub mod descriptors;
pub mod keyframe_database;
pub mod patch_alignment;
pub mod relocalization_map;
pub mod relocalizer;
pub mod rolling_shutter_pose;
pub mod rotation_relocalization;
pub mod saved_map;
pub mod vocabulary;
pub mod wire;

pub use descriptors::{hamming, Descriptor, OrbDescriber};
pub use keyframe_database::{Candidate, KeyframeDatabase};
pub use relocalizer::{
    MapFeature, MapKeyframe, QueryFeatures, Relocalization, RelocalizationError, RelocalizationMap,
    Relocalizer, RelocalizerOptions, TentativePoseOptions,
};
pub use saved_map::{decode_map, encode_map, intrinsics_to_pb, lens_from_pb, SavedMapError};
pub use vocabulary::{
    default_vocabulary, BowVector, Vocabulary, VocabularyError, VocabularyOptions,
};
