//! Decoding the next frames on a second thread while the caller works on the current one.
//!
//! Decoding a 640x480 PNG takes about half as long as tracking it (zlib's inflate and
//! libpng's filters), so a reader that decodes and then tracks on one thread spends a third
//! of its time waiting for the decoder. [`with_read_ahead`] runs the source on a scoped
//! thread that stays a few frames ahead, through a bounded channel.

use crate::{Frame, FrameSource, Layout, SourceError};
use std::sync::mpsc::{sync_channel, Receiver};

/// Runs `read` on a source that yields `source`'s frames, decoded by a second thread that
/// keeps up to `depth` frames ready. The thread reads at most `frames` frames (what `read`
/// may consume), so `source` is never read further than that; it stops as soon as `read`
/// returns. Frames come in the source's order, errors included.
pub fn with_read_ahead<T>(
    source: &mut dyn FrameSource,
    frames: usize,
    depth: usize,
    read: impl FnOnce(&mut dyn FrameSource) -> T,
) -> T {
    let layout = source.layout().clone();
    let len_hint = source.len_hint();
    let (sender, receiver) = sync_channel(depth.max(1));
    std::thread::scope(|scope| {
        scope.spawn(move || {
            for _ in 0..frames {
                let Some(frame) = source.next_frame() else {
                    break;
                };
                // The reader is gone (it took what it needed): stop decoding.
                if sender.send(frame).is_err() {
                    break;
                }
            }
        });
        let mut ahead = Ahead {
            receiver,
            layout,
            len_hint,
        };
        // Returning drops `ahead` and its receiver, which ends the decoding thread before
        // the scope joins it.
        read(&mut ahead)
    })
}

/// The caller's side of [`with_read_ahead`].
struct Ahead {
    receiver: Receiver<Result<Frame, SourceError>>,
    layout: Layout,
    len_hint: Option<usize>,
}

impl FrameSource for Ahead {
    fn len_hint(&self) -> Option<usize> {
        self.len_hint
    }

    fn next_frame(&mut self) -> Option<Result<Frame, SourceError>> {
        // A closed channel: the decoding thread read its `frames` or the source ended.
        self.receiver.recv().ok()
    }

    fn layout(&self) -> &Layout {
        &self.layout
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{Mat, Scalar, CV_8UC1};

    /// A source of `n` blank frames with an error in place of frame `bad`, counting reads.
    struct Counting {
        layout: Layout,
        n: u64,
        bad: u64,
        read: u64,
    }

    impl FrameSource for Counting {
        fn len_hint(&self) -> Option<usize> {
            Some(self.n as usize)
        }

        fn next_frame(&mut self) -> Option<Result<Frame, SourceError>> {
            if self.read == self.n {
                return None;
            }
            let index = self.read;
            self.read += 1;
            if index == self.bad {
                return Some(Err(SourceError::BadImage {
                    path: format!("frame {index}").into(),
                }));
            }
            let image = Mat::new_rows_cols_with_default(2, 2, CV_8UC1, Scalar::all(0.0))
                .expect("a 2x2 image");
            Some(Ok(Frame {
                index,
                timestamp: index as f64 / 30.0,
                image,
                source: format!("frame {index}"),
            }))
        }

        fn layout(&self) -> &Layout {
            &self.layout
        }
    }

    fn counting(n: u64, bad: u64) -> Counting {
        Counting {
            layout: Layout::ImageFolder {
                dir: "frames".into(),
            },
            n,
            bad,
            read: 0,
        }
    }

    #[test]
    fn frames_and_errors_come_in_order_and_the_source_is_read_no_further_than_allowed() {
        let mut source = counting(50, 3);
        let seen = with_read_ahead(&mut source, 10, 4, |ahead| {
            assert_eq!(ahead.len_hint(), Some(50));
            std::iter::from_fn(|| ahead.next_frame())
                .map(|f| f.map(|f| f.index).map_err(|_| ()))
                .collect::<Vec<_>>()
        });
        let expected: Vec<Result<u64, ()>> = (0..10)
            .map(|i| if i == 3 { Err(()) } else { Ok(i) })
            .collect();
        assert_eq!(seen, expected);
        assert_eq!(source.read, 10);
    }

    #[test]
    fn a_reader_that_stops_early_stops_the_decoder() {
        let mut source = counting(1000, u64::MAX);
        let first = with_read_ahead(&mut source, 1000, 4, |ahead| {
            (0..5).filter_map(|_| ahead.next_frame()?.ok()).count()
        });
        assert_eq!(first, 5);
        // The five taken, the channel's four and one blocked in send at most.
        assert!(source.read <= 10, "read {} frames", source.read);
        let short = with_read_ahead(&mut counting(3, u64::MAX), 1000, 4, |ahead| {
            std::iter::from_fn(|| ahead.next_frame()).count()
        });
        assert_eq!(short, 3);
    }
}
