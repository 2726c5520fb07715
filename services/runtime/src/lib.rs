//! What every egoslam service process (replay, frontend, solver, merger) shares, apart from
//! the bus: [`stats`], the statistics file each writes and the launcher gathers into
//! report.json, with [`latency`] histograms per hop; [`systemd`] readiness and watchdog
//! notifications (kept only while the bus is active); [`memory`], handing freed heap back to the system;
//! [`process_role`], which process of a run a command line is.

pub mod latency;
pub mod memory;
pub mod process_role;
pub mod stats;
pub mod systemd;

pub use latency::LatencyHistogram;
pub use stats::{cpu_seconds, peak_rss_kib, ServiceStats, StatsError};
