//! What the session's stages cost and counted: wall time per stage and free counters, handed
//! to the merger service's statistics (report.json) after each window.

use std::collections::BTreeMap;
use std::time::Instant;

/// Milliseconds per stage and counters, accumulated until taken.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct Tally {
    pub timings_ms: BTreeMap<String, f64>,
    pub counters: BTreeMap<String, u64>,
}

impl Tally {
    /// Runs `f`, adding its wall time to `stage` (and recording a tracing span for it).
    pub fn time<T>(&mut self, stage: &str, f: impl FnOnce() -> T) -> T {
        let _span = tracing::debug_span!("stage", service = "merger", stage).entered();
        let start = Instant::now();
        let out = f();
        self.add_time(stage, start.elapsed().as_secs_f64() * 1e3);
        out
    }

    /// Adds `ms` to `stage`'s total (tens of calls per window: allocating the key each time
    /// costs nothing next to a window).
    pub fn add_time(&mut self, stage: &str, ms: f64) {
        *self.timings_ms.entry(stage.to_string()).or_default() += ms;
    }

    /// Adds `n` to `counter`.
    pub fn count(&mut self, counter: &str, n: u64) {
        *self.counters.entry(counter.to_string()).or_default() += n;
    }

    /// Everything tallied since the last take, leaving this empty.
    pub fn take(&mut self) -> Tally {
        std::mem::take(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stages_and_counters_add_up_until_taken() {
        let mut tally = Tally::default();
        tally.count("loops_closed", 1);
        tally.count("loops_closed", 2);
        tally.add_time("align", 1.5);
        let seven = tally.time("align", || 7);
        assert_eq!(seven, 7);
        let taken = tally.take();
        assert_eq!(taken.counters["loops_closed"], 3);
        assert!(taken.timings_ms["align"] >= 1.5);
        assert_eq!(tally, Tally::default());
    }
}
