//! Pure geometry of egoslam: camera models, rigid and similarity transforms, trajectory
//! alignment and accuracy. Nothing here reads files or talks to the bus, so every estimator
//! is unit-tested on synthetic truth.

pub mod alignment;
pub mod camera;
pub mod lens;
pub mod median;
pub mod orientation_error;
pub mod point_uncertainty;
pub mod relative_pose_error;
pub mod structure_error;
pub mod trajectory;

pub use alignment::{
    nearest_rotation, rigid_alignment, rotation_aligning, rotation_aligning_trimmed, umeyama,
    umeyama_ransac, AlignmentError, BearingPair, RobustAlignmentOptions, Similarity,
};
pub use camera::{CameraError, PinholeRadtan};
pub use lens::{LensModel, MAX_TANGENT_PLANE_ANGLE};
pub use median::median;
pub use orientation_error::{orientation_error, OrientationReport};
pub use point_uncertainty::PointInformation;
pub use relative_pose_error::{relative_pose_error, RpeReport};
pub use structure_error::{alignment_from_poses, structure_error, StructureReport};
pub use trajectory::{absolute_trajectory_error, associate, AteReport, StampedPose};
