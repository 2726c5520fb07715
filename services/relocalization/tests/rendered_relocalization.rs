//! The relocalizer against exact geometry: a map built from rendered keyframes (points
//! from the renderer's depth), frames between them relocalized from scratch. This isolates
//! relocalization from the SLAM map's own error; the paper's Table 5 reports 0.98 cm and
//! 0.005 deg on a real sequence.

use egoslam_geometry::{PinholeRadtan, StampedPose};
use egoslam_relocalization::descriptors::{detect_corners, DescriberOptions, QueryCornerOptions};
use egoslam_relocalization::{
    default_vocabulary, MapFeature, MapKeyframe, OrbDescriber, QueryFeatures, RelocalizationMap,
    Relocalizer, RelocalizerOptions,
};
use egoslam_synth::{render_frame, CameraPath, RenderOptions, Scene, WalkerOptions};
use nalgebra::{Point2, Vector3};
use opencv::core::{Mat, CV_8UC1};
use opencv::prelude::*;
use std::collections::HashMap;

fn image(frame: &egoslam_synth::Frame) -> Mat {
    let m = Mat::new_rows_cols_with_data(frame.height as i32, frame.width as i32, &frame.grey)
        .expect("wrap");
    let owned = m.try_clone().expect("copy");
    assert_eq!(owned.typ(), CV_8UC1);
    owned
}

#[test]
fn frames_between_rendered_keyframes_relocalize_to_millimetres() {
    let camera =
        PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera");
    let scene = Scene::room(7);
    let poses: Vec<StampedPose> = CameraPath::Walker(WalkerOptions::default()).poses(150, 30.0);
    let render = RenderOptions::default();
    let mut describer = OrbDescriber::new(DescriberOptions::default()).expect("orb");
    let corners_options = QueryCornerOptions::default();
    let mut keyframes = Vec::new();
    let mut points = HashMap::new();
    let mut next_track = 0u64;
    for (i, pose) in poses.iter().enumerate().step_by(6) {
        let frame = render_frame(&scene, &camera, &[*pose], i as u64, &render);
        let img = image(&frame);
        let corners = detect_corners(&img, &corners_options).expect("corners");
        let descriptors = describer.describe(&img, &corners).expect("describe");
        let mut features = Vec::new();
        for (c, d) in corners.iter().zip(descriptors) {
            let Some(descriptor) = d else { continue };
            let (u, v) = (c.x.round() as usize, c.y.round() as usize);
            let z = f64::from(frame.depth[v * 640 + u]);
            if z <= 0.0 {
                continue;
            }
            let pc = Vector3::new(
                (f64::from(c.x) - camera.cx) / camera.fx * z,
                (f64::from(c.y) - camera.cy) / camera.fy * z,
                z,
            );
            points.insert(next_track, (0, pose.rotation * pc + pose.position));
            features.push(MapFeature {
                track_id: next_track,
                descriptor,
                pixel: Point2::new(c.x, c.y),
            });
            next_track += 1;
        }
        keyframes.push(MapKeyframe {
            keyframe_id: keyframes.len() as u64,
            segment: 0,
            pose: *pose,
            features,
        });
    }
    let relocalizer = Relocalizer::new(
        default_vocabulary().expect("built-in vocabulary"),
        RelocalizationMap {
            camera,
            keyframes,
            points,
        },
    );
    let options = RelocalizerOptions::default();
    let (mut position, mut rotation, mut tried) = (Vec::new(), Vec::new(), 0);
    for (i, truth) in poses.iter().enumerate().skip(3).step_by(6) {
        tried += 1;
        let frame = render_frame(&scene, &camera, &[*truth], 1000 + i as u64, &render);
        let img = image(&frame);
        let corners = detect_corners(&img, &corners_options).expect("corners");
        let descriptors = describer.describe(&img, &corners).expect("describe");
        let mut query = QueryFeatures::default();
        for (c, d) in corners.iter().zip(descriptors) {
            if let Some(d) = d {
                query
                    .pixels
                    .push(Point2::new(f64::from(c.x), f64::from(c.y)));
                query.descriptors.push(d);
            }
        }
        if let Ok(r) = relocalizer.relocalize(&query, &options) {
            position.push((r.pose.position - truth.position).norm());
            rotation.push(r.pose.rotation.angle_to(&truth.rotation).to_degrees());
        }
    }
    position.sort_by(f64::total_cmp);
    rotation.sort_by(f64::total_cmp);
    let (p, r) = (position[position.len() / 2], rotation[rotation.len() / 2]);
    println!(
        "relocalized {} of {tried}; median {:.2} mm, {:.3} deg",
        position.len(),
        p * 1e3,
        r
    );
    assert!(
        position.len() * 100 >= tried * 95,
        "{} of {tried}",
        position.len()
    );
    assert!(p < 0.01, "median position error {p} m");
    assert!(r < 0.2, "median rotation error {r} deg");
}
