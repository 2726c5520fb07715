//! Property tests of every parser of outside files: whatever the bytes, a parser returns a
//! value or an error naming the file, never panics or hangs, and what it returns is usable.
//! CI runs proptest's default 256 cases per property; the bench mode runs 10,000:
//! `PROPTEST_CASES=10000 cargo test -p egoslam-sources --test parser_properties`.

use egoslam_sources::calibration::read_calibration_file;
use egoslam_sources::{load_ground_truth, open_source, FrameSource};
use opencv::prelude::*;
use proptest::prelude::*;

/// Numbers as files have them, hostile ones included.
fn number() -> impl Strategy<Value = String> {
    prop_oneof![
        (-1e4f64..1e4).prop_map(|v| v.to_string()),
        Just("nan".to_string()),
        Just("inf".to_string()),
        Just("-inf".to_string()),
        Just("1e308".to_string()),
        Just("0".to_string()),
        Just("-1".to_string()),
        "[a-z]{1,4}",
    ]
}

fn yaml_value() -> impl Strategy<Value = String> {
    prop_oneof![
        number(),
        prop::collection::vec(number(), 0..7).prop_map(|v| format!("[{}]", v.join(", "))),
        Just("{rows: 1, cols: 4, data: [500, 500, 320, 240]}".to_string()),
        Just("*alias".to_string()),
        Just("".to_string()),
    ]
}

const CALIBRATION_KEYS: &[&str] = &[
    "fx",
    "fy",
    "cx",
    "cy",
    "width",
    "height",
    "k1",
    "p2",
    "distortion",
    "intrinsics",
    "resolution",
    "distortion_coefficients",
    "distortion_model",
    "Camera.fx",
    "Camera.fy",
    "Camera.cx",
    "Camera.cy",
];

proptest! {
    #[test]
    fn calibration_files_parse_or_fail_with_the_file_named(
        entries in prop::collection::vec((prop::sample::select(CALIBRATION_KEYS), yaml_value()), 0..12)
    ) {
        let dir = tempfile::tempdir().expect("tempdir");
        let file = dir.path().join("camera.yaml");
        let text: String = entries.iter().map(|(k, v)| format!("{k}: {v}\n")).collect();
        std::fs::write(&file, text).expect("write");
        match read_calibration_file(&file) {
            Ok(c) => {
                // A usable camera or an error, for the calibration's own size or another.
                let _ = c.camera_for(640, 480);
                let _ = c.camera_for(c.width.unwrap_or(1), c.height.unwrap_or(1));
            }
            Err(e) => prop_assert!(e.to_string().contains("camera.yaml"), "{e}"),
        }
    }

    #[test]
    fn ground_truth_files_load_finite_poses_or_fail(
        rows in prop::collection::vec(prop::collection::vec(number(), 7..13), 1..20),
        kitti in any::<bool>(),
    ) {
        let dir = tempfile::tempdir().expect("tempdir");
        let file = if kitti {
            let seq = dir.path().join("sequences/00");
            std::fs::create_dir_all(&seq).expect("mkdir");
            let times: String = (0..rows.len()).map(|i| format!("{}\n", i as f64 * 0.1)).collect();
            std::fs::write(seq.join("times.txt"), times).expect("times");
            std::fs::create_dir_all(dir.path().join("poses")).expect("mkdir");
            dir.path().join("poses/00.txt")
        } else {
            dir.path().join("groundtruth.txt")
        };
        let text: String = rows.iter().map(|r| format!("{}\n", r.join(" "))).collect();
        std::fs::write(&file, text).expect("write");
        if let Ok(gt) = load_ground_truth(&file) {
            for p in &gt.poses {
                prop_assert!(p.timestamp.is_finite());
                prop_assert!(p.position.iter().all(|v| v.is_finite()));
                prop_assert!(p.rotation.coords.iter().all(|v| v.is_finite()));
            }
        }
    }

    /// A TUM index with hostile timestamps and missing, empty or unreadable frames: the
    /// stream yields finite, increasing timestamps, and every listed frame is either
    /// yielded or counted as skipped.
    #[test]
    fn frame_streams_yield_only_usable_frames_and_count_the_rest(
        lines in prop::collection::vec((number(), 0..4u8), 1..25)
    ) {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::create_dir(dir.path().join("rgb")).expect("mkdir");
        let good = opencv::core::Mat::new_rows_cols_with_default(
            8, 8, opencv::core::CV_8UC1, 90.into()).expect("mat");
        let mut index = String::new();
        for (i, (stamp, kind)) in lines.iter().enumerate() {
            let name = format!("rgb/{i}.png");
            let path = dir.path().join(&name);
            match kind {
                0 | 1 => {
                    opencv::imgcodecs::imwrite_def(path.to_str().expect("utf-8"), &good)
                        .expect("png");
                }
                2 => std::fs::write(&path, b"").expect("empty"),
                _ => {} // missing
            }
            index += &format!("{stamp} {name}\n");
        }
        std::fs::write(dir.path().join("rgb.txt"), index).expect("index");
        let Ok(mut stream) = open_source(dir.path(), 30.0) else {
            return Ok(()); // an index line without a parseable timestamp: refused whole
        };
        let mut last = f64::NEG_INFINITY;
        let mut yielded = 0u64;
        while let Some(frame) = stream.next_frame() {
            let frame = frame.expect("no fatal error from a listed sequence");
            prop_assert!(frame.timestamp.is_finite() && frame.timestamp > last);
            prop_assert_eq!((frame.image.cols(), frame.image.rows()), (8, 8));
            last = frame.timestamp;
            yielded += 1;
        }
        prop_assert_eq!(yielded + stream.skipped().total(), lines.len() as u64);
    }
}
