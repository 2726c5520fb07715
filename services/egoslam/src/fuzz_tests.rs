//! Mutation fuzzing of everything egoslam decodes from outside (issue: "10,000 fuzzed frames
//! and messages: 0 panics"): wire messages through the conversions the services apply,
//! the window journal, the merger checkpoint, the config file, calibration and ground-truth
//! files, and image frames. Each input starts from a valid sample and is mutated (bit flips,
//! byte overwrites, truncation, insertion, duplication) by a seeded generator, so a failure
//! is reproducible from the printed iteration. Errors are expected; a panic fails the test.

use crate::config::ConfigFile;
use egoslam_durability::checkpoint::Checkpoint;
use egoslam_durability::window_journal::{self, JournalWriter};
use egoslam_merger::MergerState;
use egoslam_messages::internal::v1 as internal;
use egoslam_messages::v1 as pb;
use prost::Message;
use std::path::Path;

/// A seeded mutator (64-bit LCG, Knuth's constants).
struct Mutator(u64);

impl Mutator {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0 >> 33
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }

    /// One to four random edits of `input`.
    fn mutate(&mut self, input: &[u8]) -> Vec<u8> {
        let mut v = input.to_vec();
        for _ in 0..1 + self.below(4) {
            let at = self.below(v.len());
            match self.below(5) {
                0 if !v.is_empty() => v[at] ^= 1 << self.below(8),
                1 if !v.is_empty() => v[at] = self.next() as u8,
                2 => v.truncate(at),
                3 => v.insert(at.min(v.len()), self.next() as u8),
                _ => {
                    let end = (at + 1 + self.below(16)).min(v.len());
                    let chunk = v[at.min(end)..end].to_vec();
                    v.splice(at.min(v.len())..at.min(v.len()), chunk);
                }
            }
        }
        v
    }
}

/// Feeds `n` mutations of `sample` to `decode` (which says whether it accepted the input);
/// a panic names the iteration. At least 5 % must be accepted and at least one refused:
/// the fuzzing then reaches both what runs on decoded data and the error paths, not only
/// the first check.
fn fuzz(name: &str, seed: u64, n: usize, sample: &[u8], mut decode: impl FnMut(&[u8]) -> bool) {
    let mut m = Mutator(seed);
    let mut accepted = 0;
    for i in 0..n {
        let input = m.mutate(sample);
        let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| decode(&input)));
        match caught {
            Ok(ok) => accepted += usize::from(ok),
            Err(_) => panic!("{name}: panic on iteration {i} (seed {seed})"),
        }
    }
    assert!(
        accepted >= n / 20 && accepted < n,
        "{name}: {accepted} of {n} mutated inputs accepted"
    );
}

fn fixture() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/tum_fr1_rpy_120")
}

fn window_sample() -> internal::WindowSolution {
    let pose = |i: u64| internal::KeyframePose {
        keyframe_id: i,
        pose: Some(egoslam_relocalization::wire::pose_to_pb(
            i,
            0,
            &egoslam_geometry::StampedPose {
                timestamp: i as f64,
                position: nalgebra::Vector3::new(0.1 * i as f64, 0.0, 0.0),
                rotation: nalgebra::UnitQuaternion::identity(),
            },
        )),
    };
    internal::WindowSolution {
        window_id: 1,
        stream_id: 5,
        keyframe_ids: vec![0, 1, 2],
        poses: (0..3).map(pose).collect(),
        points: vec![pb::MapPoint {
            track_id: 9,
            position: Some(pb::Vec3 {
                x: 1.0,
                y: 2.0,
                z: 3.0,
            }),
            observations: 3,
            relative_std: None,
            largest_reprojection_sigmas: None,
        }],
        observations: (0..3)
            .map(|k| internal::Observation {
                keyframe_id: k,
                track_id: 9,
                x: 100.0,
                y: 120.0,
            })
            .collect(),
        quality: Some(internal::SolutionQuality {
            status: internal::SolveStatus::Solved as i32,
            ..Default::default()
        }),
        ..Default::default()
    }
}

#[test]
fn wire_messages_and_their_conversions() {
    let window = window_sample().encode_to_vec();
    fuzz("WindowSolution", 1, 3000, &window, |b| {
        let Ok(w) = internal::WindowSolution::decode(b) else {
            return false;
        };
        let input = egoslam_merger::session::window_input(&w);
        if input.is_finite() {
            let mut map = egoslam_merger::MapBuilder::new();
            map.add_window(&input);
            map.add_window(&input);
        }
        true
    });
    let keyframe = internal::Keyframe {
        keyframe_id: 4,
        intrinsics: Some(pb::Intrinsics {
            width: 640,
            height: 480,
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
            distortion: vec![0.0; 5],
            ..Default::default()
        }),
        tracks: (0..20)
            .map(|t| internal::TrackObservation {
                track_id: t,
                x: 10.0 * t as f32,
                y: 5.0 * t as f32,
                ..Default::default()
            })
            .collect(),
        ..Default::default()
    }
    .encode_to_vec();
    fuzz("Keyframe", 2, 2000, &keyframe, |b| {
        let Ok(k) = internal::Keyframe::decode(b) else {
            return false;
        };
        let mut stats = egoslam_runtime::ServiceStats::new("solver");
        let _ = egoslam_solver_service::observations(&k, &mut stats);
        true
    });
}

#[test]
fn files_the_services_read_back() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("input");
    // Window journal.
    let journal_path = dir.path().join(window_journal::FILE_NAME);
    let mut writer = JournalWriter::create(&journal_path, 5).expect("journal");
    for _ in 0..3 {
        writer.append(&window_sample()).expect("append");
    }
    let journal = std::fs::read(&journal_path).expect("bytes");
    fuzz("journal", 3, 1500, &journal, |b| {
        std::fs::write(&path, b).expect("write");
        window_journal::read(&path).is_ok()
    });
    // Merger checkpoint.
    let mut state = MergerState::for_stream(5);
    state
        .map
        .add_window(&egoslam_merger::session::window_input(&window_sample()));
    let checkpoint_path = dir.path().join("checkpoint");
    state.save(&checkpoint_path).expect("save");
    let checkpoint = std::fs::read(&checkpoint_path).expect("bytes");
    fuzz("checkpoint", 4, 1500, &checkpoint, |b| {
        std::fs::write(&path, b).expect("write");
        matches!(MergerState::load(&path), Ok(Some(_)))
    });
    // Config file.
    let config =
        std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../deploy/egoslam.toml"))
            .expect("config");
    let command = <crate::cli::Cli as clap::CommandFactory>::command();
    fuzz("config", 5, 1000, &config, |b| {
        std::fs::write(&path, b).expect("write");
        ConfigFile::load(&path, &command).is_ok()
    });
    // Calibration and ground truth.
    let calib = std::fs::read(fixture().join("camera.yaml")).expect("calibration");
    let calib_path = dir.path().join("camera.yaml");
    fuzz("calibration", 6, 1000, &calib, |b| {
        std::fs::write(&calib_path, b).expect("write");
        let Ok(c) = egoslam_sources::calibration::read_calibration_file(&calib_path) else {
            return false;
        };
        let _ = c.camera_for(640, 480);
        true
    });
    let gt: Vec<u8> = std::fs::read(fixture().join("groundtruth.txt"))
        .expect("ground truth")
        .into_iter()
        .take(2000)
        .collect();
    let gt_path = dir.path().join("groundtruth.txt");
    fuzz("ground truth", 7, 1000, &gt, |b| {
        std::fs::write(&gt_path, b).expect("write");
        egoslam_sources::ground_truth::read_tum_file(&gt_path).is_ok()
    });
}

#[test]
fn image_frames() {
    use opencv::core::{Rect, Vector};
    use opencv::prelude::*;
    // A small JPEG cut from the fixture keeps 1000 decodes fast.
    let rgb = std::fs::read_to_string(fixture().join("rgb.txt")).expect("rgb.txt");
    let first = rgb
        .lines()
        .find(|l| !l.starts_with('#'))
        .and_then(|l| l.split_whitespace().nth(1))
        .expect("first frame");
    let image = egoslam_sources::reader::decode_grey(&fixture().join(first)).expect("decodes");
    let crop = Mat::roi(&image, Rect::new(100, 100, 64, 48))
        .and_then(|m| m.try_clone())
        .expect("crop");
    let mut jpeg = Vector::<u8>::new();
    opencv::imgcodecs::imencode(".jpg", &crop, &mut jpeg, &Vector::new()).expect("encode");
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("frame.jpg");
    fuzz("jpeg frame", 8, 1000, jpeg.as_slice(), |b| {
        std::fs::write(&path, b).expect("write");
        egoslam_sources::reader::decode_grey(&path).is_ok()
    });
}
