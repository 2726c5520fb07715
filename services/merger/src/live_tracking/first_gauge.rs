//! The gauge of a new stream's first frames, before any window is merged.
//!
//! The merger puts a new segment's first window in the gauge of one map unit per second of
//! walking ([`crate::speed_continuity::new_segment_gauge`]: the window's pace, the median
//! speed of its moving keyframes, made [`NEW_SEGMENT_PACE`]). The live tracker has to pose
//! the frames before that window in the same gauge, and has only its own points to do it
//! with: it walks its first steps at that pace and triangulates on them, and the scale of
//! those first steps stays with every point triangulated after. A start slower or faster
//! than the walk's median (a car pulling away, a wearer's first stride) then scales every
//! live pose until the first window arrives: on kitti_odometry_00 the first 6 s of live
//! poses were 1.36-1.55x the map's scale, which made the live trajectory's ATE 14.8x the
//! refined one's in a real-time replay. So, until the first window, the tracker's own pace is measured as the
//! merger will measure the window's, and the tracker's positions and points are scaled
//! about the origin (the first keyframe, which the gauge is scaled about too) to hold it
//! at [`NEW_SEGMENT_PACE`].
//!
//! [`NEW_SEGMENT_PACE`]: crate::speed_continuity::NEW_SEGMENT_PACE

use super::LiveTracker;
use crate::speed_continuity::{walking_pace, SpeedContinuityOptions};
use egoslam_geometry::StampedPose;
use nalgebra::{Point2, Vector3};

/// A correction smaller than this fraction is not applied: the pace of a few steps is
/// noisier than that, and each correction moves the published poses.
const SMALLEST_CORRECTION: f64 = 0.05;

/// Moving time the frames' pace needs before it corrects anything, seconds (the merger's
/// test asks 0.5 s of a window's refined keyframes; frames posed one by one on their own
/// young points need longer for a pace as steady: on the TUM clip's turning head the pace
/// of 0.5 s swung 2-5x from frame to frame).
const MIN_SPAN_S: f64 = 1.0;

/// Largest change of scale one frame makes (a factor of 1.1 either way): the pace of a
/// second of frames still wanders, and the correction is meant to follow a scale the
/// first steps set wrong, not that noise. At 10 frames per second a start 1.5x off is
/// corrected within half a second.
const MAX_STEP_CORRECTION: f64 = 1.1;

/// Shortest step whose speed counts, seconds: the merger measures a window's pace between
/// keyframes refined by its bundle adjustment, the tracker between frames posed one by
/// one, whose jitter over a frame's 33 ms is a speed of its own (a standing head's
/// millimetres of PnP noise would read as walking).
const MIN_STEP_S: f64 = 0.2;

/// The stream's first this-many seconds are what the gauge is measured over (the first
/// window's pace is its first keyframes', a few seconds of video): a stream whose first
/// window never comes (a solver that fails every window) neither grows the record nor the
/// work per frame past them.
const MAX_GAUGE_S: f64 = 10.0;

/// The frames the tracker posed by PnP since the stream began, while no window is merged,
/// with each frame's median scene depth.
#[derive(Debug, Default)]
pub(super) struct FirstGauge {
    poses: Vec<StampedPose>,
    depths: Vec<f64>,
}

impl FirstGauge {
    /// Adds a frame posed by PnP and the median depth of the points it was posed on (not
    /// past [`MAX_GAUGE_S`] after the first).
    pub(super) fn push(&mut self, pose: StampedPose, depth: f64) {
        let late = self
            .poses
            .first()
            .is_some_and(|first| pose.timestamp - first.timestamp > MAX_GAUGE_S);
        if depth.is_finite() && depth > 0.0 && !late {
            self.poses.push(pose);
            self.depths.push(depth);
        }
    }

    /// The factor the positions are to be scaled by, about the origin, so that the frames
    /// walk at `pace`, at most [`MAX_STEP_CORRECTION`] at once: `None` while they do not
    /// clearly walk (the merger's test: moving steps of at least `min_speed_depths_per_s`
    /// scene depths per second, over at least [`MIN_SPAN_S`] in steps of at least
    /// [`MIN_STEP_S`]) or when they already walk within [`SMALLEST_CORRECTION`] of it.
    pub(super) fn correction(&self, pace: f64) -> Option<f64> {
        let options = SpeedContinuityOptions {
            min_span_s: MIN_SPAN_S,
            ..SpeedContinuityOptions::default()
        };
        let depth = crate::median(self.depths.clone())?;
        let mut poses: Vec<&StampedPose> = Vec::new();
        for p in &self.poses {
            if poses
                .last()
                .is_none_or(|q| p.timestamp - q.timestamp >= MIN_STEP_S)
            {
                poses.push(p);
            }
        }
        let own = walking_pace(&poses, options.min_speed_depths_per_s * depth, &options)?;
        let scale = pace / own;
        (scale.is_finite() && scale > 0.0 && (scale - 1.0).abs() > SMALLEST_CORRECTION)
            .then(|| scale.clamp(1.0 / MAX_STEP_CORRECTION, MAX_STEP_CORRECTION))
    }

    /// Scales the frames' positions and depths by `scale` about the origin.
    pub(super) fn scale(&mut self, scale: f64) {
        for p in &mut self.poses {
            p.position *= scale;
        }
        for d in &mut self.depths {
            *d *= scale;
        }
    }
}

impl LiveTracker {
    /// While no window is merged: records `pose` (just posed by PnP on `correspondences`)
    /// and, when the frames so far walk off the pace, scales the tracker's positions and
    /// points about the origin back to it, `pose` included.
    pub(super) fn hold_first_gauge(
        &mut self,
        pose: &mut StampedPose,
        correspondences: &[(Vector3<f64>, Point2<f64>)],
    ) {
        let (Some(gauge), Some(pace)) = (self.first_gauge.as_mut(), self.map.pace) else {
            return;
        };
        let camera_from_world = pose.rotation.inverse();
        let depths = correspondences
            .iter()
            .map(|(x, _)| (camera_from_world * (x - pose.position)).z)
            .collect();
        let Some(depth) = crate::median(depths) else {
            return;
        };
        gauge.push(*pose, depth);
        let Some(scale) = gauge.correction(pace) else {
            return;
        };
        tracing::debug!(scale, "live poses held to the new segment's pace");
        gauge.scale(scale);
        pose.position *= scale;
        for x in self.local_points.values_mut() {
            *x *= scale;
        }
        for sighting in self.sightings.values_mut() {
            sighting.centre *= scale;
        }
        let poses = [&mut self.last, &mut self.before_last]
            .into_iter()
            .flatten();
        let remembered = self.previous.iter_mut().chain(self.recent.iter_mut());
        for p in poses
            .chain(remembered.map(|(p, _)| p))
            .chain(self.tracked.iter_mut().map(|(p, _)| p))
        {
            p.position *= scale;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::live_tracking::tests::on_axis as at;

    #[test]
    fn a_walk_faster_than_the_pace_is_scaled_down_to_it() {
        let mut gauge = FirstGauge::default();
        // 1.4 units per second, 30 frames per second, scene 5 units deep, for 1.5 s.
        for i in 0..45 {
            let t = i as f64 / 30.0;
            gauge.push(at(t, 1.4 * t), 5.0);
        }
        // Brought to the pace a tenth at a time.
        let mut steps = 0;
        while let Some(scale) = gauge.correction(1.0) {
            assert!(
                (1.0 / 1.1 - 1e-12..=1.1 + 1e-12).contains(&scale),
                "{scale}"
            );
            gauge.scale(scale);
            steps += 1;
            assert!(steps < 10, "converges");
        }
        // 1.4 / 1.1^3 = 1.052, whose correction (0.951) is within 5 %: left there.
        assert_eq!(steps, 3);
        let own = gauge.poses.last().expect("poses").position.z
            / gauge.poses.last().expect("poses").timestamp;
        assert!((own - 1.4 / 1.1f64.powi(3)).abs() < 1e-9, "{own}");
    }

    #[test]
    fn only_the_first_seconds_are_kept() {
        let mut gauge = FirstGauge::default();
        for i in 0..3000 {
            let t = i as f64 / 30.0;
            gauge.push(at(t, t), 5.0);
        }
        assert_eq!(gauge.poses.len(), 301, "10 s at 30 frames per second");
    }

    #[test]
    fn a_head_turning_in_place_or_too_short_a_walk_sets_nothing() {
        let mut standing = FirstGauge::default();
        for i in 0..60 {
            let t = i as f64 / 30.0;
            // A sway of a few millimetres before a scene 3 units away.
            standing.push(at(t, 0.003 * (t * 7.0).sin()), 3.0);
        }
        assert_eq!(standing.correction(1.0), None);
        let mut short = FirstGauge::default();
        for i in 0..27 {
            let t = i as f64 / 30.0;
            short.push(at(t, 2.0 * t), 5.0);
        }
        assert_eq!(short.correction(1.0), None, "under a second");
    }
}
