//! The live tracker's options.

use crate::frame_localization::LocalizationOptions;
use egoslam_relocalization::absolute_pose::PnpOptions;

use super::LocalAdjustmentOptions;

/// Defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LiveTrackerOptions {
    /// PnP and its acceptance: frame localization's, looser (4 px, 30 % of the
    /// correspondences, 20 deg from the prior): the prior is extrapolated, not interpolated
    /// between two posed keyframes, the tracker's own points are less refined than the
    /// map's, and a live client prefers a rougher pose to none.
    pub localization: LocalizationOptions,
    /// How long a pose predicted at constant velocity is offered as PREDICTED after the last
    /// tracked one, seconds (default 0.5: a head keeps its turn for about that long;
    /// beyond, the prediction is reported LOST).
    pub max_prediction_s: f64,
    /// Parallax between a track's first sighting and the current one before the tracker
    /// triangulates it, degrees (default 1: tracks live a fraction of a second in head
    /// motion, and at 1 px of noise on a 500 px focal the depth is then known to ~12 %,
    /// enough to carry a PnP until the map's refined point arrives).
    pub min_triangulation_angle_deg: f64,
    /// Largest reprojection error of a triangulated point in the current frame, pixels
    /// (default 2, the PnP threshold).
    pub max_triangulation_error_px: f64,
    /// Turning in place (no map point in view): the orientation is fitted to the rays of
    /// the tracks shared with the previous posed frame. A ray agrees within this angle,
    /// in pixels at the focal length (default 5: tracking noise, an uncorrected rolling
    /// shutter in a fast turn, and the parallax of a head's few centimetres of motion
    /// between frames on points a few metres away).
    pub rotation_threshold_px: f64,
    /// Least agreeing rays for an orientation from rays, and their least share of the
    /// shared tracks (defaults 20 and 0.5: a rotation has 3 degrees of freedom, and a
    /// walking camera's near points disagree, which must make it fail).
    pub rotation_min_inliers: usize,
    pub rotation_min_inlier_share: f64,
    /// How far back the tracker keeps the frames' tracks, seconds (default 3: the map
    /// arrives 0.5-2 s after its newest keyframe in a real-time run; the frames since that
    /// keyframe are re-tracked on each new map).
    pub history_s: f64,
    /// A frame posed by rotation is moved on at the map's walking pace (walked_on.rs) when
    /// its tracks' rays and those of a posed frame up to `walk_anchor_s` before miss their
    /// best rotation by `min_walk_parallax_px` in the median, pixels at the focal length
    /// (defaults 1 s, over which most tracks of a turning head are gone; and 3 px, 1.5x
    /// the window solver's test for a translation edge, `RelativePoseOptions::
    /// min_parallax_px`, so that the windows of a turn the solver solves rotation-only are
    /// not walked on).
    pub walk_anchor_s: f64,
    pub min_walk_parallax_px: f64,
    /// The frame is moved on only when that posed frame shares at least this share of its
    /// tracks (default 0.5). A walking head shows its parallax against a frame a fraction of
    /// a second back, while most tracks still live (the rendered walks: 580-840 of ~900
    /// shared, 0.1 s back); in a turn in place the search for parallax goes back 0.3-0.5 s,
    /// to a frame sharing only the 50-140 tracks that lived through the turn, whose drift
    /// (with motion blur) passes for 3 px of parallax, and each such frame walked the held
    /// position on by the pace. Such a frame is posed by the turn in place instead, or by
    /// the relative pose's turn alone where no rotation fits its rays.
    pub walk_min_track_share: f64,
    /// How fast a head may have turned since the last posed frame, degrees per second: the
    /// PnP pose may be this much further from the prior per second of the gap beyond
    /// 50 ms (default 300: quick glances peak there). After frames the tracker could not
    /// pose, the prior holds the orientation of before the turn, and a PnP pose on hundreds
    /// of correspondences was refused as 30-60 deg away while the head had turned that far.
    pub max_turn_rate_deg_s: f64,
    /// Fastest a PnP pose may have moved from the last tracked pose, in multiples of the
    /// map's walking pace (default 4: a wearer breaking into a run, a car pulling away from
    /// its median speed; pace_limit.rs has what moves faster). Beyond it the frame is
    /// posed as without a PnP.
    pub max_speed_of_pace: f64,
    /// The tracked frames of the last `local_window_s` seconds are adjusted with their
    /// points after each tracked frame (local_adjustment.rs; default 1 s, the span a
    /// walking head's tracks live; `None`: no adjustment).
    pub local_adjustment: Option<LocalAdjustmentOptions>,
    pub local_window_s: f64,
    /// Least time between two frames that run the local adjustment, seconds (default
    /// 1/15: every second frame at 30 fps; on the rendered walks' real-time records the
    /// live trajectories were as close to the refined ones as with every frame, at half
    /// the cost; a lossless replay runs the tracker as fast as the frontend goes).
    pub local_adjustment_interval_s: f64,
}

impl Default for LiveTrackerOptions {
    fn default() -> Self {
        Self {
            localization: LocalizationOptions {
                pnp: PnpOptions {
                    ransac_threshold_px: 4.0,
                    min_inlier_ratio: 0.3,
                    ..LocalizationOptions::default().pnp
                },
                max_rotation_from_prior_deg: 20.0,
                ..LocalizationOptions::default()
            },
            max_prediction_s: 0.5,
            min_triangulation_angle_deg: 1.0,
            max_triangulation_error_px: 2.0,
            history_s: 3.0,
            walk_anchor_s: 1.0,
            min_walk_parallax_px: 3.0,
            walk_min_track_share: 0.5,
            rotation_threshold_px: 5.0,
            rotation_min_inliers: 20,
            rotation_min_inlier_share: 0.5,
            max_turn_rate_deg_s: 300.0,
            max_speed_of_pace: 4.0,
            local_adjustment: Some(LocalAdjustmentOptions::default()),
            local_window_s: 1.0,
            local_adjustment_interval_s: 1.0 / 15.0,
        }
    }
}
