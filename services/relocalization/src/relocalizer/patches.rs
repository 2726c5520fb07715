//! The last step of a relocalization: the inliers' points placed in the query image by
//! their saved patches, and the pose solved again on those positions
//! ([`crate::patch_alignment`]).

use super::{Relocalization, Relocalizer, RelocalizerOptions};
use crate::absolute_pose::{solve_pnp, PnpOptions};
use crate::patch_alignment::{align_patch, viewpoint_warp};
use crate::rolling_shutter_pose::RollingShutterPose;
use egoslam_geometry::{PinholeRadtan, StampedPose};
use opencv::prelude::MatTraitConst;

impl Relocalizer {
    /// Places the points of `found`'s inliers in the query `image` (raw, 8-bit grey) by
    /// their saved patches, and solves the pose again on those positions: a point is where
    /// its track was, which the query's corners miss by a pixel or two
    /// ([`crate::patch_alignment`]). `raw_camera` is the query's camera with its
    /// distortion. `found` comes back unchanged when fewer than the PnP minimum of its
    /// points align (maps saved without patches, a blurred frame).
    pub fn refine_by_patches(
        &self,
        found: Relocalization,
        image: &impl MatTraitConst,
        raw_camera: &PinholeRadtan,
        options: &RelocalizerOptions,
    ) -> Relocalization {
        let _span =
            tracing::debug_span!("patch_alignment", inliers = found.inliers.len()).entered();
        let camera = &self.map.camera;
        let camera_from_world = found.pose.rotation.inverse();
        let turning = RollingShutterPose::from_motion(found.pose, found.angular_velocity);
        let mut aligned = Vec::new();
        let mut tracks = Vec::new();
        let every = found
            .inliers
            .len()
            .div_ceil(options.max_aligned.max(1))
            .max(1);
        for &(track, feature) in found.inliers.iter().step_by(every) {
            let (Some(&(k, p, reference_pixel)), Some((_, point))) =
                (self.patch_index.get(&track), self.map.points.get(&track))
            else {
                continue;
            };
            let keyframe = &self.map.keyframes[k];
            let Some(warp) =
                viewpoint_warp(camera, &keyframe.pose, reference_pixel, point, &found.pose)
            else {
                continue;
            };
            // Where the point is on the row that sees it: a turn of 60 deg/s over a 22 ms
            // readout moves rows at the top and bottom ~6 px from the middle row's view,
            // beyond the alignment's reach.
            let seen = if options.rolling_shutter_s > 0.0 {
                turning
                    .project(camera, point, options.rolling_shutter_s)
                    .map(|ideal| camera.bearing_from_undistorted(ideal))
            } else {
                Some(camera_from_world * (point - found.pose.position))
            };
            let Some(predicted) = seen.and_then(|ray| raw_camera.project_raw(&ray)) else {
                continue;
            };
            let patch = &keyframe.patches[p].1;
            let aligned_raw = align_patch(image, patch, predicted, &warp, &options.alignment);
            if let Some(ideal) = aligned_raw.and_then(|raw| raw_camera.undistort_pixel(raw)) {
                aligned.push((*point, ideal));
                tracks.push((track, feature));
            }
        }
        if options.rolling_shutter_s > 0.0 {
            return self.solve_rolling_shutter(found, &aligned, &tracks, options);
        }
        // A global shutter: a PnP from the pose.
        let refine = PnpOptions {
            min_inlier_ratio: 0.0,
            ransac_iterations: 50,
            ransac_threshold_px: options.aligned_threshold_px,
            ..options.pnp
        };
        // As the refinement by projection: a RANSAC from the pose may settle on another.
        let refined = solve_pnp(camera, &aligned, Some(&found.pose), &refine)
            .ok()
            .filter(|r| {
                super::confirmation::stays_near(
                    options,
                    &found.pose,
                    found.inliers.len(),
                    r,
                    &aligned,
                )
            });
        match refined {
            Some(solution) => Relocalization {
                pose: StampedPose {
                    timestamp: found.pose.timestamp,
                    ..solution.pose
                },
                inliers: solution.inliers.iter().map(|&i| tracks[i]).collect(),
                ..found
            },
            None => found,
        }
    }
}
