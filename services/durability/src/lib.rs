//! What survives a crash (docs/durability.md): the solver's window journal, the merger's
//! checkpoint, the saved map a later run relocalizes in or extends, the append-only record logs (the frontend's keyframes, the merger's keyframe
//! descriptors), the marks by which each service tells the others what they may drop, and
//! the atomic writes they all rest on. Every file here is written so that a process killed
//! at any moment leaves either the old or the new complete state.

pub mod checkpoint;
pub mod estimated_readout;
pub mod features_log;
pub mod frozen_head;
pub mod log_compaction;
pub mod map_file;
pub mod record_log;
pub mod window_journal;

use std::io::Write;

/// The frontend's log of every keyframe message it sent, in order (length-delimited): a
/// restarted solver replays the ones its predecessor had not turned into windows
/// (docs/durability.md). Its name in the state folder; see [`keyframe_log_path`].
pub const KEYFRAME_LOG: &str = "keyframes.log";

use std::path::{Path, PathBuf};

/// Memory-backed storage for what only a killed process needs and is rewritten too often
/// for the flash: systemd's `RuntimeDirectory=` (`$RUNTIME_DIRECTORY`), else `/dev/shm`;
/// `None` where neither exists.
pub fn memory_backed_dir() -> Option<PathBuf> {
    let runtime = std::env::var_os("RUNTIME_DIRECTORY")
        .and_then(|dirs| std::env::split_paths(&dirs).next())
        .filter(|d| d.is_dir());
    runtime.or_else(|| Some(PathBuf::from("/dev/shm")).filter(|d| d.is_dir()))
}

/// The name of a file of bus namespace `namespace` in [`memory_backed_dir`]: one folder
/// serves every run of the machine.
pub fn memory_backed_name(namespace: &str, file: &str) -> String {
    format!("egoslam-{namespace}-{file}")
}

/// The launcher process id of the `egoslam run` whose memory-backed file is named `name`
/// (its bus namespace is `run<pid>`, or `run<pid>r<n>` for a round started again); `None`
/// for any other file.
pub fn memory_backed_run(name: &str) -> Option<u32> {
    let rest = name.strip_prefix(memory_backed_name("run", "").trim_end_matches('-'))?;
    let digits = rest.find(|c: char| !c.is_ascii_digit())?;
    match &rest[digits..] {
        tail if tail.starts_with('-') || tail.starts_with('r') => rest[..digits].parse().ok(),
        _ => None,
    }
}

/// Where the frontend of bus namespace `namespace` logs its keyframes: in memory-backed
/// storage, since the log is for a killed solver alone (a power cut ends the stream
/// anyway) and holds every keyframe once, ~5 GB per hour of a walk that the flash would
/// wear by; in the state folder of `out` where no such storage exists.
pub fn keyframe_log_path(out: &Path, namespace: &str) -> PathBuf {
    match memory_backed_dir() {
        Some(dir) => dir.join(memory_backed_name(namespace, KEYFRAME_LOG)),
        None => state_dir(out).join(KEYFRAME_LOG),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_is_known_by_its_launcher_in_every_round() {
        assert_eq!(
            memory_backed_run("egoslam-run4242-keyframes.log"),
            Some(4242)
        );
        assert_eq!(
            memory_backed_run("egoslam-run4242r1-frontend.resume"),
            Some(4242)
        );
        assert_eq!(memory_backed_run("egoslam-default-keyframes.log"), None);
        assert_eq!(memory_backed_run("egoslam-run-keyframes.log"), None);
        assert_eq!(memory_backed_run("egoslam-run42x-keyframes.log"), None);
        assert_eq!(memory_backed_run("iox2_something"), None);
    }
}

/// Why a durable file could not be written or read back.
#[derive(Debug, thiserror::Error)]
pub enum DurabilityError {
    /// A file operation failed (the action and the file, then the system's reason).
    #[error("{action} {}", path.display())]
    Io {
        action: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A file is there but is not what egoslam writes (another format or version, a
    /// corrupt record): refused rather than misread.
    #[error("{}: {reason}", path.display())]
    Invalid { path: PathBuf, reason: String },
}

pub type Result<T> = std::result::Result<T, DurabilityError>;

/// Maps an I/O error of `action` on `path` (for `map_err`).
pub(crate) fn io_error(
    action: &'static str,
    path: &Path,
) -> impl FnOnce(std::io::Error) -> DurabilityError {
    let path = path.to_path_buf();
    move |source| DurabilityError::Io {
        action,
        path,
        source,
    }
}

/// A file at `path` that is not what egoslam writes there.
pub(crate) fn invalid(path: &Path, reason: impl Into<String>) -> DurabilityError {
    DurabilityError::Invalid {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

/// The folder of a run's internal state (checkpoint, journal, logs, marks) inside its
/// output folder, apart from the results the user asked for (docs/durability.md).
pub fn state_dir(out: &Path) -> PathBuf {
    out.join("state")
}

/// [`state_dir`], created owner-only (0700: egocentric video's descriptors and patches are
/// private) if it is not there yet.
pub fn create_state_dir(out: &Path) -> Result<PathBuf> {
    use std::os::unix::fs::DirBuilderExt;
    let dir = state_dir(out);
    std::fs::DirBuilder::new()
        .recursive(true)
        .mode(0o700)
        .create(&dir)
        .map_err(io_error("creating", &dir))?;
    Ok(dir)
}

/// Writes `bytes` to `path` via a temporary file and a rename, so readers (and a crash)
/// only ever see the old or the new complete file. The temporary file is `path` with
/// `.tmp` appended: one per target file, so processes writing different files of one
/// folder (`keyframes.tum` by the merger, `keyframes.log` by the frontend) never share it.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(io_error("creating", dir))?;
    }
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = PathBuf::from(tmp);
    let mut f = std::fs::File::create(&tmp).map_err(io_error("creating", &tmp))?;
    f.write_all(bytes).map_err(io_error("writing", &tmp))?;
    f.sync_all().ok();
    std::fs::rename(&tmp, path).map_err(io_error("renaming to", path))
}

/// Replaces the file at `path` with `prefix` followed by its bytes from `offset` on, via
/// [`write_atomically`]: how an append-only log drops its head (the journal with a new
/// header, the keyframe log with none). Only the kept tail is read.
pub fn keep_tail_atomically(path: &Path, offset: u64, prefix: &[u8]) -> Result<()> {
    use std::io::{Read, Seek};
    let mut bytes = prefix.to_vec();
    let mut file = std::fs::File::open(path).map_err(io_error("opening", path))?;
    file.seek(std::io::SeekFrom::Start(offset))
        .and_then(|_| file.read_to_end(&mut bytes))
        .map_err(io_error("reading", path))?;
    write_atomically(path, &bytes)
}
