//! The merger's keyframe descriptors on disk: an append-only log of length-delimited
//! `KeyframeFeatures` messages beside the checkpoint (docs/durability.md).
//!
//! Descriptors are most of the map's bytes (~40 KB per keyframe). Inside the checkpoint,
//! which is rewritten whole, they made a 12,000-frame walk write 363 MB every 5 s (103 s of
//! its run); appended once each, they cost O(new keyframes). The log is flushed and synced
//! before every checkpoint, so it always covers the windows the checkpoint has applied; a
//! torn record at its end (a kill mid-append) is ignored, and the windows after the
//! checkpoint are re-applied from the solver's journal, which re-appends their features.

use anyhow::Context;
use egoslam_messages::v1 as pb;
use egoslam_relocalization::saved_map::features_from_pb;
use egoslam_relocalization::MapFeature;
use prost::Message;
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

/// File name in the output folder.
pub const FILE_NAME: &str = "keyframe_features.log";

/// Largest record accepted when reading back (a keyframe message of 10,000 tracks with
/// descriptors is ~700 KB).
const MAX_RECORD_BYTES: usize = 16 << 20;

/// An append-only file of length-delimited protobuf records (the features log here, the
/// frontend's keyframe log in keyframe_log.rs).
pub struct RecordLog {
    path: PathBuf,
    writer: std::io::BufWriter<std::fs::File>,
}

/// The features log.
pub type FeaturesLog = RecordLog;

impl RecordLog {
    /// Opens `dir/keyframe_features.log` for appending (created if absent).
    pub fn open(dir: &Path) -> anyhow::Result<Self> {
        Self::open_file(&dir.join(FILE_NAME))
    }

    /// Opens the log at `path` for appending (created if absent).
    pub fn open_file(path: &Path) -> anyhow::Result<Self> {
        let path = path.to_path_buf();
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .with_context(|| format!("opening {}", path.display()))?;
        Ok(Self {
            path,
            writer: std::io::BufWriter::new(file),
        })
    }

    /// Appends one record (buffered; see [`RecordLog::sync`] and [`RecordLog::flush`]).
    pub fn append(&mut self, record: &impl Message) -> anyhow::Result<()> {
        self.writer
            .write_all(&record.encode_length_delimited_to_vec())
            .with_context(|| format!("appending to {}", self.path.display()))
    }

    /// Hands everything appended to the kernel: it survives the process being killed.
    pub fn flush(&mut self) -> anyhow::Result<()> {
        self.writer
            .flush()
            .with_context(|| format!("writing {}", self.path.display()))
    }

    /// Makes everything appended so far durable (before a checkpoint names it applied).
    pub fn sync(&mut self) -> anyhow::Result<()> {
        self.writer.flush()?;
        self.writer
            .get_ref()
            .sync_data()
            .with_context(|| format!("syncing {}", self.path.display()))
    }

    /// Empties the log (a new stream starts a new map).
    pub fn truncate(&mut self) -> anyhow::Result<()> {
        self.writer.flush()?;
        self.writer
            .get_ref()
            .set_len(0)
            .with_context(|| format!("truncating {}", self.path.display()))
    }
}

/// The records of the log at `path` in order; an absent log is empty, a torn or oversized
/// final record (a kill mid-append) is dropped with a warning, an undecodable one skipped.
pub fn read_records<M: Message + Default>(path: &Path) -> anyhow::Result<Vec<M>> {
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
    };
    let mut out = Vec::new();
    let mut rest = &bytes[..];
    while !rest.is_empty() {
        let mut probe = rest;
        let length = match prost::encoding::decode_varint(&mut probe) {
            Ok(l) if (l as usize) <= MAX_RECORD_BYTES && (l as usize) <= probe.len() => l as usize,
            _ => {
                tracing::warn!(path = %path.display(), bytes = rest.len(), "torn record at the end of a log ignored");
                break;
            }
        };
        match M::decode(&probe[..length]) {
            Ok(record) => out.push(record),
            Err(e) => {
                tracing::warn!(path = %path.display(), error = %e, "invalid record in a log skipped")
            }
        }
        rest = &probe[length..];
    }
    Ok(out)
}

/// The features in the log at `dir`, later records replacing earlier ones.
pub fn read(dir: &Path) -> anyhow::Result<BTreeMap<u64, Vec<MapFeature>>> {
    let mut out = BTreeMap::new();
    for r in read_records::<pb::KeyframeFeatures>(&dir.join(FILE_NAME))? {
        match features_from_pb(&r) {
            Some(features) => {
                out.insert(r.keyframe_id, features);
            }
            None => tracing::warn!(
                keyframe = r.keyframe_id,
                "inconsistent features in the log skipped"
            ),
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_come_back_later_ones_win_and_a_torn_tail_is_dropped() {
        let dir = tempfile::tempdir().expect("tempdir");
        let record = |k: u64, fill: u8| pb::KeyframeFeatures {
            keyframe_id: k,
            track_ids: vec![1, 2],
            descriptors: vec![fill; 64],
            x: vec![1.0, 2.0],
            y: vec![3.0, 4.0],
        };
        let mut log = FeaturesLog::open(dir.path()).expect("open");
        log.append(&record(0, 1)).expect("append");
        log.append(&record(1, 2)).expect("append");
        log.append(&record(0, 3)).expect("append");
        log.sync().expect("sync");
        let back = read(dir.path()).expect("read");
        assert_eq!(back.len(), 2);
        assert_eq!(back[&0][0].descriptor, [3; 32]);
        // A kill mid-append leaves half a record.
        let path = dir.path().join(FILE_NAME);
        let mut bytes = std::fs::read(&path).expect("bytes");
        bytes.extend_from_slice(&record(2, 4).encode_length_delimited_to_vec()[..20]);
        std::fs::write(&path, &bytes).expect("write");
        assert_eq!(read(dir.path()).expect("read").len(), 2);
        log.truncate().expect("truncate");
        assert!(read(dir.path()).expect("read").is_empty());
    }
}
