//! Bounded disk use for the two recovery logs (docs/durability.md, "Disk use").
//!
//! Each log has one writer and one reader that recovers from it: the solver's window
//! journal is read by a restarted merger, the frontend's keyframe log by a restarted
//! solver. Only the records the reader has not made durable yet are needed. The reader says
//! how far it got in a small mark file (written atomically after its own state is durable);
//! the writer, which alone rewrites its log, drops what the mark no longer needs once the
//! log has grown past a threshold. Without this both logs grew with the run (on the
//! rendered 1500-frame walk 71 and 66 MB for 50 s of video) and a long session filled the
//! disk.
//!
//! A mark is only ever behind the reader's durable state, so compaction never drops a
//! record a restarted reader asks for; a lost or stale mark only means no compaction (the
//! launcher and a fresh frontend remove stale marks).

use std::path::Path;

/// Written by the merger after each checkpoint: `stream_id next_sequence`, the first
/// window message of that solver stream the checkpoint does not hold.
pub const MERGER_MARK: &str = "merger.applied";

/// Written by the solver after each window message is journaled: `stream_id
/// first_keyframe_id`, the oldest keyframe a restarted solver would read back from the
/// keyframe log (the first of the last window's overlap keyframes).
pub const SOLVER_MARK: &str = "solver.applied";

/// Growth after which the writer compacts its log, bytes (default 16 MiB: by the sizes
/// on the rendered walks, ~1.1 MB per window message and ~84 KB per keyframe message,
/// about 15 windows or 200 keyframes, 10-15 s of walking). Each compaction copies only
/// the records the reader still needs, so a lower threshold trades a little more copying
/// for a log that stays near what recovery needs instead of swinging by the threshold.
/// `EGOSLAM_COMPACT_ABOVE_BYTES` overrides it (the tests use 100 KB).
pub const DEFAULT_COMPACT_ABOVE_BYTES: u64 = 16 << 20;

/// Writes a mark `first second` atomically (temporary file and rename).
pub fn write_mark(path: &Path, first: u64, second: u64) -> crate::Result<()> {
    crate::write_atomically(path, format!("{first} {second}\n").as_bytes())
}

/// Reads a mark; `None` when absent or unreadable (then nothing is compacted).
pub fn read_mark(path: &Path) -> Option<(u64, u64)> {
    let text = std::fs::read_to_string(path).ok()?;
    let mut parts = text.split_whitespace().map(str::parse::<u64>);
    match (parts.next(), parts.next(), parts.next()) {
        (Some(Ok(a)), Some(Ok(b)), None) => Some((a, b)),
        _ => {
            tracing::warn!(path = %path.display(), "unreadable log mark ignored");
            None
        }
    }
}

/// Removes a mark (a fresh stream must not compact by its predecessor's).
pub fn remove_mark(path: &Path) -> crate::Result<()> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            Err(crate::io_error("removing", path)(e))
        }
        _ => Ok(()),
    }
}

/// When a log is compacted: once it has grown by the threshold since the last compaction,
/// and only if its reader's mark moved since then (with no progress there is nothing to
/// drop, so a log whose reader is down is not rewritten again and again).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CompactionSchedule {
    threshold: u64,
    next: u64,
    last_mark: Option<(u64, u64)>,
}

impl CompactionSchedule {
    /// A schedule with `threshold` bytes.
    pub fn new(threshold: u64) -> Self {
        Self {
            threshold,
            next: threshold,
            last_mark: None,
        }
    }

    /// The threshold from `EGOSLAM_COMPACT_ABOVE_BYTES`, else the default.
    pub fn from_env() -> Self {
        let threshold = std::env::var("EGOSLAM_COMPACT_ABOVE_BYTES")
            .ok()
            .and_then(|v| v.parse::<u64>().ok())
            .unwrap_or(DEFAULT_COMPACT_ABOVE_BYTES);
        Self::new(threshold)
    }

    /// Whether a log of `len` bytes has outgrown the schedule (then read the mark).
    pub fn outgrown(&self, len: u64) -> bool {
        len > self.next
    }

    /// `mark` if the log should be compacted by it: present and new since the last
    /// compaction.
    pub fn fresh(&self, mark: Option<(u64, u64)>) -> Option<(u64, u64)> {
        mark.filter(|m| Some(*m) != self.last_mark)
    }

    /// Records a compaction by `mark` that left `len` bytes.
    pub fn compacted(&mut self, mark: (u64, u64), len: u64) {
        self.last_mark = Some(mark);
        self.next = len + self.threshold;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn marks_round_trip_and_bad_ones_are_none() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join(MERGER_MARK);
        assert_eq!(read_mark(&path), None);
        write_mark(&path, 7, 42).expect("write");
        assert_eq!(read_mark(&path), Some((7, 42)));
        std::fs::write(&path, "7 x\n").expect("write");
        assert_eq!(read_mark(&path), None);
        std::fs::write(&path, "1 2 3\n").expect("write");
        assert_eq!(read_mark(&path), None);
        remove_mark(&path).expect("remove");
        remove_mark(&path).expect("absent is fine");
        assert!(!path.exists());
    }

    #[test]
    fn a_log_is_compacted_after_growing_by_the_threshold_and_only_on_progress() {
        let mut s = CompactionSchedule::new(100);
        assert!(!s.outgrown(100));
        assert!(s.outgrown(101));
        assert_eq!(s.fresh(None), None);
        assert_eq!(s.fresh(Some((1, 5))), Some((1, 5)));
        s.compacted((1, 5), 60);
        assert!(!s.outgrown(160));
        assert!(s.outgrown(161));
        // The reader has not moved: nothing to drop, no rewrite.
        assert_eq!(s.fresh(Some((1, 5))), None);
        assert_eq!(s.fresh(Some((1, 9))), Some((1, 9)));
    }
}
