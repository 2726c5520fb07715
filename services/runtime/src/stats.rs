//! Per-service statistics, written to `OUT/stats/<service>.json` when a service ends (and
//! periodically), and gathered by the launcher into `report.json`.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What one service did.
#[derive(Debug, Default, Clone, Serialize, Deserialize)]
pub struct ServiceStats {
    pub service: String,
    pub frames: u64,
    pub keyframes: u64,
    pub windows: u64,
    /// Total wall time per stage, milliseconds.
    pub timings_ms: BTreeMap<String, f64>,
    /// Free counters (dropped frames, rejected tracks, failed windows...).
    pub counters: BTreeMap<String, u64>,
    /// Solver only: per window, the largest keyframe displacement from the window's first
    /// keyframe divided by the median point depth (scale-free; 0 for a rotation-only
    /// window). Shows whether motion was invented where the camera stood still.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub window_translations: Vec<f64>,
    /// Peak resident memory of the process so far (Linux VmHWM), kibibytes; 0 if unknown.
    #[serde(default)]
    pub peak_rss_kib: u64,
    /// CPU time of the process so far (user + system, every thread), seconds.
    #[serde(default)]
    pub cpu_s: f64,
    /// Per hop, each frame's time from capture to this service's step (docs/benchmarks.md,
    /// "Pose latency").
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub latency: BTreeMap<String, crate::latency::LatencyHistogram>,
}

/// This process's peak resident set size (VmHWM in /proc/self/status), KiB; 0 elsewhere.
pub fn peak_rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        })
        .unwrap_or(0)
}

/// This process's CPU time so far, user + system over every thread (getrusage), seconds.
pub fn cpu_seconds() -> f64 {
    // SAFETY: getrusage writes the struct it is given and reads nothing else.
    let usage = unsafe {
        let mut usage: libc::rusage = std::mem::zeroed();
        if libc::getrusage(libc::RUSAGE_SELF, &mut usage) != 0 {
            return 0.0;
        }
        usage
    };
    let seconds = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    seconds(usage.ru_utime) + seconds(usage.ru_stime)
}

impl ServiceStats {
    pub fn new(service: &str) -> Self {
        Self {
            service: service.into(),
            ..Self::default()
        }
    }

    /// Runs `f`, adding its wall time to `stage` (and recording a tracing span for it).
    pub fn time<T>(&mut self, stage: &str, f: impl FnOnce() -> T) -> T {
        let _span = tracing::debug_span!("stage", service = %self.service, stage).entered();
        let start = Instant::now();
        let out = f();
        self.add_time(stage, start.elapsed().as_secs_f64() * 1e3);
        out
    }

    /// Called per frame on the hot path: allocates the key only the first time.
    pub fn add_time(&mut self, stage: &str, ms: f64) {
        match self.timings_ms.get_mut(stage) {
            Some(total) => *total += ms,
            None => {
                self.timings_ms.insert(stage.into(), ms);
            }
        }
    }

    /// As [`Self::add_time`], for counters.
    pub fn count(&mut self, counter: &str, n: u64) {
        match self.counters.get_mut(counter) {
            Some(total) => *total += n,
            None => {
                self.counters.insert(counter.into(), n);
            }
        }
    }

    /// Adds the time since `captured_unix_ns` (a frame's capture) to `hop`'s latencies.
    pub fn latency_since(&mut self, hop: &str, captured_unix_ns: u64) {
        match self.latency.get_mut(hop) {
            Some(h) => h.add_since(captured_unix_ns),
            None => {
                let mut h = crate::latency::LatencyHistogram::default();
                h.add_since(captured_unix_ns);
                self.latency.insert(hop.into(), h);
            }
        }
    }

    /// Adds the timings, counters and latencies of a part of this service that kept its
    /// own (a thread).
    pub fn absorb(&mut self, part: ServiceStats) {
        for (stage, ms) in part.timings_ms {
            self.add_time(&stage, ms);
        }
        for (counter, n) in part.counters {
            self.count(&counter, n);
        }
        for (hop, histogram) in part.latency {
            self.latency.entry(hop).or_default().merge(&histogram);
        }
    }

    pub fn path(out: &Path, service: &str) -> PathBuf {
        out.join("stats").join(format!("{service}.json"))
    }

    /// Writes atomically (temp file + rename): a crash never leaves half a file.
    pub fn write(&mut self, out: &Path) -> Result<(), StatsError> {
        self.peak_rss_kib = peak_rss_kib();
        self.cpu_s = cpu_seconds();
        let path = Self::path(out, &self.service);
        let text = serde_json::to_string_pretty(self).map_err(|source| StatsError::Format {
            path: path.clone(),
            source,
        })?;
        egoslam_durability::write_atomically(&path, text.as_bytes())?;
        Ok(())
    }

    pub fn read(out: &Path, service: &str) -> Result<Self, StatsError> {
        let path = Self::path(out, service);
        let text = std::fs::read_to_string(&path).map_err(|source| StatsError::Io {
            path: path.clone(),
            source,
        })?;
        serde_json::from_str(&text).map_err(|source| StatsError::Format { path, source })
    }
}

/// Why a statistics file could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum StatsError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(transparent)]
    Write(#[from] egoslam_durability::DurabilityError),
    #[error("{path}: not a statistics file: {source}")]
    Format {
        path: PathBuf,
        source: serde_json::Error,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_time_counts_the_work_of_every_thread() {
        let before = cpu_seconds();
        // Two threads each doing a fixed amount of work (~0.1 s of CPU time each here,
        // however loaded the machine).
        let busy = || {
            let mut x = 0u64;
            for _ in 0..100_000_000u64 {
                x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
            }
            x
        };
        let other = std::thread::spawn(busy);
        busy();
        other.join().expect("thread");
        let spent = cpu_seconds() - before;
        assert!(spent > 0.05, "{spent} s");
        let mut stats = ServiceStats::new("test");
        let dir = tempfile::tempdir().expect("tempdir");
        stats.write(dir.path()).expect("write");
        assert!(ServiceStats::read(dir.path(), "test").expect("read").cpu_s >= spent);
    }
}
