//! Progress on a terminal (indicatif): a bar per long step of `egoslam run` with frames
//! done of the total, the rate and the time left. The pipeline counts the frames the merger has posed (its status over zenoh,
//! live_view.rs), so the bar ends when the results are in, not when the replay is. Off a
//! terminal (a log file, journald) nothing is drawn and the services' log lines report
//! progress instead.

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::io::{IsTerminal, Write};
use std::sync::OnceLock;
use std::time::Duration;

/// Every bar of this process, so that log lines are written above them.
fn bars() -> &'static MultiProgress {
    static BARS: OnceLock<MultiProgress> = OnceLock::new();
    BARS.get_or_init(MultiProgress::new)
}

/// stderr for the log: each line is written with the bars lifted, so that a log line
/// never leaves a half-drawn bar behind.
pub struct LogWriter;

impl Write for LogWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        bars().suspend(|| std::io::stderr().write_all(buf))?;
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}

/// Whether bars are drawn: stderr is a terminal and `EGOSLAM_PROGRESS` is not `off`.
pub fn on_terminal() -> bool {
    std::io::stderr().is_terminal()
        && std::env::var("EGOSLAM_PROGRESS").map_or(true, |v| v != "off")
}

/// A bar of `total` frames (a spinner when unknown) labelled `step`; hidden off a terminal.
pub fn frames_bar(step: &str, total: Option<u64>) -> ProgressBar {
    // Drawn nowhere until it joins the others (a first draw of its own would stay on
    // the screen as a stale line).
    let bar = ProgressBar::with_draw_target(total, ProgressDrawTarget::hidden());
    if !on_terminal() {
        return bar;
    }
    let template = match total {
        Some(_) => "{prefix:>22} [{bar:30}] {pos}/{len} frames, {per_sec}, {eta} left {msg}",
        None => "{prefix:>22} {spinner} {pos} frames, {per_sec} {msg}",
    };
    if let Ok(style) = ProgressStyle::with_template(template) {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_prefix(step.to_string());
    let bar = bars().add(bar);
    bar.enable_steady_tick(Duration::from_millis(250));
    bar
}
