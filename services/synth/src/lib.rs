//! Synthetic egocentric sequences with exact ground truth (issue: "Egocentric test bed"):
//! the paper's scene of textured planes (section "Egocentric Videos", Table 2) and larger
//! indoor scenes, head-like camera paths (the paper's three profiles, a procedural walker,
//! replayed real head trajectories) and a ray-casting renderer that produces grey frames
//! and depth. Pure computation: writing files is the `egoslam synth` command's job.

pub mod fisheye;
pub mod paths;
pub mod photo;
pub mod placement;
pub mod render;
pub mod scene;
pub mod texture;

pub use fisheye::{render_fisheye_frame, FisheyeRenderError};
pub use paths::{CameraPath, PathError, RobustnessEvent, WalkerOptions};
pub use photo::{Photo, PhotoError};
pub use render::{readout_poses, render_frame, Frame, RenderOptions};
pub use scene::{Picture, Plane, Scene};

/// Revision of what the renderer draws for given options: raised whenever the same
/// command renders different frames, so that caches of rendered sequences (`egoslam
/// bench`) know to render again. 2: a rolling shutter's rows span the readout exactly
/// (before, it was rounded to whole path samples: 20.8 ms for 20 at 30 fps).
pub const RENDER_REVISION: u32 = 2;
