//! Time to solve one window of 20 keyframes, per stage, one core: a synthetic window
//! (~1000 tracks per keyframe, 1 px noise) and a real one (KITTI 00, keyframes from the
//! real tracker). Median of 7 runs, each with an empty edge cache, once per five-point
//! RANSAC (own LO-RANSAC, OpenCV's USAC). Method in
//! docs/benchmarks.md. `cargo bench -p egoslam-solver --bench window_solve`

use egoslam_frontend::{Tracker, TrackerOptions};
use egoslam_geometry::PinholeRadtan;
use egoslam_solver::relative_pose::EssentialEstimator;
use egoslam_solver::triangulation::CameraPose;
use egoslam_solver::view_graph::{EdgeCache, KeyframeObservations};
use egoslam_solver::window_solver::{solve_window, WindowSolverOptions};
use egoslam_sources::FrameSource;
use nalgebra::{Point2, Rotation3, Vector3};
use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

/// Deterministic pseudo-random numbers in [0, 1) (keeps the bench free of dev-dependencies).
struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn synthetic() -> (PinholeRadtan, Vec<KeyframeObservations>) {
    let camera =
        PinholeRadtan::new(640, 480, [520.0, 520.0, 320.0, 240.0], [0.0; 5]).expect("camera");
    let mut rng = Lcg(9);
    let points: Vec<Vector3<f64>> = (0..2500)
        .map(|_| {
            Vector3::new(
                12.0 * rng.next() - 6.0,
                6.0 * rng.next() - 3.0,
                3.0 + 12.0 * rng.next(),
            )
        })
        .collect();
    let keyframes = (0..20)
        .map(|k| {
            let t = k as f64;
            let pose = CameraPose {
                rotation: Rotation3::from_euler_angles(
                    0.03 * (0.7 * t).sin(),
                    0.12 * (0.3 * t).sin(),
                    0.02 * t.cos(),
                ),
                centre: Vector3::new(0.03 * (0.5 * t).sin(), 0.01 * t.cos(), 0.08 * t),
            };
            let mut tracks = BTreeMap::new();
            for (id, x) in points.iter().enumerate() {
                if let Some(p) = camera.project_undistorted(&pose.to_camera(x)) {
                    if camera.contains(p) && tracks.len() < 1000 {
                        let (a, b) = (rng.next().max(1e-12), rng.next());
                        let r = (-2.0 * a.ln()).sqrt();
                        let (nx, ny) = (
                            r * (std::f64::consts::TAU * b).cos(),
                            r * (std::f64::consts::TAU * b).sin(),
                        );
                        tracks.insert(id as u64, Point2::new(p.x + nx, p.y + ny));
                    }
                }
            }
            KeyframeObservations {
                id: k,
                timestamp: t,
                tracks,
            }
        })
        .collect();
    (camera, keyframes)
}

fn kitti() -> Option<(PinholeRadtan, Vec<KeyframeObservations>)> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/kitti_odometry_00");
    if !path.exists() {
        println!("kitti window: skipped ({} absent)", path.display());
        return None;
    }
    let layout = egoslam_sources::detect_layout(&path).ok()?;
    let calib = egoslam_sources::load_calibration(&layout, None).ok()?;
    let mut source = egoslam_sources::open_source(&path, 10.0).ok()?;
    let mut tracker: Option<Tracker> = None;
    let mut keyframes = Vec::new();
    let mut camera = None;
    while let Some(Ok(frame)) = source.next_frame() {
        use opencv::prelude::MatTraitConst;
        let cam = *camera.get_or_insert(
            calib
                .camera_for(frame.image.cols() as u32, frame.image.rows() as u32)
                .ok()?,
        );
        let t = tracker.get_or_insert_with(|| Tracker::new(cam, TrackerOptions::default()));
        if let Some(k) = t.process(frame.index, &frame.image).ok()?.keyframe {
            keyframes.push(KeyframeObservations {
                id: k.keyframe_id,
                timestamp: frame.timestamp,
                tracks: k
                    .tracks
                    .iter()
                    .map(|p| {
                        (
                            p.track_id,
                            Point2::new(f64::from(p.undistorted.x), f64::from(p.undistorted.y)),
                        )
                    })
                    .collect(),
            });
            if keyframes.len() == 20 {
                break;
            }
        }
    }
    Some((camera?, keyframes))
}

fn bench(name: &str, camera: &PinholeRadtan, keyframes: &[KeyframeObservations]) {
    for estimator in [EssentialEstimator::LoRansac, EssentialEstimator::OpenCvUsac] {
        let mut options = WindowSolverOptions::default();
        options.view_graph.relative_pose.estimator = estimator;
        bench_with(
            &format!("{name} [{estimator:?}]"),
            camera,
            keyframes,
            &options,
        );
    }
}

fn bench_with(
    name: &str,
    camera: &PinholeRadtan,
    keyframes: &[KeyframeObservations],
    options: &WindowSolverOptions,
) {
    let tracks: usize = keyframes.iter().map(|k| k.tracks.len()).sum::<usize>() / keyframes.len();
    let mut totals = Vec::new();
    let mut stages: BTreeMap<&'static str, Vec<f64>> = BTreeMap::new();
    for _ in 0..7 {
        let start = Instant::now();
        let s = solve_window(camera, keyframes, options, &mut EdgeCache::new());
        totals.push(start.elapsed().as_secs_f64() * 1e3);
        for (stage, ms) in s.timings_ms {
            stages.entry(stage).or_default().push(ms);
        }
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let parts: Vec<String> = stages
        .iter_mut()
        .map(|(k, v)| format!("{k} {:.1}", median(v)))
        .collect();
    println!(
        "{name}: {} keyframes, {tracks} tracks/keyframe: median {:.1} ms total; {}",
        keyframes.len(),
        median(&mut totals),
        parts.join(", ")
    );
}

fn main() {
    opencv::core::set_num_threads(1).expect("one OpenCV thread");
    let (camera, keyframes) = synthetic();
    bench("synthetic window", &camera, &keyframes);
    if let Some((camera, keyframes)) = kitti() {
        bench(
            "kitti_odometry_00 window (first 20 keyframes)",
            &camera,
            &keyframes,
        );
    }
}
