//! The real processes over iceoryx2 on real frames.

mod common;

use common::*;
use egoslam_bus::{Bus, BusOptions, MessageSubscriber, KEYFRAMES};
use egoslam_messages::internal::v1 as internal;
use std::collections::BTreeSet;
use std::path::Path;
use std::time::Duration;

/// Runs replay + frontend as processes and collects the keyframe stream in this process.
fn keyframe_stream(input: &Path, test: &str) -> (Vec<internal::Keyframe>, usize) {
    let (keyframes, frames, _) = keyframe_stream_with(input, test, &[]);
    (keyframes, frames)
}

/// [`keyframe_stream`] with extra frontend arguments; also returns the camera and the
/// readout the frontend estimated online (`frontend.readout`, ms), if it did.
fn keyframe_stream_with(
    input: &Path,
    test: &str,
    frontend_args: &[&str],
) -> (
    Vec<internal::Keyframe>,
    usize,
    (egoslam_geometry::PinholeRadtan, Option<f64>),
) {
    let ns = namespace(test);
    let out = tempfile::tempdir().expect("tempdir");
    // Resolve the calibration the way the launcher does, through `run`'s checks, by writing
    // the dataset's own calibration in egoslam format.
    let layout = egoslam_sources::detect_layout(input).expect("layout");
    let calib = egoslam_sources::load_calibration(&layout, None).expect("calibration");
    use egoslam_sources::FrameSource;
    let mut src = egoslam_sources::open_source(input, 30.0).expect("source");
    let frames = src.len_hint().expect("known length");
    let first = src.next_frame().expect("frame").expect("decodes");
    use opencv::prelude::MatTraitConst;
    let camera = calib
        .camera_for(first.image.cols() as u32, first.image.rows() as u32)
        .expect("camera");
    let camera_file = out.path().join("camera.yaml");
    let d = camera.distortion;
    std::fs::write(
        &camera_file,
        format!(
            "width: {}\nheight: {}\nfx: {}\nfy: {}\ncx: {}\ncy: {}\ndistortion: [{}, {}, {}, {}, {}]\n",
            camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, d[0], d[1], d[2], d[3], d[4]
        ),
    )
    .expect("camera file");

    let bus = Bus::open(
        "test",
        BusOptions {
            namespace: ns.clone(),
            ..BusOptions::default()
        },
    )
    .expect("bus");
    let mut sub =
        MessageSubscriber::<internal::Keyframe>::create(&bus, KEYFRAMES).expect("subscriber");
    let common_args = [
        format!("--namespace={ns}"),
        format!("--out={}", out.path().display()),
        format!("--camera={}", camera_file.display()),
    ];
    let mut frontend = egoslam()
        .arg("frontend")
        .args(&common_args)
        .args(frontend_args)
        .spawn()
        .expect("frontend");
    let mut replay = egoslam()
        .arg("replay")
        .arg(format!("--input={}", input.display()))
        .args(&common_args)
        .spawn()
        .expect("replay");
    let mut keyframes = Vec::new();
    loop {
        let k = sub.receive().expect("receive").expect("not terminated");
        if k.end_of_stream {
            keyframes.push(k);
            break;
        }
        keyframes.push(k);
    }
    // A consumer that has read the end of stream disconnects; the producer waits for that.
    drop(sub);
    assert!(replay.wait().expect("replay exit").success());
    assert!(frontend.wait().expect("frontend exit").success());
    std::thread::sleep(Duration::from_millis(10));
    let readout = std::fs::read_to_string(out.path().join("state/frontend.readout"))
        .ok()
        .and_then(|t| t.trim().parse().ok());
    (keyframes, frames, (camera, readout))
}

/// Checks a keyframe stream: ids strictly increasing without gaps, tracks inside the image,
/// every frame accounted for exactly once, enough tracks for SfM.
fn check_stream(
    keyframes: &[internal::Keyframe],
    frames: usize,
    min_keyframes: usize,
    max_keyframes: usize,
) {
    let (eos, kfs) = keyframes.split_last().expect("end of stream");
    assert!(eos.end_of_stream);
    assert!(
        kfs.len() >= min_keyframes && kfs.len() <= max_keyframes,
        "{} keyframes",
        kfs.len()
    );
    let mut seen_frames = BTreeSet::new();
    for (i, k) in kfs.iter().enumerate() {
        assert_eq!(
            k.keyframe_id, i as u64,
            "keyframe ids must be 0,1,2,... without gaps"
        );
        let intr = k.intrinsics.as_ref().expect("intrinsics");
        assert!(
            k.tracks.len() >= 100,
            "keyframe {} has only {} tracks",
            i,
            k.tracks.len()
        );
        for t in &k.tracks {
            assert!(
                t.raw_x >= 0.0
                    && t.raw_y >= 0.0
                    && t.raw_x < intr.width as f32
                    && t.raw_y < intr.height as f32
            );
        }
        let ids: BTreeSet<u64> = k.tracks.iter().map(|t| t.track_id).collect();
        assert_eq!(
            ids.len(),
            k.tracks.len(),
            "track ids unique within a keyframe"
        );
        for f in &k.frames_since_previous {
            assert!(seen_frames.insert(f.frame_id));
        }
        assert!(seen_frames.insert(k.frame_id));
    }
    for f in &eos.trailing_frames {
        assert!(seen_frames.insert(f.frame_id));
    }
    assert_eq!(
        seen_frames,
        (0..frames as u64).collect::<BTreeSet<_>>(),
        "every frame once"
    );
    assert_eq!(kfs[0].reason, internal::KeyframeReason::First as i32);
    // Consecutive keyframes share tracks (needed for the five-point relative pose).
    for w in kfs.windows(2) {
        let a: BTreeSet<u64> = w[0].tracks.iter().map(|t| t.track_id).collect();
        let shared = w[1]
            .tracks
            .iter()
            .filter(|t| a.contains(&t.track_id))
            .count();
        assert!(
            shared >= 50,
            "keyframes {} and {} share {shared} tracks",
            w[0].keyframe_id,
            w[1].keyframe_id
        );
    }
}

#[test]
fn tum_fixture_keyframe_stream_through_real_processes() {
    let (kfs, frames) = keyframe_stream(&tum_fixture(), "tum");
    assert_eq!(frames, 120);
    // fr1_rpy turns fast (20-95 deg/s): the flow rule fires often.
    check_stream(&kfs, frames, 20, 110);
}

/// A frontend started on its own (as systemd does) with the default `auto` readout
/// estimates it from the stream's first frames, holds their keyframes until then and
/// corrects them, and corrects every keyframe after (docs/config.md).
#[test]
fn a_frontend_on_its_own_estimates_the_readout_online() {
    let (kfs, frames, (camera, readout)) = keyframe_stream_with(
        &tum_fixture(),
        "tum_readout",
        &["--rolling-shutter-ms=auto", "--readout-frames=60"],
    );
    check_stream(&kfs, frames, 20, 110);
    // Measured on the clip's first 60 frames: 18 ms (21 from all 120).
    let readout = readout.expect("frontend.readout written");
    assert!((12.0..=30.0).contains(&readout), "{readout} ms");
    // Observations are moved from the undistorted raw positions, those of the keyframes
    // held for the estimate as well.
    let shift = |k: &internal::Keyframe| {
        let total: f64 = k
            .tracks
            .iter()
            .map(|t| {
                let u = camera
                    .undistort_pixel(nalgebra::Point2::new(
                        f64::from(t.raw_x),
                        f64::from(t.raw_y),
                    ))
                    .expect("a radial-tangential pixel always undistorts");
                ((u.x - f64::from(t.x)).powi(2) + (u.y - f64::from(t.y)).powi(2)).sqrt()
            })
            .sum();
        total / k.tracks.len().max(1) as f64
    };
    let (before, after): (Vec<_>, Vec<_>) = kfs
        .iter()
        .filter(|k| !k.end_of_stream)
        .partition(|k| k.frame_id < 59);
    for (part, keyframes) in [("held", &before), ("after", &after)] {
        let moved = keyframes.iter().filter(|k| shift(k) > 0.2).count();
        assert!(
            !keyframes.is_empty() && moved * 2 > keyframes.len(),
            "{part}: {moved} of {} keyframes corrected",
            keyframes.len()
        );
    }
    // Held or not, they went out in order.
    assert!(kfs
        .windows(2)
        .all(|w| w[0].keyframe_id < w[1].keyframe_id || w[1].end_of_stream));
}

#[test]
fn kitti_keyframe_stream() {
    let Some(input) = shared("kitti_odometry_00") else {
        return;
    };
    let (kfs, frames) = keyframe_stream(&input, "kitti");
    check_stream(&kfs, frames, 15, 150);
}

#[test]
fn euroc_keyframe_stream() {
    let Some(input) = shared("euroc_v1_01") else {
        return;
    };
    let (kfs, frames) = keyframe_stream(&input, "euroc");
    // The MAV sits still: only the P = 30 rule fires (95 frames -> keyframes 0, 30, 60, 90 + last).
    check_stream(&kfs, frames, 4, 6);
}

#[test]
fn run_writes_every_output_and_the_report() {
    let out = tempfile::tempdir().expect("tempdir");
    let status = egoslam()
        .args(["run", "--input"])
        .arg(tum_fixture())
        .arg("--out")
        .arg(out.path())
        .status()
        .expect("run");
    assert!(status.success());
    for f in [
        "trajectory.tum",
        "keyframes.tum",
        "map.ply",
        "report.json",
        "camera.yaml",
    ] {
        assert!(out.path().join(f).is_file(), "{f} missing");
    }
    // Owner-only, results and state alike (egocentric video is private).
    use std::os::unix::fs::PermissionsExt;
    for entry in walk(out.path()) {
        let mode = std::fs::metadata(&entry)
            .expect("metadata")
            .permissions()
            .mode()
            & 0o777;
        let expected = if entry.is_dir() { 0o700 } else { 0o600 };
        assert_eq!(mode, expected, "{} is {mode:o}", entry.display());
    }
    let report: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.path().join("report.json")).expect("read"),
    )
    .expect("json");
    for key in [
        "frames",
        "posed_frames",
        "keyframes",
        "windows",
        "segments",
        "timings_ms",
    ] {
        assert!(report.get(key).is_some(), "report lacks {key}");
    }
    assert_eq!(report["schema_version"], 3);
    assert_eq!(report["frames"], 120);
    assert_eq!(report["dropped_frames"], 0);
    assert_eq!(report["skipped_frames"], serde_json::json!({}));
    assert!(report["interrupted_by_signal"].is_null());
    let keyframes = report["keyframes"].as_u64().expect("number");
    let windows = report["windows"].as_u64().expect("number");
    // K = 20, O = 5: 1 + ceil((keyframes - 20) / 15) windows.
    assert_eq!(windows, 1 + keyframes.saturating_sub(20).div_ceil(15));
    assert!(
        report["timings_ms"]["frontend.track"]
            .as_f64()
            .expect("timing")
            > 0.0
    );
}

/// `egoslam calibrate-readout` on the TUM clip: the estimate and the configuration line
/// (docs/config.md; measured 21 ms).
#[test]
fn calibrate_readout_reads_the_clip() {
    let out = egoslam()
        .args(["calibrate-readout", "--input"])
        .arg(tum_fixture())
        .output()
        .expect("calibrate-readout");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let ms: f64 = text
        .strip_prefix("readout ")
        .and_then(|rest| rest.split(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no readout in: {text}"));
    assert!((15.0..=30.0).contains(&ms), "{text}");
    assert!(
        text.contains(&format!("rolling_shutter_ms = {ms}")),
        "{text}"
    );
}

/// Every file and folder under `dir` (not `dir` itself, which the test made).
fn walk(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut found = Vec::new();
    for entry in std::fs::read_dir(dir).expect("read_dir").flatten() {
        let path = entry.path();
        if path.is_dir() {
            found.extend(walk(&path));
        }
        found.push(path);
    }
    found
}
