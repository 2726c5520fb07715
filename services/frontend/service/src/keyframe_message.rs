//! A keyframe as it goes on the bus: its tracks (raw and undistorted positions), the ORB
//! descriptors at the raw positions and, once per track, the patch relocalization aligns.

use egoslam_frontend::{KeyframeReason, KeyframeTracks, TrackPoint};
use egoslam_messages::internal::v1 as internal;
use egoslam_messages::v1 as pb;
use egoslam_relocalization::descriptors::OrbDescriber;
use egoslam_relocalization::patch_alignment::extract_patch;
use opencv::core::ToInputArray;
use opencv::prelude::*;
use std::collections::HashSet;

fn reason(r: KeyframeReason) -> internal::KeyframeReason {
    match r {
        KeyframeReason::First => internal::KeyframeReason::First,
        KeyframeReason::FrameCount => internal::KeyframeReason::FrameCount,
        KeyframeReason::Flow => internal::KeyframeReason::Flow,
        KeyframeReason::TrackLoss => internal::KeyframeReason::TrackLoss,
        KeyframeReason::Last => internal::KeyframeReason::Last,
    }
}

pub(crate) fn track_message(t: &TrackPoint) -> internal::TrackObservation {
    internal::TrackObservation {
        track_id: t.track_id,
        raw_x: t.raw.x,
        raw_y: t.raw.y,
        x: t.undistorted.x,
        y: t.undistorted.y,
        descriptor: Vec::new(),
        patch: Vec::new(),
    }
}

/// Attaches ORB descriptors (at the raw positions in `image`) to a keyframe's tracks, for
/// relocalization (docs/relocalization.md), and to each described track not `patched`
/// in an earlier keyframe its patch. A failure costs the descriptors, not the keyframe.
pub(crate) fn describe_tracks(
    describer: &mut OrbDescriber,
    image: &(impl MatTraitConst + ToInputArray),
    message: &mut internal::Keyframe,
    patched: &mut HashSet<u64>,
) {
    let corners: Vec<_> = message
        .tracks
        .iter()
        .map(|t| nalgebra::Point2::new(t.raw_x, t.raw_y))
        .collect();
    match describer.describe(image, &corners) {
        Ok(descriptors) => {
            for (t, d) in message.tracks.iter_mut().zip(descriptors) {
                if let Some(d) = d {
                    t.descriptor = d.to_vec();
                    if !patched.contains(&t.track_id) {
                        let raw = nalgebra::Point2::new(f64::from(t.raw_x), f64::from(t.raw_y));
                        if let Some(patch) = extract_patch(image, raw) {
                            t.patch = patch.to_vec();
                            patched.insert(t.track_id);
                        }
                    }
                }
            }
        }
        Err(e) => tracing::warn!(keyframe = message.keyframe_id, error = %e, "no descriptors"),
    }
    // A lost track never comes back: only the live ones need remembering.
    let live: HashSet<u64> = message.tracks.iter().map(|t| t.track_id).collect();
    patched.retain(|t| live.contains(t));
}

/// The proto message of a keyframe.
pub(crate) fn keyframe_message(
    k: &KeyframeTracks,
    timestamp_s: f64,
    intrinsics: &pb::Intrinsics,
    skipped: Vec<internal::FrameStamp>,
) -> internal::Keyframe {
    internal::Keyframe {
        keyframe_id: k.keyframe_id,
        frame_id: k.frame_id,
        timestamp_s,
        intrinsics: Some(intrinsics.clone()),
        tracks: k.tracks.iter().map(track_message).collect(),
        frames_since_previous: skipped,
        mean_flow_px: k.mean_flow_px as f32,
        reason: reason(k.reason) as i32,
        end_of_stream: false,
        trailing_frames: Vec::new(),
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use egoslam_relocalization::descriptors::DescriberOptions;
    use opencv::core::{Mat, Scalar, CV_8UC1};

    /// Blocks of random grey: corners everywhere, deterministic.
    fn textured() -> Mat {
        let mut img =
            Mat::new_rows_cols_with_default(240, 320, CV_8UC1, Scalar::all(0.0)).expect("image");
        let mut state = 7u64;
        for y in 0..240 {
            for x in 0..320 {
                if x % 8 == 0 && y % 8 == 0 {
                    state = state
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                }
                let v = ((state >> 56) as i32 + (x / 8 + y / 8) * 37) % 256;
                *img.at_2d_mut::<u8>(y, x).expect("pixel") = v as u8;
            }
        }
        img
    }

    pub(crate) fn keyframe(ids: &[u64]) -> internal::Keyframe {
        internal::Keyframe {
            tracks: ids
                .iter()
                .map(|&id| internal::TrackObservation {
                    track_id: id,
                    raw_x: 60.0 + 20.0 * id as f32,
                    raw_y: 120.0,
                    ..Default::default()
                })
                .collect(),
            ..Default::default()
        }
    }

    #[test]
    fn a_track_carries_its_patch_once_in_the_first_keyframe_that_describes_it() {
        let image = textured();
        let mut describer = OrbDescriber::new(DescriberOptions::default()).expect("orb");
        let mut patched = HashSet::new();
        let mut first = keyframe(&[1, 2]);
        describe_tracks(&mut describer, &image, &mut first, &mut patched);
        assert!(first.tracks.iter().all(|t| t.descriptor.len() == 32));
        assert!(first.tracks.iter().all(|t| t.patch.len() == 100));
        // Track 1 is lost, 3 is new: only 3 gets a patch, and 1 is forgotten.
        let mut second = keyframe(&[2, 3]);
        describe_tracks(&mut describer, &image, &mut second, &mut patched);
        assert!(second.tracks[0].patch.is_empty());
        assert_eq!(second.tracks[1].patch.len(), 100);
        assert_eq!(patched, HashSet::from([2, 3]));
        // The patch is the image around the track's raw position.
        let expected = extract_patch(&image, nalgebra::Point2::new(120.0, 120.0)).expect("inside");
        assert_eq!(second.tracks[1].patch, expected.to_vec());
    }
}
