//! Where a restarted solver takes over (docs/durability.md): it continues its
//! predecessor's stream instead of starting a new one, so that no keyframe is lost and the
//! merger sees one stream without a gap.
//!
//! The solver's journal says which windows were published (and the stream id and the next
//! bus sequence number); the frontend's keyframe log holds every keyframe sent. The new
//! solver seeds its window builder with the last published window's overlap keyframes and
//! replays the logged keyframes after that window, then goes on with the live channel,
//! skipping the keyframes it has already replayed.

use egoslam_durability::record_log::read_records;
use egoslam_durability::window_journal::{self, Journal};
use egoslam_messages::internal::v1 as internal;
use std::path::Path;

/// The state a restarted solver resumes from.
pub struct Resume {
    pub journal: Journal,
    /// Keyframes of the last published window that the next window shares.
    pub tail: Vec<internal::Keyframe>,
    /// Logged messages after the last published window, in order (possibly ending with
    /// the end-of-stream message).
    pub replay: Vec<internal::Keyframe>,
}

impl Resume {
    /// Windows already published (the next window's id).
    pub fn windows(&self) -> u64 {
        self.journal.next_sequence()
    }

    /// Highest keyframe id the new solver has taken (tail or replay); live keyframes up
    /// to it are duplicates.
    pub fn last_keyframe_id(&self) -> Option<u64> {
        self.replay
            .iter()
            .chain(&self.tail)
            .filter(|k| !k.end_of_stream)
            .map(|k| k.keyframe_id)
            .max()
    }
}

/// The resume point in `out`, or `None` for a fresh stream: no journal, a finished one, an
/// unreadable one (with a warning), or a log that lacks what the journal refers to.
pub fn find(out: &Path, namespace: &str, overlap: usize) -> anyhow::Result<Option<Resume>> {
    let path = egoslam_durability::state_dir(out).join(window_journal::FILE_NAME);
    if !path.exists() {
        return Ok(None);
    }
    let journal = match window_journal::read(&path) {
        Ok(j) => j,
        Err(e) => {
            tracing::warn!(error = %e, "journal unreadable: starting a new stream");
            return Ok(None);
        }
    };
    if journal.messages.last().is_some_and(|m| m.end_of_stream) {
        return Ok(None);
    }
    let logged: Vec<internal::Keyframe> =
        read_records(&egoslam_durability::keyframe_log_path(out, namespace))?;
    let (tail_ids, covered) = match journal.messages.last() {
        Some(w) => {
            let ids = &w.keyframe_ids;
            let tail = ids[ids.len().saturating_sub(overlap)..].to_vec();
            (tail, ids.iter().copied().max())
        }
        None => (Vec::new(), None),
    };
    let find_logged = |id: u64| {
        logged
            .iter()
            .rev()
            .find(|k| !k.end_of_stream && k.keyframe_id == id)
            .cloned()
    };
    let tail: Option<Vec<internal::Keyframe>> =
        tail_ids.iter().map(|id| find_logged(*id)).collect();
    let Some(tail) = tail else {
        tracing::warn!("the keyframe log lacks the last window's keyframes: starting a new stream");
        return Ok(None);
    };
    let mut replay: Vec<internal::Keyframe> = Vec::new();
    for k in logged {
        let new = k.end_of_stream || covered.is_none_or(|c| k.keyframe_id > c);
        if new
            && !replay
                .iter()
                .any(|r| !r.end_of_stream && !k.end_of_stream && r.keyframe_id == k.keyframe_id)
        {
            replay.push(k);
        }
    }
    Ok(Some(Resume {
        journal,
        tail,
        replay,
    }))
}
