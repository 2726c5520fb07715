//! The merger's results written to files (trajectory.tum, keyframes.tum,
//! keyframe_segments.txt, map.ply) and published over zenoh, from the same
//! `egoslam_merger::session::publication::MapState`.

use egoslam_durability::frozen_head::write_with_frozen_head;
use egoslam_durability::write_atomically;
use egoslam_egress::Egress;
use egoslam_export::map_ply::{self, MapPlyPoint};
use egoslam_export::tum::{tum_rows, tum_text, TUM_HEADER};
use egoslam_merger::session::frames::PosedFrame;
use egoslam_merger::session::publication::Publication;
pub use egoslam_merger::session::publication::{MapState, PublishedPoints, Revisions};
use egoslam_merger::PointConfidenceOptions;
use egoslam_messages::v1 as pb;
use std::path::Path;

/// The points as map.ply holds them: with their views, relative standard deviation
/// and grey level (`grey`, from the images); only those known within `options` unless
/// `all` (every point when no confidence was attached, as before the first window
/// brought the camera).
fn ply_points(
    state: &MapState,
    options: &PointConfidenceOptions,
    all: bool,
    grey: &dyn Fn(u64) -> Option<u8>,
) -> Vec<MapPlyPoint> {
    state
        .points
        .iter()
        .filter_map(|(track, p)| {
            let confidence = state.confidence.as_ref().and_then(|c| c.get(track));
            let known =
                state.confidence.is_none() || confidence.is_some_and(|c| c.is_known(options));
            (all || known).then(|| {
                let g = grey(*track).unwrap_or(128);
                MapPlyPoint {
                    position: [p.x as f32, p.y as f32, p.z as f32],
                    colour: [g; 3],
                    views: confidence.map_or(0, |c| c.views),
                    relative_std: confidence
                        .and_then(|c| c.relative_std)
                        .map_or(f32::NAN, |s| s as f32),
                }
            })
        })
        .collect()
}

/// trajectory.tum's rows: the frames retired since the last write (final, appended to the
/// file's frozen head of `head_len` bytes) and the frames after them (the tail, rewritten).
pub struct TrajectoryRows<'a> {
    pub head_len: u64,
    pub retired: &'a [PosedFrame],
    pub live: &'a [PosedFrame],
}

/// trajectory.tum (`trajectory`: its tail rewritten after a frozen head,
/// egoslam_durability::frozen_head), keyframes.tum, keyframe_segments.txt, map.ply, each
/// of the latter written atomically. The segments file says which map segment (own gauge
/// and scale) each keyframe is in, so that a run with breaks can be evaluated segment by
/// segment.
pub fn write_files(
    state: &MapState,
    trajectory: TrajectoryRows,
    out: &Path,
    published: &PointConfidenceOptions,
    all_points: bool,
    grey: &dyn Fn(u64) -> Option<u8>,
) -> anyhow::Result<WrittenFiles> {
    let poses = |v: &[PosedFrame]| v.iter().map(|f| f.pose).collect::<Vec<_>>();
    let points = ply_points(state, published, false, grey);
    let mut to_head = tum_rows(&poses(trajectory.retired));
    if trajectory.head_len == 0 {
        to_head.insert_str(0, TUM_HEADER);
    }
    let tail = tum_rows(&poses(trajectory.live));
    let path = out.join("trajectory.tum");
    let head = write_with_frozen_head(
        &path,
        trajectory.head_len,
        to_head.as_bytes(),
        tail.as_bytes(),
    )?;
    if head.missing > 0 {
        tracing::warn!(
            missing_bytes = head.missing,
            "trajectory.tum was cut short outside egoslam: the rows of retired frames it lost are gone"
        );
    }
    let mut written = WrittenFiles {
        published_points: points.len(),
        bytes: (to_head.len() + tail.len()) as u64,
        trajectory_head_len: head.len,
    };
    let mut write = |name: &str, bytes: &[u8]| -> anyhow::Result<()> {
        write_atomically(&out.join(name), bytes)?;
        written.bytes += bytes.len() as u64;
        Ok(())
    };
    write(
        "keyframes.tum",
        tum_text(&poses(&state.keyframes)).as_bytes(),
    )?;
    let mut segments = String::from("# timestamp segment\n");
    for k in &state.keyframes {
        segments += &format!("{:.6} {}\n", k.pose.timestamp, k.segment);
    }
    write("keyframe_segments.txt", segments.as_bytes())?;
    write(
        "map.ply",
        &map_ply::to_bytes(points, "egoslam map points (docs/merger.md)")?,
    )?;
    if all_points {
        let all = ply_points(state, published, true, grey);
        write(
            "map_all.ply",
            &map_ply::to_bytes(all, "egoslam: every triangulated point")?,
        )?;
    }
    Ok(written)
}

/// What [`write_files`] wrote.
pub struct WrittenFiles {
    /// Points map.ply holds.
    pub published_points: usize,
    /// Bytes written to all the files (what the write budget counts).
    pub bytes: u64,
    /// Length of trajectory.tum's frozen head now.
    pub trajectory_head_len: u64,
}

/// Hands a window's messages to zenoh: what changed, the keyframe trajectory and the
/// window's points, then the snapshot, then the status.
pub fn publish(
    egress: &Egress,
    publication: Publication,
    status: &pb::Status,
) -> anyhow::Result<()> {
    egress.publish_poses(&publication.poses)?;
    egress.publish_trajectory(&publication.keyframes)?;
    egress.publish_map(&publication.changed_points)?;
    // The snapshot before the status: a client that sees "finished" and then asks for the
    // snapshot (to fill what its subscription dropped) must get the final state.
    let (parts, snapshot_status) = (publication.snapshot, status.clone());
    egress.set_snapshot_source(move || parts.to_message(&snapshot_status));
    egress.publish_status(status)?;
    Ok(())
}
