//! A keyframe's rolling-shutter correction redone once the next frame is tracked.
//!
//! When a keyframe is made, each track's position is moved from its row's capture time to
//! the middle row's along a velocity extrapolated from the two frames before
//! ([`Tracker::published_raw`]: `1.5 a - 0.5 b` of the last two motions `a`, `b`). At the
//! onset of a sharp head turn (4000-5000 deg/s^2 on a walking head) that velocity lags,
//! and it carries 2.5x the tracker's position noise (0.7x for the centred difference
//! below). Windows solved from such keyframes came out 3-21 %
//! of their path off (docs/config.md, "`rolling_shutter_ms`"). With the next frame
//! tracked, the velocity at the keyframe is the centred difference
//! `(p[k+1] - p[k-1]) / (t[k+1] - t[k-1])`, half the extrapolation's error on a smooth
//! onset (a cubic) and exact on a constant acceleration. A track born on the keyframe
//! has no motion before it: its motion after is changed by the median change of the
//! older tracks' (a turn changes every track's motion alike). The frontend service
//! therefore holds each keyframe for one frame before publishing it.

use super::{KeyframeTracks, Track, TrackPoint, Tracker};
use egoslam_geometry::median;
use nalgebra::Point2;
use opencv::core::Point2f;
use std::collections::HashMap;

impl Tracker {
    /// Redoes `keyframe`'s rolling-shutter correction with each track's velocity centred
    /// on the keyframe. Call it right after processing the frame that follows the
    /// keyframe's; returns how many tracks were moved: none without a readout or when
    /// another frame came between; tracks lost on the next frame keep the extrapolated
    /// correction. Each centred track's `image_velocity` becomes the centred one, also
    /// without a readout (for [`Tracker::recorrect`] once a readout is estimated).
    pub fn centre_keyframe(&self, keyframe: &mut KeyframeTracks) -> usize {
        let readout = self.options.rolling_shutter_s;
        let span = self.last_times.1 - self.time_before_last;
        if span.is_nan() || span <= 0.0 || self.previous_frame_id != Some(keyframe.frame_id) {
            return 0;
        }
        let live: HashMap<u64, &Track> = self.tracks.iter().map(|t| (t.id, t)).collect();
        // A track born on the keyframe has no motion before it: it is taken as its motion
        // after, changed by the median change of the older tracks' motion.
        let (dx, dy): (Vec<f64>, Vec<f64>) = self
            .tracks
            .iter()
            .filter_map(|t| Some((t.velocity?, t.previous_velocity?)))
            .map(|(after, before)| (f64::from(before.x - after.x), f64::from(before.y - after.y)))
            .unzip();
        let change = (!dx.is_empty()).then(|| Point2f::new(median(dx) as f32, median(dy) as f32));
        let mut moved = 0;
        for point in &mut keyframe.tracks {
            let Some(track) = live.get(&point.track_id) else {
                continue;
            };
            // After the keyframe's frame: `velocity`; before it: `previous_velocity`.
            let (after, before) = match (track.velocity, track.previous_velocity, change) {
                (Some(after), Some(before), _) => (after, before),
                (Some(after), None, Some(c)) => (after, Point2f::new(after.x + c.x, after.y + c.y)),
                _ => continue,
            };
            point.image_velocity = Some(Point2::new(
                (f64::from(after.x + before.x) / span) as f32,
                (f64::from(after.y + before.y) / span) as f32,
            ));
            if readout <= 0.0 {
                continue;
            }
            let share = self.camera.row_offset(f64::from(point.raw.y)) * readout / span;
            let centred = Point2f::new(
                point.raw.x - (after.x + before.x) * share as f32,
                point.raw.y - (after.y + before.y) * share as f32,
            );
            let Some(undistorted) = self
                .camera
                .undistort_pixel(Point2::new(f64::from(centred.x), f64::from(centred.y)))
            else {
                continue;
            };
            point.undistorted = Point2::new(undistorted.x as f32, undistorted.y as f32);
            moved += 1;
        }
        moved
    }

    /// Moves `point` (tracked with no readout correction) from its row's capture time to
    /// the middle row's along its `image_velocity`, for a rolling-shutter readout of
    /// `readout_s` estimated after it was tracked, and undistorts it again; a point with no
    /// velocity, or a readout of 0, is left as tracked. `false` when the corrected position
    /// leaves what the camera undistorts (the point keeps its uncorrected position).
    pub fn recorrect(&self, point: &mut TrackPoint, readout_s: f64) -> bool {
        let Some(velocity) = point.image_velocity.filter(|_| readout_s > 0.0) else {
            return true;
        };
        let delay = (self.camera.row_offset(f64::from(point.raw.y)) * readout_s) as f32;
        let moved = Point2::new(
            f64::from(point.raw.x - velocity.x * delay),
            f64::from(point.raw.y - velocity.y * delay),
        );
        match self.camera.undistort_pixel(moved) {
            Some(u) => {
                point.undistorted = Point2::new(u.x as f32, u.y as f32);
                true
            }
            None => false,
        }
    }
}
