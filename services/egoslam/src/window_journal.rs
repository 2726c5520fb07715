//! The solver's journal of window messages: written before each message is sent, read by a
//! restarted merger to recover what it had not yet checkpointed (docs/durability.md).
//!
//! Layout: the magic `EGOSLAMJ`, a little-endian `u32` format version (1) and `u64` stream
//! id, then every `WindowSolution` sent, length-delimited (protobuf varint prefix). Record
//! `i` is the message the solver sent with bus sequence number `i`.

use anyhow::{bail, Context};
use egoslam_messages::v1 as pb;
use prost::Message;
use std::io::Write;
use std::path::{Path, PathBuf};

const MAGIC: &[u8; 8] = b"EGOSLAMJ";
const VERSION: u32 = 1;
const HEADER_LEN: usize = 8 + 4 + 8;

/// File name of the journal inside the output folder.
pub const FILE_NAME: &str = "windows.journal";

/// Appends window messages; one per solver process (a new solver starts a new journal).
pub struct JournalWriter {
    path: PathBuf,
    file: std::fs::File,
    buffer: Vec<u8>,
}

impl JournalWriter {
    /// Creates (truncates) the journal for a new stream.
    pub fn create(path: &Path, stream_id: u64) -> anyhow::Result<Self> {
        let mut file = std::fs::File::create(path)
            .with_context(|| format!("creating the window journal {}", path.display()))?;
        let mut header = Vec::with_capacity(HEADER_LEN);
        header.extend_from_slice(MAGIC);
        header.extend_from_slice(&VERSION.to_le_bytes());
        header.extend_from_slice(&stream_id.to_le_bytes());
        file.write_all(&header)
            .with_context(|| format!("writing {}", path.display()))?;
        Ok(Self {
            path: path.to_path_buf(),
            file,
            buffer: Vec::new(),
        })
    }

    /// Reopens the journal of a stream that a restarted solver continues: anything after
    /// the last complete record (`journal.valid_len`) is cut, then messages are appended.
    pub fn resume(path: &Path, journal: &Journal) -> anyhow::Result<Self> {
        let mut file = std::fs::OpenOptions::new()
            .write(true)
            .open(path)
            .with_context(|| format!("reopening the window journal {}", path.display()))?;
        file.set_len(journal.valid_len)
            .and_then(|()| std::io::Seek::seek(&mut file, std::io::SeekFrom::End(0)))
            .with_context(|| format!("trimming {}", path.display()))?;
        Ok(Self {
            path: path.to_path_buf(),
            file,
            buffer: Vec::new(),
        })
    }

    /// Appends one message and hands it to the kernel (and the disk) before returning, so
    /// that a message is in the journal before anyone can have received it.
    pub fn append(&mut self, message: &pb::WindowSolution) -> anyhow::Result<()> {
        self.buffer.clear();
        message.encode_length_delimited(&mut self.buffer)?;
        self.file
            .write_all(&self.buffer)
            .and_then(|()| self.file.sync_data())
            .with_context(|| format!("appending to {}", self.path.display()))
    }
}

/// A journal as read back.
#[derive(Debug)]
pub struct Journal {
    pub stream_id: u64,
    /// Messages in sequence order (index = bus sequence number).
    pub messages: Vec<pb::WindowSolution>,
    /// Bytes up to the end of the last complete record (what a resumed writer keeps).
    pub valid_len: u64,
}

/// Reads a journal. A last record cut short (the solver died while appending) is dropped:
/// that message was never sent. Anything else malformed is an error naming the file.
pub fn read(path: &Path) -> anyhow::Result<Journal> {
    let bytes =
        std::fs::read(path).with_context(|| format!("reading the journal {}", path.display()))?;
    if bytes.len() < HEADER_LEN || &bytes[..8] != MAGIC {
        bail!("{}: not an egoslam window journal", path.display());
    }
    let version = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
    if version != VERSION {
        bail!(
            "{}: journal format version {version}, this egoslam reads {VERSION}",
            path.display()
        );
    }
    let mut id = [0u8; 8];
    id.copy_from_slice(&bytes[12..20]);
    let stream_id = u64::from_le_bytes(id);
    let mut rest = &bytes[HEADER_LEN..];
    let mut messages = Vec::new();
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
        let message = pb::WindowSolution::decode(&cursor[..len])
            .with_context(|| format!("{}: record {} is corrupt", path.display(), messages.len()))?;
        messages.push(message);
        rest = &cursor[len..];
    }
    Ok(Journal {
        stream_id,
        messages,
        valid_len: (bytes.len() - rest.len()) as u64,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn window(id: u64) -> pb::WindowSolution {
        pb::WindowSolution {
            window_id: id,
            stream_id: 42,
            keyframe_ids: vec![id, id + 1],
            ..Default::default()
        }
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
}
