//! Which map points are known well enough to publish: each point's first-order covariance
//! from the keyframes that saw it, with their poses held fixed
//! ([`egoslam_geometry::PointInformation`]). Points are triangulated once their rays meet
//! at a workable angle, which is enough to use them for chaining windows and for bundle
//! adjustment, where an uncertain point costs little; a user of the map (an AR overlay, a
//! planner) needs to know it is where the map says. On the paper's frontal profile (2 m
//! forward, a scene reaching 12 m deep) most points are seen by a baseline that fixes
//! their depth to tens of centimetres at best.
//!
//! The covariance trusts the observations; a point must also agree with them in the map
//! as it stands, after windows were chained, rescaled and refined: a point some of whose
//! observations now land pixels away was placed by one window and contradicted by the
//! next (a track that slid along an occluding edge, a point on the seam of two windows).

use crate::map::MapBuilder;
use egoslam_geometry::{PinholeRadtan, PointInformation};
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
    /// reports (Table 2, 20-25 cm RMSE on a 5 m scene). On the rendered frontal profile
    /// the 177 points it keeps have a median error of 3.3 cm, the 857 it drops 11.6 cm.
    /// `f64::INFINITY` publishes every point.
    pub max_relative_std: f64,
    /// Largest reprojection error, in the map as it stands, of any inlier observation of a
    /// published point, in standard deviations of the map's own reprojection noise (robust:
    /// from the median error over every observation, which is 1.18 sigma for 2-D Gaussian
    /// noise). 5 sigma: a Gaussian inlier exceeds it once in 270,000 observations. On the
    /// rendered profiles sigma is 0.26-0.39 px, on tum_fr1_rpy 0.76 px (a map chained from
    /// windows, not adjusted as one). On the rendered egomotion profile it drops a third of
    /// the points the covariance keeps; the surface distance RMSE of the rest is 2.8x lower.
    pub max_reprojection_sigmas: f64,
    /// Fewest keyframes that must observe a published point. 3: two rays always meet (a
    /// track that jumped between two features triangulates as well as a good one), a third
    /// can disagree; ORB-SLAM culls map points seen by fewer than three keyframes for the
    /// same reason (Mur-Artal et al. 2015, section V.B). On the rendered left-right profile
    /// one two-view point 2.8 m off held half of the surface distance's squared error.
    pub min_views: u32,
}

impl Default for PointConfidenceOptions {
    fn default() -> Self {
        Self {
            pixel_sigma: 1.0,
            max_relative_std: 0.02,
            max_reprojection_sigmas: 5.0,
            min_views: 3,
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
    /// Largest distance between an inlier observation and the point's projection into
    /// that keyframe, in standard deviations of the map's reprojection noise (infinite when
    /// the point is behind one of them).
    pub largest_reprojection_sigmas: f64,
}

impl PointConfidence {
    /// Whether the point is known well enough to publish under `options` (every point
    /// when `max_relative_std` is infinite).
    pub fn is_known(&self, options: &PointConfidenceOptions) -> bool {
        options.max_relative_std.is_infinite()
            || (self
                .relative_std
                .is_some_and(|std| std <= options.max_relative_std)
                && self.largest_reprojection_sigmas <= options.max_reprojection_sigmas
                && self.views >= options.min_views)
    }
}

/// The confidence of every map point with an inlier observation (track id -> confidence),
/// from the observations the map keeps (undistorted pixels of `camera`'s ideal pinhole).
pub fn point_confidence(
    map: &MapBuilder,
    camera: &PinholeRadtan,
    options: &PointConfidenceOptions,
) -> HashMap<u64, PointConfidence> {
    let mut information: HashMap<u64, (PointInformation, u32, f64)> = HashMap::new();
    let mut errors = Vec::with_capacity(map.observations.len());
    let mut current: Option<(u64, Option<(u32, egoslam_geometry::StampedPose)>)> = None;
    for (&(keyframe, track), observed) in &map.observations {
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
        let (info, views, largest) = information.entry(track).or_default();
        let in_camera = info.add_view(point, &pose, camera.fx);
        *views += 1;
        let error = camera
            .project_undistorted(&in_camera)
            .map_or(f64::INFINITY, |p| (p - observed).norm());
        *largest = largest.max(error);
        errors.push(error);
    }
    // The median of a 2-D Gaussian error's length is sqrt(2 ln 2) = 1.1774 sigma; the floor
    // keeps an exact map (synthetic tests) finite.
    let sigma = crate::median(errors).map_or(1.0, |m| (m / 1.1774).max(1e-6));
    information
        .into_iter()
        .map(|(track, (info, views, largest))| {
            let confidence = PointConfidence {
                views,
                relative_std: info.relative_std(options.pixel_sigma),
                largest_reprojection_sigmas: largest / sigma,
            };
            (track, confidence)
        })
        .collect()
}

/// Keyframes before a window whose observations rate the points it shares with the map
/// (40: two windows back, which saw the shared points when they were triangulated).
const RATING_KEYFRAMES: u64 = 40;

impl MapBuilder {
    /// Of the points `window` shares with `segment`, as `(window, map)` positions, the
    /// better-determined half on the map's side (by relative standard deviation over the
    /// observations of the keyframes up to [`RATING_KEYFRAMES`] before the window; the
    /// ranking needs no focal length, which scales every figure alike); all of them when
    /// that half would be under `min_points`. The map's side is the end of the previous
    /// window, where points seen by its last few keyframes are triangulated from short
    /// baselines; their camera-to-point distances give a scale ratio only as good as
    /// their depth.
    pub(crate) fn better_determined_shared_points(
        &self,
        segment: u32,
        window: &crate::map::WindowInput,
        min_points: usize,
    ) -> Vec<crate::map::PointPair> {
        let shared: Vec<(u64, crate::map::PointPair)> =
            self.shared_points(window, segment).collect();
        let all = || shared.iter().map(|(_, pair)| *pair).collect();
        if shared.len() < 2 * min_points {
            return all();
        }
        let Some(first) = window.poses.first().map(|(id, _)| *id) else {
            return all();
        };
        let mut information: HashMap<u64, PointInformation> = shared
            .iter()
            .map(|(t, _)| (*t, PointInformation::default()))
            .collect();
        let from = first.saturating_sub(RATING_KEYFRAMES);
        for &(keyframe, track) in self.observations.range((from, 0)..).map(|(k, _)| k) {
            let (Some(info), Some((s, pose))) =
                (information.get_mut(&track), self.keyframes.get(&keyframe))
            else {
                continue;
            };
            if *s == segment {
                if let Some((_, x)) = self.points.get(&track) {
                    info.add_view(x, pose, 1.0);
                }
            }
        }
        let std = |track: &u64| {
            information
                .get(track)
                .and_then(|i| i.relative_std(1.0))
                .unwrap_or(f64::INFINITY)
        };
        let Some(median) = crate::median(shared.iter().map(|(t, _)| std(t)).collect()) else {
            return all();
        };
        let better: Vec<_> = shared
            .iter()
            .filter(|(t, _)| std(t) < median)
            .map(|(_, pair)| *pair)
            .collect();
        if better.len() < min_points {
            all()
        } else {
            better
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::{MapParts, WindowInput};
    use egoslam_geometry::StampedPose;
    use nalgebra::{Point2, UnitQuaternion, Vector2, Vector3};

    fn camera() -> PinholeRadtan {
        PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera")
    }

    /// Observes `point` (track `track`) from `keyframe` of `parts`, `offset` pixels off its
    /// projection.
    fn observe(parts: &mut MapParts, keyframe: u64, track: u64, offset: f64) {
        let (_, pose) = parts.keyframes[&keyframe];
        let (_, x) = parts.points[&track];
        let in_camera = pose.rotation.inverse() * (x - pose.position);
        let pixel = camera().project_undistorted(&in_camera).expect("in front");
        parts
            .observations
            .insert((keyframe, track), pixel + Vector2::new(offset, 0.0));
    }

    /// An empty map with its one segment current.
    fn one_segment() -> MapParts {
        MapParts {
            segments: 1,
            current_segment: Some(0),
            ..MapParts::default()
        }
    }

    fn pose(x: f64, z: f64) -> StampedPose {
        StampedPose {
            timestamp: x + z,
            position: Vector3::new(x, 0.0, z),
            rotation: UnitQuaternion::identity(),
        }
    }

    #[test]
    fn a_point_beside_a_sideways_walk_is_known_one_far_ahead_of_a_forward_walk_is_not() {
        let mut parts = one_segment();
        // Keyframes 0-4 walk sideways 1 m, 10-14 walk forward 1 m.
        for i in 0..5 {
            parts.keyframes.insert(i, (0, pose(0.25 * i as f64, 0.0)));
            parts
                .keyframes
                .insert(10 + i, (0, pose(5.0, 0.25 * i as f64)));
        }
        parts.points.insert(1, (0, Vector3::new(0.5, 0.3, 4.0)));
        parts.points.insert(2, (0, Vector3::new(5.05, 0.0, 10.0)));
        for i in 0..5 {
            // Alternating half-pixel errors: the map's noise.
            let offset = if i % 2 == 0 { 0.5 } else { -0.5 };
            observe(&mut parts, i, 1, offset);
            observe(&mut parts, 10 + i, 2, offset);
        }
        let map = MapBuilder::from_parts(parts);
        let options = PointConfidenceOptions::default();
        let confidence = point_confidence(&map, &camera(), &options);
        let std = |track: u64| confidence[&track].relative_std.expect("fixed");
        assert!(confidence[&1].is_known(&options), "{confidence:?}");
        assert!(!confidence[&2].is_known(&options), "{confidence:?}");
        assert!(std(2) > 10.0 * options.max_relative_std, "{confidence:?}");
        assert_eq!(confidence[&1].views, 5);
    }

    #[test]
    fn a_point_its_observations_contradict_or_only_two_views_see_is_not_known() {
        let mut parts = one_segment();
        for i in 0..5 {
            parts.keyframes.insert(i, (0, pose(0.25 * i as f64, 0.0)));
        }
        // Twenty points seen within half a pixel; track 100 lands 4 px off in one view.
        for t in 0..21u64 {
            let track = if t == 20 { 100 } else { t };
            let x = Vector3::new(0.1 * t as f64 - 1.0, 0.3, 4.0);
            parts.points.insert(track, (0, x));
            for i in 0..5 {
                let offset = match (track, i) {
                    (100, 4) => 4.0,
                    _ if (i + t) % 2 == 0 => 0.5,
                    _ => -0.5,
                };
                observe(&mut parts, i, track, offset);
            }
        }
        // Track 200 is seen exactly by the first and last keyframes only: two rays, 1 m apart.
        parts.points.insert(200, (0, Vector3::new(0.5, -0.3, 4.0)));
        observe(&mut parts, 0, 200, 0.0);
        observe(&mut parts, 4, 200, 0.0);
        let map = MapBuilder::from_parts(parts);
        let options = PointConfidenceOptions::default();
        let confidence = point_confidence(&map, &camera(), &options);
        assert!(confidence[&200].relative_std.is_some_and(|s| s < 0.02));
        assert!(
            !confidence[&200].is_known(&options),
            "{:?}",
            confidence[&200]
        );
        // The map's noise: every error is 0.5 px, sigma = 0.5 / 1.1774.
        let sigma = 0.5 / 1.1774;
        assert!((confidence[&0].largest_reprojection_sigmas - 0.5 / sigma).abs() < 1e-6);
        assert!(confidence[&0].is_known(&options), "{:?}", confidence[&0]);
        assert!(confidence[&100].relative_std.is_some_and(|s| s < 0.02));
        assert!((confidence[&100].largest_reprojection_sigmas - 4.0 / sigma).abs() < 1e-6);
        assert!(
            !confidence[&100].is_known(&options),
            "{:?}",
            confidence[&100]
        );
        // Every point, when asked for every point.
        let all = PointConfidenceOptions {
            max_relative_std: f64::INFINITY,
            ..options
        };
        assert!(confidence[&100].is_known(&all));
    }

    #[test]
    fn shared_points_seen_from_a_short_baseline_do_not_rate_the_join() {
        let mut parts = one_segment();
        for i in 0..10u64 {
            parts.keyframes.insert(i, (0, pose(0.2 * i as f64, 0.0)));
        }
        let pixel = Point2::new(0.0, 0.0);
        for t in 0..80u64 {
            let x = Vector3::new(0.05 * t as f64, 0.5, 4.0);
            parts.points.insert(t, (0, x));
            // Tracks 0-39 seen by all ten keyframes (1.8 m), 40-79 by the last two (0.2 m).
            let seen = if t < 40 { 0..10 } else { 8..10 };
            for k in seen {
                parts.observations.insert((k, t), pixel);
            }
        }
        let map = MapBuilder::from_parts(parts);
        let window = WindowInput {
            poses: vec![(8, map.keyframe(8).expect("kf").1.to_owned())],
            points: (0..80u64)
                .map(|t| (t, Vector3::new(t as f64, 0.0, 0.0)))
                .collect(),
            ..WindowInput::default()
        };
        let rated = map.better_determined_shared_points(0, &window, 30);
        assert_eq!(rated.len(), 40);
        assert!(
            rated.iter().all(|(w, _)| w.x < 40.0),
            "the wide-baseline points"
        );
        // Too few for a half: every shared point.
        assert_eq!(
            map.better_determined_shared_points(0, &window, 41).len(),
            80
        );
    }
}
