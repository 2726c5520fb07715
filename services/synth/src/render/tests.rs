//! Tests of the renderer: rolling shutter, its blur, depth, determinism.

use super::*;
use crate::paths::CameraPath;

#[test]
fn readout_poses_span_the_readout_exactly() {
    // A path sampled 32 times per 30 fps frame interval: a 20 ms readout is 19.2
    // samples, which whole samples rounded to 20 (20.8 ms).
    let walk = CameraPath::Walker(Default::default()).poses(200, 960.0);
    let centre = walk[100].timestamp;
    let rows = readout_poses(&walk, centre, 0.020, 21);
    assert_eq!(rows.len(), 21);
    assert!((rows[0].timestamp - (centre - 0.010)).abs() < 1e-12);
    assert!((rows[20].timestamp - (centre + 0.010)).abs() < 1e-12);
    // The middle row is the frame's own pose; the ends lie between path samples.
    assert!((rows[10].position - walk[100].position).norm() < 1e-12);
    let first = &rows[0];
    let (a, b) = (&walk[90], &walk[91]); // 9.6 samples before the centre
    let f = (first.timestamp - a.timestamp) / (b.timestamp - a.timestamp);
    assert!((f - 0.4).abs() < 1e-9, "{f}");
    assert!((first.position - (a.position + (b.position - a.position) * f)).norm() < 1e-12);
    // Beyond the path's ends its end poses are kept.
    let start = readout_poses(&walk, 0.0, 0.020, 5);
    assert!((start[0].position - walk[0].position).norm() < 1e-12);
    assert!(readout_poses(&[], 0.0, 0.02, 5).is_empty());
}

#[test]
fn a_rolling_shutter_renders_each_row_from_its_own_pose() {
    // Odd height: the middle row sits exactly at the middle of the readout.
    let camera =
        PinholeRadtan::new(160, 121, [120.0, 120.0, 80.0, 60.5], [0.0; 5]).expect("camera");
    let scene = Scene::room(3);
    let walk = CameraPath::Walker(Default::default()).poses(30, 30.0);
    let readout = &walk[10..13]; // three poses a frame interval apart: a fast readout
    let rolling = RenderOptions {
        rolling_shutter: true,
        ..RenderOptions::default()
    };
    let global = RenderOptions::default();
    let frame = render_frame(&scene, &camera, readout, 7, &rolling);
    let w = 160;
    let row = |f: &Frame, r: usize| f.grey[r * w..(r + 1) * w].to_vec();
    // The middle row is the middle pose's, the first and last rows the end poses'.
    let middle = render_frame(&scene, &camera, &readout[1..2], 7, &global);
    assert_eq!(row(&frame, 60), row(&middle, 60));
    assert_ne!(row(&frame, 0), row(&middle, 0));
    let first = render_frame(&scene, &camera, &readout[..1], 7, &global);
    let (r0, f0) = (row(&frame, 0), row(&first, 0));
    let close = r0
        .iter()
        .zip(&f0)
        .filter(|(a, b)| a.abs_diff(**b) <= 8)
        .count();
    assert!(
        close > w * 9 / 10,
        "first row near the first pose's: {close}/{w}"
    );
    // A still camera: a rolling shutter changes nothing.
    let still = [readout[1], readout[1], readout[1]];
    assert_eq!(
        render_frame(&scene, &camera, &still, 7, &rolling),
        render_frame(&scene, &camera, &still[..1], 7, &global)
    );
}

#[test]
fn a_rolling_shutter_with_blur_averages_each_row_over_its_own_exposure() {
    let camera =
        PinholeRadtan::new(160, 121, [120.0, 120.0, 80.0, 60.5], [0.0; 5]).expect("camera");
    let scene = Scene::room(3);
    // The walker sampled 32 times per 30 fps frame interval, around a head turn.
    let path = CameraPath::Walker(Default::default()).poses(400, 960.0);
    let centre = path[200].timestamp;
    let (readout, exposure) = (0.020, 0.5 / 30.0);
    let clean = RenderOptions {
        rolling_shutter: true,
        noise_sigma: 0.0,
        ..RenderOptions::default()
    };
    let blurred = RenderOptions {
        blur_samples: 3,
        rolling_exposure: exposure / (readout + exposure),
        ..clean
    };
    let span = readout_poses(&path, centre, readout + exposure, 65);
    let frame = render_frame(&scene, &camera, &span, 7, &blurred);
    // Three sharp rolling-shutter frames whose readouts start at the exposure's start,
    // middle and end: each row of the blurred frame is their average.
    let sharp: Vec<Frame> = [-0.5, 0.0, 0.5]
        .iter()
        .map(|s| {
            let poses = readout_poses(&path, centre + s * exposure, readout, 65);
            render_frame(&scene, &camera, &poses, 7, &clean)
        })
        .collect();
    let n = frame.grey.len();
    let close = (0..n)
        .filter(|&i| {
            let mean = sharp.iter().map(|f| f64::from(f.grey[i])).sum::<f64>() / 3.0;
            (f64::from(frame.grey[i]) - mean).abs() <= 1.0
        })
        .count();
    assert!(close >= n * 98 / 100, "{close} of {n} within a grey level");
    // It is blurred (the three differ), and its depth is the middle exposure's.
    assert!(sharp[0].grey != sharp[2].grey && frame.grey != sharp[1].grey);
    let depth_close = (0..n)
        .filter(|&i| (frame.depth[i] - sharp[1].depth[i]).abs() < 1e-3)
        .count();
    assert!(depth_close >= n * 99 / 100, "{depth_close} of {n}");
    // Without the exposure share the poses are a plain readout, as before.
    let plain = RenderOptions {
        rolling_exposure: 0.0,
        ..blurred
    };
    let readout_only = readout_poses(&path, centre, readout, 65);
    assert_eq!(
        render_frame(&scene, &camera, &readout_only, 7, &plain),
        sharp[1]
    );
}

#[test]
fn frames_have_texture_depth_and_follow_the_camera() {
    let camera =
        PinholeRadtan::new(160, 120, [120.0, 120.0, 80.0, 60.0], [0.0; 5]).expect("camera");
    let scene = Scene::paper_planes(2);
    let poses = CameraPath::Frontal.poses(10, 30.0);
    let options = RenderOptions::default();
    let first = render_frame(&scene, &camera, &poses[..1], 0, &options);
    let mean = first.grey.iter().map(|v| f64::from(*v)).sum::<f64>() / first.grey.len() as f64;
    let spread = (first
        .grey
        .iter()
        .map(|v| (f64::from(*v) - mean).powi(2))
        .sum::<f64>()
        / first.grey.len() as f64)
        .sqrt();
    assert!(spread > 20.0, "textured: {spread}");
    // The centre pixel sees the 2.56 m plane 5 m ahead; the camera moves 2 m towards it.
    let centre = 60 * 160 + 80;
    assert!(
        (first.depth[centre] - 5.0).abs() < 0.01,
        "{}",
        first.depth[centre]
    );
    let last = render_frame(&scene, &camera, &poses[9..], 9, &options);
    assert!(
        (last.depth[centre] - 3.0).abs() < 0.01,
        "{}",
        last.depth[centre]
    );
    // Deterministic.
    assert_eq!(
        first,
        render_frame(&scene, &camera, &poses[..1], 0, &options)
    );
}

/// TUM's depth PNG convention: metres x 5000, rounded, clamped to 16 bits, big-endian.
#[test]
fn depth_png_samples_follow_the_tum_convention() {
    let frame = Frame {
        width: 5,
        height: 1,
        grey: vec![0; 5],
        depth: vec![0.0, 1.0, 0.00011, 2.5002, 20.0],
    };
    let samples: Vec<u16> = frame
        .depth_png_samples()
        .chunks(2)
        .map(|b| u16::from_be_bytes([b[0], b[1]]))
        .collect();
    assert_eq!(samples, vec![0, 5000, 1, 12501, 65535]);
}

#[test]
fn cos_turns_is_the_library_cosine_to_the_last_place() {
    let mut worst: f64 = 0.0;
    for i in 0..=1_000_000u32 {
        let b = f64::from(i) / 1_000_000.0 + f64::from(i % 7) * 1e-9;
        let b = b.min(1.0);
        let exact = (std::f64::consts::TAU * b).cos();
        worst = worst.max((cos_turns(b) - exact).abs());
    }
    assert!(worst < 1e-15, "worst difference {worst:e}");
}
