//! The tracker's settings (`Tracker`, tracker.rs), each default with its reason.

use crate::keyframe_policy::KeyframePolicy;

/// Tracker settings; the defaults are the paper's where it gives one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackerOptions {
    /// Tracks kept alive (default 1000: enough for window SfM, cheap to track at 640x480).
    pub target_tracks: usize,
    /// Minimum distance between corners, pixels (default 10: spreads 1000 corners over VGA).
    pub min_corner_distance_px: f64,
    /// GFTT quality level relative to the best corner (default 0.001; OpenCV's usual 0.01
    /// leaves ~520 live tracks on TUM fr1_rpy at half resolution, 0.001 keeps ~960). Corners are detected on the first pyramid level (half resolution, 3x cheaper); the
    /// track is the patch at the detected position, so the coarser grid costs no accuracy.
    pub corner_quality: f64,
    /// Lucas-Kanade window side, pixels (default 9). OpenCV's default of 21 costs ~5x more
    /// per track (measured: 14.5 ms vs 2.7 ms for 1000 tracks one way at 640x480); with three
    /// pyramid levels a 9 px window still follows ~60 px of motion per frame.
    pub lk_window_px: i32,
    /// Pyramid levels above the base image (default 3: follows ~100 px/frame motion).
    pub pyramid_levels: i32,
    /// Maximum forward-backward error, pixels (default 1.0, as in Kalal et al. 2010's use).
    pub max_forward_backward_px: f64,
    /// Tracks closer than this to the image border are dropped (default 5 px): there the
    /// LK window is mostly outside the image and the estimate drifts.
    pub border_px: f32,
    /// Between keyframes, new corners are detected when fewer than this fraction of
    /// `target_tracks` are alive (default 0.7); at keyframes the count is always topped up.
    pub replenish_below_fraction: f64,
    /// Frames whose grey-level standard deviation is below this are treated as blind
    /// (default 4: a lens covered or lights off leaves sensor noise of ~2 levels, while the
    /// dimmest real sequences here measure > 20). GFTT's quality level is relative to the
    /// best corner, so on such a frame it would pick "corners" in the noise and LK would
    /// track them, building a map of noise; instead all tracks end and no keyframe is made
    /// until the view returns, where a new one starts (the merger then links it back by
    /// relocalization). 0 disables the check.
    pub min_contrast: f64,
    /// Tracks that LK loses from a standing start are searched again where their last
    /// frame-to-frame motion predicts them (constant image velocity; new tracks take the
    /// median motion of the others). Default true. A fast head turn moves the image 50 px
    /// per frame and more, beyond what a 9 px window on 3 pyramid levels finds from a
    /// standing start: on the rendered walk all but ~30 of 1000 tracks were lost in such
    /// turns and the window's view graph split there (a map break). With the retry the
    /// 12,000-frame walk has no break at all (3 left without it), the head shake and the
    /// blackout end in one segment (two without), and four shorter rendered walks end at
    /// 0.6-1.9 % of their path instead of 0.8-14 %. The cost: KITTI 00 (a car at 10 fps,
    /// not a head) 0.396 -> 0.486 m keyframe ATE; TUM fr1_rpy 2.43 -> 2.24 cm
    /// (docs/config.md). The backward pass starts from the prediction too, so the
    /// forward-backward check stays independent of it; tracks that passed the first time
    /// are never moved by it.
    pub predict_motion: bool,
    /// Rolling-shutter readout, seconds from the first row to the last (default 0: a
    /// global shutter). With a readout, each published observation's undistorted position
    /// (what geometry uses; the raw one stays in the image) is moved to where the track was
    /// at the middle row's time, along its own image velocity at the frame's time (its
    /// motion over the last frame carried forward by the change since the frame before;
    /// first order: constant velocity over the readout), so that the solver, which models
    /// a global shutter, sees one instant per frame. Needs the frames' timestamps
    /// ([`Tracker::process_timed`]).
    pub rolling_shutter_s: f64,
    /// Keyframe rule (P, m).
    pub keyframes: KeyframePolicy,
}

impl Default for TrackerOptions {
    fn default() -> Self {
        Self {
            target_tracks: 1000,
            min_corner_distance_px: 10.0,
            corner_quality: 0.001,
            lk_window_px: 9,
            pyramid_levels: 3,
            max_forward_backward_px: 1.0,
            border_px: 5.0,
            replenish_below_fraction: 0.7,
            min_contrast: 4.0,
            predict_motion: true,
            rolling_shutter_s: 0.0,
            keyframes: KeyframePolicy::default(),
        }
    }
}
