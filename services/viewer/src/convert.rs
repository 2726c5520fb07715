//! egoslam's result messages (`egoslam.v1`) as Foxglove's well-known schemas, so that
//! Foxglove's 3D, plot and log panels show them without a custom schema.

use egoslam_messages::v1 as pb;
use foxglove::messages::{
    log::Level, packed_element_field::NumericType, FrameTransform, Log, PackedElementField,
    PointCloud, Pose, PoseInFrame, PosesInFrame, Quaternion, Timestamp, Vector3,
};

/// The frame every map of segment 0 is drawn in; segment `n > 0` (a map part not yet
/// linked to the first) is drawn in `map_n`, as its poses are in a frame of their own.
pub const MAP_FRAME: &str = "map";
/// The camera frame `/tf` moves, for a 3D panel that follows the wearer.
pub const CAMERA_FRAME: &str = "camera";

/// The frame id of a map segment.
pub fn segment_frame(segment: u32) -> String {
    if segment == 0 {
        MAP_FRAME.to_string()
    } else {
        format!("{MAP_FRAME}_{segment}")
    }
}

/// A capture time in seconds since the epoch (the sequence's own clock) as a Foxglove
/// timestamp; times before 1970 or past 2106 are clamped.
pub fn timestamp(seconds: f64) -> Timestamp {
    Timestamp::saturating_from_epoch_secs_f64(seconds)
}

fn pose(p: &pb::Pose) -> Pose {
    let position = p.position.unwrap_or_default();
    let orientation = p.orientation.unwrap_or(pb::Quaternion {
        w: 1.0,
        ..Default::default()
    });
    Pose {
        position: Some(Vector3 {
            x: position.x,
            y: position.y,
            z: position.z,
        }),
        orientation: Some(Quaternion {
            x: orientation.x,
            y: orientation.y,
            z: orientation.z,
            w: orientation.w,
        }),
    }
}

/// A frame's pose (world_from_camera) in its segment's frame.
pub fn pose_in_frame(p: &pb::Pose) -> PoseInFrame {
    PoseInFrame {
        timestamp: Some(timestamp(p.timestamp_s)),
        frame_id: segment_frame(p.segment_id),
        pose: Some(pose(p)),
    }
}

/// The camera frame's transform from its segment's frame at that pose.
pub fn camera_transform(p: &pb::Pose) -> FrameTransform {
    let Pose {
        position,
        orientation,
    } = pose(p);
    FrameTransform {
        timestamp: Some(timestamp(p.timestamp_s)),
        parent_frame_id: segment_frame(p.segment_id),
        child_frame_id: CAMERA_FRAME.to_string(),
        translation: position,
        rotation: orientation,
    }
}

/// The keyframe trajectory of segment 0 (the map the wearer is in once linked), stamped
/// with its newest keyframe's time.
pub fn keyframe_path(t: &pb::Trajectory) -> PosesInFrame {
    let main: Vec<&pb::Pose> = t.poses.iter().filter(|p| p.segment_id == 0).collect();
    PosesInFrame {
        timestamp: Some(timestamp(
            main.iter().map(|p| p.timestamp_s).fold(0.0, f64::max),
        )),
        frame_id: MAP_FRAME.to_string(),
        poses: main.into_iter().map(pose).collect(),
    }
}

/// Points as a packed cloud of float32 x, y, z in the map frame.
pub fn point_cloud<'a>(
    points: impl ExactSizeIterator<Item = &'a [f32; 3]>,
    time: Timestamp,
) -> PointCloud {
    let mut data = Vec::with_capacity(points.len() * 12);
    for p in points {
        for c in p {
            data.extend_from_slice(&c.to_le_bytes());
        }
    }
    let field = |name: &str, offset: u32| PackedElementField {
        name: name.to_string(),
        offset,
        r#type: NumericType::Float32 as i32,
    };
    PointCloud {
        timestamp: Some(time),
        frame_id: MAP_FRAME.to_string(),
        pose: Some(Pose {
            position: Some(Vector3::default()),
            orientation: Some(Quaternion {
                w: 1.0,
                ..Default::default()
            }),
        }),
        point_stride: 12,
        fields: vec![field("x", 0), field("y", 4), field("z", 8)],
        data: data.into(),
    }
}

/// A service's status as a log line: its state and counts.
pub fn status_log(s: &pb::Status, time: Timestamp) -> Log {
    let state = pb::ServiceState::try_from(s.state).unwrap_or(pb::ServiceState::Unspecified);
    let level = match state {
        pb::ServiceState::Failed => Level::Error,
        _ => Level::Info,
    };
    let mut message = format!(
        "{}: {} frames, {} keyframes, {} windows",
        state.as_str_name(),
        s.frames,
        s.keyframes,
        s.windows
    );
    if !s.message.is_empty() {
        message += &format!(" ({})", s.message);
    }
    Log {
        timestamp: Some(time),
        level: level as i32,
        message,
        name: s.service.clone(),
        file: String::new(),
        line: 0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pb_pose(segment: u32, x: f64) -> pb::Pose {
        pb::Pose {
            frame_id: 7,
            timestamp_s: 1305031102.175304,
            position: Some(pb::Vec3 { x, y: 2.0, z: 3.0 }),
            orientation: Some(pb::Quaternion {
                x: 0.0,
                y: 0.0,
                z: std::f64::consts::FRAC_1_SQRT_2,
                w: std::f64::consts::FRAC_1_SQRT_2,
            }),
            segment_id: segment,
            revision: 0,
            interpolated: false,
            ..Default::default()
        }
    }

    #[test]
    fn a_pose_keeps_its_position_orientation_time_and_segment_frame() {
        let f = pose_in_frame(&pb_pose(0, 1.5));
        let t = f.timestamp.expect("stamped");
        assert_eq!(t.sec(), 1305031102);
        assert!((t.nsec() as f64 - 175_304_000.0).abs() < 1_000.0);
        assert_eq!(f.frame_id, "map");
        let p = f.pose.expect("pose");
        assert_eq!(p.position.map(|v| (v.x, v.y, v.z)), Some((1.5, 2.0, 3.0)));
        assert_eq!(
            p.orientation.map(|q| q.z),
            Some(std::f64::consts::FRAC_1_SQRT_2)
        );
        assert_eq!(pose_in_frame(&pb_pose(2, 0.0)).frame_id, "map_2");
        let tf = camera_transform(&pb_pose(0, 1.5));
        assert_eq!(
            (tf.parent_frame_id.as_str(), tf.child_frame_id.as_str()),
            ("map", "camera")
        );
        assert_eq!(tf.translation.map(|v| v.x), Some(1.5));
    }

    #[test]
    fn the_keyframe_path_holds_the_first_segment_only() {
        let t = pb::Trajectory {
            poses: vec![pb_pose(0, 1.0), pb_pose(1, 5.0), pb_pose(0, 2.0)],
        };
        let path = keyframe_path(&t);
        let xs: Vec<f64> = path
            .poses
            .iter()
            .filter_map(|p| p.position.map(|v| v.x))
            .collect();
        assert_eq!(xs, vec![1.0, 2.0]);
    }

    #[test]
    fn a_point_cloud_packs_little_endian_float_triples() {
        let points = [[1.0f32, -2.0, 0.5], [4.0, 5.0, 6.0]];
        let cloud = point_cloud(points.iter(), Timestamp::new(1, 0));
        assert_eq!(cloud.point_stride, 12);
        assert_eq!(cloud.data.len(), 24);
        let z1 = f32::from_le_bytes(cloud.data[20..24].try_into().expect("4 bytes"));
        assert_eq!(z1, 6.0);
        let y0 = f32::from_le_bytes(cloud.data[4..8].try_into().expect("4 bytes"));
        assert_eq!(y0, -2.0);
        let names: Vec<&str> = cloud.fields.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, ["x", "y", "z"]);
        assert!(cloud
            .fields
            .iter()
            .all(|f| f.r#type == NumericType::Float32 as i32));
    }

    #[test]
    fn a_failed_service_logs_an_error() {
        let s = pb::Status {
            service: "merger".into(),
            state: pb::ServiceState::Failed as i32,
            frames: 3,
            message: "disk full".into(),
            ..Default::default()
        };
        let log = status_log(&s, Timestamp::new(0, 0));
        assert_eq!(log.level, Level::Error as i32);
        assert!(log.message.contains("disk full"), "{}", log.message);
        assert!(log.message.starts_with("SERVICE_STATE_FAILED: 3 frames"));
    }
}
