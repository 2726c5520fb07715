//! Rendering throughput of `egoslam synth`'s default sequence: the walker in the room at
//! 640x480, global shutter, 2 grey levels of noise (what issue 5's 12,000-frame walk is
//! rendered with), without the PNG encoding the command adds on its own thread. Frames
//! 0-299 of the walk, every 10th (a room's views differ in cost: walls near or far, the
//! central block in view or not); median of 5 passes, all cores and then one thread. The
//! checksum of the grey frames tells an optimisation that changed the images from one
//! that did not.
//! `cargo bench -p egoslam-synth --bench render`

use egoslam_geometry::PinholeRadtan;
use egoslam_synth::{render_frame, CameraPath, RenderOptions, Scene, WalkerOptions};
use std::time::Instant;

/// Frames of the walk rendered per pass (every 10th of its first 300).
const FRAMES: usize = 30;

fn main() {
    let camera =
        PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera");
    let scene = Scene::room(0);
    let poses = CameraPath::Walker(WalkerOptions::default()).poses(300, 30.0);
    let all_cores = RenderOptions::default();
    let one_thread = RenderOptions {
        threads: 1,
        ..all_cores
    };
    for (label, options) in [("all cores", all_cores), ("one thread", one_thread)] {
        let mut per_frame_ms = Vec::new();
        let mut checksum = 0u64;
        for _ in 0..5 {
            let start = Instant::now();
            checksum = 0;
            for index in (0..poses.len()).step_by(poses.len() / FRAMES) {
                let frame = render_frame(
                    &scene,
                    &camera,
                    &poses[index..=index],
                    index as u64,
                    &options,
                );
                // FNV-1a over the grey levels.
                for &g in &frame.grey {
                    checksum = (checksum ^ u64::from(g)).wrapping_mul(0x100_0000_01b3);
                }
            }
            per_frame_ms.push(start.elapsed().as_secs_f64() * 1000.0 / FRAMES as f64);
        }
        per_frame_ms.sort_by(f64::total_cmp);
        println!(
            "render, {label} ({} threads): median {:.1} ms per frame (passes {:.1}-{:.1}); 12,000 frames ~{:.0} s; grey checksum {checksum:016x}",
            options.threads,
            per_frame_ms[2],
            per_frame_ms[0],
            per_frame_ms[4],
            per_frame_ms[2] * 12.0,
        );
    }
}
