//! The merger (paper, section 5): successive windows, each solved in its own frame and scale,
//! are chained by a 7-DoF similarity estimated on the keyframes they share; frames between
//! keyframes are posed by interpolation.

pub mod base_map;
pub mod chaining;
pub mod frame_localization;
pub mod interior_cut;
pub mod interpolation;
pub mod keyframe_budget;
pub mod keyframe_coverage;
pub mod keyframe_culling;
pub mod live_tracking;
pub mod loop_closure;
pub mod map;
pub mod map_points;
pub mod point_confidence;
pub mod point_reassociation;
pub mod provisional_scale;
pub mod refinement;
pub mod refinement_rebase;
pub mod relocalized_scale;
pub mod retriangulation;
pub mod scale_break;
pub mod scene_depth;
pub mod segment_linking;
pub mod session;
pub mod speed_continuity;
pub mod turn_scale_step;
pub mod window_alignment;

pub use base_map::next_free_id;
pub use map::{MapBuilder, MapParts, ProvisionalScale, ScaleSource, WindowInput, WindowOutcome};
pub use session::{MergerSession, MergerState, SessionOptions, StreamStart};

/// The median of `values` (the upper one of an even count); `None` when empty. Scales,
/// depths and errors in the merger are all taken this way, robust to the tail of points
/// on occlusion edges and near the camera cluster.
pub(crate) fn median(values: Vec<f64>) -> Option<f64> {
    (!values.is_empty()).then(|| egoslam_geometry::median(values))
}
pub use frame_localization::{localize_frame, LocalizationError, LocalizationOptions, Localized};
pub use interpolation::{interpolate_between, interpolate_frames};
pub use keyframe_budget::KeyframeBudget;
pub use keyframe_culling::{CulledKeyframe, CullingReport, KeyframeCullingOptions};
pub use live_tracking::{LivePose, LiveTracker, LiveTrackerOptions, MapView, TrackingState};
pub use loop_closure::{find_loop, LoopClosure, LoopNotApplied, LoopOptions, LoopReport};
pub use point_confidence::{point_confidence, PointConfidence, PointConfidenceOptions};
pub use provisional_scale::SettledScale;
pub use refinement::{RefinementJob, RefinementOptions, RefinementOutcome, RefinementReport};
pub use relocalized_scale::{relocalized_window_scale, RelocalizedScale, RelocalizedScaleOptions};
pub use retriangulation::RetriangulationReport;
pub use segment_linking::{
    find_link, KeyframeFeatureSource, LinkOptions, RelocalizationSources, SegmentLink,
};
pub use turn_scale_step::{MendedStep, TurnScaleStepOptions};
