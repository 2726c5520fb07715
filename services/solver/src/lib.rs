//! The window solver (paper, sections 3-4). Keyframes are grouped into overlapping temporal
//! windows ([`windowing`]); each window is solved as a global SfM problem.

pub mod windowing;

pub use windowing::{WindowBuilder, WindowOptions};
