//! Feature tracking: GFTT corners followed by bidirectional pyramidal Lucas-Kanade.
//!
//! Shi and Tomasi, "Good Features to Track", CVPR 1994 (corners); Bouguet, "Pyramidal
//! Implementation of the Lucas Kanade Feature Tracker", Intel 2000 (tracking); Kalal et al.,
//! "Forward-Backward Error: Automatic Detection of Tracking Failures", ICPR 2010 (the
//! bidirectional check the paper uses to drop drifting correspondences).

use crate::keyframe_policy::{KeyframeDecision, KeyframeReason};
use egoslam_geometry::PinholeRadtan;
use nalgebra::Point2;
use opencv::core::{
    Mat, Point, Point2f, Scalar, Size, TermCriteria, ToInputArray, Vector, CV_8UC1,
};
use opencv::prelude::*;
use opencv::{imgproc, video};

/// Errors of [`Tracker::process`].
#[derive(Debug, thiserror::Error)]
pub enum TrackerError {
    /// The frame is not 8-bit single channel.
    #[error("frame {frame_id}: expected 8-bit grey image, got type {cv_type}")]
    NotGrey { frame_id: u64, cv_type: i32 },
    /// The frame's size differs from the calibrated camera's.
    #[error("frame {frame_id}: size {width}x{height} differs from the camera's {camera_width}x{camera_height}")]
    SizeMismatch {
        frame_id: u64,
        width: i32,
        height: i32,
        camera_width: u32,
        camera_height: u32,
    },
    /// An OpenCV call failed.
    #[error("frame {frame_id}: OpenCV: {message}")]
    OpenCv { frame_id: u64, message: String },
}

pub use crate::tracker_options::TrackerOptions;

/// One track's position in a keyframe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackPoint {
    pub track_id: u64,
    /// Raw (distorted) pixel.
    pub raw: Point2<f32>,
    /// Undistorted pixel (ideal pinhole with the same intrinsics).
    pub undistorted: Point2<f32>,
    /// The track's image velocity at the frame's time, pixels per second, as a
    /// rolling-shutter correction takes it ([`Tracker::recorrect`]); `None` before two
    /// frames were tracked.
    pub image_velocity: Option<Point2<f32>>,
}

/// The tracks of a new keyframe.
#[derive(Debug, Clone, PartialEq)]
pub struct KeyframeTracks {
    pub keyframe_id: u64,
    pub frame_id: u64,
    pub reason: KeyframeReason,
    /// Mean flow since the previous keyframe, pixels.
    pub mean_flow_px: f64,
    pub tracks: Vec<TrackPoint>,
}

/// What one frame produced.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameOutcome {
    pub keyframe: Option<KeyframeTracks>,
    /// Tracks alive after this frame.
    pub live_tracks: usize,
    /// Tracks dropped by the forward-backward check on this frame.
    pub rejected_forward_backward: usize,
    /// Mean flow since the last keyframe, pixels.
    pub mean_flow_px: f64,
    /// The frame had too little contrast to track (see `TrackerOptions::min_contrast`).
    pub blind: bool,
}

#[derive(Debug, Clone, Copy)]
struct Track {
    id: u64,
    pos: Point2f,
    /// Position at the last keyframe, if the track existed then.
    at_keyframe: Option<Point2f>,
    /// Motion over the last frame, pixels (`None` for a track born on the last frame).
    velocity: Option<Point2f>,
    /// Motion over the frame before (`None` for a track younger than two frames).
    previous_velocity: Option<Point2f>,
}

/// Stateful tracker of one stream.
pub struct Tracker {
    options: TrackerOptions,
    camera: PinholeRadtan,
    tracks: Vec<Track>,
    previous_pyramid: Option<Vector<Mat>>,
    next_track_id: u64,
    next_keyframe_id: u64,
    frames_since_keyframe: u32,
    tracks_at_keyframe: usize,
    last_frame_id: Option<u64>,
    last_mean_flow: f64,
    /// Median motion of the tracks over the last frame (the prediction for new tracks).
    image_velocity: Point2f,
    /// Timestamps of the last two frames processed, seconds (NaN: not given).
    last_times: (f64, f64),
    /// Timestamp of the frame before those two (NaN: not given).
    time_before_last: f64,
    /// The tracked frame before the last one, if tracks continued from it.
    previous_frame_id: Option<u64>,
}

fn cv_err(frame_id: u64) -> impl Fn(opencv::Error) -> TrackerError {
    move |e| TrackerError::OpenCv {
        frame_id,
        message: e.to_string(),
    }
}

impl Tracker {
    /// A tracker for frames of `camera`.
    pub fn new(camera: PinholeRadtan, options: TrackerOptions) -> Self {
        Self {
            options,
            camera,
            tracks: Vec::with_capacity(options.target_tracks),
            previous_pyramid: None,
            next_track_id: 0,
            next_keyframe_id: 0,
            frames_since_keyframe: 0,
            tracks_at_keyframe: 0,
            last_frame_id: None,
            last_mean_flow: 0.0,
            image_velocity: Point2f::new(0.0, 0.0),
            last_times: (f64::NAN, f64::NAN),
            time_before_last: f64::NAN,
            previous_frame_id: None,
        }
    }

    /// Sets the rolling-shutter readout from now on (seconds; `auto` on a live stream
    /// decides it after the first frames). Keyframes already made keep their positions.
    pub fn set_rolling_shutter_s(&mut self, readout_s: f64) {
        self.options.rolling_shutter_s = readout_s;
    }

    /// The rolling-shutter readout the tracks are corrected for, seconds (0: none).
    pub fn rolling_shutter_s(&self) -> f64 {
        self.options.rolling_shutter_s
    }

    /// The camera the tracks are undistorted with.
    pub fn camera(&self) -> PinholeRadtan {
        self.camera
    }

    /// The ids the next keyframe and the next new track will get.
    pub fn next_ids(&self) -> (u64, u64) {
        (self.next_keyframe_id, self.next_track_id)
    }

    /// Continues numbering after a restart: ids stay unique over the whole stream, so the
    /// solver and merger never mistake a new keyframe or track for an old one.
    pub fn resume_ids(&mut self, next_keyframe_id: u64, next_track_id: u64) {
        self.next_keyframe_id = self.next_keyframe_id.max(next_keyframe_id);
        self.next_track_id = self.next_track_id.max(next_track_id);
    }

    /// Tracks into `image` (8-bit grey) and decides whether it is a keyframe.
    /// `image` is any 8-bit grey matrix, including one borrowed from shared memory.
    pub fn process(
        &mut self,
        frame_id: u64,
        image: &(impl MatTraitConst + ToInputArray),
    ) -> Result<FrameOutcome, TrackerError> {
        self.process_timed(frame_id, f64::NAN, image)
    }

    /// [`Tracker::process`] for a frame captured at `timestamp_s`: what a rolling-shutter
    /// correction needs (`TrackerOptions::rolling_shutter_s`) to turn image motion per
    /// frame into motion per second.
    pub fn process_timed(
        &mut self,
        frame_id: u64,
        timestamp_s: f64,
        image: &(impl MatTraitConst + ToInputArray),
    ) -> Result<FrameOutcome, TrackerError> {
        let _span = tracing::trace_span!("track_frame", frame_id).entered();
        if image.typ() != CV_8UC1 {
            return Err(TrackerError::NotGrey {
                frame_id,
                cv_type: image.typ(),
            });
        }
        self.check_size(frame_id, image)?;
        // Only a frame that is tracked sets the time step its velocities span (a refused
        // frame in between would otherwise shorten it).
        self.time_before_last = self.last_times.0;
        self.last_times = (self.last_times.1, timestamp_s);
        let err = cv_err(frame_id);
        let (mut mean, mut deviation) = (Mat::default(), Mat::default());
        if self.options.min_contrast > 0.0 {
            opencv::core::mean_std_dev(image, &mut mean, &mut deviation, &opencv::core::no_array())
                .map_err(&err)?;
            let contrast = *deviation.at::<f64>(0).map_err(&err)?;
            if contrast < self.options.min_contrast {
                // Blind frame: every track ends, nothing is detected, no keyframe is made.
                let lost = self.tracks.len();
                self.tracks.clear();
                self.previous_pyramid = None;
                self.image_velocity = Point2f::new(0.0, 0.0);
                self.previous_frame_id = None;
                tracing::debug!(frame_id, contrast, lost, "blind frame");
                return Ok(FrameOutcome {
                    keyframe: None,
                    live_tracks: 0,
                    rejected_forward_backward: 0,
                    mean_flow_px: 0.0,
                    blind: true,
                });
            }
        }
        let win = Size::new(self.options.lk_window_px, self.options.lk_window_px);
        let mut pyramid = Vector::<Mat>::new();
        video::build_optical_flow_pyramid_def(
            image,
            &mut pyramid,
            win,
            self.options.pyramid_levels,
        )
        .map_err(&err)?;

        let mut rejected = 0;
        if let Some(previous) = self.previous_pyramid.take() {
            rejected = self.track_into(&previous, &pyramid, frame_id)?;
        }
        self.frames_since_keyframe += 1;
        let (mean_flow, surviving) = self.flow_since_keyframe();
        let decision = if self.last_frame_id.is_none() {
            KeyframeDecision::Keyframe(KeyframeReason::First)
        } else {
            self.options
                .keyframes
                .decide(self.frames_since_keyframe, mean_flow, surviving)
        };
        let keyframe = match decision {
            KeyframeDecision::Keyframe(reason) => {
                self.replenish(&pyramid, frame_id, 1.0)?;
                Some(self.make_keyframe(frame_id, reason, mean_flow))
            }
            KeyframeDecision::Skip => {
                self.replenish(&pyramid, frame_id, self.options.replenish_below_fraction)?;
                None
            }
        };
        self.previous_pyramid = Some(pyramid);
        self.previous_frame_id = self.last_frame_id;
        self.last_frame_id = Some(frame_id);
        self.last_mean_flow = mean_flow;
        Ok(FrameOutcome {
            keyframe,
            live_tracks: self.tracks.len(),
            rejected_forward_backward: rejected,
            mean_flow_px: mean_flow,
            blind: false,
        })
    }

    /// Fails unless `image` has the camera's size.
    fn check_size(&self, frame_id: u64, image: &impl MatTraitConst) -> Result<(), TrackerError> {
        if (image.cols() as u32, image.rows() as u32) != (self.camera.width, self.camera.height) {
            return Err(TrackerError::SizeMismatch {
                frame_id,
                width: image.cols(),
                height: image.rows(),
                camera_width: self.camera.width,
                camera_height: self.camera.height,
            });
        }
        Ok(())
    }

    /// Makes the last processed frame a keyframe (end of stream), unless it already is one.
    pub fn finish(&mut self) -> Option<KeyframeTracks> {
        let frame_id = self.last_frame_id?;
        (self.frames_since_keyframe > 0)
            .then(|| self.make_keyframe(frame_id, KeyframeReason::Last, self.last_mean_flow))
    }

    /// Up to `max` of the live tracks that were alive at the last keyframe (evenly spread
    /// over the list), undistorted: what a frame between keyframes can be localized with.
    pub fn sample_tracks(&self, max: usize) -> Vec<TrackPoint> {
        let old: Vec<&Track> = self
            .tracks
            .iter()
            .filter(|t| t.at_keyframe.is_some())
            .collect();
        let step = old.len().div_ceil(max.max(1)).max(1);
        old.iter()
            .step_by(step)
            .filter_map(|t| self.track_point(t))
            .collect()
    }

    /// Every live track that can be published (see `track_point`), undistorted: what the
    /// live tracker localizes the frame with and triangulates new points from.
    pub fn live_track_points(&self) -> Vec<TrackPoint> {
        self.tracks
            .iter()
            .filter_map(|t| self.track_point(t))
            .collect()
    }

    /// Number of live tracks.
    pub fn live_tracks(&self) -> usize {
        self.tracks.len()
    }

    fn track_into(
        &mut self,
        previous: &Vector<Mat>,
        current: &Vector<Mat>,
        frame_id: u64,
    ) -> Result<usize, TrackerError> {
        if self.tracks.is_empty() {
            return Ok(0);
        }
        let err = cv_err(frame_id);
        let win = Size::new(self.options.lk_window_px, self.options.lk_window_px);
        let criteria = TermCriteria::new(
            opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
            // 10 iterations / 0.03 px: OpenCV's sample settings; more iterations only move
            // tracks that are about to fail the forward-backward check anyway.
            10,
            0.03,
        )
        .map_err(&err)?;
        let levels = self.options.pyramid_levels;
        // One bidirectional LK pass over `index`: each search starts at the point moved by
        // `guess` (forward) and back by it (backward), OPTFLOW_USE_INITIAL_FLOW. Returns,
        // per point, the new position if it passed, else whether the forward-backward
        // check (as opposed to LK itself or the border) rejected it.
        let pass = |index: &[usize], guess: &[Point2f]| {
            let p0: Vector<Point2f> = index.iter().map(|&i| self.tracks[i].pos).collect();
            let moved = |points: &Vector<Point2f>, sign: f32| -> Vector<Point2f> {
                points
                    .iter()
                    .zip(guess)
                    .map(|(p, v)| Point2f::new(p.x + sign * v.x, p.y + sign * v.y))
                    .collect()
            };
            let lk = |from: &Vector<Mat>, to: &Vector<Mat>, points: &Vector<Point2f>, start| {
                let (mut next, mut status, mut lk_err) =
                    (start, Vector::<u8>::new(), Vector::<f32>::new());
                video::calc_optical_flow_pyr_lk(
                    from,
                    to,
                    points,
                    &mut next,
                    &mut status,
                    &mut lk_err,
                    win,
                    levels,
                    criteria,
                    video::OPTFLOW_USE_INITIAL_FLOW,
                    1e-4,
                )
                .map(|_| (next, status))
            };
            let (p1, st1) = lk(previous, current, &p0, moved(&p0, 1.0))?;
            let (back, st2) = lk(current, previous, &p1, moved(&p1, -1.0))?;
            let max_fb2 = (self.options.max_forward_backward_px
                * self.options.max_forward_backward_px) as f32;
            let (w, h) = (self.camera.width as f32, self.camera.height as f32);
            let m = self.options.border_px;
            let outcome: Vec<Result<Point2f, bool>> = (0..index.len())
                .map(|k| {
                    let (ok1, ok2) = (st1.get(k).unwrap_or(0) == 1, st2.get(k).unwrap_or(0) == 1);
                    let (Ok(a), Ok(b), Ok(c)) = (p0.get(k), p1.get(k), back.get(k)) else {
                        return Err(false);
                    };
                    if !(ok1 && ok2) || b.x < m || b.y < m || b.x > w - 1.0 - m || b.y > h - 1.0 - m
                    {
                        return Err(false);
                    }
                    let (dx, dy) = (a.x - c.x, a.y - c.y);
                    if dx * dx + dy * dy > max_fb2 {
                        return Err(true);
                    }
                    Ok(b)
                })
                .collect();
            Ok::<_, opencv::Error>(outcome)
        };
        // First from where each track was (as LK is usually run); then the tracks that
        // failed once more, from where their last motion predicts them (see
        // `TrackerOptions::predict_motion`). Tracks that passed the first time are never
        // moved by the prediction.
        let all: Vec<usize> = (0..self.tracks.len()).collect();
        let still = vec![Point2f::new(0.0, 0.0); all.len()];
        let mut outcome = pass(&all, &still).map_err(&err)?;
        if self.options.predict_motion {
            let retry: Vec<usize> = all
                .iter()
                .copied()
                .filter(|&i| outcome[i].is_err())
                .collect();
            let guess: Vec<Point2f> = retry
                .iter()
                .map(|&i| self.tracks[i].velocity.unwrap_or(self.image_velocity))
                .collect();
            let worth = guess.iter().any(|v| v.x * v.x + v.y * v.y > 1.0);
            if !retry.is_empty() && worth {
                for (&i, again) in retry.iter().zip(pass(&retry, &guess).map_err(&err)?) {
                    if again.is_ok() || outcome[i] == Err(false) {
                        outcome[i] = again;
                    }
                }
            }
        }
        let mut rejected = 0;
        let mut kept = Vec::with_capacity(self.tracks.len());
        for (track, result) in self.tracks.iter().zip(&outcome) {
            match result {
                Ok(b) => kept.push(Track {
                    pos: *b,
                    velocity: Some(Point2f::new(b.x - track.pos.x, b.y - track.pos.y)),
                    previous_velocity: track.velocity,
                    ..*track
                }),
                Err(true) => rejected += 1,
                Err(false) => {}
            }
        }
        let median = |mut v: Vec<f32>| {
            let mid = v.len() / 2;
            v.select_nth_unstable_by(mid, f32::total_cmp);
            v[mid]
        };
        // Only the retry reads it: no per-frame median when the prediction is off.
        self.image_velocity = if kept.is_empty() || !self.options.predict_motion {
            Point2f::new(0.0, 0.0)
        } else {
            let (vx, vy): (Vec<f32>, Vec<f32>) = kept
                .iter()
                .filter_map(|t| t.velocity)
                .map(|v| (v.x, v.y))
                .unzip();
            Point2f::new(median(vx), median(vy))
        };
        self.tracks = kept;
        Ok(rejected)
    }

    fn flow_since_keyframe(&self) -> (f64, f64) {
        let (mut sum, mut n) = (0.0f64, 0usize);
        for t in &self.tracks {
            if let Some(k) = t.at_keyframe {
                sum += f64::from(((t.pos.x - k.x).powi(2) + (t.pos.y - k.y).powi(2)).sqrt());
                n += 1;
            }
        }
        let mean = if n > 0 { sum / n as f64 } else { 0.0 };
        let surviving = if self.tracks_at_keyframe > 0 {
            n as f64 / self.tracks_at_keyframe as f64
        } else {
            1.0
        };
        (mean, surviving)
    }

    fn replenish(
        &mut self,
        pyramid: &Vector<Mat>,
        frame_id: u64,
        below_fraction: f64,
    ) -> Result<(), TrackerError> {
        let target = self.options.target_tracks;
        if self.tracks.len() as f64 >= below_fraction * target as f64 || self.tracks.len() >= target
        {
            return Ok(());
        }
        let err = cv_err(frame_id);
        // Level 1 of the LK pyramid (entries alternate image, derivatives).
        let half = pyramid.get(2).map_err(&err)?;
        let mut mask =
            Mat::new_rows_cols_with_default(half.rows(), half.cols(), CV_8UC1, Scalar::all(255.0))
                .map_err(&err)?;
        let min_distance = 0.5 * self.options.min_corner_distance_px;
        let radius = min_distance.round() as i32;
        for t in &self.tracks {
            let c = Point::new(
                (0.5 * t.pos.x).round() as i32,
                (0.5 * t.pos.y).round() as i32,
            );
            imgproc::circle(
                &mut mask,
                c,
                radius,
                Scalar::all(0.0),
                -1,
                imgproc::LINE_8,
                0,
            )
            .map_err(&err)?;
        }
        let mut corners = Vector::<Point2f>::new();
        imgproc::good_features_to_track(
            &half,
            &mut corners,
            (target - self.tracks.len()) as i32,
            self.options.corner_quality,
            min_distance,
            &mask,
            3,
            false,
            0.04,
        )
        .map_err(&err)?;
        let m = self.options.border_px;
        let (w, h) = (self.camera.width as f32, self.camera.height as f32);
        for c in corners {
            let pos = Point2f::new(2.0 * c.x, 2.0 * c.y);
            if pos.x < m || pos.y < m || pos.x > w - 1.0 - m || pos.y > h - 1.0 - m {
                continue;
            }
            self.tracks.push(Track {
                id: self.next_track_id,
                pos,
                at_keyframe: None,
                velocity: None,
                previous_velocity: None,
            });
            self.next_track_id += 1;
        }
        Ok(())
    }

    /// The raw position a track's geometry is computed from (its undistorted pixel): with
    /// a rolling shutter, moved along its velocity at this frame (the motion over the last
    /// frame extrapolated by the change from the frame before, when the track is that old;
    /// for a track born on this frame, the median motion, which is only measured when
    /// `predict_motion` is on, else none) from its row's capture time to the middle row's; its
    /// row is read `(y - h/2) / h` of the readout after the middle row. The published raw
    /// position stays where the track is in the image, for descriptors and patches.
    fn published_raw(&self, t: &Track) -> Point2f {
        let readout = self.options.rolling_shutter_s;
        let step = self.last_times.1 - self.last_times.0;
        if !(readout > 0.0 && step > 0.0) {
            return t.pos;
        }
        let v = self.frame_motion(t);
        let shift = (self.camera.row_offset(f64::from(t.pos.y)) * readout / step) as f32;
        Point2f::new(t.pos.x - v.x * shift, t.pos.y - v.y * shift)
    }

    /// A track's image motion over one frame at this frame's time: the motion over the
    /// last frame is the velocity half a frame ago; with the frame before, it is carried
    /// to this frame's time (second order); a track born on this frame takes the median
    /// motion.
    fn frame_motion(&self, t: &Track) -> Point2f {
        match (t.velocity, t.previous_velocity) {
            (Some(a), Some(b)) => Point2f::new(a.x + 0.5 * (a.x - b.x), a.y + 0.5 * (a.y - b.y)),
            (Some(a), None) => a,
            _ => self.image_velocity,
        }
    }

    /// [`Self::frame_motion`] per second; `None` before two frames were tracked.
    fn image_velocity(&self, t: &Track) -> Option<Point2<f32>> {
        let step = self.last_times.1 - self.last_times.0;
        if step.is_nan() || step <= 0.0 {
            return None;
        }
        let v = self.frame_motion(t);
        Some(Point2::new(
            (f64::from(v.x) / step) as f32,
            (f64::from(v.y) / step) as f32,
        ))
    }

    /// A track as published: its raw image position and its undistorted geometric one
    /// ([`Tracker::published_raw`]); `None` for a fisheye track whose ray the ideal
    /// pinhole plane does not carry (it keeps being tracked, and is published again if it
    /// comes nearer the axis).
    fn track_point(&self, t: &Track) -> Option<TrackPoint> {
        let p = self.published_raw(t);
        let und = self
            .camera
            .undistort_pixel(Point2::new(f64::from(p.x), f64::from(p.y)))?;
        Some(TrackPoint {
            track_id: t.id,
            raw: Point2::new(t.pos.x, t.pos.y),
            undistorted: Point2::new(und.x as f32, und.y as f32),
            image_velocity: self.image_velocity(t),
        })
    }

    fn make_keyframe(
        &mut self,
        frame_id: u64,
        reason: KeyframeReason,
        mean_flow_px: f64,
    ) -> KeyframeTracks {
        let tracks = self
            .tracks
            .iter()
            .filter_map(|t| self.track_point(t))
            .collect();
        for t in &mut self.tracks {
            t.at_keyframe = Some(t.pos);
        }
        self.tracks_at_keyframe = self.tracks.len();
        self.frames_since_keyframe = 0;
        let keyframe_id = self.next_keyframe_id;
        self.next_keyframe_id += 1;
        KeyframeTracks {
            keyframe_id,
            frame_id,
            reason,
            mean_flow_px,
            tracks,
        }
    }
}

mod keyframe_centring;
mod resume;
pub use resume::ResumePoint;

#[cfg(test)]
mod tests;
