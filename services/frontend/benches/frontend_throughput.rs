//! Frontend throughput on real sequences, one thread: frames/s of `Tracker::process` over
//! pre-decoded frames (decode excluded), median of 5 passes. Method in docs/benchmarks.md.
//!
//! `cargo bench -p egoslam-frontend --bench frontend_throughput`

use egoslam_frontend::{Tracker, TrackerOptions};
use egoslam_sources::{calibration::load_calibration, detect_layout, open_source, FrameSource};
use opencv::core::Mat;
use opencv::prelude::*;
use std::path::Path;
use std::time::Instant;

fn bench(name: &str, path: &Path) {
    if !path.exists() {
        println!("{name}: skipped ({} absent)", path.display());
        return;
    }
    let layout = detect_layout(path).expect("layout");
    let calib = load_calibration(&layout, None).expect("calibration");
    let mut source = open_source(path, 30.0).expect("source");
    let mut frames: Vec<Mat> = Vec::new();
    while let Some(f) = source.next_frame() {
        frames.push(f.expect("frame").image);
    }
    let camera = calib
        .camera_for(frames[0].cols() as u32, frames[0].rows() as u32)
        .expect("camera");
    let mut rates = Vec::new();
    let mut live = Vec::new();
    for _ in 0..5 {
        let mut tracker = Tracker::new(camera, TrackerOptions::default());
        let start = Instant::now();
        for (i, img) in frames.iter().enumerate() {
            let out = tracker.process(i as u64, img).expect("track");
            live.push(out.live_tracks);
        }
        rates.push(frames.len() as f64 / start.elapsed().as_secs_f64());
    }
    rates.sort_by(f64::total_cmp);
    live.sort_unstable();
    println!(
        "{name}: {}x{}, {} frames: median {:.1} frames/s (min {:.1}, max {:.1}); live tracks median {}, 10th percentile {}",
        frames[0].cols(),
        frames[0].rows(),
        frames.len(),
        rates[2],
        rates[0],
        rates[4],
        live[live.len() / 2],
        live[live.len() / 10]
    );
}

fn main() {
    opencv::core::set_num_threads(1).expect("one OpenCV thread");
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    bench(
        "tum_fr1_rpy (in-repo JPEG clip)",
        &root.join("tests/data/tum_fr1_rpy_120"),
    );
    bench(
        "tum_fr1_rpy (shared, PNG)",
        &root.join("../shared/data/tum_fr1_rpy"),
    );
    bench(
        "kitti_odometry_00",
        &root.join("../shared/data/kitti_odometry_00"),
    );
    bench("euroc_v1_01", &root.join("../shared/data/euroc_v1_01"));
}
