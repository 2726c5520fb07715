//! Which map points are known well enough to publish: each point's first-order covariance
//! from the keyframes that saw it, with their poses held fixed
//! ([`egoslam_geometry::PointInformation`]). Points are triangulated once their rays meet
//! at a workable angle, which is enough to use them for chaining windows and for bundle
//! adjustment, where an uncertain point costs little; a user of the map (an AR overlay, a
//! planner) needs to know it is where the map says. On the paper's frontal profile (2 m
//! forward, a scene reaching 12 m deep) most points are seen by a baseline that fixes
//! their depth to tens of centimetres at best.

use crate::chaining::MapBuilder;
use egoslam_geometry::PointInformation;
use std::collections::HashMap;

/// What counts as a known point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointConfidenceOptions {
    /// Pixel noise of an inlier observation. 1 px: the windows' reprojection RMSE after
    /// bundle adjustment is 0.3-0.8 px on real and rendered sequences, so this is an upper
    /// bound, not a tuning.
    pub pixel_sigma: f64,
    /// Largest standard deviation of a published point over its distance to the nearest
    /// camera that saw it. 2 %: 6 cm at 3 m, the scale of the structure errors the paper
    /// reports (Table 2, 20-25 cm RMSE on a 5 m scene), and what separated the points of
    /// the rendered frontal profile with a 4 cm median error (below) from those with 10-16
    /// cm (above). `f64::INFINITY` publishes every point.
    pub max_relative_std: f64,
}

impl Default for PointConfidenceOptions {
    fn default() -> Self {
        Self {
            pixel_sigma: 1.0,
            max_relative_std: 0.02,
        }
    }
}

/// How well one map point is known.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointConfidence {
    /// Keyframes with an inlier observation of it.
    pub views: u32,
    /// Largest standard deviation over the distance to the nearest of those keyframes;
    /// `None` when they do not fix the point (one view, parallel rays).
    pub relative_std: Option<f64>,
}

impl PointConfidence {
    /// Whether the point is known well enough to publish under `options`.
    pub fn is_known(&self, options: &PointConfidenceOptions) -> bool {
        options.max_relative_std.is_infinite()
            || self
                .relative_std
                .is_some_and(|std| std <= options.max_relative_std)
    }
}

/// The confidence of every map point with an inlier observation (track id -> confidence),
/// from the observations the map keeps, for an ideal pinhole of focal length `focal_px`.
pub fn point_confidence(
    map: &MapBuilder,
    focal_px: f64,
    options: &PointConfidenceOptions,
) -> HashMap<u64, PointConfidence> {
    let mut information: HashMap<u64, (PointInformation, u32)> = HashMap::new();
    let mut current: Option<(u64, Option<(u32, egoslam_geometry::StampedPose)>)> = None;
    for &(keyframe, track) in map.observations.keys() {
        if current.map(|c| c.0) != Some(keyframe) {
            current = Some((keyframe, map.keyframes.get(&keyframe).copied()));
        }
        let Some((_, Some((segment, pose)))) = current else {
            continue;
        };
        let Some((point_segment, point)) = map.points.get(&track) else {
            continue;
        };
        if *point_segment != segment {
            continue;
        }
        let (info, views) = information.entry(track).or_default();
        info.add_view(point, &pose, focal_px);
        *views += 1;
    }
    information
        .into_iter()
        .map(|(track, (info, views))| {
            let confidence = PointConfidence {
                views,
                relative_std: info.relative_std(options.pixel_sigma),
            };
            (track, confidence)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::chaining::MapParts;
    use egoslam_geometry::StampedPose;
    use nalgebra::{Point2, UnitQuaternion, Vector3};

    #[test]
    fn a_point_beside_a_sideways_walk_is_known_one_far_ahead_of_a_forward_walk_is_not() {
        let pose = |x: f64, z: f64| StampedPose {
            timestamp: x + z,
            position: Vector3::new(x, 0.0, z),
            rotation: UnitQuaternion::identity(),
        };
        let mut parts = MapParts {
            segments: 1,
            current_segment: Some(0),
            ..MapParts::default()
        };
        // Keyframes 0-4 walk sideways 1 m, 10-14 walk forward 1 m.
        for i in 0..5 {
            parts.keyframes.insert(i, (0, pose(0.25 * i as f64, 0.0)));
            parts
                .keyframes
                .insert(10 + i, (0, pose(5.0, 0.25 * i as f64)));
        }
        parts.points.insert(1, (0, Vector3::new(0.5, 0.3, 4.0)));
        parts.points.insert(2, (0, Vector3::new(5.05, 0.0, 10.0)));
        let pixel = Point2::new(0.0, 0.0); // not used: the poses are held fixed
        for i in 0..5 {
            parts.observations.insert((i, 1), pixel);
            parts.observations.insert((10 + i, 2), pixel);
        }
        let map = MapBuilder::from_parts(parts);
        let options = PointConfidenceOptions::default();
        let confidence = point_confidence(&map, 500.0, &options);
        let std = |track: u64| confidence[&track].relative_std.expect("fixed");
        assert!(confidence[&1].is_known(&options), "{confidence:?}");
        assert!(!confidence[&2].is_known(&options), "{confidence:?}");
        assert!(std(2) > 10.0 * options.max_relative_std, "{confidence:?}");
        assert_eq!(confidence[&1].views, 5);
    }
}
