//! The solver's journal of window messages: written before each message is sent, read by a
//! restarted merger to recover what it had not yet checkpointed (docs/durability.md).
//!
//! Layout: the magic `EGOSLAMJ`, a little-endian `u32` format version (2), `u64` stream id
//! and `u64` first sequence number, then the `WindowSolution`s sent from that one on,
//! length-delimited (protobuf varint prefix): record `i` is the message the solver sent
//! with bus sequence number `first + i`. The first sequence number is 0 until the solver
//! compacts the journal (log_compaction.rs). Version 1 (no first sequence number, always
//! 0) is still read.

use crate::record_log::read_length_prefix;
use egoslam_messages::internal::v1 as internal;
use prost::Message;
use std::io::Write;
use std::path::{Path, PathBuf};

const MAGIC: &[u8; 8] = b"EGOSLAMJ";
const VERSION: u32 = 2;
const HEADER_LEN_V1: usize = 8 + 4 + 8;
const HEADER_LEN: usize = HEADER_LEN_V1 + 8;

fn header(stream_id: u64, first_sequence: u64) -> Vec<u8> {
    let mut header = Vec::with_capacity(HEADER_LEN);
    header.extend_from_slice(MAGIC);
    header.extend_from_slice(&VERSION.to_le_bytes());
    header.extend_from_slice(&stream_id.to_le_bytes());
    header.extend_from_slice(&first_sequence.to_le_bytes());
    header
}

/// File name of the journal inside the output folder.
pub const FILE_NAME: &str = "windows.journal";

/// Appends window messages; one per solver process (a new solver starts a new journal).
pub struct JournalWriter {
    path: PathBuf,
    file: std::fs::File,
    buffer: Vec<u8>,
    stream_id: u64,
    /// Sequence number of the file's first record.
    first_sequence: u64,
    /// Byte offset of each record in the file, oldest first: compaction cuts at one
    /// without reading what it drops.
    record_offsets: std::collections::VecDeque<u64>,
}

impl JournalWriter {
    /// Creates (truncates) the journal for a new stream.
    pub fn create(path: &Path, stream_id: u64) -> crate::Result<Self> {
        let mut file = std::fs::File::create(path)
            .map_err(crate::io_error("creating the window journal", path))?;
        file.write_all(&header(stream_id, 0))
            .map_err(crate::io_error("writing", path))?;
        Ok(Self {
            path: path.to_path_buf(),
            file,
            buffer: Vec::new(),
            stream_id,
            first_sequence: 0,
            record_offsets: Default::default(),
        })
    }

    /// Reopens the journal of a stream that a restarted solver continues: anything after
    /// the last complete record (`journal.valid_len`) is cut, then messages are appended.
    pub fn resume(path: &Path, journal: &Journal) -> crate::Result<Self> {
        let mut file = std::fs::OpenOptions::new()
            .write(true)
            .open(path)
            .map_err(crate::io_error("reopening the window journal", path))?;
        file.set_len(journal.valid_len)
            .and_then(|()| std::io::Seek::seek(&mut file, std::io::SeekFrom::End(0)))
            .map_err(crate::io_error("trimming", path))?;
        Ok(Self {
            path: path.to_path_buf(),
            file,
            buffer: Vec::new(),
            stream_id: journal.stream_id,
            first_sequence: journal.first_sequence,
            record_offsets: journal.record_offsets.iter().copied().collect(),
        })
    }

    /// Bytes in the journal file.
    pub fn len_bytes(&self) -> crate::Result<u64> {
        Ok(self
            .file
            .metadata()
            .map_err(crate::io_error("reading the size of", &self.path))?
            .len())
    }

    /// Drops the records before `sequence` (a merger checkpoint holds them), always keeping
    /// the last one: a restarted solver continues after it. The file is rewritten
    /// atomically (a reader sees the old or the new journal, both holding every record from
    /// `sequence` on). Returns the number of records dropped.
    pub fn compact_before(&mut self, sequence: u64) -> crate::Result<u64> {
        let records = self.record_offsets.len() as u64;
        let keep_from = sequence.min((self.first_sequence + records).saturating_sub(1));
        if keep_from <= self.first_sequence {
            return Ok(0);
        }
        let dropped = keep_from - self.first_sequence;
        self.record_offsets.drain(..dropped as usize);
        let cut = self.record_offsets.front().copied().unwrap_or(0);
        crate::keep_tail_atomically(&self.path, cut, &header(self.stream_id, keep_from))?;
        self.file = std::fs::OpenOptions::new()
            .append(true)
            .open(&self.path)
            .map_err(crate::io_error("reopening", &self.path))?;
        for offset in &mut self.record_offsets {
            *offset = *offset - cut + HEADER_LEN as u64;
        }
        self.first_sequence = keep_from;
        Ok(dropped)
    }

    /// Appends one message and hands it to the kernel (and the disk) before returning, so
    /// that a message is in the journal before anyone can have received it.
    pub fn append(&mut self, message: &internal::WindowSolution) -> crate::Result<()> {
        let offset = self.len_bytes()?;
        self.buffer.clear();
        // A Vec grows as needed: encoding cannot run out of room.
        message
            .encode_length_delimited(&mut self.buffer)
            .map_err(|e| crate::invalid(&self.path, format!("encoding a window: {e}")))?;
        self.file
            .write_all(&self.buffer)
            .and_then(|()| self.file.sync_data())
            .map_err(crate::io_error("appending to", &self.path))?;
        self.record_offsets.push_back(offset);
        Ok(())
    }
}

/// A journal as read back.
#[derive(Debug)]
pub struct Journal {
    pub stream_id: u64,
    /// Bus sequence number of `messages[0]` (0 unless the journal was compacted).
    pub first_sequence: u64,
    /// Messages in sequence order (index = bus sequence number - `first_sequence`).
    pub messages: Vec<internal::WindowSolution>,
    /// Byte offset of each message's record in the file.
    pub record_offsets: Vec<u64>,
    /// Bytes up to the end of the last complete record (what a resumed writer keeps).
    pub valid_len: u64,
}

impl Journal {
    /// The sequence number the next message gets (how many the stream has sent).
    pub fn next_sequence(&self) -> u64 {
        self.first_sequence + self.messages.len() as u64
    }

    /// The message with bus sequence number `sequence`, if the journal holds it.
    pub fn message(&self, sequence: u64) -> Option<&internal::WindowSolution> {
        let index = usize::try_from(sequence.checked_sub(self.first_sequence)?).ok()?;
        self.messages.get(index)
    }
}

/// Length of the header of the journal `bytes` (by its version); an error for anything
/// that is not a journal this egoslam reads.
fn header_len(bytes: &[u8], path: &Path) -> crate::Result<usize> {
    if bytes.len() < HEADER_LEN_V1 || &bytes[..8] != MAGIC {
        return Err(crate::invalid(path, "not an egoslam window journal"));
    }
    let version = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
    match version {
        1 => Ok(HEADER_LEN_V1),
        2 if bytes.len() >= HEADER_LEN => Ok(HEADER_LEN),
        2 => Err(crate::invalid(path, "journal header cut short")),
        _ => Err(crate::invalid(
            path,
            format!("journal format version {version}, this egoslam reads 1 and {VERSION}"),
        )),
    }
}

/// The header at the start of `bytes`: its length, the stream id and the first record's
/// sequence number (0 in version 1).
fn parse_header(bytes: &[u8], path: &Path) -> crate::Result<(usize, u64, u64)> {
    let header_len = header_len(bytes, path)?;
    let word = |at: usize| {
        let mut w = [0u8; 8];
        w.copy_from_slice(&bytes[at..at + 8]);
        u64::from_le_bytes(w)
    };
    let first_sequence = if header_len == HEADER_LEN {
        word(20)
    } else {
        0
    };
    Ok((header_len, word(12), first_sequence))
}

/// Reads a journal. A last record cut short (the solver died while appending) is dropped:
/// that message was never sent. Anything else malformed is an error naming the file.
pub fn read(path: &Path) -> crate::Result<Journal> {
    let bytes = std::fs::read(path).map_err(crate::io_error("reading the journal", path))?;
    let (header_len, stream_id, first_sequence) = parse_header(&bytes, path)?;
    let mut rest = &bytes[header_len..];
    let mut messages = Vec::new();
    let mut record_offsets = Vec::new();
    while !rest.is_empty() {
        let mut cursor = rest;
        let Ok(len) = prost::encoding::decode_varint(&mut cursor) else {
            break;
        };
        let Ok(len) = usize::try_from(len) else { break };
        if cursor.len() < len {
            tracing::warn!(path = %path.display(), records = messages.len(), "journal ends in a partial record (ignored)");
            break;
        }
        let message = internal::WindowSolution::decode(&cursor[..len]).map_err(|e| {
            crate::invalid(path, format!("record {} is corrupt ({e})", messages.len()))
        })?;
        messages.push(message);
        record_offsets.push((bytes.len() - rest.len()) as u64);
        rest = &cursor[len..];
    }
    Ok(Journal {
        stream_id,
        first_sequence,
        messages,
        record_offsets,
        valid_len: (bytes.len() - rest.len()) as u64,
    })
}

/// Reads the one message with bus sequence number `sequence` of stream `stream_id`
/// without loading the journal: the header, then record lengths, skipping to the record.
/// `Ok(None)` when the journal is of another stream or does not (or no longer) hold it.
/// Safe while the solver appends (the record was whole before its message was sent) or
/// compacts (a rename: the file opened holds every record from the merger's mark on).
pub fn read_one(
    path: &Path,
    stream_id: u64,
    sequence: u64,
) -> crate::Result<Option<internal::WindowSolution>> {
    use std::io::{BufReader, Read, Seek, SeekFrom};
    let file = std::fs::File::open(path).map_err(crate::io_error("opening the journal", path))?;
    let mut reader = BufReader::new(file);
    let mut head = [0u8; HEADER_LEN];
    let read = reader
        .read(&mut head)
        .map_err(crate::io_error("reading the journal", path))?;
    let (header_len, journal_stream, first_sequence) = parse_header(&head[..read], path)?;
    if journal_stream != stream_id || sequence < first_sequence {
        return Ok(None);
    }
    let io = || crate::io_error("reading the journal", path);
    reader
        .seek(SeekFrom::Start(header_len as u64))
        .map_err(io())?;
    for _ in first_sequence..sequence {
        let Some((len, _)) = read_length_prefix(&mut reader).map_err(io())? else {
            return Ok(None);
        };
        let len = i64::try_from(len).map_err(|_| crate::invalid(path, "record length"))?;
        reader.seek_relative(len).map_err(io())?;
    }
    let Some((len, _)) = read_length_prefix(&mut reader).map_err(io())? else {
        return Ok(None);
    };
    let len = usize::try_from(len).map_err(|_| crate::invalid(path, "record length"))?;
    let mut record = vec![0u8; len];
    if reader.read_exact(&mut record).is_err() {
        return Ok(None); // cut short: not sent yet
    }
    let message = internal::WindowSolution::decode(record.as_slice())
        .map_err(|e| crate::invalid(path, format!("record {sequence} is corrupt ({e})")))?;
    Ok(Some(message))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn window(id: u64) -> internal::WindowSolution {
        internal::WindowSolution {
            window_id: id,
            stream_id: 42,
            keyframe_ids: vec![id, id + 1],
            ..Default::default()
        }
    }

    #[test]
    fn one_message_is_read_by_its_sequence_number_also_after_compaction() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join(FILE_NAME);
        let mut w = JournalWriter::create(&path, 42).expect("create");
        for i in 0..5 {
            w.append(&window(i)).expect("append");
        }
        for i in 0..5 {
            assert_eq!(read_one(&path, 42, i).expect("read"), Some(window(i)));
        }
        assert_eq!(read_one(&path, 42, 5).expect("read"), None, "not sent yet");
        assert_eq!(read_one(&path, 7, 1).expect("read"), None, "another stream");
        w.compact_before(3).expect("compact");
        assert_eq!(
            read_one(&path, 42, 2).expect("read"),
            None,
            "compacted away"
        );
        assert_eq!(read_one(&path, 42, 3).expect("read"), Some(window(3)));
        assert_eq!(read_one(&path, 42, 4).expect("read"), Some(window(4)));
        // A record cut short (the solver died appending it) was never sent.
        w.append(&window(5)).expect("append");
        let full = std::fs::read(&path).expect("bytes");
        std::fs::write(&path, &full[..full.len() - 3]).expect("truncate");
        assert_eq!(read_one(&path, 42, 5).expect("read"), None);
        assert_eq!(read_one(&path, 42, 4).expect("read"), Some(window(4)));
    }

    #[test]
    fn round_trip_and_a_cut_short_tail() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join(FILE_NAME);
        let mut w = JournalWriter::create(&path, 42).expect("create");
        for i in 0..3 {
            w.append(&window(i)).expect("append");
        }
        let j = read(&path).expect("read");
        assert_eq!(j.stream_id, 42);
        assert_eq!(j.messages, (0..3).map(window).collect::<Vec<_>>());
        // A crash mid-append leaves a partial record: it is dropped, the rest kept.
        let full = std::fs::read(&path).expect("bytes");
        std::fs::write(&path, &full[..full.len() - 3]).expect("truncate");
        assert_eq!(read(&path).expect("read").messages.len(), 2);
        std::fs::write(&path, b"garbage").expect("write");
        let e = read(&path).expect_err("not a journal");
        assert!(
            e.to_string().contains("not an egoslam window journal"),
            "{e}"
        );
    }

    #[test]
    fn compaction_keeps_the_tail_and_appending_goes_on() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join(FILE_NAME);
        let mut w = JournalWriter::create(&path, 42).expect("create");
        for i in 0..5 {
            w.append(&window(i)).expect("append");
        }
        let before = w.len_bytes().expect("len");
        assert_eq!(w.compact_before(3).expect("compact"), 3);
        assert!(w.len_bytes().expect("len") < before);
        // Nothing more to drop before 3; a mark past the end keeps the last record.
        assert_eq!(w.compact_before(3).expect("compact"), 0);
        w.append(&window(5)).expect("append");
        let j = read(&path).expect("read");
        assert_eq!((j.stream_id, j.first_sequence), (42, 3));
        assert_eq!(j.next_sequence(), 6);
        assert_eq!(j.message(2), None);
        assert_eq!(j.message(4), Some(&window(4)));
        assert_eq!(j.message(6), None);
        assert_eq!(w.compact_before(100).expect("compact"), 2);
        let j = read(&path).expect("read");
        assert_eq!((j.first_sequence, j.messages.clone()), (5, vec![window(5)]));
        // A resumed writer knows where the file starts.
        let mut resumed = JournalWriter::resume(&path, &j).expect("resume");
        resumed.append(&window(6)).expect("append");
        assert_eq!(resumed.compact_before(7).expect("compact"), 1);
        assert_eq!(read(&path).expect("read").message(6), Some(&window(6)));
    }

    #[test]
    fn version_1_journals_are_read_from_sequence_0() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join(FILE_NAME);
        let mut bytes = Vec::new();
        bytes.extend_from_slice(MAGIC);
        bytes.extend_from_slice(&1u32.to_le_bytes());
        bytes.extend_from_slice(&9u64.to_le_bytes());
        window(0)
            .encode_length_delimited(&mut bytes)
            .expect("encode");
        std::fs::write(&path, &bytes).expect("write");
        let j = read(&path).expect("read");
        assert_eq!((j.stream_id, j.first_sequence), (9, 0));
        assert_eq!(j.message(0), Some(&window(0)));
        bytes[8] = 3;
        std::fs::write(&path, &bytes).expect("write");
        let e = read(&path).expect_err("version 3");
        assert!(e.to_string().contains("version 3"), "{e}");
    }
}
