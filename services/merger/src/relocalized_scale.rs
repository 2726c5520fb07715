//! The chaining scale of a window that shares too few points with the map, measured by
//! relocalizing its keyframes against the map's recent keyframes.
//!
//! A window normally takes its scale from the points it shares with the map
//! ([`crate::window_alignment::align_shared`]). After a stop or a turn on the spot, no track lives
//! through: the head scans while standing, the windows in between are rotation-only (no
//! points), and the first window that moves again shares no point with the map. Its scale
//! then came from the ratio of median scene depths before and after
//! ([`crate::scene_depth`]), which is only as good as the two views see the same depths: on
//! the rendered 12,000-frame walk the map's metres-per-unit went 13 -> 362 at one such
//! boundary and 10 -> 7 million over the walk (the map shrank to a point; its 1.35 % ATE
//! was the walk's distance from its own centroid).
//!
//! The scene before the stop is usually still in view, or comes back after the turn, or
//! an earlier pass saw it. So the window's keyframes are relocalized by their descriptors
//! against the segment's keyframes (the segment-linking machinery, [`crate::segment_linking`]), and each
//! inlier that is also a point of the window gives a 3-D/3-D pair of one physical point
//! in both frames; the scale is the median ratio of camera-to-point distances over those
//! pairs, as for shared points.

use crate::map::WindowInput;
use crate::segment_linking::{
    relocalize_consistently, LinkOptions, OlderKeyframes, RelocalizationSources,
};
use nalgebra::Vector3;
use std::collections::HashMap;

/// When the relocalized scale is used; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelocalizedScaleOptions {
    /// The segment's newest keyframes (before the window) searched (default: all). A stop
    /// of a few seconds is within the last ~300 (~15 s of walking), but a wearer who stops
    /// where an earlier pass went has that pass's keyframes of the same place, seeing the
    /// same points: limited to the newest 300, the rendered corridor walked back and forth
    /// relocalized 5 of 120 such windows and took the others' scale from the pace, 0.4-0.8x
    /// off at its stops.
    pub recent_keyframes: usize,
    /// Windows with fewer points are not relocalized (default 30: a stop's windows have a
    /// handful, and relocalizing their keyframes was most of this function's cost).
    pub min_window_points: usize,
    /// Fewest 3-D/3-D pairs for a scale to be returned at all (default 10). The chaining
    /// takes one from fewer than 30 pairs (a median of fewer is noisy, see
    /// [`crate::loop_closure::LoopOptions::min_shared_points`]) only when the walking pace
    /// does not give the scale either: on the 12,000-frame walk a window before a stop
    /// relocalized with 7 keyframes agreeing on 11 pairs (scale 0.31, its neighbours 0.26 and
    /// 0.35), was refused, and the centres then gave 0.06.
    pub min_shared_points: usize,
    /// Acceptance of the relocalized keyframes (segment linking's defaults: 3 must agree).
    pub link: LinkOptions,
}

impl Default for RelocalizedScaleOptions {
    fn default() -> Self {
        Self {
            recent_keyframes: usize::MAX,
            min_window_points: 30,
            min_shared_points: 10,
            link: LinkOptions::default(),
        }
    }
}

/// A window's scale measured by relocalization, with the number of 3-D/3-D pairs it rests on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelocalizedScale {
    /// Map units per window unit.
    pub scale: f64,
    /// Point pairs whose distance ratios gave it.
    pub point_pairs: usize,
}

/// The scale of `window` relative to `segment`, from its keyframes relocalized against the
/// segment's recent keyframes; `None` when they do not relocalize consistently or give too
/// few point pairs.
pub fn relocalized_window_scale(
    sources: &RelocalizationSources,
    segment: u32,
    window: &WindowInput,
    options: &RelocalizedScaleOptions,
) -> Option<RelocalizedScale> {
    let _span = tracing::debug_span!("relocalized_window_scale", segment).entered();
    // A rotation-only window (a stop) has no points to pair: nothing to measure, and
    // relocalizing its keyframes was most of this function's cost on the long walk.
    if window.points.len() < options.min_window_points {
        return None;
    }
    let first = window.poses.first()?.0;
    let map = sources.map;
    let recent: Vec<u64> = map
        .keyframes()
        .filter(|(id, s, _)| *s == segment && *id < first)
        .map(|(id, _, _)| id)
        .collect();
    let oldest = *recent
        .iter()
        .rev()
        .nth(options.recent_keyframes.saturating_sub(1))
        .or(recent.first())?;
    let points: HashMap<u64, Vector3<f64>> = window.points.iter().copied().collect();
    let queries: Vec<_> = window
        .poses
        .iter()
        .filter(|(id, _)| sources.features.is_described(*id))
        .copied()
        .collect();
    // Only keyframes that see map points can give pairs: the keyframes of the stop itself
    // (rotation-only windows, no points) look most like the window and would fill the
    // candidate list with nothing to match.
    let accept = |id: u64, s: u32| {
        s == segment
            && id >= oldest
            && id < first
            && map.observed_points(id) >= options.min_shared_points
    };
    let older = OlderKeyframes {
        query_point: &|track| points.get(&track).copied(),
        accept: &accept,
    };
    let agreement = relocalize_consistently(sources, &queries, &older, &options.link)?;
    tracing::debug!(
        keyframes = agreement.keyframes,
        shared_points = agreement.shared_points,
        scale = agreement.transform.scale,
        "window relocalized in the map"
    );
    (agreement.shared_points >= options.min_shared_points).then_some(RelocalizedScale {
        scale: agreement.transform.scale,
        point_pairs: agreement.shared_points,
    })
}
