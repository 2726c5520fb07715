//! Frames between keyframes: localized by PnP on the merged map once both keyframes around
//! them are in it (`egoslam_merger::frame_localization`); those that cannot be stay
//! interpolated and are marked so on the wire.

use crate::merger::map_state::{relative, FrameIndex, LocalizedFrame};
use crate::stats::ServiceStats;
use egoslam_geometry::PinholeRadtan;
use egoslam_merger::{interpolate_between, localize_frame, LocalizationOptions, MapBuilder};

/// Tries every pending frame whose bracketing keyframes are both posed in one segment;
/// frames whose next keyframe is not yet in the map stay pending, unless that keyframe is
/// older than `oldest_live_keyframe` (no later window can pose it: it stays unposed).
pub fn localize_pending(
    index: &mut FrameIndex,
    map: &MapBuilder,
    camera: &PinholeRadtan,
    oldest_live_keyframe: u64,
    stats: &mut ServiceStats,
) {
    let options = LocalizationOptions::default();
    let before = index.pending.len();
    index.pending.retain(|_, p| {
        p.next_keyframe >= oldest_live_keyframe || map.keyframe(p.next_keyframe).is_some()
    });
    stats.count("unposed_frames", (before - index.pending.len()) as u64);
    let ready: Vec<u64> = index
        .pending
        .iter()
        .filter(|(_, p)| map.keyframe(p.next_keyframe).is_some())
        .map(|(f, _)| *f)
        .collect();
    for frame_id in ready {
        let Some(pending) = index.pending.remove(&frame_id) else {
            continue;
        };
        let (Some(timestamp), Some(anchor_id)) = (
            index.frames.get(&frame_id).copied(),
            pending.next_keyframe.checked_sub(1),
        ) else {
            continue;
        };
        let (Some((sa, anchor)), Some((sb, next))) =
            (map.keyframe(anchor_id), map.keyframe(pending.next_keyframe))
        else {
            stats.count("interpolated_frames", 1);
            continue;
        };
        if sa != sb {
            stats.count("interpolated_frames", 1);
            continue;
        }
        let prior = interpolate_between(anchor, next, timestamp);
        let correspondences: Vec<_> = pending
            .tracks
            .iter()
            .filter_map(|(track, px)| match map.point(*track) {
                Some((s, x)) if s == sa => Some((*x, *px)),
                _ => None,
            })
            .collect();
        match localize_frame(camera, &correspondences, &prior, &options) {
            Ok(l) => {
                let bracket_length = (next.position - anchor.position).norm();
                tracing::debug!(
                    frame = frame_id,
                    from_prior = (l.pose.position - prior.position).norm(),
                    bracket = bracket_length,
                    inliers = l.inliers,
                    "frame localized"
                );
                index.localized.insert(
                    frame_id,
                    LocalizedFrame {
                        anchor_keyframe: anchor_id,
                        relative: relative(anchor, &l.pose),
                        next_keyframe: pending.next_keyframe,
                        bracket_length,
                    },
                );
                stats.count("localized_frames", 1);
            }
            Err(e) => {
                tracing::debug!(frame = frame_id, reason = %e, "frame interpolated");
                stats.count("interpolated_frames", 1);
            }
        }
    }
}
