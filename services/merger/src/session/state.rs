//! Everything the merger must not lose: the map, every frame and how it is posed, where the
//! stream stands. The service checkpoints it (egoslam's durability/checkpoint.rs) and a
//! restarted merger resumes from it.

use super::frame_retirement::RetiredFrames;
use super::frames::FrameIndex;
use crate::MapBuilder;
use std::collections::BTreeMap;

/// The merger's durable state.
#[derive(Default)]
pub struct MergerState {
    pub map: MapBuilder,
    pub frames: FrameIndex,
    /// The solver stream this state belongs to (`None` before the first message).
    pub stream_id: Option<u64>,
    /// Bus sequence number of the last message applied.
    pub last_sequence: Option<u64>,
    /// The end-of-stream message was applied.
    pub finished: bool,
    pub windows: u64,
    pub unsolved_windows: u64,
    /// Keyframes with smaller ids were looked at for culling (session/keyframe_culling.rs).
    pub culling_checked_before: u64,
    /// frame id -> last revision published over zenoh.
    pub revisions: BTreeMap<u64, u32>,
    /// keyframe id -> the tracks first described in it, whose patches (relocalization's
    /// patch alignment) it holds in the features log, on disk only; with each patch's
    /// grey level (map.ply's colour).
    pub patched_tracks: BTreeMap<u64, Vec<(u64, u8)>>,
    /// The frames retired past the horizon (session/frame_retirement.rs).
    pub retired: RetiredFrames,
}

impl MergerState {
    /// An empty state for a new stream.
    pub fn for_stream(stream_id: u64) -> Self {
        Self {
            stream_id: Some(stream_id),
            ..Self::default()
        }
    }

    /// The sequence number of the next message to apply.
    pub fn next_sequence(&self) -> u64 {
        self.last_sequence.map_or(0, |s| s + 1)
    }
}
