//! What relocalization searches and what it is asked: a map's keyframes with their
//! described features and poses, its points, and a query frame's features. Plain data, so
//! that the saved-map format (`saved_map`), the merger's live map and the relocalizer share
//! it.

use crate::descriptors::Descriptor;
use crate::patch_alignment::Patch;
use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Point2, Vector3};
use std::collections::HashMap;

/// A described track of a keyframe; it gives matches when the map has its track as a
/// point, and makes the keyframe's bag of words either way.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapFeature {
    pub track_id: u64,
    pub descriptor: Descriptor,
    /// Undistorted pixel in the keyframe.
    pub pixel: Point2<f32>,
}

/// A keyframe of a relocalization map.
#[derive(Debug, Clone, PartialEq)]
pub struct MapKeyframe {
    pub keyframe_id: u64,
    /// Map segment of the keyframe (poses of different segments are in different frames).
    pub segment: u32,
    /// world_from_camera, in the segment's frame.
    pub pose: StampedPose,
    pub features: Vec<MapFeature>,
    /// The patches of the tracks first described in this keyframe (track id, patch), for placing
    /// their points in a query image ([`crate::patch_alignment`]); empty in maps saved
    /// before patches were kept.
    pub patches: Vec<(u64, Patch)>,
}

/// What relocalization searches: keyframes with described features and the points.
#[derive(Debug, Clone, PartialEq)]
pub struct RelocalizationMap {
    /// Ideal pinhole camera of the undistorted pixels.
    pub camera: PinholeRadtan,
    pub keyframes: Vec<MapKeyframe>,
    /// track id -> (segment, position).
    pub points: HashMap<u64, (u32, Vector3<f64>)>,
    /// Rolling-shutter readout the map's keyframes were corrected for, seconds (0: a global
    /// shutter or unknown): the default for query frames from the same camera.
    pub rolling_shutter_s: f64,
}

/// A query frame's features (undistorted pixels and their descriptors, same order).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct QueryFeatures {
    pub pixels: Vec<Point2<f64>>,
    pub descriptors: Vec<Descriptor>,
}
