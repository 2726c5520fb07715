//! Keyframes of a place the map already holds (a revisit): the wearer walks the same
//! corridor all day, and every pass brings its own keyframes and points of the same walls.
//! Their tracks are new, so the covisibility rule ([`crate::keyframe_culling`]) does not
//! see them as redundant, and the map would grow with the time walked instead of with the
//! ground covered. A keyframe is covered when an older keyframe of an earlier pass stands
//! where it stands and looks where it looks; it is then culled like a redundant one, as the
//! reduced pose graph of Johannsson et al. ("Temporally scalable visual SLAM using a reduced
//! pose graph", ICRA 2013) adds no keyframe where the map already has one. The culled
//! keyframes' frames are then posed relative to the kept keyframe nearest in space, often
//! one of the earlier pass (`session::keyframe_culling`), so a pass walked over known ground
//! leaves nothing in the map.

use crate::map::MapBuilder;
use egoslam_geometry::StampedPose;
use nalgebra::Vector3;

/// When a keyframe is covered by an older one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CoverageOptions {
    /// Only keyframes at least this many ids older count (an earlier pass; the keyframes
    /// just before are the covisibility rule's). 200: ~10 s of a head-mounted walk.
    pub min_age: u64,
    /// Centres at most this fraction of the keyframe's median scene depth apart.
    pub max_offset: f64,
    /// Optical axes at most this far apart, degrees (ORB-SLAM's loop and relocalization
    /// candidates share most of their view at 20-30 deg).
    pub max_angle_deg: f64,
}

impl Default for CoverageOptions {
    fn default() -> Self {
        Self {
            min_age: 200,
            max_offset: 0.1,
            max_angle_deg: 20.0,
        }
    }
}

/// The keyframes a culling pass may find covering its candidates.
pub struct OlderKeyframes {
    /// (id, segment, centre, optical axis), in id order.
    entries: Vec<(u64, u32, Vector3<f64>, Vector3<f64>)>,
    options: CoverageOptions,
}

/// The optical axis of the camera at `pose`, in the map.
pub(crate) fn axis(pose: &StampedPose) -> Vector3<f64> {
    pose.rotation * Vector3::z()
}

impl OlderKeyframes {
    /// The keyframes of `map` older than `newest_candidate` by at least `min_age` ids (each
    /// candidate looks at those older than itself by that much).
    pub fn of(map: &MapBuilder, newest_candidate: u64, options: &CoverageOptions) -> Self {
        let before = newest_candidate.saturating_sub(options.min_age);
        let entries = map
            .keyframes
            .range(..before)
            .map(|(id, (s, p))| (*id, *s, p.position, axis(p)))
            .collect();
        Self {
            entries,
            options: *options,
        }
    }

    /// Whether keyframe `id` of `segment` at `pose` is covered by an older keyframe.
    pub fn cover(&self, map: &MapBuilder, id: u64, segment: u32, pose: &StampedPose) -> bool {
        let o = &self.options;
        // A keyframe without points of its own is measured by the scene depth of the
        // older keyframe that would cover it.
        let own_depth = map.observed_depth(id, pose);
        let (centre, view) = (pose.position, axis(pose));
        let cos_max = o.max_angle_deg.to_radians().cos();
        let last = id.saturating_sub(o.min_age);
        self.entries
            .iter()
            .take_while(|(k, ..)| *k < last)
            .any(|(k, s, c, a)| {
                if *s != segment || a.dot(&view) < cos_max {
                    return false;
                }
                let depth = own_depth.or_else(|| {
                    let (_, older) = map.keyframes.get(k)?;
                    map.observed_depth(*k, older)
                });
                depth.is_some_and(|d| (c - centre).norm() <= o.max_offset * d)
                    && map.keyframes.contains_key(k)
            })
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::keyframe_culling::KeyframeCullingOptions;
    use crate::map::MapParts;
    use nalgebra::{Point2, UnitQuaternion};

    fn pose(t: f64, x: f64, yaw_deg: f64) -> StampedPose {
        StampedPose {
            timestamp: t,
            position: Vector3::new(x, 0.0, 0.0),
            rotation: UnitQuaternion::from_euler_angles(0.0, yaw_deg.to_radians(), 0.0),
        }
    }

    /// A corridor walked along x twice: keyframes 0..300 at x = k / 100, then keyframes
    /// 300..600 at the same places again, each seeing 10 tracks of its own (no shared
    /// points: only coverage can cull) 5 units ahead; the second pass looks `yaw` away.
    pub(crate) fn two_passes(yaw_deg: f64) -> MapBuilder {
        let mut parts = MapParts::default();
        for k in 0..600u64 {
            let x = (k % 300) as f64 / 100.0;
            let yaw = if k >= 300 { yaw_deg } else { 0.0 };
            parts.keyframes.insert(k, (0, pose(k as f64, x, yaw)));
            for t in 0..10 {
                let track = k * 10 + t;
                parts
                    .points
                    .insert(track, (0, Vector3::new(x, 0.1 * t as f64, 5.0)));
                parts.observations.insert((k, track), Point2::new(1.0, 2.0));
            }
        }
        MapBuilder::from_parts(parts)
    }

    #[test]
    fn a_second_pass_over_known_ground_leaves_nothing_and_a_new_view_is_kept() {
        let options = crate::keyframe_culling::tests::any_size();
        let candidates: Vec<u64> = (300..590).collect();
        let mut map = two_passes(5.0);
        let report = map.cull_keyframes(&candidates, &options);
        // 5 deg away, 0.01 apart at depth 5: every candidate is covered.
        assert_eq!(report.culled.len(), 290);
        assert_eq!(
            map.keyframes()
                .filter(|(id, ..)| (300..590).contains(id))
                .count(),
            0
        );
        // Their own points went with them.
        assert_eq!(report.removed_points, 10 * report.culled.len());
        // The first pass is untouched.
        assert_eq!(map.keyframes().filter(|(id, ..)| *id < 300).count(), 300);

        // Looking 40 deg away, the second pass sees something else: nothing is culled.
        let mut map = two_passes(40.0);
        assert!(map.cull_keyframes(&candidates, &options).culled.is_empty());
        // Without the rule, nothing either (no shared points).
        let mut map = two_passes(5.0);
        let without = KeyframeCullingOptions {
            revisits: None,
            ..options
        };
        assert!(map.cull_keyframes(&candidates, &without).culled.is_empty());
    }

    #[test]
    fn a_revisit_keyframe_without_points_is_covered_by_the_depth_before_it() {
        // The second pass's keyframes see no point except one in ten (the points of the
        // others went with neighbours culled before them).
        let mut parts = two_passes(5.0).to_parts();
        parts
            .observations
            .retain(|(k, _), _| *k < 300 || k % 10 == 0);
        let mut map = MapBuilder::from_parts(parts);
        let options = crate::keyframe_culling::tests::any_size();
        let candidates: Vec<u64> = (300..590).collect();
        let report = map.cull_keyframes(&candidates, &options);
        // As with points: every candidate is covered.
        assert_eq!(report.culled.len(), 290);
        // Without the older pass there is nothing to cover them, and without points they
        // are not redundant: none goes.
        let mut parts = two_passes(5.0).to_parts();
        parts.keyframes.retain(|k, _| *k >= 300);
        parts.observations.retain(|(k, _), _| k % 10 == 0);
        let mut alone = MapBuilder::from_parts(parts);
        let report = alone.cull_keyframes(&candidates, &options);
        assert!(
            report.culled.iter().all(|c| c.keyframe_id % 10 == 0),
            "{:?}",
            report.culled
        );
    }
}
