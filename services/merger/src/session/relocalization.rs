//! The merger's uses of relocalization inside the map: linking a segment that began after
//! a break to an older one, and closing loops inside a segment
//! (docs/relocalization.md, docs/merger.md).

use super::MergerSession;
use crate::{
    find_link, find_loop, relocalized_window_scale, KeyframeFeatureSource, LinkOptions,
    LoopNotApplied, LoopOptions, RelocalizationSources, RelocalizedScale, RelocalizedScaleOptions,
    WindowInput,
};
use egoslam_geometry::PinholeRadtan;

/// A segment is tried for linking to older ones while it has at most this many keyframes
/// (three windows): after a break the first windows decide; a segment that found no link
/// by then stays a segment of its own (each attempt relocalizes up to 12 keyframes).
const LINK_ATTEMPT_KEYFRAMES: usize = 60;

/// The segment new windows go to, once past [`LINK_ATTEMPT_KEYFRAMES`], is tried again
/// every this many windows with its newest [`LINK_RETRY_KEYFRAMES`] keyframes: a walk that
/// returns to a place the older map saw is linked there (a loop closure across the break).
const LINK_RETRY_WINDOWS: u64 = 10;
const LINK_RETRY_KEYFRAMES: usize = 20;

/// The segment new windows go to is searched for a loop every this many windows (each
/// attempt relocalizes its newest 12 keyframes, ~20 ms each). A wearer back in a mapped
/// place is held to the map by these loops, so the chain may drift only between two
/// attempts. Attempts go on while a background refinement runs: the loop is replayed onto
/// its result at the fold (crate::refinement_rebase).
const LOOP_ATTEMPT_WINDOWS: u64 = 2;

impl MergerSession {
    /// Runs `f` on the merger's map, descriptors and index as relocalization reads them,
    /// timed as `stage`.
    fn relocalize<T>(
        &mut self,
        camera: &PinholeRadtan,
        features: &dyn KeyframeFeatureSource,
        stage: &str,
        f: impl FnOnce(&RelocalizationSources) -> T,
    ) -> T {
        let sources = RelocalizationSources {
            map: &self.state.map,
            features,
            database: &self.database,
            camera,
            vocabulary: &self.vocabulary,
        };
        self.tally.time(stage, || f(&sources))
    }

    /// The scale of a window that shares too few points with the map, from its keyframes
    /// relocalized against the map's recent ones (crate::relocalized_scale);
    /// `None` when it shares enough points or does not relocalize.
    pub(super) fn relocalized_scale(
        &mut self,
        window: &WindowInput,
        features: &dyn KeyframeFeatureSource,
    ) -> Option<RelocalizedScale> {
        let camera = self.camera?;
        let segment = self.state.map.current_segment()?;
        if !self.state.map.lacks_shared_points(window) {
            return None;
        }
        let options = RelocalizedScaleOptions::default();
        let scale = self.relocalize(&camera, features, "relocalized_scale", |sources| {
            relocalized_window_scale(sources, segment, window, &options)
        });
        self.tally.count(
            if scale.is_some() {
                "relocalized_scales"
            } else {
                "relocalized_scales_failed"
            },
            1,
        );
        tracing::debug!(?scale, "window scale by relocalization");
        scale
    }

    /// Links a young segment to an older one by relocalizing its keyframes, and merges it
    /// when they agree (docs/relocalization.md, "Segment linking"). After a merge the other
    /// young segments are tried again: a segment that saw nothing of the older map may see
    /// what the merged one brought.
    pub(super) fn try_link(
        &mut self,
        window_id: u64,
        segment: u32,
        features: &dyn KeyframeFeatureSource,
    ) {
        let Some(camera) = self.camera else {
            return;
        };
        let current = segment;
        let mut queue = vec![segment];
        while let Some(segment) = queue.pop() {
            let map = &self.state.map;
            let young = map.segment_keyframes(segment).len() <= LINK_ATTEMPT_KEYFRAMES;
            let retry = segment == current && window_id.is_multiple_of(LINK_RETRY_WINDOWS);
            if !(young || retry) || map.live_segments() < 2 {
                continue;
            }
            let options = LinkOptions {
                only_newest: (!young).then_some(LINK_RETRY_KEYFRAMES),
                ..LinkOptions::default()
            };
            let link = self.relocalize(&camera, features, "link_segments", |sources| {
                find_link(sources, segment, &options)
            });
            let Some(link) = link else { continue };
            tracing::info!(
                window = window_id,
                from = link.from,
                to = link.to,
                keyframes = link.keyframes,
                shared_points = link.shared_points,
                scale = link.transform.scale,
                "break healed: segment linked by relocalization"
            );
            self.state.map.merge_segment(&link);
            let live: std::collections::BTreeSet<u32> =
                self.state.map.keyframes().map(|(_, s, _)| s).collect();
            queue = live.into_iter().filter(|s| *s != link.to).collect();
        }
    }

    /// Closes a loop inside `segment` when its newest keyframes relocalize into a part of
    /// it mapped long before (crate::loop_closure).
    pub(super) fn try_close_loop(
        &mut self,
        window_id: u64,
        segment: u32,
        features: &dyn KeyframeFeatureSource,
    ) {
        let Some(camera) = self.camera else {
            return;
        };
        if !self.options.loop_closure || !window_id.is_multiple_of(LOOP_ATTEMPT_WINDOWS) {
            return;
        }
        let options = LoopOptions::default();
        let closure = self.relocalize(&camera, features, "find_loop", |sources| {
            find_loop(sources, segment, &options)
        });
        let Some(closure) = closure else {
            self.tally.count("loops_not_found", 1);
            return;
        };
        let report = match self.state.map.close_loop(&closure, &options) {
            Ok(report) => report,
            Err(e @ LoopNotApplied::TooLarge { .. }) => {
                self.tally.count("loops_refused", 1);
                tracing::warn!(
                    window = window_id,
                    anchor = closure.anchor_keyframe,
                    shared_points = closure.shared_points,
                    "loop refused: {e}"
                );
                return;
            }
            Err(e) => {
                tracing::debug!(
                    window = window_id,
                    anchor = closure.anchor_keyframe,
                    "loop not applied: {e}"
                );
                return;
            }
        };
        self.tally.count("loops_closed", 1);
        // A refinement running meanwhile gets the loop replayed onto its result.
        self.refiner.record_loop(&report);
        self.loop_sightings = closure.sightings.clone();
        tracing::info!(
            window = window_id,
            anchor = closure.anchor_keyframe,
            keyframes = report.keyframes,
            points = report.points,
            sightings = closure.sightings.len(),
            correction = report.correction,
            path = report.path,
            scale = closure.transform.scale,
            shared_points = closure.shared_points,
            "loop closed"
        );
    }
}
