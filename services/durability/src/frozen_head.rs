//! A file whose head only grows and whose tail is rewritten: trajectory.tum, whose rows of
//! frames retired past the horizon are final (services/merger/src/session/frame_retirement.rs)
//! while the rows after them may still move. Rewriting the whole file at every persist
//! would write a day's trajectory (~140 MB at 30 fps) again and again; this writes the
//! newly final rows once and the live tail.
//!
//! Not atomic, unlike [`crate::write_atomically`]: the tail is truncated and written in
//! place, so a reader or a crash mid-write can see the head with part of the tail. The
//! head's length is recorded in the checkpoint only after the write (the merger persists
//! files first), so a restarted merger cuts the file back to the head it knows and writes
//! the rest again.

use crate::io_error;
use std::io::{Seek, SeekFrom, Write};
use std::path::Path;

/// What [`write_with_frozen_head`] found and left.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrozenHead {
    /// The head's length now, bytes (`head_len` + what was appended to it).
    pub len: u64,
    /// Bytes of the head that were missing from the file (it was shorter than `head_len`:
    /// removed or cut by hand); 0 normally.
    pub missing: u64,
}

/// Keeps the first `head_len` bytes of the file at `path` (created if absent), appends
/// `to_head` to them, then writes `tail` after, replacing whatever followed; synced.
pub fn write_with_frozen_head(
    path: &Path,
    head_len: u64,
    to_head: &[u8],
    tail: &[u8],
) -> crate::Result<FrozenHead> {
    let mut file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(path)
        .map_err(io_error("opening", path))?;
    let found = file
        .metadata()
        .map_err(io_error("reading the length of", path))?
        .len();
    let kept = head_len.min(found);
    file.set_len(kept)
        .and_then(|_| file.seek(SeekFrom::Start(kept)))
        .and_then(|_| file.write_all(to_head))
        .and_then(|_| file.write_all(tail))
        .and_then(|_| file.sync_data())
        .map_err(io_error("writing", path))?;
    Ok(FrozenHead {
        len: kept + to_head.len() as u64,
        missing: head_len - kept,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_head_grows_and_the_tail_is_replaced() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("trajectory.tum");
        let read = || std::fs::read_to_string(&path).expect("read");
        let head = write_with_frozen_head(&path, 0, b"# h\n", b"1\n2\n3\n").expect("write");
        assert_eq!((head.len, read().as_str()), (4, "# h\n1\n2\n3\n"));
        // 1 is final now; 2 and 3 moved, 4 is new.
        let head = write_with_frozen_head(&path, head.len, b"1\n", b"2b\n3b\n4\n").expect("write");
        assert_eq!((head.len, read().as_str()), (6, "# h\n1\n2b\n3b\n4\n"));
        // A tail shorter than the last one leaves nothing of it behind.
        let head = write_with_frozen_head(&path, head.len, b"", b"2c\n").expect("write");
        assert_eq!(
            (head, read().as_str()),
            (FrozenHead { len: 6, missing: 0 }, "# h\n1\n2c\n")
        );
        // A crash after the head grew but before the checkpoint recorded it: the
        // restarted merger's shorter head is kept, the rest written again.
        let crashed = write_with_frozen_head(&path, 6, b"2c\n", b"3\n").expect("write");
        assert_eq!(crashed.len, 9);
        let again = write_with_frozen_head(&path, 6, b"2d\n", b"3d\n").expect("write");
        assert_eq!((again.len, read().as_str()), (9, "# h\n1\n2d\n3d\n"));
        // A file cut by hand: what is left of the head stays, the loss is reported.
        std::fs::write(&path, "# h\n").expect("cut");
        let cut = write_with_frozen_head(&path, 9, b"5\n", b"6\n").expect("write");
        assert_eq!(cut, FrozenHead { len: 6, missing: 5 });
        assert_eq!(read(), "# h\n5\n6\n");
    }
}
