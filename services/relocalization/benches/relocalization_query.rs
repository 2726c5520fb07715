//! Relocalization query time against a 1,000-keyframe map (issue 7: median <= 30 ms per
//! frame on one core). The map: 1,000 keyframes rendered along a 3,000-frame walk (every
//! third frame, points from the rendered depth); the queries: 60 frames between keyframes,
//! each relocalized from scratch. Reported: median and 90th percentile of the whole query
//! (GFTT corners + ORB descriptors + relocalization + patch alignment) and of relocalization
//! with patch alignment alone.
//! `cargo bench -p egoslam-relocalization --bench relocalization_query`

#[path = "../tests/support/mod.rs"]
mod support;

use egoslam_relocalization::descriptors::{detect_corners, DescriberOptions, QueryCornerOptions};
use egoslam_relocalization::{default_vocabulary, OrbDescriber, Relocalizer, RelocalizerOptions};
use egoslam_synth::{render_frame, CameraPath, RenderOptions, Scene, WalkerOptions};
use opencv::core::Mat;
use opencv::prelude::*;
use std::time::Instant;
use support::rendered_map::{camera, described_frame, rendered_map};

fn percentile(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    let scene = Scene::room(3);
    let poses = CameraPath::Walker(WalkerOptions::default()).poses(3000, 30.0);
    let mut describer = OrbDescriber::new(DescriberOptions::default()).expect("orb");
    let started = Instant::now();
    let map = rendered_map(&scene, &poses, 3, &mut describer, |k| {
        if k % 100 == 0 {
            eprintln!("rendering keyframe {k} of 1000");
        }
    });
    eprintln!("map built in {:.0} s", started.elapsed().as_secs_f64());
    let started = Instant::now();
    let relocalizer = Relocalizer::new(default_vocabulary().expect("vocabulary"), map);
    let index_s = started.elapsed().as_secs_f64();
    let options = RelocalizerOptions::default();
    let (mut whole, mut relocalize_only, mut found) = (Vec::new(), Vec::new(), 0);
    let mut alignment = Vec::new();
    for (i, pose) in poses.iter().enumerate().skip(1).step_by(50) {
        let frame = render_frame(
            &scene,
            &camera(),
            &[*pose],
            5000 + i as u64,
            &RenderOptions::default(),
        );
        let image = Mat::new_rows_cols_with_data(480, 640, &frame.grey)
            .expect("wrap")
            .try_clone()
            .expect("copy");
        let t0 = Instant::now();
        let corners = detect_corners(&image, &QueryCornerOptions::default()).expect("corners");
        let _ = describer.describe(&image, &corners).expect("describe");
        let features_ms = t0.elapsed().as_secs_f64() * 1e3;
        // The same features as the map's (exact pixels), for the relocalization timing.
        let (query, _, _) = described_frame(&scene, pose, 5000 + i as u64, &mut describer);
        let t1 = Instant::now();
        if let Ok(r) = relocalizer.relocalize(&query, &options) {
            let t2 = Instant::now();
            let _ = relocalizer.refine_by_patches(r, &image, &camera(), &options);
            alignment.push(t2.elapsed().as_secs_f64() * 1e3);
            found += 1;
        }
        let ms = t1.elapsed().as_secs_f64() * 1e3;
        relocalize_only.push(ms);
        whole.push(features_ms + ms);
    }
    let n = whole.len();
    println!(
        "1000-keyframe map ({} points), indexed in {:.2} s; {} queries, {} relocalized",
        relocalizer.map().points.len(),
        index_s,
        n,
        found
    );
    println!(
        "whole query: median {:.1} ms, p90 {:.1} ms; relocalization alone: median {:.1} ms, p90 {:.1} ms",
        percentile(&mut whole, 0.5),
        percentile(&mut whole, 0.9),
        percentile(&mut relocalize_only, 0.5),
        percentile(&mut relocalize_only, 0.9)
    );
    println!(
        "of which patch alignment: median {:.1} ms, p90 {:.1} ms",
        percentile(&mut alignment, 0.5),
        percentile(&mut alignment, 0.9)
    );
}
