//! The run's files in memory-backed storage (egoslam_durability::memory_backed_dir): the
//! frontend's keyframe log and its resume frame. They take RAM, so the run that made them
//! removes them; the keyframe log goes into the state folder, where the rest of the run's
//! state stays for a look after the run (one write of a log compacted to ~16 MiB, against
//! ~5 GB per hour of video it would have written there during the run).

use egoslam_durability::{keyframe_log_path, memory_backed_dir, memory_backed_run, KEYFRAME_LOG};
use std::path::{Path, PathBuf};

/// The memory-backed files of one round's bus namespace; dropped, the keyframe log moves
/// into the state folder and the resume frame goes.
pub struct RunMemoryFiles {
    out: PathBuf,
    namespace: String,
}

impl RunMemoryFiles {
    pub fn new(out: &Path, namespace: &str) -> Self {
        Self {
            out: out.to_path_buf(),
            namespace: namespace.to_string(),
        }
    }

    /// The files of `namespace` from now on (a round started again has its own).
    pub fn follow(&mut self, namespace: &str) {
        self.namespace = namespace.to_string();
    }

    /// Removes them (a round started again from the first frame has no use for them).
    pub fn discard(&self) {
        if memory_backed_dir().is_none() {
            return; // the keyframe log is in the state folder, as the rest of the state
        }
        let log = keyframe_log_path(&self.out, &self.namespace);
        let resume = egoslam_frontend_service::resume::path(&self.namespace);
        for path in std::iter::once(log).chain(resume) {
            let _ = std::fs::remove_file(path);
        }
    }

    /// Removes the files of runs whose launcher is gone (killed by SIGKILL or the OOM
    /// killer), which nothing else ever would: `egoslam-run<pid>...` of a dead process.
    pub fn remove_stale() {
        let Some(dir) = memory_backed_dir() else {
            return;
        };
        let Ok(entries) = std::fs::read_dir(&dir) else {
            return;
        };
        for entry in entries.flatten() {
            let name = entry.file_name();
            let Some(pid) = name.to_str().and_then(memory_backed_run) else {
                continue;
            };
            if !Path::new(&format!("/proc/{pid}")).exists() {
                tracing::debug!(file = %entry.path().display(), "memory-backed file of a dead run removed");
                let _ = std::fs::remove_file(entry.path());
            }
        }
    }
}

impl Drop for RunMemoryFiles {
    fn drop(&mut self) {
        let log = keyframe_log_path(&self.out, &self.namespace);
        let kept = egoslam_durability::state_dir(&self.out).join(KEYFRAME_LOG);
        if log != kept && log.exists() {
            // Another file system: a rename cannot cross it.
            if let Err(e) = std::fs::copy(&log, &kept) {
                tracing::warn!(log = %log.display(), error = %e, "the keyframe log could not be kept in the state folder");
            }
        }
        self.discard();
    }
}
