//! What survives a crash: the solver's window journal, the merger's checkpoint, the
//! keyframe features log, and their compaction (docs/durability.md).

pub mod checkpoint;
pub mod features_log;
pub mod log_compaction;
pub mod record_log;
pub mod window_journal;
