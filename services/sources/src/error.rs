//! The one error type of this crate: every variant names the path it is about.

use std::path::PathBuf;

/// Why a sequence, calibration or ground-truth file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// The path does not exist or cannot be read (the OS error follows in the chain).
    #[error("{path}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The path exists but matches none of the supported layouts.
    #[error("{path}: unknown layout (expected a TUM folder with rgb.txt, a KITTI sequence with image_0/ and times.txt, an EuRoC folder with mav0/cam0/data.csv, a video file or a folder of images)")]
    UnknownLayout { path: PathBuf },
    /// The sequence holds no frames.
    #[error("{path}: empty sequence (no frames listed)")]
    Empty { path: PathBuf },
    /// A line of an index, calibration or ground-truth file could not be parsed.
    #[error("{path}:{line}: {problem}")]
    Parse {
        path: PathBuf,
        line: usize,
        problem: String,
    },
    /// An image could not be decoded (unreadable, truncated, not an image).
    #[error("{path}: cannot decode image (unreadable or truncated)")]
    BadImage { path: PathBuf },
    /// No calibration was given and none could be found next to the sequence.
    #[error("{path}: missing calibration (none found next to the sequence; pass --calib FILE)")]
    MissingCalibration { path: PathBuf },
    /// The calibration's image size differs from the frames'.
    #[error(
        "{path}: calibration is for {calib_width}x{calib_height} but frames are {width}x{height}"
    )]
    CalibrationSize {
        path: PathBuf,
        calib_width: u32,
        calib_height: u32,
        width: u32,
        height: u32,
    },
    /// The calibration values are invalid (e.g. zero focal length).
    #[error("{path}: invalid calibration")]
    BadCalibration {
        path: PathBuf,
        #[source]
        source: egoslam_geometry::CameraError,
    },
    /// OpenCV failed on this file (e.g. a video that cannot be opened).
    #[error("{path}: {message}")]
    OpenCv { path: PathBuf, message: String },
    /// So many frames in a row could not be used that the source is taken to be broken.
    #[error("{path}: {frames} frames in a row could not be used (missing, unreadable or out of order); giving up")]
    TooManyBadFrames { path: PathBuf, frames: u32 },
}

impl SourceError {
    /// The file or folder the error is about.
    pub fn path(&self) -> Option<&std::path::Path> {
        match self {
            Self::Io { path, .. }
            | Self::UnknownLayout { path }
            | Self::Empty { path }
            | Self::Parse { path, .. }
            | Self::BadImage { path }
            | Self::MissingCalibration { path }
            | Self::CalibrationSize { path, .. }
            | Self::BadCalibration { path, .. }
            | Self::OpenCv { path, .. }
            | Self::TooManyBadFrames { path, .. } => Some(path),
        }
    }

    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io {
            path: path.into(),
            source,
        }
    }

    pub(crate) fn parse(path: impl Into<PathBuf>, line: usize, problem: impl Into<String>) -> Self {
        Self::Parse {
            path: path.into(),
            line,
            problem: problem.into(),
        }
    }
}

/// Reads a whole text file, naming it on failure.
pub(crate) fn read_text(path: &std::path::Path) -> Result<String, SourceError> {
    std::fs::read_to_string(path).map_err(|e| SourceError::io(path, e))
}

/// Non-empty, non-comment lines with their 1-based line numbers.
pub(crate) fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

/// Parses whitespace- or comma-separated floats of one line.
pub(crate) fn parse_floats(
    path: &std::path::Path,
    line_no: usize,
    line: &str,
) -> Result<Vec<f64>, SourceError> {
    line.split(|c: char| c.is_whitespace() || c == ',')
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<f64>()
                .map_err(|_| SourceError::parse(path, line_no, format!("not a number: {s:?}")))
        })
        .collect()
}
