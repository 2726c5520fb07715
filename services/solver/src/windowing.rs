//! Grouping keyframes into overlapping temporal windows (paper, "Temporal Window Generation").
//!
//! A window of K keyframes is solved as one global SfM problem; consecutive windows share O
//! keyframes so that the merger can chain them with a similarity transform.

/// Window size and overlap.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WindowOptions {
    /// K: keyframes per window (default 20; the paper uses 10-30: larger windows constrain
    /// averaging better but drift through long transitive track chains).
    pub size: usize,
    /// O: keyframes shared with the previous window (default 5: Umeyama needs >= 3 centres
    /// and more make the alignment robust to one bad pose).
    pub overlap: usize,
    /// With [`WindowBuilder::with_adaptive_end`]: how many keyframes a window's end may
    /// move before or after K (default 5, so windows stay within 15-25 at K = 20, inside
    /// the paper's 10-30); 0 disables it.
    pub end_slack: usize,
    /// The end moves only when fewer tracks than this are seen by all O keyframes of the
    /// overlap at K (default 100). The overlap that broke the 12,000-frame walk's scale had
    /// 1-31 inlier observations per keyframe in the window before (400-700 elsewhere).
    /// Moving every end to the strongest overlap instead changed windows everywhere and
    /// doubled KITTI's ATE (0.49 -> 0.96 m); with this threshold TUM and KITTI are
    /// unchanged.
    pub min_overlap_tracks: usize,
}

impl Default for WindowOptions {
    fn default() -> Self {
        Self {
            size: 20,
            overlap: 5,
            end_slack: 5,
            min_overlap_tracks: 100,
        }
    }
}

/// Errors of [`WindowBuilder::new`].
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum WindowOptionsError {
    /// The overlap must leave at least one new keyframe per window and be at least 3.
    #[error("window size {size} and overlap {overlap}: need 3 <= overlap < size")]
    BadOverlap { size: usize, overlap: usize },
}

/// Accumulates keyframes (of any type `K`) and hands out windows.
#[derive(Debug)]
pub struct WindowBuilder<K> {
    options: WindowOptions,
    pending: Vec<K>,
    /// Keyframes at the front of `pending` that the previous window already contained.
    carried: usize,
    /// See [`WindowBuilder::with_adaptive_end`].
    adaptive: Option<fn(&[K]) -> usize>,
    /// See [`WindowBuilder::with_track_breaks`]: the shared tracks of two keyframes, and
    /// the fewest that are not a break.
    breaks: Option<(SharedTracks<K>, usize)>,
}

/// Counts the tracks two keyframes share.
type SharedTracks<K> = fn(&K, &K) -> usize;

/// One window: its keyframes and how many of the leading ones the previous window had.
#[derive(Debug, Clone, PartialEq)]
pub struct Window<K> {
    pub keyframes: Vec<K>,
    pub overlap: usize,
}

impl<K: Clone> WindowBuilder<K> {
    /// Checks the options once.
    pub fn new(options: WindowOptions) -> Result<Self, WindowOptionsError> {
        if options.overlap < 3 || options.overlap >= options.size {
            return Err(WindowOptionsError::BadOverlap {
                size: options.size,
                overlap: options.overlap,
            });
        }
        Ok(Self {
            options,
            pending: Vec::new(),
            carried: 0,
            adaptive: None,
            breaks: None,
        })
    }

    /// Lets each window end up to `end_slack` keyframes before or after K where the O
    /// keyframes it will share with the next window are best tied together, when those at
    /// K are not (`min_overlap_tracks`). `strength(overlap)` scores a candidate overlap
    /// (the solver counts the tracks seen by all of its keyframes). The merger chains
    /// windows on the shared keyframes; an overlap that falls in a fast head turn, where
    /// tracks live for a frame or two, gives the map poses resting on a handful of points.
    /// On the rendered 12,000-frame walk one such overlap (1-31 inlier observations per
    /// keyframe, against 400-700 elsewhere) broke the map's scale 17x. Windows then wait
    /// for `end_slack` more keyframes before they are solved.
    pub fn with_adaptive_end(mut self, strength: fn(&[K]) -> usize) -> Self {
        if self.options.end_slack > 0 {
            self.adaptive = Some(strength);
        }
        self
    }

    /// Ends a window at a track break: a keyframe sharing fewer than `min_shared` tracks
    /// with the one before (`shared` counts them) after frames lost to the stream (a
    /// camera stall, a frontend that could not keep up) or a blackout. Tracks only end,
    /// so no keyframe after the break shares more with any before it: no relative pose
    /// can cross it (`RelativePoseOptions::min_matches`), and a window across it falls
    /// into pieces of which only the largest is solved, losing the keyframes of the other
    /// (up to 15 of 20). The keyframes before the break are handed out as a window at once
    /// (if there are at least two, and any the previous window did not have), and the next
    /// window starts at the break with nothing carried: the merger begins a new segment
    /// there and links it back by relocalization.
    pub fn with_track_breaks(mut self, shared: SharedTracks<K>, min_shared: usize) -> Self {
        self.breaks = Some((shared, min_shared));
        self
    }

    /// Adds a keyframe; returns a window when K keyframes are collected.
    /// A builder that continues after a window already emitted (by a predecessor process):
    /// `tail` are that window's last `overlap` keyframes, shared with the next window.
    pub fn resume(options: WindowOptions, tail: Vec<K>) -> Result<Self, WindowOptionsError> {
        let mut builder = Self::new(options)?;
        builder.carried = tail.len();
        builder.pending = tail;
        Ok(builder)
    }

    pub fn push(&mut self, keyframe: K) -> Option<Window<K>> {
        if let (Some((shared, min_shared)), Some(last)) = (self.breaks, self.pending.last()) {
            if shared(last, &keyframe) < min_shared {
                let before =
                    (self.pending.len() >= 2 && self.pending.len() > self.carried).then(|| {
                        Window {
                            keyframes: std::mem::take(&mut self.pending),
                            overlap: self.carried,
                        }
                    });
                self.pending = vec![keyframe];
                self.carried = 0;
                return before;
            }
        }
        self.pending.push(keyframe);
        let Some(strength) = self.adaptive else {
            return (self.pending.len() >= self.options.size).then(|| self.emit());
        };
        let (slack, min_strength) = (self.options.end_slack, self.options.min_overlap_tracks);
        if self.pending.len() < self.options.size + slack {
            return None;
        }
        let (size, overlap) = (self.options.size, self.options.overlap);
        if strength(&self.pending[size - overlap..size]) >= min_strength {
            return Some(self.emit_until(size));
        }
        let lowest = size
            .saturating_sub(slack)
            .max(overlap + 1)
            .max(self.carried + 1);
        // The strongest overlap; ties go to the end nearest K, then the earlier one.
        let end = (lowest..=self.pending.len())
            .max_by_key(|&e| {
                (
                    strength(&self.pending[e - overlap..e]),
                    std::cmp::Reverse(e.abs_diff(size)),
                    std::cmp::Reverse(e),
                )
            })
            .unwrap_or(size);
        Some(self.emit_until(end))
    }

    /// At end of stream: the last, possibly short, window if it holds new keyframes.
    pub fn finish(&mut self) -> Option<Window<K>> {
        (self.pending.len() > self.carried).then(|| self.emit())
    }

    fn emit(&mut self) -> Window<K> {
        self.emit_until(self.pending.len())
    }

    /// Emits `pending[..end]`; the next window starts with its last O keyframes.
    fn emit_until(&mut self, end: usize) -> Window<K> {
        let window = Window {
            keyframes: self.pending[..end].to_vec(),
            overlap: self.carried,
        };
        let keep = self.options.overlap.min(end);
        self.pending.drain(..end - keep);
        self.carried = keep;
        window
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows_overlap_and_cover_every_keyframe_once_as_new() {
        let mut b = WindowBuilder::new(WindowOptions {
            size: 10,
            overlap: 3,
            ..WindowOptions::default()
        })
        .expect("valid");
        let mut windows: Vec<Window<u32>> = (0..33).filter_map(|k| b.push(k)).collect();
        windows.extend(b.finish());
        assert_eq!(windows[0].keyframes, (0..10).collect::<Vec<_>>());
        assert_eq!(windows[0].overlap, 0);
        assert_eq!(windows[1].keyframes, (7..17).collect::<Vec<_>>());
        assert_eq!(windows[1].overlap, 3);
        let last = windows.last().expect("some");
        assert_eq!(*last.keyframes.last().expect("kf"), 32);
        let new: Vec<u32> = windows
            .iter()
            .flat_map(|w| w.keyframes[w.overlap..].to_vec())
            .collect();
        assert_eq!(new, (0..33).collect::<Vec<_>>());
        assert!(b.finish().is_none());
        // A builder resumed after window 1 emits exactly what the original emitted next.
        let mut resumed = WindowBuilder::resume(
            WindowOptions {
                size: 10,
                overlap: 3,
                ..WindowOptions::default()
            },
            vec![14, 15, 16],
        )
        .expect("valid");
        let again: Vec<Window<u32>> = (17..33).filter_map(|k| resumed.push(k)).collect();
        assert_eq!(again[0], windows[2]);
    }

    #[test]
    fn a_track_break_ends_the_window_and_the_next_starts_at_it() {
        // Keyframes are numbers; 13 and 30 share nothing with the keyframe before them
        // (frames lost), 31 nothing with 30 (a lone keyframe between two breaks).
        fn shared(a: &u32, b: &u32) -> usize {
            if [13, 30, 31].contains(b) && *a + 1 == *b {
                0
            } else {
                100
            }
        }
        let mut b = WindowBuilder::new(WindowOptions {
            size: 10,
            overlap: 3,
            end_slack: 0,
            ..WindowOptions::default()
        })
        .expect("valid")
        .with_track_breaks(shared, 30);
        let mut windows: Vec<Window<u32>> = (0..45).filter_map(|k| b.push(k)).collect();
        windows.extend(b.finish());
        let spans: Vec<(u32, u32, usize)> = windows
            .iter()
            .map(|w| (w.keyframes[0], *w.keyframes.last().expect("kf"), w.overlap))
            .collect();
        assert_eq!(
            spans,
            [
                (0, 9, 0),
                (7, 12, 3), // cut short before the break
                (13, 22, 0),
                (20, 29, 3),
                // 27-29 at the break before 30: nothing new, not handed out.
                (31, 40, 0),
                (38, 44, 3),
            ]
        );
        // Keyframe 30 alone between two breaks is in no window; every other keyframe is
        // new in exactly one.
        let new: Vec<u32> = windows
            .iter()
            .flat_map(|w| w.keyframes[w.overlap..].to_vec())
            .collect();
        assert_eq!(new, (0..45).filter(|k| *k != 30).collect::<Vec<_>>());
    }

    #[test]
    fn an_adaptive_end_moves_the_overlap_out_of_a_weak_stretch() {
        // Keyframes are numbers; an overlap is weak where it contains any of 18-22 (a
        // fast turn), strong elsewhere.
        fn strength(overlap: &[u32]) -> usize {
            usize::from(!overlap.iter().any(|k| (18..=22).contains(k)))
        }
        let mut b = WindowBuilder::new(WindowOptions {
            size: 20,
            overlap: 5,
            end_slack: 5,
            min_overlap_tracks: 1,
        })
        .expect("valid")
        .with_adaptive_end(strength);
        let mut windows: Vec<Window<u32>> = (0..60).filter_map(|k| b.push(k)).collect();
        windows.extend(b.finish());
        // Plain K = 20 would share 15-19 (weak); the nearest strong end is 18 (13-17).
        assert_eq!(windows[0].keyframes, (0..18).collect::<Vec<_>>());
        assert_eq!(windows[1].keyframes[..5], [13, 14, 15, 16, 17]);
        assert_eq!(windows[1].overlap, 5);
        // Every keyframe is new in exactly one window, in order.
        let new: Vec<u32> = windows
            .iter()
            .flat_map(|w| w.keyframes[w.overlap..].to_vec())
            .collect();
        assert_eq!(new, (0..60).collect::<Vec<_>>());
        assert!(windows.iter().all(|w| w.keyframes.len() <= 25));
    }

    #[test]
    fn rejects_overlap_that_cannot_chain() {
        assert!(WindowBuilder::<u8>::new(WindowOptions {
            size: 10,
            overlap: 10,
            ..WindowOptions::default()
        })
        .is_err());
        assert!(WindowBuilder::<u8>::new(WindowOptions {
            size: 10,
            overlap: 2,
            ..WindowOptions::default()
        })
        .is_err());
    }
}
