//! The merger's current results in one place: keyframe and frame poses (with revisions),
//! points; written to files and published over zenoh from the same values.

use crate::convert::{pose_to_pb, vec3_to_pb};
use crate::output::{ply_text, tum_text, write_atomically};
use egoslam_egress::Egress;
use egoslam_geometry::StampedPose;
use egoslam_merger::{interpolate_frames, MapBuilder};
use egoslam_messages::v1 as pb;
use nalgebra::Vector3;
use std::collections::BTreeMap;
use std::path::Path;

/// Every frame known to the merger and which keyframe is which frame.
#[derive(Default)]
pub struct FrameIndex {
    /// frame id -> timestamp
    pub frames: BTreeMap<u64, f64>,
    /// keyframe id -> frame id
    pub keyframe_frames: BTreeMap<u64, u64>,
}

impl FrameIndex {
    pub fn add_stamp(&mut self, k: &pb::KeyframeStamp) {
        self.frames.insert(k.frame_id, k.timestamp_s);
        self.keyframe_frames.insert(k.keyframe_id, k.frame_id);
        for (id, t) in k
            .frames_since_previous_ids
            .iter()
            .zip(&k.frames_since_previous_timestamps_s)
        {
            self.frames.insert(*id, *t);
        }
    }
}

/// A posed frame.
#[derive(Debug, Clone, Copy)]
pub struct PosedFrame {
    pub frame_id: u64,
    pub segment: u32,
    pub pose: StampedPose,
    pub interpolated: bool,
}

/// The results at one moment.
pub struct MapState {
    pub keyframes: Vec<PosedFrame>,
    pub frames: Vec<PosedFrame>,
    pub points: Vec<(u64, Vector3<f64>)>,
}

impl MapState {
    pub fn of(map: &MapBuilder, index: &FrameIndex) -> Self {
        let mut keyframes: Vec<PosedFrame> = map
            .keyframes()
            .map(|(kf, segment, pose)| PosedFrame {
                frame_id: index.keyframe_frames.get(&kf).copied().unwrap_or(u64::MAX),
                segment,
                pose: *pose,
                interpolated: false,
            })
            .collect();
        keyframes.sort_by(|a, b| a.pose.timestamp.total_cmp(&b.pose.timestamp));
        let anchors: Vec<(u32, StampedPose)> =
            keyframes.iter().map(|k| (k.segment, k.pose)).collect();
        let ids: Vec<u64> = index.frames.keys().copied().collect();
        let stamps: Vec<f64> = index.frames.values().copied().collect();
        let keyframe_ids: std::collections::BTreeSet<u64> =
            keyframes.iter().map(|k| k.frame_id).collect();
        let frames = interpolate_frames(&anchors, &stamps)
            .into_iter()
            .map(|(i, pose, segment)| PosedFrame {
                frame_id: ids[i],
                segment,
                pose,
                interpolated: !keyframe_ids.contains(&ids[i]),
            })
            .collect();
        let points = map.points().map(|(track, _, x)| (track, *x)).collect();
        Self {
            keyframes,
            frames,
            points,
        }
    }

    /// trajectory.tum, keyframes.tum, map.ply, each written atomically.
    pub fn write_files(&self, out: &Path) -> anyhow::Result<()> {
        let poses = |v: &[PosedFrame]| v.iter().map(|f| f.pose).collect::<Vec<_>>();
        let points: Vec<Vector3<f64>> = self.points.iter().map(|p| p.1).collect();
        write_atomically(
            &out.join("trajectory.tum"),
            tum_text(&poses(&self.frames)).as_bytes(),
        )?;
        write_atomically(
            &out.join("keyframes.tum"),
            tum_text(&poses(&self.keyframes)).as_bytes(),
        )?;
        write_atomically(&out.join("map.ply"), ply_text(&points).as_bytes())
    }
}

/// Revision bookkeeping: which frame poses are new or changed since last published.
#[derive(Default)]
pub struct Revisions {
    published: BTreeMap<u64, (StampedPose, u32)>,
}

impl Revisions {
    /// The frames whose pose is new (revision 0) or moved (revision + 1), as messages.
    pub fn changed(&mut self, frames: &[PosedFrame]) -> Vec<pb::Pose> {
        let mut out = Vec::new();
        for f in frames {
            let revision = match self.published.get(&f.frame_id) {
                None => 0,
                Some((old, rev)) => {
                    let moved = (old.position - f.pose.position).norm() > 1e-9
                        || old.rotation.angle_to(&f.pose.rotation) > 1e-9;
                    if !moved {
                        continue;
                    }
                    rev + 1
                }
            };
            self.published.insert(f.frame_id, (f.pose, revision));
            out.push(message(f, revision));
        }
        out
    }

    fn revision(&self, frame_id: u64) -> u32 {
        self.published.get(&frame_id).map_or(0, |p| p.1)
    }
}

fn message(f: &PosedFrame, revision: u32) -> pb::Pose {
    pb::Pose {
        revision,
        interpolated: f.interpolated,
        ..pose_to_pb(f.frame_id, f.segment, &f.pose)
    }
}

/// Publishes what changed, the keyframe trajectory, the window's points and the status,
/// and refreshes the snapshot.
pub fn publish(
    egress: &Egress,
    state: &MapState,
    revisions: &mut Revisions,
    changed_points: &[u64],
    status: &pb::Status,
) -> anyhow::Result<()> {
    let poses = revisions.changed(&state.frames);
    egress.publish_poses(&poses)?;
    let trajectory = |v: &[PosedFrame]| pb::Trajectory {
        poses: v
            .iter()
            .map(|f| message(f, revisions.revision(f.frame_id)))
            .collect(),
    };
    let keyframes = trajectory(&state.keyframes);
    egress.publish_trajectory(&keyframes)?;
    let all: BTreeMap<u64, Vector3<f64>> = state.points.iter().copied().collect();
    let point = |track: u64, x: &Vector3<f64>| pb::MapPoint {
        track_id: track,
        position: Some(vec3_to_pb(x)),
        observations: 0,
    };
    let changed: Vec<pb::MapPoint> = changed_points
        .iter()
        .filter_map(|t| all.get(t).map(|x| point(*t, x)))
        .collect();
    egress.publish_map(&changed)?;
    egress.publish_status(status)?;
    egress.set_snapshot(&pb::Snapshot {
        keyframes: Some(keyframes),
        frames: Some(trajectory(&state.frames)),
        map: Some(pb::MapPoints {
            points: state.points.iter().map(|(t, x)| point(*t, x)).collect(),
        }),
        status: Some(status.clone()),
    });
    Ok(())
}
