//! The egoslam frontend: turns frames into feature tracks and picks keyframes.
//!
//! Paper, section 3 ("Key Framing"): GFTT corners tracked by bidirectional sparse pyramidal
//! Lucas-Kanade; correspondences with a high forward-backward error are dropped; a keyframe
//! is made every P frames or when the mean flow since the last keyframe exceeds m pixels.

pub mod keyframe_policy;
pub mod readout_estimation;
pub mod tracker;
pub mod tracker_options;

pub use keyframe_policy::{KeyframeDecision, KeyframePolicy, KeyframeReason};
pub use readout_estimation::{
    estimate_readout, EarlyGlobalShutter, FrameTracks, OnlineReadout, OnlineReadoutEstimator,
    ReadoutEstimate, ReadoutEstimationError, ReadoutEstimationOptions,
};
pub use tracker::{
    FrameOutcome, KeyframeTracks, TrackPoint, Tracker, TrackerError, TrackerOptions,
};
