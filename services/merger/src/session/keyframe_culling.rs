//! The merger drops redundant keyframes once no window can bring them again
//! (crate::keyframe_culling): the map, the checkpoint, the descriptors and the
//! bag-of-words index keep the keyframes that see something the others do not. A culled
//! keyframe's frame stays in the trajectory, posed relative to the kept keyframes around
//! it (a `LocalizedFrame`), as do the frames that were posed against it.

use super::frames::{frame_poses, relative, LocalizedFrame};
use super::MergerSession;
use crate::{CulledKeyframe, KeyframeBudget, KeyframeCullingOptions, KeyframeFeatureSource};
use egoslam_geometry::StampedPose;
use std::collections::BTreeMap;

impl MergerSession {
    /// Culls among the keyframes older than `oldest_live` (the newest window's first: the
    /// next window overlaps only that one) not looked at before. Not while a background
    /// refinement runs: its result holds those keyframes (a fold finding one gone drops
    /// the whole result); they are looked at after it is folded. Nor from the first
    /// keyframe of a stretch waiting for its scale on: settling it rescales its keyframes
    /// about that one, which frames kept relative to keyframes before it would not follow.
    pub(super) fn cull_keyframes(
        &mut self,
        oldest_live: u64,
        features: &dyn KeyframeFeatureSource,
    ) {
        let provisional = self.state.map.provisional_scale().map(|p| p.first_keyframe);
        let oldest_live = provisional.map_or(oldest_live, |first| first.min(oldest_live));
        if !self.options.cull_keyframes {
            return;
        }
        let options = KeyframeCullingOptions::default();
        let checked = self.state.culling_checked_before;
        if oldest_live > checked && !self.refiner.is_running() {
            let candidates: Vec<u64> = self
                .state
                .map
                .keyframes()
                .map(|(id, _, _)| id)
                .filter(|id| (checked..oldest_live).contains(id))
                .collect();
            self.state.culling_checked_before = oldest_live;
            self.cull(&candidates, oldest_live, features, "redundant", |map| {
                map.cull_keyframes(&candidates, &options)
            });
        }
        let budget = KeyframeBudget {
            max_keyframes: self.options.max_map_keyframes,
            ..KeyframeBudget::default()
        };
        if budget.max_keyframes > 0 {
            // The ceiling also applies while a refinement runs, to keyframes older than
            // those it holds: refinements started back to back otherwise left it unapplied
            // for most of a long run.
            let before = oldest_live.min(self.refiner.free_before());
            let map = &self.state.map;
            let over = self.tally.time("keyframe_budget", || {
                map.over_budget_keyframes(before, &budget)
            });
            self.cull(&over, oldest_live, features, "over_budget", |map| {
                map.remove_keyframes(&over, &options)
            });
        }
    }

    /// Runs `remove` (which culls among `candidates`, all older than `oldest_live`) and
    /// keeps the frames posed and the descriptors and index in step with the map.
    fn cull(
        &mut self,
        candidates: &[u64],
        oldest_live: u64,
        features: &dyn KeyframeFeatureSource,
        rule: &'static str,
        remove: impl FnOnce(&mut crate::MapBuilder) -> crate::CullingReport,
    ) {
        let Some(&first) = candidates.iter().min() else {
            return;
        };
        // The frames that may be posed against a candidate, as they are posed now.
        let frames = &self.state.frames;
        let span = |id: Option<u64>| id.and_then(|k| frames.keyframe_frames.get(&k).copied());
        let map = &self.state.map;
        let before_first = map
            .keyframes()
            .map(|(id, _, _)| id)
            .take_while(|id| *id < first);
        let from = span(before_first.last().or(Some(first)));
        let to = span(
            map.keyframes()
                .map(|(id, _, _)| id)
                .find(|id| *id >= oldest_live),
        );
        let (Some(from), Some(to)) = (from, to) else {
            return;
        };
        let before = frame_poses(map, frames, from..=to);
        let map = &mut self.state.map;
        let report = self.tally.time("cull_keyframes", || remove(map));
        if report.culled.is_empty() {
            return;
        }
        let culled: BTreeMap<u64, CulledKeyframe> =
            report.culled.iter().map(|c| (c.keyframe_id, *c)).collect();
        self.keep_frames_posed(&culled, &before);
        for id in culled.keys() {
            // Unreadable descriptors (the source says so) leave the keyframe in the index.
            if let Some(described) = features.features(*id) {
                let descriptors: Vec<_> = described.iter().map(|f| f.descriptor).collect();
                self.database
                    .remove(*id, &self.vocabulary.bag_of_words(&descriptors));
            }
            self.keep_patches_of(*id);
        }
        tracing::debug!(
            rule,
            keyframes = culled.len(),
            points = report.removed_points,
            "keyframes culled"
        );
        self.tally
            .count(&format!("culled_keyframes_{rule}"), culled.len() as u64);
        self.tally
            .count("culled_points", report.removed_points as u64);
    }

    /// A culled keyframe's patches of tracks still in the map stay, with those tracks'
    /// features (their pixels), in the features log: a patch is kept only in the keyframe
    /// that first described its track, and relocalization's patch alignment
    /// (docs/relocalization.md) warps it from that keyframe's pose, which its frame keeps
    /// (egoslam's `map_file::relocalization_map`). Without them, the rendered walks' relocalization
    /// error rose by a quarter to a half.
    fn keep_patches_of(&mut self, keyframe: u64) {
        let map = &self.state.map;
        let Some(patches) = self.state.patched_tracks.get_mut(&keyframe) else {
            return;
        };
        patches.retain(|(track, _)| map.point(*track).is_some());
        if patches.is_empty() {
            self.state.patched_tracks.remove(&keyframe);
        }
    }

    /// Drops the patches culled keyframes keep of tracks that left the map since (later
    /// culls): otherwise they would pile up with the time walked, in memory and in the
    /// features log's compactions. Drops every keyframe's patches past the retention
    /// (`SessionOptions::patch_retention_s`) too, with the grey levels map.ply colours
    /// their points by.
    pub fn prune_culled_patches(&mut self) {
        let expired: Vec<u64> = self
            .state
            .patched_tracks
            .keys()
            .copied()
            .filter(|k| self.patches_expired(*k))
            .collect();
        for keyframe in expired {
            self.state.patched_tracks.remove(&keyframe);
        }
        let map = &self.state.map;
        self.state.patched_tracks.retain(|keyframe, kept| {
            if map.keyframe(*keyframe).is_some() {
                return true;
            }
            kept.retain(|(track, _)| map.point(*track).is_some());
            !kept.is_empty()
        });
    }

    /// Keeps each culled keyframe's frame, and every frame posed against a culled keyframe,
    /// at its pose in `before`, relative to the kept keyframes around it. Frames that were
    /// interpolated stay interpolated (now between the kept keyframes).
    fn keep_frames_posed(
        &mut self,
        culled: &BTreeMap<u64, CulledKeyframe>,
        before: &BTreeMap<u64, (u32, StampedPose)>,
    ) {
        let kept: Vec<(u64, u32, StampedPose)> = self
            .state
            .map
            .keyframes()
            .map(|(id, s, p)| (id, s, *p))
            .collect();
        let index = &mut self.state.frames;
        let mut frozen: Vec<u64> = culled
            .keys()
            .filter_map(|k| index.keyframe_frames.get(k).copied())
            .collect();
        // Only frames `before` poses can be kept: the localized ones outside it are skipped
        // without looking at every frame of the run.
        let (Some((&first, _)), Some((&last, _))) =
            (before.first_key_value(), before.last_key_value())
        else {
            return;
        };
        frozen.extend(index.localized.range(first..=last).filter_map(|(f, l)| {
            (culled.contains_key(&l.anchor_keyframe) || culled.contains_key(&l.next_keyframe))
                .then_some(*f)
        }));
        for frame in frozen {
            let Some(&(segment, pose)) = before.get(&frame) else {
                continue;
            };
            match bracket(&kept, pose.timestamp, segment) {
                Some((anchor_id, anchor, next_id, next)) => {
                    index.localized.insert(
                        frame,
                        LocalizedFrame {
                            anchor_keyframe: anchor_id,
                            relative: relative(&anchor, &pose),
                            next_keyframe: next_id,
                            bracket_length: (next.position - anchor.position).norm(),
                        },
                    );
                }
                None => {
                    index.localized.remove(&frame);
                }
            }
        }
    }
}

/// The kept keyframes (`kept`, in time order) just before and after time `t`, when both
/// are in `segment`.
fn bracket(
    kept: &[(u64, u32, StampedPose)],
    t: f64,
    segment: u32,
) -> Option<(u64, StampedPose, u64, StampedPose)> {
    let after = kept.partition_point(|(_, _, p)| p.timestamp <= t);
    let (a_id, a_segment, anchor) = *kept.get(after.checked_sub(1)?)?;
    let (n_id, n_segment, next) = *kept.get(after)?;
    (a_segment == segment && n_segment == segment).then_some((a_id, anchor, n_id, next))
}
