use super::*;
use nalgebra::{Point2, Vector3};

/// Twelve keyframes turning about y, averaged rotations exact; adjusted ones in a gauge
/// turned 0.4 rad from the averaging's, as bundle adjustment may leave them.
fn window() -> (Vec<Rotation3<f64>>, Vec<CameraPose>, Rotation3<f64>) {
    let averaged: Vec<Rotation3<f64>> = (0..12)
        .map(|k| Rotation3::from_euler_angles(0.0, 0.05 * k as f64, 0.01 * k as f64))
        .collect();
    let gauge = Rotation3::from_euler_angles(0.1, 0.4, -0.2);
    let poses = averaged
        .iter()
        .enumerate()
        .map(|(k, r)| CameraPose {
            rotation: r * gauge,
            centre: Vector3::new(0.1 * k as f64, 0.0, 0.0),
        })
        .collect();
    (averaged, poses, gauge)
}

/// Observations: every keyframe sees points 0-99 except the `group`, which sees points
/// 100-199 and `ties` of points 0-99.
fn observations(group: &[usize], ties: usize) -> Vec<Observation> {
    let pixel = Point2::new(0.0, 0.0);
    let mut all = Vec::new();
    for camera in 0..12 {
        let points: Vec<usize> = if group.contains(&camera) {
            (100..200).chain(0..ties).collect()
        } else {
            (0..100).collect()
        };
        all.extend(points.into_iter().map(|point| Observation {
            camera,
            point,
            pixel,
        }));
    }
    all
}

#[test]
fn a_group_turned_with_its_own_points_gets_its_averaged_rotations_back() {
    let (averaged, mut poses, gauge) = window();
    let turn = Rotation3::from_euler_angles(0.0, 0.0, 14f64.to_radians());
    for pose in &mut poses[9..12] {
        pose.rotation = turn * pose.rotation;
    }
    let obs = observations(&[9, 10, 11], 5);
    let outlier = vec![false; obs.len()];
    let before = poses.clone();
    let detached = restore_detached_keyframes(
        &mut poses,
        &averaged,
        &obs,
        &outlier,
        &DetachedKeyframeOptions::default(),
    );
    assert_eq!(detached, vec![9, 10, 11]);
    for k in 0..12 {
        let expected = averaged[k] * gauge;
        assert!(
            angle(&(expected.inverse() * poses[k].rotation)) < 1e-6,
            "keyframe {k}"
        );
        assert_eq!(poses[k].centre, before[k].centre, "centres are left alone");
    }
}

#[test]
fn a_group_tied_to_the_window_by_shared_points_keeps_its_adjusted_rotations() {
    let (averaged, mut poses, _) = window();
    let turn = Rotation3::from_euler_angles(0.0, 0.0, 14f64.to_radians());
    for pose in &mut poses[9..12] {
        pose.rotation = turn * pose.rotation;
    }
    let obs = observations(&[9, 10, 11], 20);
    let mut outlier = vec![false; obs.len()];
    let before = poses.clone();
    let options = DetachedKeyframeOptions::default();
    assert!(restore_detached_keyframes(&mut poses, &averaged, &obs, &outlier, &options).is_empty());
    assert_eq!(poses, before);
    // The same ties rejected by the adjustment as outliers no longer hold the group.
    for (o, out) in obs.iter().zip(outlier.iter_mut()) {
        *out = [9, 10, 11].contains(&o.camera) && o.point < 100;
    }
    assert_eq!(
        restore_detached_keyframes(&mut poses, &averaged, &obs, &outlier, &options),
        vec![9, 10, 11]
    );
}

#[test]
fn small_departures_and_a_split_window_change_nothing() {
    let (averaged, mut poses, _) = window();
    let nudge = Rotation3::from_euler_angles(0.0, 0.0, 2f64.to_radians());
    poses[5].rotation = nudge * poses[5].rotation;
    let obs = observations(&[], 0);
    let outlier = vec![false; obs.len()];
    let options = DetachedKeyframeOptions::default();
    let before = poses.clone();
    assert!(restore_detached_keyframes(&mut poses, &averaged, &obs, &outlier, &options).is_empty());
    assert_eq!(poses, before);
    // Half the window turned one way and half the other: no gauge most keyframes share.
    let turn = Rotation3::from_euler_angles(0.0, 0.0, 0.3);
    for (k, pose) in poses.iter_mut().enumerate() {
        let t = if k < 6 { turn } else { turn.inverse() };
        pose.rotation = t * pose.rotation;
    }
    let before = poses.clone();
    assert!(restore_detached_keyframes(&mut poses, &averaged, &obs, &outlier, &options).is_empty());
    assert_eq!(poses, before);
}
