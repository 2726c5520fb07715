//! Bundle adjustment of the live tracker's last tracked frames and the points they see
//! (ORB-SLAM's local mapping in spirit, Mur-Artal et al., T-RO 2015, on a sliding window of
//! frames instead of covisible keyframes).
//!
//! Between two maps the tracker poses frames by PnP on points it triangulated itself from
//! two of its own poses. A small error in those poses goes into the points and from them
//! into the next poses: in a sharp turn while walking, where a sideways step and a turn of
//! the head move the image alike, the poses turned 10 deg too far in 0.7 s and the
//! position stood still. Adjusting the poses of the last second's frames together with the
//! points they share ties every pose to many baselines at once; the older frames are held,
//! so the window keeps the gauge and scale it was tracked in.

use super::LiveTracker;
use egoslam_geometry::{PinholeRadtan, StampedPose};
use egoslam_solver::bundle_adjustment::{bundle_adjust, BundleAdjustmentOptions, Observation};
use egoslam_solver::triangulation::CameraPose;
use nalgebra::{Point2, UnitQuaternion, Vector3};
use rustc_hash::FxHashMap;

/// Defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalAdjustmentOptions {
    /// Frames adjusted at most, the newest included, spread over the window (default 10:
    /// at 30 fps about every third frame of the last second).
    pub max_frames: usize,
    /// Oldest of those frames held fixed (default 7: only the newest three move). With
    /// the two oldest held, which fix the gauge and scale over a short baseline, the
    /// newest frame of the rendered 300-frame walk moved 4-34 cm per adjustment at the
    /// tracks' noise and its live trajectory drifted off (1.09 m ATE); with four held,
    /// still 3-5 cm per frame walking ahead (0.054 m); with most of the window held, each
    /// frame is adjusted against a second of baselines already settled.
    pub fixed_frames: usize,
    /// Least observations of a point among the adjusted frames (default 2).
    pub min_views: usize,
    /// LM iterations (default 5: the frames start close to the optimum, from PnP; 3 to 20
    /// gave the same live trajectories on the rendered walks).
    pub max_iterations: usize,
    /// Least angle between a point's rays from the first and the last adjusted frame that
    /// see it, degrees (default 1, the tracker's triangulation angle): a point without
    /// parallax in the window, as in a turn in place, pins no frame's position, and with
    /// only such points the positions drift freely along with the points' depths.
    pub min_parallax_deg: f64,
    /// Observations further than this from the optical axis are left out, degrees
    /// (default 60, as frame localization's `max_ray_angle_deg`: the residuals are measured
    /// on the ideal pinhole plane, which stretches a fisheye's tracking noise beyond it).
    pub max_ray_angle_deg: f64,
    /// Least observations of points with parallax in each frame adjusted (default 30): a
    /// frame pinned by a few points only (a turn in place, a blank wall) is not adjusted
    /// at all, since with a handful of points the poses and depths trade off freely.
    pub min_frame_observations: usize,
    /// Points adjusted at most, those seen in the most frames first (default 250: the
    /// cost grows with the observations, and a few hundred well-spread points pin the
    /// frames as well as all of them).
    pub max_points: usize,
}

impl Default for LocalAdjustmentOptions {
    fn default() -> Self {
        Self {
            max_frames: 10,
            fixed_frames: 7,
            min_views: 2,
            max_iterations: 5,
            min_parallax_deg: 1.0,
            max_ray_angle_deg: 60.0,
            min_frame_observations: 30,
            max_points: 250,
        }
    }
}

impl LiveTracker {
    /// The tracked frame's pose after adjusting the last tracked frames with it (when
    /// `adjust` and the options have an adjustment); the adjusted frames and points replace
    /// the tracker's.
    pub(super) fn adjusted(
        &mut self,
        adjust: bool,
        camera: &PinholeRadtan,
        pose: StampedPose,
        tracks: &[(u64, Point2<f64>)],
    ) -> StampedPose {
        let timestamp = pose.timestamp;
        while self
            .tracked
            .front()
            .is_some_and(|(p, _)| p.timestamp < timestamp - self.options.local_window_s)
        {
            self.tracked.pop_front();
        }
        self.tracked.push_back((pose, tracks.to_vec()));
        let Some(options) = self.options.local_adjustment.filter(|_| adjust) else {
            return pose;
        };
        let n = self.tracked.len();
        let m = options.max_frames.min(n);
        if m < 2 {
            return pose;
        }
        let chosen: Vec<usize> = (0..m)
            .map(|k| (k * (n - 1) + (m - 1) / 2) / (m - 1))
            .collect();
        let frames: Vec<&TrackedFrame> = chosen.iter().map(|&i| &self.tracked[i]).collect();
        let (map, local) = (&self.map.points, &self.local_points);
        let Some(adjusted) = adjust_window(
            camera,
            &frames,
            |t| map.get(&t).or_else(|| local.get(&t)).copied(),
            &options,
        ) else {
            return pose;
        };
        for (&i, p) in chosen.iter().zip(&adjusted.poses) {
            self.tracked[i].0 = *p;
        }
        for (t, x) in adjusted.points {
            if !self.map.points.contains_key(&t) {
                self.local_points.insert(t, x);
            }
        }
        adjusted.poses.last().copied().unwrap_or(pose)
    }
}

/// One tracked frame in the window: its pose and its tracks `(id, undistorted pixel)`.
pub(super) type TrackedFrame = (StampedPose, Vec<(u64, Point2<f64>)>);

/// The adjusted window: the frames' poses (in the order given) and the points moved.
pub(super) struct Adjusted {
    pub poses: Vec<StampedPose>,
    pub points: FxHashMap<u64, Vector3<f64>>,
}

/// Adjusts `frames` (oldest first; the last is the frame just tracked) and the points
/// `point_of` gives for their tracks. `None` when there is too little to adjust.
pub(super) fn adjust_window(
    camera: &PinholeRadtan,
    frames: &[&TrackedFrame],
    point_of: impl Fn(u64) -> Option<Vector3<f64>>,
    options: &LocalAdjustmentOptions,
) -> Option<Adjusted> {
    if frames.len() <= options.fixed_frames {
        return None;
    }
    // Only the undistorted positions are used: the pinhole with the camera's intrinsics.
    let pinhole = PinholeRadtan::new(
        camera.width,
        camera.height,
        [camera.fx, camera.fy, camera.cx, camera.cy],
        [0.0; 5],
    )
    .ok()?;
    // Each frame's tracks near the axis, tested once per track.
    let min_axis_cos = options.max_ray_angle_deg.to_radians().cos();
    let near_axis: Vec<Vec<&(u64, Point2<f64>)>> = frames
        .iter()
        .map(|(_, tracks)| {
            tracks
                .iter()
                .filter(|(_, px)| pinhole.bearing_from_undistorted(*px).z >= min_axis_cos)
                .collect()
        })
        .collect();
    // Each track's views among the frames, and the first and last frame seeing it.
    let mut views: FxHashMap<u64, (usize, usize, usize)> = FxHashMap::default();
    for (c, tracks) in near_axis.iter().enumerate() {
        for (t, _) in tracks {
            let v = views.entry(*t).or_insert((0, c, c));
            v.0 += 1;
            v.2 = c;
        }
    }
    let min_cos = options.min_parallax_deg.to_radians().cos();
    let with_parallax = |x: &Vector3<f64>, first: usize, last: usize| {
        let a = (x - frames[first].0.position).normalize();
        let b = (x - frames[last].0.position).normalize();
        a.dot(&b) <= min_cos
    };
    // The points seen most often, in track order among equals (the result does not
    // depend on the hash order).
    let mut candidates: Vec<(usize, u64, Vector3<f64>)> = views
        .iter()
        .filter(|(_, (seen, _, _))| *seen >= options.min_views)
        .filter_map(|(t, &(seen, first, last))| {
            let x = point_of(*t).filter(|x| with_parallax(x, first, last))?;
            Some((seen, *t, x))
        })
        .collect();
    candidates.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
    candidates.truncate(options.max_points);
    let index: FxHashMap<u64, usize> = candidates
        .iter()
        .enumerate()
        .map(|(i, (_, t, _))| (*t, i))
        .collect();
    let ids: Vec<u64> = candidates.iter().map(|(_, t, _)| *t).collect();
    let points: Vec<Vector3<f64>> = candidates.iter().map(|(_, _, x)| *x).collect();
    let mut observations = Vec::new();
    for (c, tracks) in near_axis.iter().enumerate() {
        for (t, px) in tracks {
            if let Some(&point) = index.get(t) {
                observations.push(Observation {
                    camera: c,
                    point,
                    pixel: *px,
                });
            }
        }
    }
    let mut per_frame = vec![0usize; frames.len()];
    for o in &observations {
        per_frame[o.camera] += 1;
    }
    if per_frame[options.fixed_frames..]
        .iter()
        .any(|&n| n < options.min_frame_observations)
    {
        return None;
    }
    let poses: Vec<CameraPose> = frames
        .iter()
        .map(|(p, _)| CameraPose {
            rotation: p.rotation.inverse().to_rotation_matrix(),
            centre: p.position,
        })
        .collect();
    let ba_options = BundleAdjustmentOptions {
        max_iterations: options.max_iterations,
        fixed_cameras: options.fixed_frames,
        ..BundleAdjustmentOptions::default()
    };
    let result = bundle_adjust(&pinhole, &poses, &points, &observations, &ba_options).ok()?;
    let mut outlier_points = vec![false; points.len()];
    for &o in &result.outliers {
        outlier_points[observations[o].point] = true;
    }
    let poses = frames
        .iter()
        .zip(&result.poses)
        .map(|((p, _), adjusted)| StampedPose {
            timestamp: p.timestamp,
            position: adjusted.centre,
            rotation: UnitQuaternion::from_rotation_matrix(&adjusted.rotation.inverse()),
        })
        .collect();
    let points = ids
        .into_iter()
        .zip(result.points)
        .zip(outlier_points)
        .filter(|(_, outlier)| !outlier)
        .map(|((id, x), _)| (id, x))
        .collect();
    Some(Adjusted { poses, points })
}
