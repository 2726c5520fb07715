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
}

impl Default for WindowOptions {
    fn default() -> Self {
        Self {
            size: 20,
            overlap: 5,
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
}

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
        })
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
        self.pending.push(keyframe);
        (self.pending.len() >= self.options.size).then(|| self.emit())
    }

    /// At end of stream: the last, possibly short, window if it holds new keyframes.
    pub fn finish(&mut self) -> Option<Window<K>> {
        (self.pending.len() > self.carried).then(|| self.emit())
    }

    fn emit(&mut self) -> Window<K> {
        let window = Window {
            keyframes: self.pending.clone(),
            overlap: self.carried,
        };
        let keep = self.options.overlap.min(self.pending.len());
        self.pending.drain(..self.pending.len() - keep);
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
            },
            vec![14, 15, 16],
        )
        .expect("valid");
        let again: Vec<Window<u32>> = (17..33).filter_map(|k| resumed.push(k)).collect();
        assert_eq!(again[0], windows[2]);
    }

    #[test]
    fn rejects_overlap_that_cannot_chain() {
        assert!(WindowBuilder::<u8>::new(WindowOptions {
            size: 10,
            overlap: 10
        })
        .is_err());
        assert!(WindowBuilder::<u8>::new(WindowOptions {
            size: 10,
            overlap: 2
        })
        .is_err());
    }
}
