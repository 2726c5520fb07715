//! Continuing a stream's tracks after the tracker's process was restarted.
//!
//! A frontend that crashes and comes back would start new tracks with new ids, and the
//! keyframes after the restart would share no track with those before: the solver's window
//! then falls apart in two and the map splits. Instead the frontend keeps the last frame it
//! tracked (image and live track positions, services/egoslam/src/frontend/resume.rs) and a restarted tracker
//! starts from it: the first new frame is tracked from that image by the usual
//! bidirectional LK, so the tracks that survive keep their ids and link the map across the
//! restart. Tracks LK loses there end as at any frame, and new ones are detected.

use super::{Track, Tracker, TrackerError};
use opencv::core::{Mat, Point2f, Size, Vector};
use opencv::video;

/// A tracked frame to continue from: the frame, its time and its live tracks.
pub struct ResumePoint<'a> {
    pub frame_id: u64,
    pub timestamp_s: f64,
    /// 8-bit grey, the camera's size.
    pub image: &'a Mat,
    /// `(track id, raw pixel position)` of the tracks alive in that frame that were alive
    /// at the last keyframe (the ones the map knows).
    pub tracks: &'a [(u64, Point2f)],
}

impl Tracker {
    /// `(track id, raw pixel)` of the live tracks that were alive at the last keyframe: what
    /// [`ResumePoint::tracks`] takes. Raw positions only (no undistortion): the frontend
    /// saves them after every frame.
    pub fn resumable_tracks(&self) -> impl ExactSizeIterator<Item = (u64, Point2f)> + '_ {
        let kept: Vec<(u64, Point2f)> = self
            .tracks
            .iter()
            .filter(|t| t.at_keyframe.is_some())
            .map(|t| (t.id, t.pos))
            .collect();
        kept.into_iter()
    }

    /// Continues from `point` as if it had just been tracked: the next frame is tracked from
    /// it and the keyframe rule counts from it. Ids already given (see
    /// [`Tracker::resume_ids`]) are not reused.
    pub fn resume_from(&mut self, point: &ResumePoint) -> Result<(), TrackerError> {
        let frame_id = point.frame_id;
        let image = point.image;
        self.check_size(frame_id, image)?;
        let win = Size::new(self.options.lk_window_px, self.options.lk_window_px);
        let mut pyramid = Vector::<Mat>::new();
        video::build_optical_flow_pyramid_def(
            image,
            &mut pyramid,
            win,
            self.options.pyramid_levels,
        )
        .map_err(super::cv_err(frame_id))?;
        self.tracks = point
            .tracks
            .iter()
            .map(|&(id, pos)| Track {
                id,
                pos,
                at_keyframe: Some(pos),
                velocity: None,
                previous_velocity: None,
            })
            .collect();
        let next_track_id = point.tracks.iter().map(|(id, _)| id + 1).max().unwrap_or(0);
        self.next_track_id = self.next_track_id.max(next_track_id);
        self.previous_pyramid = Some(pyramid);
        self.frames_since_keyframe = 0;
        self.tracks_at_keyframe = self.tracks.len();
        self.last_frame_id = Some(frame_id);
        self.previous_frame_id = None;
        self.last_mean_flow = 0.0;
        self.image_velocity = Point2f::new(0.0, 0.0);
        self.last_times = (f64::NAN, point.timestamp_s);
        self.time_before_last = f64::NAN;
        Ok(())
    }
}
