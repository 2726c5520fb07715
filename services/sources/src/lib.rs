//! Frame sources, calibration and ground truth for egoslam.
//!
//! Each dataset is read in its own published layout (TUM RGB-D, KITTI odometry, EuRoC MAV),
//! plus video files and plain image folders, so users never convert data. Every failure names
//! the file and the problem ([`SourceError`]): a SLAM run that dies on frame 3000 of a bad PNG
//! must say which one.

pub mod calibration;
mod calibration_colmap;
mod calibration_yaml;
pub mod error;
pub mod frame_stream;
pub mod ground_truth;
pub mod layout;
pub mod reader;

pub use calibration::{load_calibration, Calibration};

/// A sequence of `../shared/data` for tests, or `None` (with a message) when absent.
#[cfg(test)]
pub(crate) fn shared_test_data(sub: &str) -> Option<std::path::PathBuf> {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(sub);
    p.exists().then_some(p).or_else(|| {
        // CI (`CI` set, as .ci/run does) always has it: absent there is a failure.
        assert!(
            std::env::var_os("CI").is_none_or(|v| v.is_empty() || v == "false"),
            "../shared/data/{sub} is absent, and CI always has the shared test data"
        );
        eprintln!("skipping: ../shared/data/{sub} is absent");
        None
    })
}
pub use error::SourceError;
pub use frame_stream::{FrameStream, FrameStreamOptions, SkipReason, SkippedFrames};
pub use ground_truth::load_ground_truth;
pub use layout::{detect_layout, Layout};
pub use reader::{image_files, open_source, Frame, FrameSource};
