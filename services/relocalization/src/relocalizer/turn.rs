//! A rolling-shutter query's pose with the camera's turn during the readout
//! ([`crate::rolling_shutter_pose`]): the points searched for again where the turning camera
//! sees them, and the pose solved on aligned positions with the turn. With the middle row's
//! pose alone, a head turning at 60 deg/s over a 22 ms readout (TUM fr1_rpy) puts the top
//! and bottom rows ~6 px from where it predicts them, so the search and the refinements'
//! thresholds kept mostly the rows near the middle one.

use super::confirmation::pose_stays_near;
use super::{QueryFeatures, Relocalization, Relocalizer, RelocalizerOptions};
use crate::rolling_shutter_pose::{refine_rolling_shutter_inliers, RollingShutterPose};
use nalgebra::{Point2, Vector3};

impl Relocalizer {
    /// `found` searched again by projection with the camera's turn during the readout and
    /// refined with it on the matches it explains: the first search placed the points with
    /// the middle row's pose, so rows far from it (moved most by the turn) fell outside the
    /// search radius or the refinement's threshold. `found` unchanged with a global
    /// shutter, or when the search finds fewer inliers or leaves its pose.
    pub(super) fn searched_with_turn(
        &self,
        query: &QueryFeatures,
        local: &[usize],
        found: Relocalization,
        options: &RelocalizerOptions,
    ) -> Relocalization {
        let readout = options.rolling_shutter_s;
        if readout <= 0.0 || found.angular_velocity == Vector3::zeros() {
            return found;
        }
        let camera = &self.map.camera;
        let turning = RollingShutterPose::from_motion(found.pose, found.angular_velocity);
        let matches = self.match_projected(
            query,
            local,
            |x| turning.project(camera, x, readout),
            options,
        );
        let pairs = self.correspondences(query, &matches);
        let threshold = options.refine_threshold_px;
        let min_kept = found.inliers.len().max(options.pnp.min_inliers);
        self.refined_with_turn(found, &pairs, &matches, threshold, min_kept, options)
    }

    /// The pose of a rolling-shutter frame solved on aligned positions with the camera's
    /// turn during the readout ([`refine_rolling_shutter_inliers`]): a global-shutter PnP
    /// at the aligned threshold would keep only the rows near the middle one, which the
    /// turn moved least. `found` unchanged when the refinement fails or leaves it.
    pub(super) fn solve_rolling_shutter(
        &self,
        found: Relocalization,
        aligned: &[(Vector3<f64>, Point2<f64>)],
        tracks: &[(u64, usize)],
        options: &RelocalizerOptions,
    ) -> Relocalization {
        let (threshold, min_kept) = (options.aligned_threshold_px, options.pnp.min_inliers);
        self.refined_with_turn(found, aligned, tracks, threshold, min_kept, options)
    }

    /// `found` refined with the turn on `pairs` ([`refine_rolling_shutter_inliers`] at
    /// `threshold_px`, at least `min_kept` kept), its inliers the kept pairs' `matches`
    /// (`(track, query feature)`, index for index with `pairs`); `found` unchanged when the
    /// refinement fails or leaves the refinement's bounds of it.
    fn refined_with_turn(
        &self,
        found: Relocalization,
        pairs: &[(Vector3<f64>, Point2<f64>)],
        matches: &[(u64, usize)],
        threshold_px: f64,
        min_kept: usize,
        options: &RelocalizerOptions,
    ) -> Relocalization {
        let Some((refined, kept)) = refine_rolling_shutter_inliers(
            &self.map.camera,
            pairs,
            &found.pose,
            options.rolling_shutter_s,
            threshold_px,
            min_kept,
            &options.rolling_shutter,
        ) else {
            return found;
        };
        let points = kept.iter().map(|&i| &pairs[i].0);
        if !pose_stays_near(options, &found.pose, &refined.pose, points) {
            return found;
        }
        Relocalization {
            pose: refined.pose,
            inliers: kept.iter().map(|&i| matches[i]).collect(),
            angular_velocity: refined.angular_velocity,
            ..found
        }
    }
}
