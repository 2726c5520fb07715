//! Per-frame latency from capture to each hop, as a histogram: bounded in size however long
//! the run (an hour of 30 fps frames is 108,000 samples), exact to 0.1 ms.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Buckets per millisecond (0.1 ms wide).
const BUCKETS_PER_MS: f64 = 10.0;

/// Latencies of one hop: counts per 0.1 ms bucket (sparse), and the largest.
#[derive(Debug, Default, Clone, PartialEq, Serialize, Deserialize)]
pub struct LatencyHistogram {
    /// Bucket index (latency / 0.1 ms, rounded down) -> frames.
    buckets: BTreeMap<u32, u64>,
    max_ms: f64,
}

/// What report.json gives per hop.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LatencySummary {
    pub frames: u64,
    pub p50_ms: f64,
    pub p95_ms: f64,
    pub max_ms: f64,
}

impl LatencyHistogram {
    /// Adds one frame's latency; a negative one (clocks of two machines) counts as 0.
    pub fn add(&mut self, ms: f64) {
        let ms = if ms.is_finite() { ms.max(0.0) } else { 0.0 };
        let bucket = (ms * BUCKETS_PER_MS).min(f64::from(u32::MAX)) as u32;
        *self.buckets.entry(bucket).or_insert(0) += 1;
        self.max_ms = self.max_ms.max(ms);
    }

    /// Adds the time from `since_unix_ns` to now; nothing when the start is unknown (0).
    pub fn add_since(&mut self, since_unix_ns: u64) {
        if since_unix_ns == 0 {
            return;
        }
        let now = egoslam_bus::unix_now_ns();
        self.add(now.saturating_sub(since_unix_ns) as f64 / 1e6);
    }

    /// Adds another histogram's frames.
    pub fn merge(&mut self, other: &LatencyHistogram) {
        for (bucket, count) in &other.buckets {
            *self.buckets.entry(*bucket).or_insert(0) += count;
        }
        self.max_ms = self.max_ms.max(other.max_ms);
    }

    pub fn frames(&self) -> u64 {
        self.buckets.values().sum()
    }

    /// The upper edge of the bucket holding quantile `q` (0..=1); `None` without frames.
    pub fn quantile_ms(&self, q: f64) -> Option<f64> {
        let n = self.frames();
        if n == 0 {
            return None;
        }
        let rank = ((q.clamp(0.0, 1.0) * n as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (bucket, count) in &self.buckets {
            seen += count;
            if seen >= rank {
                return Some((f64::from(*bucket) + 1.0) / BUCKETS_PER_MS);
            }
        }
        Some(self.max_ms)
    }

    pub fn summary(&self) -> Option<LatencySummary> {
        Some(LatencySummary {
            frames: self.frames(),
            p50_ms: self.quantile_ms(0.5)?,
            p95_ms: self.quantile_ms(0.95)?,
            max_ms: self.max_ms,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_come_from_the_buckets() {
        let mut h = LatencyHistogram::default();
        for i in 0..100 {
            h.add(f64::from(i)); // 0 .. 99 ms
        }
        h.add(-3.0);
        let s = h.summary().expect("frames");
        assert_eq!(s.frames, 101);
        assert!((s.p50_ms - 49.1).abs() < 1e-9, "{}", s.p50_ms);
        assert!((s.p95_ms - 94.1).abs() < 1e-9, "{}", s.p95_ms);
        assert_eq!(s.max_ms, 99.0);
        assert!(LatencyHistogram::default().summary().is_none());
    }
}
