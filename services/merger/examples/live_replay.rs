//! Replays a live tracker's record (`EGOSLAM_DUMP_LIVE=FILE egoslam run --realtime ...`,
//! docs/merger.md "Live poses") through the tracker with default options and prints each
//! frame's live pose as the service would have published it: a TUM line (`egoslam eval`
//! and ../shared/checks/ate.py read it) followed by the tracking state (0 tracking,
//! 1 rotation, 2 predicted, 3 lost) and the inliers.
//!
//! `cargo run --release -p egoslam-merger --example live_replay RECORD [--no-local-adjustment]
//! > live.tum`
use anyhow::Context;
use egoslam_merger::live_tracking::recording::{parse_line, Recorded};
use egoslam_merger::{LiveTracker, LiveTrackerOptions};

fn main() -> anyhow::Result<()> {
    let path = std::env::args()
        .nth(1)
        .context("usage: live_replay RECORD (written by EGOSLAM_DUMP_LIVE=RECORD egoslam run)")?;
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {path}"))?;
    let mut options = LiveTrackerOptions::default();
    if std::env::args().any(|a| a == "--no-local-adjustment") {
        options.local_adjustment = None;
    }
    let mut tracker = LiveTracker::new(options);
    for (n, line) in text.lines().enumerate() {
        let live = match parse_line(line, n + 1)? {
            Recorded::Map(view) => {
                tracker.set_map(view);
                None
            }
            Recorded::Origin {
                segment,
                camera,
                timestamp,
                tracks,
            } => Some(tracker.begin_at_origin(camera, segment, timestamp, &tracks)),
            Recorded::Frame { timestamp, tracks } => tracker.track(timestamp, &tracks),
        };
        if let Some(l) = live {
            let (p, q) = (l.pose.position, l.pose.rotation.coords);
            println!(
                "{:.6} {} {} {} {} {} {} {} {} {}",
                l.pose.timestamp, p.x, p.y, p.z, q.x, q.y, q.z, q.w, l.state as u8, l.inliers
            );
        }
    }
    Ok(())
}
