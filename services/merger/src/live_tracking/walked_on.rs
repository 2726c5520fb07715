//! A frame no map point places while the wearer walks: its position moved on from an
//! earlier posed frame along the direction the tracks' rays give, by the map's walking pace.
//!
//! Without points in view (after a turn in place, whose rotation-only windows bring no
//! points, or beyond the map's points before the next window arrives) the tracker fits the
//! frame's orientation to the rays and holds the position ([`TrackingState::Rotation`]).
//! When the wearer walks on, the held position falls behind at walking pace until a window
//! with translation arrives, seconds later. With both orientations known, each track seen
//! in an earlier posed frame and in this one gives the relative pose between the two
//! (five-point, `egoslam_solver::relative_pose`, as a window's edges): the turn, and the
//! direction of travel. Its length is what a monocular camera cannot see: the map's recent
//! walking pace times the time between the frames is taken (the constant-pace prior the
//! merger chains a window across a blind turn with, [`crate::speed_continuity`]). The
//! tracks are then triangulated on that baseline, and the next frames are tracked by PnP on
//! them.
//!
//! [`TrackingState::Rotation`]: super::TrackingState::Rotation

use super::own_points::{closest_point, Sighting};
use egoslam_geometry::{rotation_aligning, PinholeRadtan, StampedPose};
use egoslam_solver::relative_pose::{estimate_relative_pose, RelativePoseOptions};
use nalgebra::{UnitQuaternion, Vector3};
use rustc_hash::FxHashMap;

/// A posed frame: its pose and its tracks' rays in its camera frame.
pub(super) type PosedRays<'a> = (&'a StampedPose, &'a FxHashMap<u64, Vector3<f64>>);

/// What [`walked_on`] found: the frame's pose, the tracks triangulated on the baseline, and
/// how many tracks agree with the relative pose.
pub(super) struct Walked {
    /// The posed frame it moved on from.
    pub anchor: StampedPose,
    pub pose: StampedPose,
    pub points: Vec<(u64, Vector3<f64>)>,
    pub inliers: usize,
}

/// When the relative pose is trusted.
pub(super) struct WalkCheck {
    pub min_inliers: usize,
    pub min_inlier_share: f64,
    /// Largest reprojection error of a triangulated track in the frame, pixels.
    pub max_triangulation_error_px: f64,
    /// Least share of the frame's tracks the anchor must share for the frame to be moved:
    /// with fewer, a walk cannot be told from the drift of the tracks that lived through a
    /// turn, and the pose keeps the anchor's position with the relative pose's turn alone
    /// (no track triangulated).
    pub min_track_share: f64,
}

/// The median angle by which the rays of the tracks `anchor` and `now` share miss the
/// rotation that best takes one set onto the other: the parallax a translation leaves
/// (the window solver's test for a translation edge, on rays); `None` with fewer than
/// `min_shared` shared tracks.
pub(super) fn rotation_residual(
    anchor_rays: &FxHashMap<u64, Vector3<f64>>,
    now_rays: &FxHashMap<u64, Vector3<f64>>,
    min_shared: usize,
) -> Option<f64> {
    let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = now_rays
        .iter()
        .filter_map(|(t, r)| anchor_rays.get(t).map(|a| (*r, *a)))
        .collect();
    if pairs.len() < min_shared {
        return None;
    }
    let rotation = rotation_aligning(&pairs);
    crate::median(pairs.iter().map(|(r, a)| (rotation * r).angle(a)).collect())
}

/// `now` (orientation fitted, position held) moved on from `anchor` by `pace` map units per
/// second along the direction its shared tracks give (module doc); `None` when the relative
/// pose is not clear, or when `turned` (a rotation alone fits the frame's rays) and the
/// anchor shares too few tracks to tell a walk from drift (the turn poses the frame then).
pub(super) fn walked_on(
    camera: &PinholeRadtan,
    (anchor, anchor_rays): PosedRays,
    (now, now_rays): PosedRays,
    pace: f64,
    check: &WalkCheck,
    turned: bool,
) -> Option<Walked> {
    let elapsed = now.timestamp - anchor.timestamp;
    if !(pace > 0.0 && elapsed > 0.0) {
        return None;
    }
    // Shared tracks in track order (the RANSAC's sample must not depend on the hash order).
    let mut shared: Vec<(u64, Vector3<f64>, Vector3<f64>)> = now_rays
        .iter()
        .filter_map(|(t, r)| anchor_rays.get(t).map(|a| (*t, *a, *r)))
        .collect();
    shared.sort_by_key(|(t, _, _)| *t);
    if shared.len() < check.min_inliers {
        return None;
    }
    let moved = shared.len() as f64 >= check.min_track_share * now_rays.len() as f64;
    if !moved && turned {
        return None;
    }
    let normalised = |r: &Vector3<f64>| (r.x / r.z, r.y / r.z);
    let (before, after): (Vec<_>, Vec<_>) = shared
        .iter()
        .map(|(_, a, b)| (normalised(a), normalised(b)))
        .unzip();
    let edge =
        estimate_relative_pose(&before, &after, camera.fx, &RelativePoseOptions::default()).ok()?;
    tracing::debug!(
        inliers = edge.inliers,
        matches = edge.matches,
        parallax_px = edge.parallax_px,
        translation = edge.has_translation,
        "walked on"
    );
    if !edge.has_translation
        || edge.inliers < check.min_inliers
        || (edge.inliers as f64) < check.min_inlier_share * edge.matches as f64
    {
        return None;
    }
    // x_now = R x_anchor + t in the cameras' frames: the world turn of `now` and its centre
    // moved by -R_now t, `pace * elapsed` long.
    let rotation = anchor.rotation * UnitQuaternion::from_rotation_matrix(&edge.rotation.inverse());
    let length = if moved { pace * elapsed } else { 0.0 };
    let centre = anchor.position - (rotation * edge.translation) * length;
    let pose = StampedPose {
        timestamp: now.timestamp,
        position: centre,
        rotation,
    };
    let r_cw = rotation.inverse();
    let points = shared
        .iter()
        .filter(|_| moved)
        .filter_map(|(t, a, b)| {
            let first = Sighting {
                centre: anchor.position,
                ray: anchor.rotation * a,
            };
            let x = closest_point(&first, centre, rotation * b)?;
            let seen = camera.project_undistorted(&(r_cw * (x - centre)))?;
            let observed = camera.project_undistorted(b)?;
            ((seen - observed).norm() <= check.max_triangulation_error_px).then_some((*t, x))
        })
        .collect();
    Some(Walked {
        anchor: *anchor,
        pose,
        points,
        inliers: edge.inliers,
    })
}
