//! Median scene depth on either side of a window boundary: the scale evidence a window has
//! when it shares too few points with the map to measure scale from them.
//!
//! After the wearer stood still (rotation-only windows: no points, every centre equal) or
//! after a turn that ended every track, the next window shares keyframes with the map but
//! no points, and the shared centres have no spread; the chaining then had no scale at all
//! and kept the window's own (1.0), an arbitrary jump: on a rendered 1500-frame walk three
//! such windows moved the map's scale by 0.3x-2.7x. A head-mounted camera looks at the same
//! room before and after it stops, so the typical depth of what it sees is the best scale
//! evidence left: the scale is taken so that the median depth of the window's points, seen
//! from its first keyframes, equals that of the map's points seen from the segment's latest
//! keyframes (the normalisation monocular systems use at initialisation, e.g. ORB-SLAM's
//! median scene depth of 1).

use crate::map::{MapBuilder, WindowInput};
use crate::median;
use egoslam_geometry::StampedPose;
use nalgebra::Vector3;
use std::collections::HashMap;

/// Keyframes whose depths are pooled on each side (default 5: the windows' overlap).
const KEYFRAMES: usize = 5;
/// Points a keyframe must see for its median depth to count.
const MIN_POINTS: usize = 10;
/// Map keyframes searched back from the newest (a stop can hold this many without points).
const MAX_SEARCHED: usize = 400;

/// Depths (along the optical axis) of those of `points` in front of the camera at `pose`.
fn depths_in_front<'a>(
    pose: &StampedPose,
    points: impl Iterator<Item = &'a Vector3<f64>>,
) -> Vec<f64> {
    let to_camera = pose.rotation.inverse();
    points
        .map(|x| (to_camera * (x - pose.position)).z)
        .filter(|z| *z > 0.0 && z.is_finite())
        .collect()
}

/// Median depth (along the optical axis) of `points` seen from `pose`, if enough are in front.
fn keyframe_depth<'a>(
    pose: &StampedPose,
    points: impl Iterator<Item = &'a Vector3<f64>>,
) -> Option<f64> {
    let depths = depths_in_front(pose, points);
    (depths.len() >= MIN_POINTS)
        .then(|| median(depths))
        .flatten()
}

/// Median scene depth of the window's first keyframes that see enough of its points.
pub(crate) fn window_scene_depth(window: &WindowInput) -> Option<f64> {
    let points: HashMap<u64, &Vector3<f64>> = window.points.iter().map(|(t, x)| (*t, x)).collect();
    let mut seen: HashMap<u64, Vec<&Vector3<f64>>> = HashMap::new();
    for (kf, track, _) in &window.observations {
        if let Some(x) = points.get(track) {
            seen.entry(*kf).or_default().push(x);
        }
    }
    let depths: Vec<f64> = window
        .poses
        .iter()
        .filter_map(|(id, pose)| keyframe_depth(pose, seen.get(id)?.iter().copied()))
        .take(KEYFRAMES)
        .collect();
    median(depths)
}

impl MapBuilder {
    /// Median depth of the map points keyframe `id`, at `pose`, observes (any number of
    /// them in front of it).
    pub(crate) fn observed_depth(&self, id: u64, pose: &StampedPose) -> Option<f64> {
        self.observed_depth_of(id, pose, 0)
    }

    /// [`Self::observed_depth`] when at least `min_points` of the points are in front of
    /// the keyframe, else `None`.
    pub(crate) fn observed_depth_of(
        &self,
        id: u64,
        pose: &StampedPose,
        min_points: usize,
    ) -> Option<f64> {
        let points = self
            .observations
            .range((id, 0)..=(id, u64::MAX))
            .filter_map(|((_, track), _)| self.points.get(track))
            .map(|(_, x)| x);
        let depths = depths_in_front(pose, points);
        (depths.len() >= min_points)
            .then(|| median(depths))
            .flatten()
    }

    /// Median scene depth of the latest keyframes of `segment` that see enough map points.
    pub(crate) fn recent_scene_depth(&self, segment: u32) -> Option<f64> {
        let depths: Vec<f64> = self
            .keyframes
            .iter()
            .rev()
            .filter(|(_, (s, _))| *s == segment)
            .take(MAX_SEARCHED)
            .filter_map(|(id, (_, pose))| {
                let points = self
                    .observations
                    .range((*id, 0)..=(*id, u64::MAX))
                    .filter_map(|((_, track), _)| match self.points.get(track) {
                        Some((s, x)) if *s == segment => Some(x),
                        _ => None,
                    });
                keyframe_depth(pose, points)
            })
            .take(KEYFRAMES)
            .collect();
        median(depths)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    fn pose(id: u64, x: f64) -> (u64, StampedPose) {
        (
            id,
            StampedPose {
                timestamp: id as f64,
                position: Vector3::new(x, 0.0, 0.0),
                rotation: UnitQuaternion::identity(),
            },
        )
    }

    /// A window of 3 keyframes looking at a wall `depth` ahead (20 points), `prefix` on the
    /// track ids.
    fn window(depth: f64, first_id: u64, prefix: u64) -> WindowInput {
        let poses = vec![
            pose(first_id, 0.0),
            pose(first_id + 1, 0.1),
            pose(first_id + 2, 0.2),
        ];
        let points: Vec<(u64, Vector3<f64>)> = (0..20)
            .map(|k| (prefix + k, Vector3::new(k as f64 * 0.1 - 1.0, 0.3, depth)))
            .collect();
        WindowInput::seeing_all(poses, points, 0)
    }

    #[test]
    fn depths_of_the_map_and_of_a_window_without_shared_points() {
        let mut map = MapBuilder::new();
        map.add_window(&window(4.0, 0, 1000));
        assert_eq!(map.recent_scene_depth(0), Some(4.0));
        // The same wall seen by a window in a frame 8x smaller: depth 0.5.
        let w = window(0.5, 2, 5000);
        assert_eq!(window_scene_depth(&w), Some(0.5));
        // Too few points seen: no depth.
        let mut sparse = window(0.5, 2, 5000);
        sparse.points.truncate(5);
        assert_eq!(window_scene_depth(&sparse), None);
        assert_eq!(map.recent_scene_depth(7), None);
    }

    #[test]
    fn after_a_stop_the_scale_comes_from_the_scene_depth() {
        let mut map = MapBuilder::new();
        // Walking: keyframes 0-2, 0.1 m apart, a wall 4 m ahead.
        map.add_window(&window(4.0, 0, 1000));
        // Standing: keyframes 1-4 all at the last position, no points (rotation-only).
        let stand = WindowInput {
            poses: (1..5).map(|id| pose(id, 0.0)).collect(),
            ..Default::default()
        };
        map.add_window(&stand);
        // Walking on, in a window frame 8x smaller than the map's (the wall at 0.5), sharing
        // keyframes 3-4 but no track: the 0.1 step to keyframe 5 is 0.8 in the map.
        let mut on = window(0.5, 3, 5000);
        on.poses[0].1.position = Vector3::zeros();
        on.poses[1].1.position = Vector3::zeros();
        on.poses[2].1.position = Vector3::new(0.1, 0.0, 0.0);
        let outcome = map.add_window(&on);
        match outcome {
            crate::WindowOutcome::Aligned { transform, .. } => {
                assert!((transform.scale - 8.0).abs() < 1e-9, "{}", transform.scale)
            }
            other => panic!("{other:?}"),
        }
        let (_, k5) = map.keyframe(5).expect("keyframe 5");
        let (_, k4) = map.keyframe(4).expect("keyframe 4");
        assert!(((k5.position - k4.position).norm() - 0.8).abs() < 1e-9);
    }
}
