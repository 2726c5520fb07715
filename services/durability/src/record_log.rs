//! Append-only logs of length-delimited protobuf records: the merger's keyframe
//! descriptors (features_log.rs) and the frontend's keyframe messages (keyframes.log, read
//! by a restarted solver). A kill mid-append leaves a torn last record, which a reader
//! drops; anything flushed before survives the process.
//!
//! Layout: the magic `EGOSLAMR` and a little-endian `u32` format version (1), then the
//! records. A log without the header (written before it existed) is read as it is and
//! gets the header when it is next rewritten; a log of another version is refused.

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
    /// Byte offset at which the next record starts (the file's length with what is
    /// buffered).
    end: u64,
}

impl RecordLog {
    /// Opens the log at `path` for appending (created if absent).
    pub fn open(path: &Path) -> crate::Result<Self> {
        let path = path.to_path_buf();
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(crate::io_error("opening", &path))?;
        let mut log = Self {
            path,
            writer: std::io::BufWriter::new(file),
            end: 0,
        };
        log.end = log.len_bytes()?;
        if log.end == 0 {
            log.write_header()?;
        }
        Ok(log)
    }

    fn write_header(&mut self) -> crate::Result<()> {
        self.writer
            .write_all(&header())
            .map_err(crate::io_error("writing the header of", &self.path))?;
        self.end = HEADER_LEN;
        Ok(())
    }

    /// Appends one record (buffered; see [`RecordLog::sync`] and [`RecordLog::flush`]);
    /// returns its byte offset, at which [`LogReader::read_at`] finds it.
    pub fn append(&mut self, record: &impl Message) -> crate::Result<u64> {
        let bytes = record.encode_length_delimited_to_vec();
        self.writer
            .write_all(&bytes)
            .map_err(crate::io_error("appending to", &self.path))?;
        let at = self.end;
        self.end += bytes.len() as u64;
        Ok(at)
    }

    /// A reader of everything appended so far (flushed first).
    pub fn reader(&mut self) -> crate::Result<LogReader> {
        self.flush()?;
        LogReader::open(&self.path)
    }

    /// Hands everything appended to the kernel: it survives the process being killed.
    pub fn flush(&mut self) -> crate::Result<()> {
        self.writer
            .flush()
            .map_err(crate::io_error("writing", &self.path))
    }

    /// Makes everything appended so far durable (before a checkpoint names it applied).
    pub fn sync(&mut self) -> crate::Result<()> {
        self.flush()?;
        self.writer
            .get_ref()
            .sync_data()
            .map_err(crate::io_error("syncing", &self.path))
    }

    /// Bytes in the log, including what is still buffered.
    pub fn len_bytes(&mut self) -> crate::Result<u64> {
        self.flush()?;
        self.end = self
            .writer
            .get_ref()
            .metadata()
            .map_err(crate::io_error("reading the size of", &self.path))?
            .len();
        Ok(self.end)
    }

    /// Drops the records before byte `offset` (a record boundary): the rest is copied,
    /// after the header, to a new file that atomically replaces the log, without decoding a
    /// record. Only the kept tail is read, so the cost does not grow with what is dropped.
    /// Returns the offset at which the kept records now start.
    pub fn cut_before(&mut self, offset: u64) -> crate::Result<u64> {
        self.flush()?;
        crate::keep_tail_atomically(&self.path, offset, &header())?;
        self.reopen()?;
        Ok(HEADER_LEN)
    }

    /// Replaces the whole log, atomically, by what `write` appends to a new one while
    /// reading the current one (compaction: the records still wanted, copied one at a time,
    /// so memory does not grow with the log); appending goes on after them.
    pub fn rewrite(
        &mut self,
        write: impl FnOnce(&mut LogReader, &mut LogWriter) -> crate::Result<()>,
    ) -> crate::Result<()> {
        let mut reader = self.reader()?;
        let mut writer = LogWriter::create(&self.path)?;
        write(&mut reader, &mut writer)?;
        writer.commit()?;
        self.reopen()
    }

    /// Appends to the file now at the log's path (after it was replaced).
    fn reopen(&mut self) -> crate::Result<()> {
        let file = std::fs::OpenOptions::new()
            .append(true)
            .open(&self.path)
            .map_err(crate::io_error("reopening", &self.path))?;
        self.writer = std::io::BufWriter::new(file);
        self.len_bytes().map(|_| ())
    }

    /// Empties the log (a new stream starts a new map).
    pub fn truncate(&mut self) -> crate::Result<()> {
        self.flush()?;
        self.writer
            .get_ref()
            .set_len(0)
            .map_err(crate::io_error("truncating", &self.path))?;
        self.write_header()
    }
}

/// The records of the log at `path` in order; an absent log is empty, a torn or oversized
/// final record (a kill mid-append) is dropped with a warning, an undecodable one skipped.
pub fn read_records<M: Message + Default>(path: &Path) -> crate::Result<Vec<M>> {
    Ok(read_records_at(path)?.into_iter().map(|(_, r)| r).collect())
}

/// [`read_records`] with each record's byte offset in the log.
pub fn read_records_at<M: Message + Default>(path: &Path) -> crate::Result<Vec<(u64, M)>> {
    let mut out = Vec::new();
    for_each_record(path, |at, record| out.push((at, record)))?;
    Ok(out)
}

/// Calls `each` with every record of the log at `path` and its byte offset, in order, one
/// record in memory at a time; as [`read_records`] for an absent log and a torn end.
pub fn for_each_record<M: Message + Default>(
    path: &Path,
    mut each: impl FnMut(u64, M),
) -> crate::Result<()> {
    let mut reader = match LogReader::open(path) {
        Ok(r) => r,
        Err(e) if !path.exists() => {
            tracing::debug!(error = %e, "no log yet");
            return Ok(());
        }
        Err(e) => return Err(e),
    };
    let mut at = reader.first_record()?;
    loop {
        match reader.next_record::<M>(at) {
            Ok(Some((record, next))) => {
                match record {
                    Some(r) => each(at, r),
                    None => {
                        tracing::warn!(path = %path.display(), "invalid record in a log skipped")
                    }
                }
                at = next;
            }
            Ok(None) => return Ok(()),
            Err(NextRecordError::Torn) => {
                tracing::warn!(path = %path.display(), offset = at, "torn record at the end of a log ignored");
                return Ok(());
            }
            Err(NextRecordError::Io(e)) => return Err(crate::io_error("reading", path)(e)),
        }
    }
}

/// Why the record at an offset could not be read.
#[derive(Debug, thiserror::Error)]
pub enum NextRecordError {
    #[error("a torn or oversized record")]
    Torn,
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// Reads records of a log at their byte offsets.
pub struct LogReader {
    path: PathBuf,
    file: std::io::BufReader<std::fs::File>,
    len: u64,
}

impl LogReader {
    /// Opens the log at `path` for reading.
    pub fn open(path: &Path) -> crate::Result<Self> {
        let file = std::fs::File::open(path).map_err(crate::io_error("opening", path))?;
        let len = file
            .metadata()
            .map_err(crate::io_error("reading the size of", path))?
            .len();
        Ok(Self {
            path: path.to_path_buf(),
            file: std::io::BufReader::new(file),
            len,
        })
    }

    /// The offset of the first record: after the header, when the log has one (a log
    /// written before headers existed starts with its first record).
    fn first_record(&mut self) -> crate::Result<u64> {
        use std::io::{Read, Seek};
        let mut head = [0u8; HEADER_LEN as usize];
        self.file
            .seek(std::io::SeekFrom::Start(0))
            .map_err(crate::io_error("reading", &self.path))?;
        let mut got = 0;
        while got < head.len() {
            match self.file.read(&mut head[got..]) {
                Ok(0) => break,
                Ok(n) => got += n,
                Err(e) => return Err(crate::io_error("reading", &self.path)(e)),
            }
        }
        if got < MAGIC.len() || &head[..MAGIC.len()] != MAGIC {
            return Ok(0);
        }
        if got < head.len() {
            // A header torn by a kill right after the file was created: no record yet.
            return Ok(self.len);
        }
        let version = u32::from_le_bytes([head[8], head[9], head[10], head[11]]);
        if version != FORMAT_VERSION {
            return Err(crate::invalid(
                &self.path,
                format!(
                    "record log format version {version}, this egoslam reads {FORMAT_VERSION} \
                     (and logs without a header)"
                ),
            ));
        }
        Ok(HEADER_LEN)
    }

    /// The record at byte `offset` (one that [`RecordLog::append`] returned).
    pub fn read_at<M: Message + Default>(&mut self, offset: u64) -> crate::Result<M> {
        match self.next_record::<M>(offset) {
            Ok(Some((Some(record), _))) => Ok(record),
            Ok(Some((None, _))) => Err(crate::invalid(
                &self.path,
                format!("the record at byte {offset} does not decode"),
            )),
            Ok(None) => Err(crate::invalid(
                &self.path,
                format!("no record at byte {offset}"),
            )),
            Err(NextRecordError::Torn) => Err(crate::invalid(
                &self.path,
                format!("the record at byte {offset} is torn or oversized"),
            )),
            Err(NextRecordError::Io(e)) => Err(crate::io_error("reading", &self.path)(e)),
        }
    }

    /// The record at `offset` (`None` when it does not decode) and the offset of the
    /// next; `None` at the end of the log.
    fn next_record<M: Message + Default>(
        &mut self,
        offset: u64,
    ) -> Result<Option<(Option<M>, u64)>, NextRecordError> {
        use std::io::{Read, Seek};
        if offset >= self.len {
            return Ok(None);
        }
        self.file.seek(std::io::SeekFrom::Start(offset))?;
        let Some((length, varint_len)) = read_length_prefix(&mut self.file)? else {
            return Err(NextRecordError::Torn);
        };
        let start = offset + varint_len;
        if length > MAX_RECORD_BYTES as u64 || start + length > self.len {
            return Err(NextRecordError::Torn);
        }
        let mut bytes = vec![0u8; length as usize];
        self.file.read_exact(&mut bytes)?;
        Ok(Some((M::decode(&bytes[..]).ok(), start + length)))
    }
}

/// The varint length prefix of the record `reader` is at, and the bytes it takes; `None`
/// when the reader ends inside it or it runs past 10 bytes (a torn or foreign record).
pub(crate) fn read_length_prefix(
    reader: &mut impl std::io::Read,
) -> std::io::Result<Option<(u64, u64)>> {
    let mut value = 0u64;
    for taken in 0..10u64 {
        let mut byte = [0u8; 1];
        if reader.read(&mut byte)? == 0 {
            return Ok(None);
        }
        value |= u64::from(byte[0] & 0x7f) << (7 * taken);
        if byte[0] & 0x80 == 0 {
            return Ok(Some((value, taken + 1)));
        }
    }
    Ok(None)
}

/// A new log being written beside the one it replaces ([`RecordLog::rewrite`]).
pub struct LogWriter {
    tmp: PathBuf,
    path: PathBuf,
    writer: std::io::BufWriter<std::fs::File>,
    end: u64,
}

impl LogWriter {
    fn create(path: &Path) -> crate::Result<Self> {
        let mut tmp = path.as_os_str().to_owned();
        tmp.push(".tmp");
        let tmp = PathBuf::from(tmp);
        let file = std::fs::File::create(&tmp).map_err(crate::io_error("creating", &tmp))?;
        let mut writer = std::io::BufWriter::new(file);
        writer
            .write_all(&header())
            .map_err(crate::io_error("writing", &tmp))?;
        Ok(Self {
            tmp,
            path: path.to_path_buf(),
            writer,
            end: HEADER_LEN,
        })
    }

    /// Appends one record; returns its byte offset in the new log.
    pub fn append(&mut self, record: &impl Message) -> crate::Result<u64> {
        let bytes = record.encode_length_delimited_to_vec();
        self.writer
            .write_all(&bytes)
            .map_err(crate::io_error("writing", &self.tmp))?;
        let at = self.end;
        self.end += bytes.len() as u64;
        Ok(at)
    }

    /// Makes the new log durable and puts it in place of the old one.
    fn commit(self) -> crate::Result<()> {
        let file = self
            .writer
            .into_inner()
            .map_err(|e| e.into_error())
            .map_err(crate::io_error("writing", &self.tmp))?;
        file.sync_all()
            .map_err(crate::io_error("syncing", &self.tmp))?;
        std::fs::rename(&self.tmp, &self.path).map_err(crate::io_error("renaming to", &self.path))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use egoslam_messages::internal::v1 as internal;

    fn keyframe(id: u64) -> internal::Keyframe {
        internal::Keyframe {
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
        let at: Vec<(u64, internal::Keyframe)> = read_records_at(&path).expect("read");
        assert_eq!(at.len(), 10);
        assert_eq!(at[0].0, HEADER_LEN);
        let before = log.len_bytes().expect("len");
        assert_eq!(log.cut_before(at[6].0).expect("cut"), HEADER_LEN);
        assert_eq!(log.len_bytes().expect("len"), before - at[6].0 + HEADER_LEN);
        log.append(&keyframe(10)).expect("append");
        log.flush().expect("flush");
        let ids: Vec<u64> = read_records::<internal::Keyframe>(&path)
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
        let ids: Vec<u64> = read_records::<internal::Keyframe>(&path)
            .expect("read")
            .iter()
            .map(|k| k.keyframe_id)
            .collect();
        assert_eq!(ids, [0, 1, 2]);
        let mut newer = MAGIC.to_vec();
        newer.extend_from_slice(&2u32.to_le_bytes());
        newer.extend_from_slice(&bytes);
        std::fs::write(&path, &newer).expect("write");
        let e = read_records::<internal::Keyframe>(&path).expect_err("version 2");
        assert!(e.to_string().contains("format version 2"), "{e}");
        // Emptied, a log starts over with the header.
        let mut log = RecordLog::open(&path).expect("open");
        log.truncate().expect("truncate");
        log.append(&keyframe(5)).expect("append");
        log.flush().expect("flush");
        let back: Vec<(u64, internal::Keyframe)> = read_records_at(&path).expect("read");
        assert_eq!(back.len(), 1);
        assert_eq!(back[0].0, HEADER_LEN);
    }
}
