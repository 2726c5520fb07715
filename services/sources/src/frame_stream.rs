//! The one rule for bad frames: skip, count, log, go on.
//!
//! [`FrameStream`] wraps any [`FrameSource`] and yields only frames the pipeline can use: a
//! frame that is missing, unreadable, undecodable, of another size than the stream's first,
//! or stamped out of order (non-finite, duplicate or decreasing timestamp) is skipped with a
//! warning that names the file and the reason, and counted by reason ([`SkippedFrames`]).
//! Every reader of frames (the replay service, the calibration pre-passes, `localize`) goes
//! through it, so they all skip the same frames.

use crate::reader::{Frame, FrameSource};
use crate::{Layout, SourceError};
use opencv::prelude::*;
use std::collections::BTreeMap;

/// Why a frame was skipped; the names are report.json's keys.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum SkipReason {
    /// The listed file does not exist.
    Missing,
    /// The file exists but cannot be read (a directory, no permission).
    Unreadable,
    /// The bytes are not a whole image (zero bytes, truncated, not an image).
    Decode,
    /// Non-finite, duplicate or decreasing timestamp.
    Timestamp,
    /// A size other than the stream's first frame's.
    Size,
}

impl SkipReason {
    /// The key under `skipped_frames` in report.json.
    pub fn name(self) -> &'static str {
        match self {
            Self::Missing => "missing",
            Self::Unreadable => "unreadable",
            Self::Decode => "decode",
            Self::Timestamp => "timestamp",
            Self::Size => "size",
        }
    }

    /// The reason a per-frame read error is skipped for.
    fn of(error: &SourceError) -> Self {
        match error {
            SourceError::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
                Self::Missing
            }
            SourceError::Io { .. } => Self::Unreadable,
            _ => Self::Decode,
        }
    }
}

/// Frames skipped so far, by reason.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SkippedFrames {
    counts: BTreeMap<SkipReason, u64>,
}

impl SkippedFrames {
    /// Counts one more frame skipped for `reason`.
    pub fn add(&mut self, reason: SkipReason) {
        *self.counts.entry(reason).or_default() += 1;
    }

    /// Frames skipped for `reason`.
    pub fn get(&self, reason: SkipReason) -> u64 {
        self.counts.get(&reason).copied().unwrap_or(0)
    }

    /// Frames skipped for any reason.
    pub fn total(&self) -> u64 {
        self.counts.values().sum()
    }

    /// `(reason name, count)` for every reason that occurred.
    pub fn iter(&self) -> impl Iterator<Item = (&'static str, u64)> + '_ {
        self.counts.iter().map(|(r, n)| (r.name(), *n))
    }
}

/// Options of a [`FrameStream`].
#[derive(Debug, Clone, Copy)]
pub struct FrameStreamOptions {
    /// Bad frames in a row after which the stream ends with an error: a camera or video that
    /// fails on every read would otherwise be skipped through forever. 300 = 10 s at 30 fps.
    pub max_consecutive_bad: u32,
    /// Log skipped frames at warn level (the run) or debug level (a pre-pass reading the
    /// same frames again, which would repeat every warning).
    pub warn: bool,
}

impl Default for FrameStreamOptions {
    fn default() -> Self {
        Self {
            max_consecutive_bad: 300,
            warn: true,
        }
    }
}

/// A [`FrameSource`] that yields only usable frames (see the module documentation).
pub struct FrameStream {
    inner: Box<dyn FrameSource>,
    options: FrameStreamOptions,
    skipped: SkippedFrames,
    consecutive_bad: u32,
    size: Option<(i32, i32)>,
    last_timestamp: Option<f64>,
}

impl FrameStream {
    /// Wraps `inner` with the default options.
    pub fn new(inner: Box<dyn FrameSource>) -> Self {
        Self::with_options(inner, FrameStreamOptions::default())
    }

    pub fn with_options(inner: Box<dyn FrameSource>, options: FrameStreamOptions) -> Self {
        Self {
            inner,
            options,
            skipped: SkippedFrames::default(),
            consecutive_bad: 0,
            size: None,
            last_timestamp: None,
        }
    }

    /// Skipped frames are logged at debug level only (for pre-passes).
    pub fn quiet(mut self) -> Self {
        self.options.warn = false;
        self
    }

    /// Frames skipped so far, by reason.
    pub fn skipped(&self) -> &SkippedFrames {
        &self.skipped
    }

    /// The size every yielded frame has (the first usable frame's), once known.
    pub fn frame_size(&self) -> Option<(i32, i32)> {
        self.size
    }

    fn skip(&mut self, reason: SkipReason, what: &str, problem: &dyn std::fmt::Display) {
        self.skipped.add(reason);
        self.consecutive_bad += 1;
        let reason = reason.name();
        if self.options.warn {
            tracing::warn!(frame = what, reason, "frame skipped: {problem}");
        } else {
            tracing::debug!(frame = what, reason, "frame skipped: {problem}");
        }
    }

    /// Why `frame` cannot be used, if it cannot.
    fn check(&self, frame: &Frame) -> Option<(SkipReason, String)> {
        let t = frame.timestamp;
        if !t.is_finite() {
            return Some((
                SkipReason::Timestamp,
                format!("timestamp {t} is not finite"),
            ));
        }
        if let Some(last) = self.last_timestamp {
            if t == last {
                return Some((SkipReason::Timestamp, format!("duplicate timestamp {t}")));
            }
            if t < last {
                return Some((
                    SkipReason::Timestamp,
                    format!("timestamp {t} is before the previous frame's {last}"),
                ));
            }
        }
        let size = (frame.image.cols(), frame.image.rows());
        match self.size {
            Some(first) if first != size => Some((
                SkipReason::Size,
                format!(
                    "frame is {}x{}, the stream {}x{}",
                    size.0, size.1, first.0, first.1
                ),
            )),
            _ => None,
        }
    }
}

impl FrameSource for FrameStream {
    fn len_hint(&self) -> Option<usize> {
        self.inner.len_hint()
    }

    fn next_frame(&mut self) -> Option<Result<Frame, SourceError>> {
        loop {
            if self.consecutive_bad >= self.options.max_consecutive_bad {
                let path = self.inner.layout().root().to_path_buf();
                let n = self.consecutive_bad;
                self.consecutive_bad = 0;
                return Some(Err(SourceError::TooManyBadFrames { path, frames: n }));
            }
            match self.inner.next_frame()? {
                Ok(frame) => {
                    if let Some((reason, problem)) = self.check(&frame) {
                        let source = frame.source.clone();
                        self.skip(reason, &source, &problem);
                        continue;
                    }
                    self.consecutive_bad = 0;
                    self.last_timestamp = Some(frame.timestamp);
                    self.size
                        .get_or_insert((frame.image.cols(), frame.image.rows()));
                    return Some(Ok(frame));
                }
                Err(e) => {
                    let what = e
                        .path()
                        .map(|p| p.display().to_string())
                        .unwrap_or_default();
                    self.skip(SkipReason::of(&e), &what, &e);
                }
            }
        }
    }

    fn layout(&self) -> &Layout {
        self.inner.layout()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{Mat, CV_8UC1};
    use std::path::PathBuf;

    /// A scripted source: each item a frame `(timestamp, width)` or an error.
    struct Scripted {
        layout: Layout,
        items: std::vec::IntoIter<Result<(f64, i32), SourceError>>,
        index: u64,
    }

    fn scripted(items: Vec<Result<(f64, i32), SourceError>>) -> FrameStream {
        FrameStream::new(Box::new(Scripted {
            layout: Layout::ImageFolder {
                dir: PathBuf::from("/seq"),
            },
            items: items.into_iter(),
            index: 0,
        }))
    }

    impl FrameSource for Scripted {
        fn len_hint(&self) -> Option<usize> {
            None
        }
        fn next_frame(&mut self) -> Option<Result<Frame, SourceError>> {
            let item = self.items.next()?;
            self.index += 1;
            Some(item.map(|(timestamp, width)| Frame {
                index: self.index - 1,
                timestamp,
                image: Mat::new_rows_cols_with_default(4, width, CV_8UC1, 0.into()).expect("mat"),
                source: format!("f{}", self.index - 1),
            }))
        }
        fn layout(&self) -> &Layout {
            &self.layout
        }
    }

    fn io(kind: std::io::ErrorKind) -> SourceError {
        SourceError::Io {
            path: "/seq/x.png".into(),
            source: kind.into(),
        }
    }

    #[test]
    fn every_kind_of_bad_frame_is_skipped_and_counted_by_reason() {
        let mut s = scripted(vec![
            Err(io(std::io::ErrorKind::NotFound)),
            Ok((1.0, 8)),
            Err(SourceError::BadImage {
                path: "/seq/t.png".into(),
            }),
            Ok((f64::INFINITY, 8)),
            Ok((f64::NAN, 8)),
            Ok((1.0, 8)),
            Ok((0.5, 8)),
            Err(io(std::io::ErrorKind::IsADirectory)),
            Ok((2.0, 6)),
            Ok((3.0, 8)),
        ]);
        let kept: Vec<f64> = std::iter::from_fn(|| s.next_frame())
            .map(|f| f.expect("only good frames").timestamp)
            .collect();
        assert_eq!(kept, vec![1.0, 3.0]);
        let k = s.skipped();
        assert_eq!(k.get(SkipReason::Missing), 1);
        assert_eq!(k.get(SkipReason::Decode), 1);
        assert_eq!(k.get(SkipReason::Timestamp), 4);
        assert_eq!(k.get(SkipReason::Unreadable), 1);
        assert_eq!(k.get(SkipReason::Size), 1);
        assert_eq!(k.total(), 8);
    }

    #[test]
    fn a_source_that_only_fails_ends_with_an_error_instead_of_spinning() {
        let bad = (0..1000)
            .map(|_| Err(io(std::io::ErrorKind::PermissionDenied)))
            .collect();
        let mut s = FrameStream::with_options(
            Box::new(Scripted {
                layout: Layout::ImageFolder {
                    dir: PathBuf::from("/seq"),
                },
                items: Vec::into_iter(bad),
                index: 0,
            }),
            FrameStreamOptions {
                max_consecutive_bad: 10,
                warn: false,
            },
        );
        let err = s.next_frame().expect("an item").err().expect("an error");
        assert!(err.to_string().contains("10 frames in a row"), "{err}");
        assert_eq!(s.skipped().total(), 10);
    }
}
