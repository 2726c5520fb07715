//! Points that became stable (paper, section 5: "re-adding points"): a track whose rays
//! met at too small an angle inside any one window may, once later windows add views from
//! further along, be triangulated from the merged poses. The merger keeps such tracks'
//! observations and tries them after each window; a point that passes the angle,
//! cheirality and reprojection checks joins the map with its observations (and so the
//! global refinement).

use crate::map::MapBuilder;
use egoslam_geometry::PinholeRadtan;
use egoslam_solver::triangulation::{triangulate_track, CameraPose, TriangulationOptions};
use nalgebra::Point2;

/// Fewest views before a weak track is tried again (default 3: two views already failed
/// inside a window).
pub const MIN_VIEWS: usize = 3;

/// A re-added point nearer to a keyframe that sees it than this fraction of the segment's
/// recent scene depth is refused (default 0.1; real near structure, a hand at 0.3 m in a
/// 3 m room, is about that near, and such tracks are optional extras here). On the
/// rendered 1500-frame walk with a 20 ms readout and motion blur, run told its readout,
/// the keyframes of a turn in place (centres apart only by the correction's remainder)
/// re-added 85 points at ~1/40 of the scene depth; they became the map's recent scene
/// depth, the next window was joined to it 8x too small and the walk ended 4.2 m off.
pub const MIN_DEPTH_FRACTION: f64 = 0.1;

/// What one pass did.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RetriangulationReport {
    /// Tracks tried (all views posed in the current segment).
    pub tried: usize,
    /// Tracks whose points were added to the map.
    pub added: Vec<u64>,
    /// Tracks given up because they ended (not seen by the newest window).
    pub dropped: usize,
}

impl MapBuilder {
    /// Keeps observations of tracks a window could not triangulate.
    pub(crate) fn add_weak_observations(&mut self, observations: &[(u64, u64, Point2<f64>)]) {
        for (kf, track, px) in observations {
            if !self.points.contains_key(track) {
                self.weak.entry(*track).or_default().insert(*kf, *px);
            }
        }
    }

    /// Tries every weak track whose views are all posed in the current segment; tracks not
    /// seen since `oldest_live_keyframe` have ended and are dropped.
    pub fn retriangulate(
        &mut self,
        camera: &PinholeRadtan,
        options: &TriangulationOptions,
        oldest_live_keyframe: u64,
    ) -> RetriangulationReport {
        let mut report = RetriangulationReport::default();
        let Some(segment) = self.current_segment else {
            return report;
        };
        let nearest = self
            .recent_scene_depth(segment)
            .map_or(0.0, |depth| MIN_DEPTH_FRACTION * depth);
        let mut done = Vec::new();
        let mut added = Vec::new();
        for (track, views) in &self.weak {
            let newest = views.keys().next_back().copied().unwrap_or(0);
            if newest < oldest_live_keyframe {
                done.push(*track);
                report.dropped += 1;
                continue;
            }
            if views.len() < MIN_VIEWS || self.points.contains_key(track) {
                continue;
            }
            let (mut poses, mut obs, mut keyframes) = (Vec::new(), Vec::new(), Vec::new());
            for (kf, px) in views {
                if let Some((s, p)) = self.keyframes.get(kf) {
                    if *s == segment {
                        obs.push((poses.len(), *px));
                        keyframes.push(*kf);
                        poses.push(CameraPose {
                            rotation: p.rotation.inverse().to_rotation_matrix(),
                            centre: p.position,
                        });
                    }
                }
            }
            if obs.len() < MIN_VIEWS {
                continue;
            }
            report.tried += 1;
            let Ok(point) = triangulate_track(camera, &poses, &obs, options) else {
                continue;
            };
            if point.inliers.len() < MIN_VIEWS {
                continue;
            }
            let too_near = point
                .inliers
                .iter()
                .any(|&i| poses[obs[i].0].to_camera(&point.position).z < nearest);
            if too_near {
                continue;
            }
            let kept: Vec<(u64, Point2<f64>)> = point
                .inliers
                .iter()
                .map(|&i| (keyframes[obs[i].0], obs[i].1))
                .collect();
            done.push(*track);
            added.push((*track, point.position, kept));
        }
        report.added = added.iter().map(|(track, _, _)| *track).collect();
        for (track, x, kept) in added {
            self.points.insert(track, (segment, x));
            for (kf, px) in kept {
                self.observations.insert((kf, track), px);
            }
        }
        for track in done {
            self.weak.remove(&track);
        }
        report
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::WindowInput;
    use egoslam_geometry::StampedPose;
    use nalgebra::{UnitQuaternion, Vector3};

    #[test]
    fn a_far_point_weak_in_each_window_is_triangulated_from_both() {
        let camera =
            PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera");
        // Keyframes 5 cm apart along x, looking down +z; the point 20 m ahead: inside one
        // window of 5 keyframes the rays meet at < 0.6 deg, over 12 keyframes at ~1.7 deg.
        let pose = |i: u64| StampedPose {
            timestamp: i as f64,
            position: Vector3::new(0.05 * i as f64, 0.0, 0.0),
            rotation: UnitQuaternion::identity(),
        };
        let x = Vector3::new(0.3, 0.5, 20.0);
        let pixel = |i: u64| {
            let p = pose(i);
            camera
                .project_undistorted(&(x - p.position))
                .expect("in front")
        };
        let window = |ids: std::ops::Range<u64>| WindowInput {
            poses: ids.clone().map(|i| (i, pose(i))).collect(),
            weak_observations: ids.map(|i| (i, 77, pixel(i))).collect(),
            ..WindowInput::default()
        };
        let mut map = MapBuilder::new();
        map.add_window(&window(0..7));
        let options = TriangulationOptions::default();
        let first = map.retriangulate(&camera, &options, 0);
        assert_eq!(
            (first.tried, first.added.len()),
            (1, 0),
            "angle too small so far"
        );
        map.add_window(&window(5..13));
        let second = map.retriangulate(&camera, &options, 5);
        assert_eq!(second.added, vec![77]);
        let (_, got) = map.point(77).expect("point added");
        assert!((got - x).norm() < 1e-6 * x.norm(), "{got:?}");
        assert_eq!(
            map.observations
                .range((0, 77)..=(12, 77))
                .filter(|((_, t), _)| *t == 77)
                .count(),
            13
        );
        // A track that stopped being seen is dropped, not kept forever.
        map.add_window(&WindowInput {
            weak_observations: vec![(12, 78, pixel(12)), (13, 78, pixel(12))],
            poses: (12..20).map(|i| (i, pose(i))).collect(),
            ..WindowInput::default()
        });
        let third = map.retriangulate(&camera, &options, 30);
        assert_eq!(third.dropped, 1);
        assert!(map.weak.is_empty());
    }

    #[test]
    fn a_point_far_nearer_than_the_scene_is_not_re_added() {
        let camera =
            PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera");
        // A head turning in place whose centres differ by 1 mm of noise: a track whose
        // pixels are the ones of a point 5 cm ahead triangulates there, at 1/60 of the 3 m
        // the keyframes' points see; the same track of a point 1 m ahead is kept.
        let pose = |i: u64| StampedPose {
            timestamp: i as f64 * 0.03,
            position: Vector3::new(0.001 * i as f64, 0.0, 0.0),
            rotation: UnitQuaternion::identity(),
        };
        let scene: Vec<(u64, Vector3<f64>)> = (0..30)
            .map(|k| {
                let a = k as f64 * 0.05;
                (1000 + k, Vector3::new(a.sin(), a.cos() - 0.5, 3.0))
            })
            .collect();
        let near = Vector3::new(0.0, 0.0, 0.05);
        let metre = Vector3::new(0.0, 0.0, 1.0);
        // Ten keyframes of 1 mm steps give the metre-away point's rays ~0.5 deg, under the
        // triangulation angle: that case walks, its keyframes 2 cm apart.
        let wide = |i: u64| StampedPose {
            position: Vector3::new(0.02 * i as f64, 0.0, 0.0),
            ..pose(i)
        };
        // Ten keyframes posed by `at`, seeing the scene's points and weak track `track` of
        // the point `weak`.
        let window = |at: &dyn Fn(u64) -> StampedPose, track: u64, weak: &Vector3<f64>| {
            let pixel = |x: &Vector3<f64>, i: u64| {
                camera
                    .project_undistorted(&(x - at(i).position))
                    .expect("in front")
            };
            WindowInput {
                poses: (0..10).map(|i| (i, at(i))).collect(),
                points: scene.clone(),
                observations: (0..10)
                    .flat_map(|i| scene.iter().map(move |(t, x)| (i, *t, *x)))
                    .map(|(i, t, x)| (i, t, pixel(&x, i)))
                    .collect(),
                weak_observations: (0..10).map(|i| (i, track, pixel(weak, i))).collect(),
            }
        };
        let window_near = window(&pose, 77, &near);
        let mut map = MapBuilder::new();
        map.add_window(&window_near);
        let options = TriangulationOptions::default();
        let report = map.retriangulate(&camera, &options, 0);
        assert_eq!((report.tried, report.added.len()), (1, 0), "{report:?}");
        // With no scene depth to compare with, the same track would have been added: the
        // refusal is the depth check's.
        let mut bare = MapBuilder::new();
        bare.add_window(&WindowInput {
            points: Vec::new(),
            observations: Vec::new(),
            ..window_near
        });
        assert_eq!(bare.retriangulate(&camera, &options, 0).added, vec![77]);
        // A metre away (a third of the scene depth) is real near structure: kept.
        let mut far = MapBuilder::new();
        far.add_window(&window(&wide, 78, &metre));
        assert_eq!(far.retriangulate(&camera, &options, 0).added, vec![78]);
    }
}
