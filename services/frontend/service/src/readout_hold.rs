//! Keyframes held back while the rolling-shutter readout is estimated from the stream.
//!
//! Given `auto`, the frontend estimates the readout from its first frames
//! (online_readout.rs) instead of a pre-pass that would track them a second time before
//! the start. The keyframes of those frames were tracked with no correction; rather than
//! solving them so, the frontend holds them (with the frames' tracks sent between them)
//! until the estimate, then moves each observation from its row's capture time to the
//! middle row's along the image velocity recorded with it (`Tracker::recorrect`) and
//! publishes them in order: the windows see what a run told the readout would have sent.
//! Only the first attempt holds (the readout's frames, 150 by default, 5 s at 30 fps): a
//! start too still to estimate releases its keyframes uncorrected, and a later estimate
//! corrects from then on. A frontend that dies while holding loses those keyframes (its
//! restart begins a new stream: docs/durability.md).

use egoslam_frontend::{KeyframeTracks, TrackPoint, Tracker};
use egoslam_messages::internal::v1 as internal;

/// A keyframe waiting for the readout, with the tracks of the frames sent before it.
struct HeldKeyframe {
    tracks: KeyframeTracks,
    message: internal::Keyframe,
    /// The tracks of `message.frames_since_previous`, in order.
    frames_before: Vec<Vec<TrackPoint>>,
}

/// The keyframes held during the first estimation attempt, and the tracks of the frames
/// since the last of them.
#[derive(Default)]
pub struct ReadoutHold {
    held: Vec<HeldKeyframe>,
    /// The tracks of the frame stamps the service collects for the next keyframe.
    frames_since_held: Vec<Vec<TrackPoint>>,
}

impl ReadoutHold {
    /// Notes the tracks sent with a frame stamp that will go with the next keyframe.
    pub fn note_frame(&mut self, tracks: Vec<TrackPoint>) {
        self.frames_since_held.push(tracks);
    }

    /// Holds keyframe `tracks` (its message `message`, which took the frame stamps noted
    /// since the last keyframe).
    pub fn hold(&mut self, tracks: KeyframeTracks, message: internal::Keyframe) {
        let frames_before = std::mem::take(&mut self.frames_since_held);
        debug_assert_eq!(frames_before.len(), message.frames_since_previous.len());
        self.held.push(HeldKeyframe {
            tracks,
            message,
            frames_before,
        });
    }

    /// How many keyframes are held.
    pub fn len(&self) -> usize {
        self.held.len()
    }

    /// Whether none is.
    pub fn is_empty(&self) -> bool {
        self.held.is_empty()
    }

    /// The held keyframes, in order, corrected for `readout_s`, and the frame stamps
    /// collected since the last of them (`pending_frames`, the service's) corrected as
    /// well. With a readout of 0 everything is as tracked.
    pub fn release(
        self,
        tracker: &Tracker,
        readout_s: f64,
        pending_frames: &mut [internal::FrameStamp],
    ) -> Vec<(KeyframeTracks, internal::Keyframe)> {
        if readout_s <= 0.0 {
            return self
                .held
                .into_iter()
                .map(|h| (h.tracks, h.message))
                .collect();
        }
        let mut uncorrected = 0usize;
        let mut correct = |points: &mut [TrackPoint],
                           messages: &mut [internal::TrackObservation]| {
            uncorrected += recorrect(tracker, readout_s, points, messages);
        };
        let mut released = Vec::with_capacity(self.held.len());
        for mut held in self.held {
            correct(&mut held.tracks.tracks, &mut held.message.tracks);
            let stamps = &mut held.message.frames_since_previous;
            for (points, stamp) in held.frames_before.iter_mut().zip(stamps.iter_mut()) {
                correct(points, &mut stamp.tracks);
            }
            released.push((held.tracks, held.message));
        }
        let mut frames_since = self.frames_since_held;
        for (points, stamp) in frames_since.iter_mut().zip(pending_frames.iter_mut()) {
            correct(points, &mut stamp.tracks);
        }
        if uncorrected > 0 {
            tracing::debug!(
                uncorrected,
                "held observations whose corrected position the camera does not undistort"
            );
        }
        released
    }
}

/// Recorrects `points` for `readout_s` (`Tracker::recorrect`) and moves their messages'
/// undistorted positions with them (`messages[i]` is `points[i]`'s); returns how many the
/// camera could not undistort once moved (they keep their position).
pub fn recorrect(
    tracker: &Tracker,
    readout_s: f64,
    points: &mut [TrackPoint],
    messages: &mut [internal::TrackObservation],
) -> usize {
    debug_assert_eq!(points.len(), messages.len());
    let mut uncorrected = 0;
    for (point, message) in points.iter_mut().zip(messages) {
        if !tracker.recorrect(point, readout_s) {
            uncorrected += 1;
        }
        (message.x, message.y) = (point.undistorted.x, point.undistorted.y);
    }
    uncorrected
}
