//! Frame sources, calibration and ground truth for egoslam.
//!
//! Each dataset is read in its own published layout (TUM RGB-D, KITTI odometry, EuRoC MAV),
//! plus video files and plain image folders, so users never convert data. Every failure names
//! the file and the problem ([`SourceError`]): a SLAM run that dies on frame 3000 of a bad PNG
//! must say which one.

pub mod calibration;
pub mod error;
pub mod ground_truth;
pub mod layout;
pub mod reader;

pub use calibration::{load_calibration, Calibration};
pub use error::SourceError;
pub use ground_truth::load_ground_truth;
pub use layout::{detect_layout, Layout};
pub use reader::{open_source, Frame, FrameSource};
