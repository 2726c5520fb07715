//! Maps and queries from rendered frames with exact geometry (shared by the rendered
//! relocalization test and the query benchmark).

use egoslam_geometry::{PinholeRadtan, StampedPose};
use egoslam_relocalization::descriptors::{detect_corners, QueryCornerOptions};
use egoslam_relocalization::patch_alignment::extract_patch;
use egoslam_relocalization::{MapFeature, MapKeyframe, OrbDescriber, QueryFeatures};
use egoslam_synth::{render_frame, RenderOptions, Scene};
use nalgebra::{Point2, Vector3};
use opencv::core::Mat;
use opencv::prelude::*;
use std::collections::HashMap;

pub fn camera() -> PinholeRadtan {
    PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera")
}

/// Renders `pose` and returns its described corners with their depth (0: nothing hit),
/// and the image.
pub fn described_frame(
    scene: &Scene,
    pose: &StampedPose,
    index: u64,
    describer: &mut OrbDescriber,
) -> (QueryFeatures, Vec<f64>, Mat) {
    let frame = render_frame(scene, &camera(), &[*pose], index, &RenderOptions::default());
    let wrapped =
        Mat::new_rows_cols_with_data(frame.height as i32, frame.width as i32, &frame.grey)
            .expect("wrap");
    let image = wrapped.try_clone().expect("copy");
    let corners = detect_corners(&image, &QueryCornerOptions::default()).expect("corners");
    let descriptors = describer.describe(&image, &corners).expect("describe");
    let mut query = QueryFeatures::default();
    let mut depths = Vec::new();
    for (c, d) in corners.iter().zip(descriptors) {
        if let Some(d) = d {
            let (u, v) = (c.x.round() as usize, c.y.round() as usize);
            depths.push(f64::from(frame.depth[v * frame.width as usize + u]));
            query
                .pixels
                .push(Point2::new(f64::from(c.x), f64::from(c.y)));
            query.descriptors.push(d);
        }
    }
    (query, depths, image)
}

/// A keyframe whose points are its corners back-projected with the rendered depth; track
/// ids continue from `next_track`.
pub fn rendered_keyframe(
    scene: &Scene,
    pose: &StampedPose,
    keyframe_id: u64,
    next_track: &mut u64,
    points: &mut HashMap<u64, (u32, Vector3<f64>)>,
    describer: &mut OrbDescriber,
) -> MapKeyframe {
    let c = camera();
    let (features, depths, image) = described_frame(scene, pose, keyframe_id, describer);
    let mut out = Vec::new();
    let mut patches = Vec::new();
    for ((px, descriptor), z) in features.pixels.iter().zip(features.descriptors).zip(depths) {
        if z <= 0.0 {
            continue;
        }
        let pc = Vector3::new((px.x - c.cx) / c.fx * z, (px.y - c.cy) / c.fy * z, z);
        points.insert(*next_track, (0, pose.rotation * pc + pose.position));
        out.push(MapFeature {
            track_id: *next_track,
            descriptor,
            pixel: Point2::new(px.x as f32, px.y as f32),
        });
        if let Some(patch) = extract_patch(&image, *px) {
            patches.push((*next_track, patch));
        }
        *next_track += 1;
    }
    MapKeyframe {
        keyframe_id,
        segment: 0,
        pose: *pose,
        features: out,
        patches,
    }
}

/// A relocalization map of every `step`-th of `poses` rendered in `scene` (track ids and
/// points shared across keyframes); `progress` is told each keyframe's index as it is made.
pub fn rendered_map(
    scene: &Scene,
    poses: &[StampedPose],
    step: usize,
    describer: &mut OrbDescriber,
    mut progress: impl FnMut(usize),
) -> egoslam_relocalization::RelocalizationMap {
    let (mut points, mut next_track) = (HashMap::new(), 0);
    let keyframes = poses
        .iter()
        .step_by(step)
        .enumerate()
        .map(|(k, pose)| {
            progress(k);
            rendered_keyframe(
                scene,
                pose,
                k as u64,
                &mut next_track,
                &mut points,
                describer,
            )
        })
        .collect();
    egoslam_relocalization::RelocalizationMap {
        camera: camera(),
        keyframes,
        points,
        rolling_shutter_s: 0.0,
    }
}
