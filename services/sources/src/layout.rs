//! Recognising what kind of sequence a path holds.

use crate::SourceError;
use std::path::{Path, PathBuf};

/// A supported input layout, with the folder or file that holds its frames.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Layout {
    /// TUM RGB-D: a folder with `rgb.txt` ("timestamp path" lines).
    Tum { dir: PathBuf },
    /// KITTI odometry sequence: `image_0/NNNNNN.png` and `times.txt`.
    Kitti { dir: PathBuf },
    /// EuRoC MAV: `cam0/data.csv` and `cam0/data/*.png` under `mav0/`.
    Euroc { cam_dir: PathBuf },
    /// A video file readable by OpenCV's videoio (FFMPEG backend).
    Video { file: PathBuf },
    /// A folder of images, taken in file-name order at a fixed rate.
    ImageFolder { dir: PathBuf },
    /// A live V4L2 camera (`/dev/videoN`), read through OpenCV's V4L2 backend; frames are
    /// stamped with the wall clock when captured.
    Camera { device: PathBuf },
}

/// Whether `path` names a V4L2 capture device.
fn is_camera_device(path: &Path) -> bool {
    use std::os::unix::fs::FileTypeExt;
    path.to_str().is_some_and(|p| p.starts_with("/dev/video"))
        && std::fs::metadata(path).is_ok_and(|m| m.file_type().is_char_device())
}

const VIDEO_EXTENSIONS: &[&str] = &["mp4", "avi", "mkv", "mov", "webm", "m4v", "mpg", "mpeg"];
pub(crate) const IMAGE_EXTENSIONS: &[&str] =
    &["png", "jpg", "jpeg", "bmp", "tif", "tiff", "pgm", "ppm"];

fn has_extension(path: &Path, list: &[&str]) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| list.contains(&e.to_ascii_lowercase().as_str()))
}

pub(crate) fn is_image(path: &Path) -> bool {
    has_extension(path, IMAGE_EXTENSIONS)
}

fn layout_here(dir: &Path) -> Option<Layout> {
    if dir.join("rgb.txt").is_file() {
        return Some(Layout::Tum { dir: dir.into() });
    }
    if dir.join("image_0").is_dir() && dir.join("times.txt").is_file() {
        return Some(Layout::Kitti { dir: dir.into() });
    }
    for cam in [dir.join("mav0/cam0"), dir.join("cam0"), dir.to_path_buf()] {
        if cam.join("data.csv").is_file() && cam.join("data").is_dir() {
            return Some(Layout::Euroc { cam_dir: cam });
        }
    }
    None
}

fn sorted_subdirs(dir: &Path) -> Vec<PathBuf> {
    let mut subdirs: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .map(|e| e.path())
                .filter(|p| p.is_dir())
                .collect()
        })
        .unwrap_or_default();
    subdirs.sort();
    subdirs
}

/// Finds the layout of `path`: the path itself, or the one dataset folder below it (up to
/// four levels, so the root of a downloaded dataset works as well as the sequence folder).
pub fn detect_layout(path: &Path) -> Result<Layout, SourceError> {
    let meta = std::fs::metadata(path).map_err(|e| SourceError::io(path, e))?;
    if is_camera_device(path) {
        return Ok(Layout::Camera {
            device: path.into(),
        });
    }
    if meta.is_file() {
        return if has_extension(path, VIDEO_EXTENSIONS) {
            Ok(Layout::Video { file: path.into() })
        } else {
            Err(SourceError::UnknownLayout { path: path.into() })
        };
    }
    let mut level = vec![path.to_path_buf()];
    for _ in 0..5 {
        let mut found: Vec<Layout> = level.iter().filter_map(|d| layout_here(d)).collect();
        if !found.is_empty() {
            return Ok(found.swap_remove(0));
        }
        level = level.iter().flat_map(|d| sorted_subdirs(d)).collect();
        if level.is_empty() {
            break;
        }
    }
    let has_images = std::fs::read_dir(path)
        .map_err(|e| SourceError::io(path, e))?
        .filter_map(|e| e.ok())
        .any(|e| is_image(&e.path()));
    if has_images {
        Ok(Layout::ImageFolder { dir: path.into() })
    } else {
        Err(SourceError::UnknownLayout { path: path.into() })
    }
}

impl Layout {
    /// The kind's name, as report.json gives it: `tum`, `kitti`, `euroc`, `video`,
    /// `image_folder` or `camera`.
    pub fn kind(&self) -> &'static str {
        match self {
            Layout::Tum { .. } => "tum",
            Layout::Kitti { .. } => "kitti",
            Layout::Euroc { .. } => "euroc",
            Layout::Video { .. } => "video",
            Layout::ImageFolder { .. } => "image_folder",
            Layout::Camera { .. } => "camera",
        }
    }

    /// The folder, file or device the frames are read from.
    pub fn path(&self) -> &Path {
        match self {
            Layout::Tum { dir } | Layout::Kitti { dir } | Layout::ImageFolder { dir } => dir,
            Layout::Euroc { cam_dir } => cam_dir,
            Layout::Video { file } => file,
            Layout::Camera { device } => device,
        }
    }

    /// The folder that holds the sequence (where calibration is looked for first).
    pub fn root(&self) -> &Path {
        match self {
            Layout::Tum { dir } | Layout::Kitti { dir } | Layout::ImageFolder { dir } => dir,
            Layout::Euroc { cam_dir } => cam_dir,
            Layout::Video { file } => file.parent().unwrap_or(Path::new(".")),
            // Calibration of a camera is never searched next to /dev: it must be given.
            Layout::Camera { device } => device,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn detects_each_shared_dataset_from_its_root() {
        let Some(data) = crate::shared_test_data("") else {
            return;
        };
        assert!(matches!(
            detect_layout(&data.join("tum_fr1_rpy")),
            Ok(Layout::Tum { .. })
        ));
        assert!(matches!(
            detect_layout(&data.join("kitti_odometry_00")),
            Ok(Layout::Kitti { .. })
        ));
        assert!(matches!(
            detect_layout(&data.join("euroc_v1_01")),
            Ok(Layout::Euroc { .. })
        ));
    }

    #[test]
    fn unknown_and_missing_paths_are_clear_errors() {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::write(dir.path().join("notes.txt"), "hello").expect("write");
        let err = detect_layout(dir.path()).expect_err("no layout");
        assert!(err.to_string().contains("unknown layout"), "{err}");
        let err = detect_layout(&dir.path().join("nope")).expect_err("missing");
        assert!(err.to_string().contains("nope"), "{err}");
        // A camera that is not there is named, not mistaken for a file.
        let err = detect_layout(Path::new("/dev/video97")).expect_err("no such camera");
        assert!(err.to_string().contains("/dev/video97"), "{err}");
        let vid = dir.path().join("clip.mp4");
        std::fs::write(&vid, b"x").expect("write");
        assert_eq!(
            detect_layout(&vid).expect("video"),
            Layout::Video { file: vid }
        );
    }
}
