//! Append-only logs of length-delimited protobuf records: the merger's keyframe
//! descriptors (features_log.rs) and the frontend's keyframe messages (keyframes.log, read
//! by a restarted solver). A kill mid-append leaves a torn last record, which a reader
//! drops; anything flushed before survives the process.
//!
//! Layout: the magic `EGOSLAMR` and a little-endian `u32` format version (1), then the
//! records. A log without the header (written before it existed) is read as it is and
//! gets the header when it is next rewritten; a log of another version is refused.

use anyhow::Context;
use prost::Message;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Largest record accepted when reading back (a keyframe message of 10,000 tracks with
/// descriptors is ~700 KB).
const MAX_RECORD_BYTES: usize = 16 << 20;

const MAGIC: &[u8; 8] = b"EGOSLAMR";
const FORMAT_VERSION: u32 = 1;
/// Bytes before the first record of a log with a header.
pub const HEADER_LEN: u64 = 12;

fn header() -> Vec<u8> {
    let mut h = MAGIC.to_vec();
    h.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    h
}

/// An append-only file of length-delimited protobuf records.
pub struct RecordLog {
    path: PathBuf,
    writer: std::io::BufWriter<std::fs::File>,
}

impl RecordLog {
    /// Opens the log at `path` for appending (created if absent).
    pub fn open(path: &Path) -> anyhow::Result<Self> {
        let path = path.to_path_buf();
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .with_context(|| format!("opening {}", path.display()))?;
        let mut log = Self {
            path,
            writer: std::io::BufWriter::new(file),
        };
        if log.len_bytes()? == 0 {
            log.write_header()?;
        }
        Ok(log)
    }

    fn write_header(&mut self) -> anyhow::Result<()> {
        self.writer
            .write_all(&header())
            .with_context(|| format!("writing the header of {}", self.path.display()))
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
        self.flush()?;
        self.writer
            .get_ref()
            .sync_data()
            .with_context(|| format!("syncing {}", self.path.display()))
    }

    /// Bytes in the log, including what is still buffered.
    pub fn len_bytes(&mut self) -> anyhow::Result<u64> {
        self.flush()?;
        Ok(self
            .writer
            .get_ref()
            .metadata()
            .with_context(|| format!("reading the size of {}", self.path.display()))?
            .len())
    }

    /// Drops the records before byte `offset` (a record boundary): the rest is copied,
    /// after the header, to a new file that atomically replaces the log, without decoding a
    /// record. Only the kept tail is read, so the cost does not grow with what is dropped.
    /// Returns the offset at which the kept records now start.
    pub fn cut_before(&mut self, offset: u64) -> anyhow::Result<u64> {
        self.flush()?;
        crate::output::keep_tail_atomically(&self.path, offset, &header())?;
        self.reopen()?;
        Ok(HEADER_LEN)
    }

    /// Replaces the whole log, atomically, by `records` (compaction: the records still
    /// wanted, written once each); appending goes on after them.
    pub fn replace_with<'a, M: Message + 'a>(
        &mut self,
        records: impl IntoIterator<Item = &'a M>,
    ) -> anyhow::Result<()> {
        self.flush()?;
        let mut bytes = header();
        for r in records {
            r.encode_length_delimited(&mut bytes)
                .with_context(|| format!("encoding a record of {}", self.path.display()))?;
        }
        crate::output::write_atomically(&self.path, &bytes)?;
        self.reopen()
    }

    /// Appends to the file now at the log's path (after it was replaced).
    fn reopen(&mut self) -> anyhow::Result<()> {
        let file = std::fs::OpenOptions::new()
            .append(true)
            .open(&self.path)
            .with_context(|| format!("reopening {}", self.path.display()))?;
        self.writer = std::io::BufWriter::new(file);
        Ok(())
    }

    /// Empties the log (a new stream starts a new map).
    pub fn truncate(&mut self) -> anyhow::Result<()> {
        self.flush()?;
        self.writer
            .get_ref()
            .set_len(0)
            .with_context(|| format!("truncating {}", self.path.display()))?;
        self.write_header()
    }
}

/// The records of the log at `path` in order; an absent log is empty, a torn or oversized
/// final record (a kill mid-append) is dropped with a warning, an undecodable one skipped.
pub fn read_records<M: Message + Default>(path: &Path) -> anyhow::Result<Vec<M>> {
    Ok(read_records_at(path)?.into_iter().map(|(_, r)| r).collect())
}

/// [`read_records`] with each record's byte offset in the log.
pub fn read_records_at<M: Message + Default>(path: &Path) -> anyhow::Result<Vec<(u64, M)>> {
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
    };
    let mut out = Vec::new();
    let mut rest = &bytes[..];
    if rest.starts_with(MAGIC) {
        let Some(version) = rest.get(8..12) else {
            // A header torn by a kill right after the file was created: no record yet.
            return Ok(out);
        };
        let version = u32::from_le_bytes([version[0], version[1], version[2], version[3]]);
        if version != FORMAT_VERSION {
            anyhow::bail!(
                "{}: record log format version {version}, this egoslam reads {FORMAT_VERSION} \
                 (and logs without a header)",
                path.display()
            );
        }
        rest = &rest[HEADER_LEN as usize..];
    }
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
            Ok(record) => out.push(((bytes.len() - rest.len()) as u64, record)),
            Err(e) => {
                tracing::warn!(path = %path.display(), error = %e, "invalid record in a log skipped")
            }
        }
        rest = &probe[length..];
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use egoslam_messages::v1 as pb;

    fn keyframe(id: u64) -> pb::Keyframe {
        pb::Keyframe {
            keyframe_id: id,
            ..Default::default()
        }
    }

    #[test]
    fn cutting_at_a_record_keeps_the_rest_and_appending_goes_on() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("keyframes.log");
        let mut log = RecordLog::open(&path).expect("open");
        for id in 0..10 {
            log.append(&keyframe(id)).expect("append");
        }
        log.flush().expect("flush");
        let at: Vec<(u64, pb::Keyframe)> = read_records_at(&path).expect("read");
        assert_eq!(at.len(), 10);
        assert_eq!(at[0].0, HEADER_LEN);
        let before = log.len_bytes().expect("len");
        assert_eq!(log.cut_before(at[6].0).expect("cut"), HEADER_LEN);
        assert_eq!(log.len_bytes().expect("len"), before - at[6].0 + HEADER_LEN);
        log.append(&keyframe(10)).expect("append");
        log.flush().expect("flush");
        let ids: Vec<u64> = read_records::<pb::Keyframe>(&path)
            .expect("read")
            .iter()
            .map(|k| k.keyframe_id)
            .collect();
        assert_eq!(ids, [6, 7, 8, 9, 10]);
    }

    #[test]
    fn a_log_without_header_is_read_and_another_version_refused() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("old.log");
        let mut bytes = Vec::new();
        for id in 0..3 {
            keyframe(id)
                .encode_length_delimited(&mut bytes)
                .expect("encode");
        }
        std::fs::write(&path, &bytes).expect("write");
        let ids: Vec<u64> = read_records::<pb::Keyframe>(&path)
            .expect("read")
            .iter()
            .map(|k| k.keyframe_id)
            .collect();
        assert_eq!(ids, [0, 1, 2]);
        let mut newer = MAGIC.to_vec();
        newer.extend_from_slice(&2u32.to_le_bytes());
        newer.extend_from_slice(&bytes);
        std::fs::write(&path, &newer).expect("write");
        let e = read_records::<pb::Keyframe>(&path).expect_err("version 2");
        assert!(e.to_string().contains("format version 2"), "{e}");
        // Emptied, a log starts over with the header.
        let mut log = RecordLog::open(&path).expect("open");
        log.truncate().expect("truncate");
        log.append(&keyframe(5)).expect("append");
        log.flush().expect("flush");
        let back: Vec<(u64, pb::Keyframe)> = read_records_at(&path).expect("read");
        assert_eq!(back.len(), 1);
        assert_eq!(back[0].0, HEADER_LEN);
    }
}
