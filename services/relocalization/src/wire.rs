//! Conversions between wire messages (`egoslam.v1`) and geometry types, for the services
//! and the merger session.

use egoslam_geometry::{PinholeRadtan, StampedPose};
use egoslam_messages::v1 as pb;
use nalgebra::{Quaternion, UnitQuaternion, Vector3};

pub fn vec3_from_pb(v: &Option<pb::Vec3>) -> Vector3<f64> {
    v.as_ref()
        .map_or_else(Vector3::zeros, |v| Vector3::new(v.x, v.y, v.z))
}

pub fn pose_from_pb(p: &pb::Pose) -> StampedPose {
    let q = p
        .orientation
        .as_ref()
        .map_or_else(Quaternion::identity, |q| {
            Quaternion::new(q.w, q.x, q.y, q.z)
        });
    StampedPose {
        timestamp: p.timestamp_s,
        position: vec3_from_pb(&p.position),
        rotation: UnitQuaternion::from_quaternion(q),
    }
}

pub fn vec3_to_pb(v: &Vector3<f64>) -> pb::Vec3 {
    pb::Vec3 {
        x: v.x,
        y: v.y,
        z: v.z,
    }
}

pub fn pose_to_pb(frame_id: u64, segment_id: u32, p: &StampedPose) -> pb::Pose {
    let q = p.rotation.quaternion();
    pb::Pose {
        frame_id,
        timestamp_s: p.timestamp,
        position: Some(vec3_to_pb(&p.position)),
        orientation: Some(pb::Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        }),
        segment_id,
        revision: 0,
        interpolated: false,
        tracking: pb::TrackingState::Refined as i32,
        inliers: 0,
    }
}

/// The camera of a message (a message from before lens models is radial-tangential);
/// `None` when it is not a valid camera or its lens model is unknown to this version.
pub fn camera_from_pb(i: &pb::Intrinsics) -> Option<PinholeRadtan> {
    let mut distortion = [0.0; 5];
    for (slot, v) in distortion.iter_mut().zip(&i.distortion) {
        *slot = *v;
    }
    let lens = crate::saved_map::lens_from_pb(i.lens)?;
    PinholeRadtan::new(i.width, i.height, [i.fx, i.fy, i.cx, i.cy], distortion)
        .and_then(|camera| camera.with_lens(lens))
        .ok()
}
