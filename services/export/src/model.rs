//! What every export holds: the camera, the posed images with their keypoints, and the
//! points with their tracks (which keypoints of which images see them).

use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Point2, Vector3};
use std::collections::BTreeMap;

/// A keypoint of an image: its pixel in the image as stored (distorted), and the point it
/// observes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Keypoint {
    pub pixel: Point2<f64>,
    pub point: u64,
}

/// A posed image.
#[derive(Debug, Clone, PartialEq)]
pub struct ExportImage {
    /// The image's path relative to the sequence folder (e.g. `rgb/1305031102.175304.png`).
    pub name: String,
    /// world_from_camera.
    pub pose: StampedPose,
    pub keypoints: Vec<Keypoint>,
}

/// A map point seen by at least two exported images.
#[derive(Debug, Clone, PartialEq)]
pub struct ExportPoint {
    pub id: u64,
    pub position: Vector3<f64>,
    /// RGB, sampled from the images by the caller (grey until then).
    pub colour: [u8; 3],
    /// (image index, keypoint index) of every observation.
    pub track: Vec<(usize, usize)>,
    /// Mean reprojection error in pixels over the track.
    pub error: f64,
}

/// The model every format is written from.
#[derive(Debug, Clone, PartialEq)]
pub struct ExportModel {
    pub camera: PinholeRadtan,
    pub images: Vec<ExportImage>,
    pub points: Vec<ExportPoint>,
}

/// The map as egoslam keeps it: keyframes with image names, points, and observations as
/// undistorted pixels (the camera's focal lengths and centre, no distortion).
pub struct MapView<'a> {
    pub camera: PinholeRadtan,
    /// (keyframe id, image name, world_from_camera), one segment's.
    pub keyframes: Vec<(u64, String, StampedPose)>,
    pub points: &'a BTreeMap<u64, Vector3<f64>>,
    /// (keyframe id, track id) -> undistorted pixel.
    pub observations: &'a BTreeMap<(u64, u64), Point2<f64>>,
}

/// Where an undistorted pixel lies in the image as recorded.
fn distorted(camera: &PinholeRadtan, undistorted: Point2<f64>) -> Point2<f64> {
    let n = Point2::new(
        (undistorted.x - camera.cx) / camera.fx,
        (undistorted.y - camera.cy) / camera.fy,
    );
    let d = camera.distort_normalized(n);
    Point2::new(d.x * camera.fx + camera.cx, d.y * camera.fy + camera.cy)
}

impl ExportModel {
    /// The images of `view`'s keyframes and the points at least two of them see, with
    /// each observation moved back into the recorded (distorted) image.
    pub fn from_map(view: &MapView) -> Self {
        let camera = view.camera;
        let mut images: Vec<ExportImage> = view
            .keyframes
            .iter()
            .map(|(_, name, pose)| ExportImage {
                name: name.clone(),
                pose: *pose,
                keypoints: Vec::new(),
            })
            .collect();
        let index: BTreeMap<u64, usize> = view
            .keyframes
            .iter()
            .enumerate()
            .map(|(i, (id, _, _))| (*id, i))
            .collect();
        let mut tracks: BTreeMap<u64, Vec<(usize, Point2<f64>)>> = BTreeMap::new();
        for ((keyframe, track), pixel) in view.observations {
            if let (Some(&image), true) = (index.get(keyframe), view.points.contains_key(track)) {
                tracks.entry(*track).or_default().push((image, *pixel));
            }
        }
        let mut points = Vec::new();
        for (id, seen) in tracks {
            if seen.len() < 2 {
                continue;
            }
            let position = view.points[&id];
            let mut track = Vec::with_capacity(seen.len());
            let mut error = 0.0;
            for (image, undistorted) in &seen {
                let pose = &images[*image].pose;
                let in_camera = pose.rotation.inverse() * (position - pose.position);
                error += camera
                    .project_undistorted(&in_camera)
                    .map_or(0.0, |p| (p - undistorted).norm());
                let keypoints = &mut images[*image].keypoints;
                track.push((*image, keypoints.len()));
                keypoints.push(Keypoint {
                    pixel: distorted(&camera, *undistorted),
                    point: id,
                });
            }
            points.push(ExportPoint {
                id,
                position,
                colour: [128; 3],
                error: error / seen.len() as f64,
                track,
            });
        }
        Self {
            camera,
            images,
            points,
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    /// Three cameras along x looking down +z at a grid of points 4 m away, observed
    /// exactly through a camera with distortion.
    pub(crate) fn scene() -> ExportModel {
        let camera = PinholeRadtan::new(
            640,
            480,
            [500.0, 510.0, 320.0, 240.0],
            [0.1, -0.05, 0.001, 0.002, 0.0],
        )
        .expect("camera");
        let keyframes: Vec<(u64, String, StampedPose)> = (0..3)
            .map(|k| {
                (
                    10 + k,
                    format!("rgb/{}.png", 100.0 + k as f64 * 0.5),
                    StampedPose {
                        timestamp: 100.0 + k as f64 * 0.5,
                        position: Vector3::new(k as f64 * 0.2, 0.0, 0.0),
                        rotation: UnitQuaternion::from_euler_angles(0.0, 0.05 * k as f64, 0.0),
                    },
                )
            })
            .collect();
        let mut points = BTreeMap::new();
        let mut observations = BTreeMap::new();
        for i in 0..5 {
            for j in 0..4 {
                let track = 1000 + i * 10 + j;
                let p = Vector3::new(i as f64 * 0.5 - 1.0, j as f64 * 0.5 - 0.75, 4.0);
                points.insert(track, p);
                for (id, _, pose) in &keyframes {
                    let c = pose.rotation.inverse() * (p - pose.position);
                    let pixel = camera.project_undistorted(&c).expect("in front");
                    observations.insert((*id, track), pixel);
                }
            }
        }
        // A point seen once is left out; an observation of an unknown point is ignored.
        points.insert(5, Vector3::new(0.0, 0.0, 3.0));
        observations.insert((10, 5), Point2::new(320.0, 240.0));
        observations.insert((11, 77), Point2::new(10.0, 10.0));
        ExportModel::from_map(&MapView {
            camera,
            keyframes,
            points: &points,
            observations: &observations,
        })
    }

    #[test]
    fn points_seen_twice_are_kept_with_distorted_keypoints_and_no_error() {
        let m = scene();
        assert_eq!(m.images.len(), 3);
        assert_eq!(m.points.len(), 20);
        assert!(m
            .points
            .iter()
            .all(|p| p.track.len() == 3 && p.error < 1e-9));
        assert!(m.images.iter().all(|i| i.keypoints.len() == 20));
        // Every keypoint, undistorted again, is where the camera projects its point.
        for image in &m.images {
            for k in &image.keypoints {
                let p = m.points.iter().find(|p| p.id == k.point).expect("point");
                let c = image.pose.rotation.inverse() * (p.position - image.pose.position);
                let raw = m.camera.project_raw(&c).expect("in front");
                assert!((raw - k.pixel).norm() < 1e-6, "{raw} vs {}", k.pixel);
            }
        }
    }
}
