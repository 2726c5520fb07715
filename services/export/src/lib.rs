//! egoslam's results in the formats of the tools users read them with (docs/export.md):
//! [`colmap`] text models (cameras.txt, images.txt, points3D.txt) and [`nerfstudio`]'s
//! transforms.json, both from one [`ExportModel`] built from the map's keyframes,
//! observations and points; the map's points as PLY ([`map_ply`]); trajectories as TUM
//! text ([`tum`]); the calibration as egoslam's YAML ([`camera_yaml`]).

pub mod camera_yaml;
pub mod colmap;
pub mod map_ply;
pub mod model;
pub mod nerfstudio;
pub mod tum;

pub use model::{ExportImage, ExportModel, ExportPoint, Keypoint, MapView};

/// Why an export could not be written.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error("writing {path}: {source}")]
    Write {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
    #[error("nothing to export: {0}")]
    Empty(String),
    #[error("the {format} format has no camera model for a {lens} lens")]
    UnsupportedLens {
        format: &'static str,
        lens: &'static str,
    },
    #[error("reading {path}: {source}")]
    Read {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
}

pub(crate) fn write_file(path: &std::path::Path, text: &str) -> Result<(), ExportError> {
    std::fs::write(path, text).map_err(|source| ExportError::Write {
        path: path.to_path_buf(),
        source,
    })
}
