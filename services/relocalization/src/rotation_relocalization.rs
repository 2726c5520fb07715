//! Relocalization where the map has no points: the keyframes of a head turning in place.
//!
//! A window without parallax is solved for rotations only, with every keyframe at one centre
//! (the window solver's rotation-only case), and no track of it is triangulated, so a frame
//! of that stretch finds no map point to solve a PnP with: on a rendered 300-frame walk 3.7 s
//! of a turn in place were all lost. Such a frame is placed by the rotation that maps its
//! bearings onto those of a candidate keyframe of the stretch (2-point RANSAC, then the
//! least-squares rotation of all inliers: Kabsch 1976), at the stretch's centre. The model
//! holds only without parallax, which is checked twice: the keyframe shares its centre with
//! a neighbour (it was solved without parallax), and most matches fit the rotation.

use crate::descriptors::{hamming_all, pack};
use crate::relocalizer::{
    MapKeyframe, QueryFeatures, Relocalization, RelocalizationMap, RelocalizerOptions,
};
use egoslam_geometry::{rotation_aligning, StampedPose};
use nalgebra::{Rotation3, UnitQuaternion, Vector3};

/// Draws of the 2-point RANSAC (200: at half inliers, an all-inlier pair is missed with
/// probability 0.75^200).
const ITERATIONS: usize = 200;

/// Whether keyframe `i` was solved without parallax: a neighbour in its segment has the
/// same centre (a rotation-only window puts all its keyframes at one).
fn turns_in_place(map: &RelocalizationMap, i: usize) -> bool {
    let k = &map.keyframes[i];
    let same = |j: usize| {
        map.keyframes.get(j).is_some_and(|n: &MapKeyframe| {
            n.segment == k.segment && k.pose.shares_centre_with(&n.pose)
        })
    };
    (i > 0 && same(i - 1)) || same(i + 1)
}

/// Query features matched to all described tracks of `keyframe` (points or not): nearest
/// descriptor within `options.max_hamming` passing Lowe's ratio test.
fn match_keyframe(
    query: &QueryFeatures,
    keyframe: &MapKeyframe,
    options: &RelocalizerOptions,
) -> Vec<(usize, usize)> {
    let packed: Vec<_> = keyframe
        .features
        .iter()
        .map(|f| pack(&f.descriptor))
        .collect();
    let mut distances = Vec::with_capacity(packed.len());
    let mut matches = Vec::new();
    for (qi, d) in query.descriptors.iter().enumerate() {
        hamming_all(&pack(d), &packed, &mut distances);
        let (mut best, mut second, mut at) = (u32::MAX, u32::MAX, 0);
        for (fi, &h) in distances.iter().enumerate() {
            if h < best {
                (second, best, at) = (best, h, fi);
            } else if h < second {
                second = h;
            }
        }
        if best <= options.max_hamming && (best as f32) < options.ratio * second as f32 {
            matches.push((qi, at));
        }
    }
    matches
}

/// The rotation `R` and angular velocity `w` (query camera frame, rad/s) that best map each
/// query bearing `q`, read `tau` seconds after the middle row, onto its keyframe bearing
/// `k`: `R exp(w tau) q = k` (least squares, Gauss-Newton from `start` and no turn);
/// `None` with fewer than 6 pairs or a singular system.
fn rotation_with_turn(
    pairs: &[(Vector3<f64>, Vector3<f64>, f64)],
    start: &Rotation3<f64>,
) -> Option<(Rotation3<f64>, Vector3<f64>)> {
    if pairs.len() < 6 {
        return None;
    }
    let (mut rotation, mut turn) = (*start, Vector3::zeros());
    for _ in 0..10 {
        let (mut jtj, mut jtr) = (
            nalgebra::Matrix6::<f64>::zeros(),
            nalgebra::Vector6::zeros(),
        );
        for (q, k, tau) in pairs {
            let turned = Rotation3::new(turn * *tau) * q;
            let predicted = rotation * turned;
            let residual = predicted - k;
            // d(R exp(d) v)/dd = -R [v]x for the rotation; the turn enters as tau d.
            let block = -(rotation.matrix() * turned.cross_matrix());
            let mut j = nalgebra::Matrix3x6::<f64>::zeros();
            j.fixed_view_mut::<3, 3>(0, 0).copy_from(&block);
            j.fixed_view_mut::<3, 3>(0, 3).copy_from(&(block * *tau));
            jtj += j.transpose() * j;
            jtr += j.transpose() * residual;
        }
        let delta = jtj.cholesky()?.solve(&(-jtr));
        rotation *= Rotation3::new(Vector3::new(delta[0], delta[1], delta[2]));
        turn += Vector3::new(delta[3], delta[4], delta[5]);
        if delta.norm() < 1e-12 {
            break;
        }
    }
    Some((rotation, turn))
}

/// The pose of `query` from the first of `candidates` (keyframe indices, best first) that
/// turns in place and whose matches a rotation explains; `None` if none does.
pub(crate) fn relocalize_by_rotation(
    map: &RelocalizationMap,
    query: &QueryFeatures,
    candidates: &[usize],
    options: &RelocalizerOptions,
) -> Option<Relocalization> {
    let camera = &map.camera;
    let threshold = options.rotation_threshold_px / camera.fx;
    for &i in candidates {
        if !turns_in_place(map, i) {
            continue;
        }
        let keyframe = &map.keyframes[i];
        let matches = match_keyframe(query, keyframe, options);
        if matches.len() < options.pnp.min_inliers {
            continue;
        }
        let pixel = |fi: usize| keyframe.features[fi].pixel.cast::<f64>();
        // Query bearing -> keyframe bearing, both in their own camera.
        let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = matches
            .iter()
            .map(|&(qi, fi)| {
                (
                    camera.bearing_from_undistorted(query.pixels[qi]),
                    camera.bearing_from_undistorted(pixel(fi)),
                )
            })
            .collect();
        let inliers_of = |r: &Rotation3<f64>| -> Vec<usize> {
            (0..pairs.len())
                .filter(|&m| (r * pairs[m].0 - pairs[m].1).norm() < threshold)
                .collect()
        };
        // A fixed-seed generator: the same query gives the same pose.
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut draw = |n: usize| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 33) as usize) % n
        };
        let mut best: Vec<usize> = Vec::new();
        for _ in 0..ITERATIONS {
            let (a, b) = (draw(pairs.len()), draw(pairs.len()));
            if a == b {
                continue;
            }
            let inliers = inliers_of(&rotation_aligning(&[pairs[a], pairs[b]]));
            if inliers.len() > best.len() {
                best = inliers;
            }
        }
        let mut refined = rotation_aligning(&best.iter().map(|&m| pairs[m]).collect::<Vec<_>>());
        let mut inliers = inliers_of(&refined);
        // A rolling shutter shears a turning frame's bearings beyond the threshold: fit the
        // turn during the readout on the matches near the rotation, and count again.
        if options.rolling_shutter_s > 0.0 {
            // Each match's capture time after the query's middle row.
            let tau: Vec<f64> = matches
                .iter()
                .map(|&(qi, _)| camera.row_offset(query.pixels[qi].y) * options.rolling_shutter_s)
                .collect();
            let near: Vec<(Vector3<f64>, Vector3<f64>, f64)> = (0..pairs.len())
                .filter(|&m| (refined * pairs[m].0 - pairs[m].1).norm() < 4.0 * threshold)
                .map(|m| (pairs[m].0, pairs[m].1, tau[m]))
                .collect();
            if let Some((r, turn)) = rotation_with_turn(&near, &refined) {
                let rs_inliers: Vec<usize> = (0..pairs.len())
                    .filter(|&m| {
                        let turned = r * Rotation3::new(turn * tau[m]) * pairs[m].0;
                        (turned - pairs[m].1).norm() < threshold
                    })
                    .collect();
                if rs_inliers.len() > inliers.len() {
                    (refined, inliers) = (r, rs_inliers);
                }
            }
        }
        let enough = inliers.len() >= options.pnp.min_inliers
            && inliers.len() as f64 >= options.rotation_min_inlier_ratio * pairs.len() as f64;
        if !enough {
            continue;
        }
        // world_from_query = world_from_keyframe * keyframe_from_query.
        let keyframe_from_query = UnitQuaternion::from_rotation_matrix(&refined);
        return Some(Relocalization {
            pose: StampedPose {
                timestamp: keyframe.pose.timestamp,
                position: keyframe.pose.position,
                rotation: keyframe.pose.rotation * keyframe_from_query,
            },
            segment: keyframe.segment,
            keyframe_id: keyframe.keyframe_id,
            inliers: inliers
                .iter()
                .map(|&m| (keyframe.features[matches[m].1].track_id, matches[m].0))
                .collect(),
            angular_velocity: Vector3::zeros(),
        });
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::relocalizer::MapFeature;
    use egoslam_geometry::PinholeRadtan;
    use std::collections::HashMap;

    fn camera() -> PinholeRadtan {
        PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera")
    }

    /// 300 scene points 1.5-3.5 m in front of the origin, each with its own descriptor.
    fn scene() -> Vec<(Vector3<f64>, [u8; 32])> {
        let mut state = 1u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..300)
            .map(|_| {
                let depth = 1.5 + 2.0 * next();
                let x = Vector3::new((next() - 0.5) * 1.2, (next() - 0.5) * 0.9, 1.0) * depth;
                let mut d = [0u8; 32];
                d.iter_mut().for_each(|b| *b = (next() * 256.0) as u8);
                (x, d)
            })
            .collect()
    }

    /// The features `pose` sees of `points` (track id = index).
    fn seen(points: &[(Vector3<f64>, [u8; 32])], pose: &StampedPose) -> Vec<MapFeature> {
        points
            .iter()
            .enumerate()
            .filter_map(|(t, (x, d))| {
                let p = camera()
                    .project_undistorted(&(pose.rotation.inverse() * (x - pose.position)))?;
                camera().contains(p).then(|| MapFeature {
                    track_id: t as u64,
                    descriptor: *d,
                    pixel: p.cast::<f32>(),
                })
            })
            .collect()
    }

    fn pose(yaw_deg: f64, x: f64) -> StampedPose {
        StampedPose {
            timestamp: 0.0,
            position: Vector3::new(x, 0.0, 0.0),
            rotation: UnitQuaternion::from_euler_angles(0.0, yaw_deg.to_radians(), 0.0),
        }
    }

    fn map(points: &[(Vector3<f64>, [u8; 32])], second_x: f64) -> RelocalizationMap {
        let keyframes = [pose(0.0, 0.0), pose(4.0, second_x)]
            .iter()
            .enumerate()
            .map(|(k, p)| MapKeyframe {
                keyframe_id: k as u64,
                segment: 0,
                pose: *p,
                features: seen(points, p),
                patches: Vec::new(),
            })
            .collect();
        RelocalizationMap {
            camera: camera(),
            keyframes,
            points: HashMap::new(),
            rolling_shutter_s: 0.0,
        }
    }

    fn query(points: &[(Vector3<f64>, [u8; 32])], pose: &StampedPose) -> QueryFeatures {
        let features = seen(points, pose);
        QueryFeatures {
            pixels: features.iter().map(|f| f.pixel.cast::<f64>()).collect(),
            descriptors: features.iter().map(|f| f.descriptor).collect(),
        }
    }

    #[test]
    fn a_frame_of_a_turn_in_place_is_placed_by_its_rotation_and_parallax_is_refused() {
        let points = scene();
        let options = RelocalizerOptions::default();
        // Two keyframes of a turn in place; the query turned 7 deg from the first.
        let turning = map(&points, 0.0);
        let truth = pose(7.0, 0.0);
        let found = relocalize_by_rotation(&turning, &query(&points, &truth), &[0, 1], &options)
            .expect("placed");
        assert_eq!(found.keyframe_id, 0);
        assert!(found.pose.position.norm() < 1e-12);
        let error = found.pose.rotation.angle_to(&truth.rotation).to_degrees();
        assert!(error < 0.01, "{error} deg");
        assert!(found.inliers.len() > 100, "{}", found.inliers.len());
        // Keyframes that moved 30 cm apart were not solved without parallax: not used.
        let walking = map(&points, 0.3);
        assert!(
            relocalize_by_rotation(&walking, &query(&points, &truth), &[0, 1], &options).is_none()
        );
        // A query 25 cm from a turning keyframe: no rotation explains its matches.
        let moved = pose(7.0, 0.25);
        assert!(
            relocalize_by_rotation(&turning, &query(&points, &moved), &[0, 1], &options).is_none()
        );
    }

    #[test]
    fn a_turn_during_the_readout_is_fitted_with_the_rotation() {
        // Bearings across the image, each read tau after the middle row, turned by a head
        // scan of 150 deg/s (and some pitch) during a 30 ms readout.
        let rotation = Rotation3::from_euler_angles(0.1, -0.4, 0.05);
        let turn = Vector3::new(0.5, 2.6, 0.1);
        let pairs: Vec<(Vector3<f64>, Vector3<f64>, f64)> = (0..60)
            .map(|i| {
                let (x, y) = ((i % 10) as f64 * 0.1 - 0.45, (i / 10) as f64 * 0.12 - 0.3);
                let q = Vector3::new(x, y, 1.0).normalize();
                let tau = y / 0.6 * 0.03;
                (q, rotation * Rotation3::new(turn * tau) * q, tau)
            })
            .collect();
        // From the rotation alone, a little off, as the 2-point RANSAC leaves it.
        let start = rotation * Rotation3::from_euler_angles(0.01, 0.0, -0.01);
        let (r, w) = rotation_with_turn(&pairs, &start).expect("fitted");
        assert!(r.angle_to(&rotation) < 1e-6, "{}", r.angle_to(&rotation));
        assert!((w - turn).norm() < 1e-3, "{w}");
        assert!(rotation_with_turn(&pairs[..5], &start).is_none());
    }
}
