//! The merger drops redundant keyframes once no window can bring them again
//! (crate::keyframe_culling): the map, the checkpoint, the descriptors and the
//! bag-of-words index keep the keyframes that see something the others do not. A culled
//! keyframe's frame stays in the trajectory, posed relative to the kept keyframes around
//! it (a `LocalizedFrame`), as do the frames that were posed against it.

use super::frames::{frame_poses, relative, LocalizedFrame};
use super::MergerSession;
use crate::{CulledKeyframe, KeyframeBudget, KeyframeCullingOptions};
use egoslam_geometry::StampedPose;
use std::collections::{BTreeMap, BTreeSet};

impl MergerSession {
    /// Culls among the keyframes older than `oldest_live` (the newest window's first: the
    /// next window overlaps only that one) not looked at before. Not while a background
    /// refinement runs: its result holds those keyframes (a fold finding one gone drops
    /// the whole result); they are looked at after it is folded. Nor from the first
    /// keyframe of a stretch waiting for its scale on: settling it rescales its keyframes
    /// about that one, which frames kept relative to keyframes before it would not follow.
    pub(super) fn cull_keyframes(&mut self, oldest_live: u64) {
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
            self.cull(&candidates, oldest_live, "redundant", |map| {
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
            self.cull(&over, oldest_live, "over_budget", |map| {
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
        let mut before = frame_poses(map, frames, from..=to);
        // Frames of later passes posed against a candidate (culling anchors a revisit's
        // frames to the kept keyframe nearest in space, which may be one of these).
        let candidate_ids: BTreeSet<u64> = candidates.iter().copied().collect();
        for (frame, l) in frames.localized.iter() {
            let posed_against = candidate_ids.contains(&l.anchor_keyframe)
                || candidate_ids.contains(&l.next_keyframe);
            if !posed_against || before.contains_key(frame) {
                continue;
            }
            if let Some(posed) = l.posed_in(map) {
                before.insert(*frame, posed);
            }
        }
        let map = &mut self.state.map;
        let report = self.tally.time("cull_keyframes", || remove(map));
        if report.culled.is_empty() {
            return;
        }
        let culled: BTreeMap<u64, CulledKeyframe> =
            report.culled.iter().map(|c| (c.keyframe_id, *c)).collect();
        self.keep_frames_posed(&culled, &before, oldest_live);
        for id in culled.keys() {
            self.database.remove(*id);
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
    /// (`egoslam_durability::map_file::relocalization_map`). Without them, the rendered walks' relocalization
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

    /// Keeps each culled keyframe's frame, every frame posed against a culled keyframe and
    /// the interpolated frames among them at their pose in `before`, relative to the kept
    /// keyframe nearest in space among those no later window brings again (older than
    /// `oldest_live`) and the ones just around it in time: on a revisit that is a keyframe
    /// of the earlier pass, in a first visit one of its neighbours. A frame whose anchor is
    /// the keyframe just before it in time follows the scale of its bracket; the others
    /// move rigidly with their anchor. Interpolated frames stay marked so.
    fn keep_frames_posed(
        &mut self,
        culled: &BTreeMap<u64, CulledKeyframe>,
        before: &BTreeMap<u64, (u32, StampedPose)>,
        oldest_live: u64,
    ) {
        let kept: Vec<(u64, u32, StampedPose)> = self
            .state
            .map
            .keyframes()
            .map(|(id, s, p)| (id, s, *p))
            .collect();
        let index = &mut self.state.frames;
        let kept_frames: BTreeSet<u64> = kept
            .iter()
            .filter_map(|(k, ..)| index.keyframe_frames.get(k).copied())
            .collect();
        let culled_frames: BTreeSet<u64> = culled
            .keys()
            .filter_map(|k| index.keyframe_frames.get(k).copied())
            .collect();
        // `before` holds every frame posed against a candidate (`cull`): no other can be.
        let posed_against_culled = before.keys().copied().filter(|f| {
            index.localized.get(f).is_some_and(|l| {
                culled.contains_key(&l.anchor_keyframe) || culled.contains_key(&l.next_keyframe)
            })
        });
        // Interpolated frames of the span: between the kept keyframes left around them
        // they could be interpolated across a whole culled pass.
        let interpolated: BTreeSet<u64> = before
            .keys()
            .copied()
            .filter(|f| {
                !index.localized.contains_key(f)
                    && !index.pending.contains_key(f)
                    && !kept_frames.contains(f)
                    && !culled_frames.contains(f)
            })
            .collect();
        let frozen: BTreeSet<u64> = culled_frames
            .iter()
            .copied()
            .chain(posed_against_culled)
            .chain(interpolated.iter().copied())
            .collect();
        let settled: Vec<&(u64, u32, StampedPose)> =
            kept.iter().filter(|(k, ..)| *k < oldest_live).collect();
        for frame in frozen {
            let Some(&(segment, pose)) = before.get(&frame) else {
                continue;
            };
            let was_interpolated = interpolated.contains(&frame)
                || index.localized.get(&frame).is_some_and(|l| l.interpolated);
            let distance = |p: &StampedPose| (p.position - pose.position).norm();
            let nearest = settled
                .iter()
                .filter(|(_, s, _)| *s == segment)
                .min_by(|a, b| distance(&a.2).total_cmp(&distance(&b.2)));
            let bracketed = bracket(&kept, pose.timestamp, segment).filter(|(_, anchor, ..)| {
                nearest.is_none_or(|(_, _, n)| distance(anchor) <= distance(n))
            });
            let frozen = match (bracketed, nearest) {
                (Some((anchor_id, anchor, next_id, next)), _) => LocalizedFrame {
                    anchor_keyframe: anchor_id,
                    relative: relative(&anchor, &pose),
                    next_keyframe: next_id,
                    bracket_length: (next.position - anchor.position).norm(),
                    interpolated: was_interpolated,
                },
                (None, Some((anchor_id, _, anchor))) => LocalizedFrame {
                    anchor_keyframe: *anchor_id,
                    relative: relative(anchor, &pose),
                    next_keyframe: *anchor_id,
                    bracket_length: 0.0,
                    interpolated: was_interpolated,
                },
                (None, None) => {
                    index.localized.remove(&frame);
                    continue;
                }
            };
            index.localized.insert(frame, frozen);
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

#[cfg(test)]
mod tests {
    use super::super::frames::{FrameIndex, PosedFrame};
    use super::*;
    use crate::session::frames::{posed_frames, posed_keyframes};
    use crate::{MapBuilder, MapParts, SessionOptions};
    use egoslam_relocalization::default_vocabulary;
    use nalgebra::Vector3;

    /// The corridor walked twice of `keyframe_coverage`'s tests (keyframes 0..300 and
    /// 300..600 at x = (k % 300) / 100, at time k, each seeing 10 points of its own), with
    /// keyframe k as frame 2k and a frame 2k + 1 half-way to the next: those after an even
    /// keyframe of the second pass localized, the others interpolated. Keyframes below
    /// `shift_first_pass_below` stand 1 unit aside in y.
    fn two_passes(shift_first_pass_below: u64) -> (MapParts, FrameIndex) {
        let mut parts = crate::keyframe_coverage::tests::two_passes(0.0).to_parts();
        let mut index = FrameIndex::default();
        for (&k, (_, pose)) in parts.keyframes.iter_mut() {
            if k < shift_first_pass_below {
                pose.position.y += 1.0;
            }
            let t = k as f64;
            index.frames.insert(2 * k, t);
            index.frames.insert(2 * k + 1, t + 0.5);
            index.keyframe_frames.insert(k, 2 * k);
            if k >= 300 && k % 2 == 0 {
                let frame = StampedPose {
                    timestamp: t + 0.5,
                    position: pose.position + Vector3::new(0.005, 0.0, 0.0),
                    ..*pose
                };
                index.localized.insert(
                    2 * k + 1,
                    LocalizedFrame {
                        anchor_keyframe: k,
                        relative: relative(pose, &frame),
                        next_keyframe: k + 1,
                        bracket_length: 0.01,
                        interpolated: false,
                    },
                );
            }
        }
        parts.segments = 1;
        parts.current_segment = Some(0);
        (parts, index)
    }

    fn posed(session: &MergerSession) -> Vec<PosedFrame> {
        let (map, index) = (&session.state.map, &session.state.frames);
        posed_frames(map, index, &posed_keyframes(map, index), ..)
    }

    #[test]
    fn a_culled_revisit_is_posed_against_the_earlier_pass_and_follows_it() {
        let vocabulary = default_vocabulary().expect("the built-in vocabulary");
        let mut session = MergerSession::new(SessionOptions::default(), vocabulary);
        let (parts, index) = two_passes(0);
        session.state.map = MapBuilder::from_parts(parts);
        session.state.frames = index;
        let before = posed(&session);
        let candidates: Vec<u64> = (300..590).collect();
        let options = crate::keyframe_culling::tests::any_size();
        session.cull(&candidates, 590, "redundant", |map| {
            map.cull_keyframes(&candidates, &options)
        });
        assert_eq!(session.state.map.keyframes().count(), 310, "the pass went");
        // Every frame is where it was, marked as it was.
        let after = posed(&session);
        assert_eq!(before.len(), after.len());
        for (b, a) in before.iter().zip(&after) {
            assert_eq!(b.frame_id, a.frame_id);
            assert!(
                (b.pose.position - a.pose.position).norm() < 1e-9,
                "{b:?} {a:?}"
            );
            let was_keyframe = b.frame_id % 2 == 0;
            assert_eq!(a.interpolated, b.interpolated && !was_keyframe, "{a:?}");
        }
        // The second pass's frames hang on the first pass's keyframes at their place.
        for frame in 600..1180 {
            let l = session.state.frames.localized[&frame];
            assert!(l.anchor_keyframe < 300, "frame {frame}: {l:?}");
            assert!(l.relative.position.norm() <= 0.011, "frame {frame}: {l:?}");
        }
        // A correction of the first pass's start moves the revisit's frames there with it,
        // not those over the rest of the corridor.
        let (mut shifted, _) = two_passes(150);
        shifted
            .keyframes
            .retain(|k, _| session.state.map.keyframe(*k).is_some());
        session.state.map = MapBuilder::from_parts(shifted);
        for f in posed(&session)
            .iter()
            .filter(|f| (600..1180).contains(&f.frame_id))
        {
            let x = f.pose.position.x;
            let expected_y = if x < 1.49 { 1.0 } else { 0.0 };
            if !(1.49..=1.51).contains(&x) {
                assert!((f.pose.position.y - expected_y).abs() < 1e-9, "{f:?}");
            }
        }
    }
}
