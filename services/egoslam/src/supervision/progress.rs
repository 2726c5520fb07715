//! Progress on a terminal (indicatif): a bar per long step of `egoslam run` with frames
//! done of the total, the rate and the time left. The calibration passes count the frames
//! they read; the pipeline counts the frames the merger has posed (its status over zenoh,
//! live_view.rs), so the bar ends when the results are in, not when the replay is. Off a
//! terminal (a log file, journald) nothing is drawn and the services' log lines report
//! progress instead.

use egoslam_sources::{with_read_ahead, Frame, FrameSource, Layout, SourceError};
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

/// Runs `read` on `source` under a bar labelled `step` that counts the frames it reads, of
/// the `frames` it reads at most (fewer when the sequence is shorter); `already` were read
/// before (a first frame taken out to check the input). The frames are decoded a few
/// ahead on a second thread (`with_read_ahead`), so that `read` does not wait for the
/// decoder; `source` is read no further than `frames - already`.
pub fn reading_frames<T>(
    step: &str,
    source: &mut dyn FrameSource,
    frames: usize,
    already: u64,
    read: impl FnOnce(&mut dyn FrameSource) -> T,
) -> T {
    /// Frames decoded ahead: enough to absorb one slow file, few enough to hold (640x480
    /// grey: 0.3 MB each).
    const DECODED_AHEAD: usize = 4;
    let total = source.len_hint().map_or(frames, |n| n.min(frames));
    let bar = frames_bar(step, Some(total as u64));
    bar.inc(already);
    let to_read = frames.saturating_sub(already as usize);
    let result = with_read_ahead(source, to_read, DECODED_AHEAD, |ahead| {
        read(&mut Counted {
            inner: ahead,
            bar: &bar,
        })
    });
    bar.finish_and_clear();
    result
}

/// A frame source that moves `bar` by one per frame read.
struct Counted<'a> {
    inner: &'a mut dyn FrameSource,
    bar: &'a ProgressBar,
}

impl FrameSource for Counted<'_> {
    fn len_hint(&self) -> Option<usize> {
        self.inner.len_hint()
    }

    fn next_frame(&mut self) -> Option<Result<Frame, SourceError>> {
        let frame = self.inner.next_frame();
        if frame.is_some() {
            self.bar.inc(1);
        }
        frame
    }

    fn layout(&self) -> &Layout {
        self.inner.layout()
    }
}
