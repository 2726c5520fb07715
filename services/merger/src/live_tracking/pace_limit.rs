//! A PnP pose that moved faster than the wearer can is not a pose of the wearer.
//!
//! The tracker's own points are triangulated from its own poses, over 1 deg of parallax. In
//! a fast turn of a rolling-shutter camera whose readout is not yet known (the frontend
//! estimates it over the stream's first 5 s and corrects the tracks only from then on), the
//! readout's shear is such a parallax: points triangulated from a head turning in place
//! lie anywhere, and a PnP on hundreds of them is consistent and wrong. On the rendered
//! 30 ms walk the live poses of its first turn in place ran 5-20 m from where the head
//! stood, at tens of map units per second against a pace of one. A PnP pose is therefore
//! held to a multiple of the map's walking pace from the last tracked pose; beyond it the
//! frame is posed as without a PnP (by rotation, walked on, or predicted).

use super::LiveTracker;
use egoslam_geometry::StampedPose;

impl LiveTracker {
    /// `Err` with the speed when `pose` (a PnP pose of the frame at its timestamp) is
    /// further from the last tracked pose than [`super::LiveTrackerOptions::max_speed_of_pace`]
    /// times the map's pace allows over the time between them (at least a frame's, 1/30 s).
    /// Without a pace or a last pose, nothing is checked.
    pub(super) fn within_pace(&self, pose: &StampedPose) -> Result<(), String> {
        let (Some(pace), Some(last)) = (self.map.pace, self.last) else {
            return Ok(());
        };
        let dt = (pose.timestamp - last.timestamp).max(1.0 / 30.0);
        let speed = (pose.position - last.position).norm() / dt;
        if speed <= self.options.max_speed_of_pace * pace {
            return Ok(());
        }
        Err(format!(
            "moved at {speed:.2} map units per second, {:.1}x the map's pace",
            speed / pace
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::live_tracking::tests::on_axis as at;
    use crate::live_tracking::{LiveTrackerOptions, MapView};

    #[test]
    fn a_pose_faster_than_four_paces_is_refused() {
        let mut tracker = LiveTracker::new(LiveTrackerOptions::default());
        tracker.map = MapView {
            pace: Some(1.0),
            ..MapView::default()
        };
        tracker.last = Some(at(0.0, 0.0));
        assert!(tracker.within_pace(&at(0.1, 0.35)).is_ok(), "3.5 units/s");
        assert!(tracker.within_pace(&at(0.1, 0.5)).is_err(), "5 units/s");
        assert!(tracker.within_pace(&at(1.0, 3.0)).is_ok(), "after a gap");
        assert!(
            tracker.within_pace(&at(0.0, 0.1)).is_ok(),
            "at least a frame's time"
        );
        tracker.map.pace = None;
        assert!(tracker.within_pace(&at(0.1, 10.0)).is_ok(), "no pace known");
    }
}
