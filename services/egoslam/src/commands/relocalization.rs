//! `egoslam vocab train` and `egoslam localize` (docs/relocalization.md).

use anyhow::{bail, Context};
use clap::Args;
use egoslam_durability::map_file::{load_vocabulary, read_map};
use egoslam_durability::write_atomically;
use egoslam_geometry::{
    absolute_trajectory_error, alignment_from_poses, associate, PinholeRadtan, StampedPose,
};
use egoslam_relocalization::descriptors::{detect_corners, DescriberOptions, QueryCornerOptions};
use egoslam_relocalization::{
    Descriptor, OrbDescriber, QueryFeatures, Relocalizer, RelocalizerOptions, Vocabulary,
    VocabularyOptions,
};
use egoslam_sources::{
    detect_layout, load_calibration, load_ground_truth, open_source, FrameSource,
};
use opencv::core::Mat;
use opencv::prelude::*;
use serde_json::json;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Args, Debug)]
pub struct VocabTrainArgs {
    /// Images, or folders of images (png, jpg), to learn the words from.
    #[arg(required = true)]
    pub images: Vec<PathBuf>,
    /// Vocabulary file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Use every n-th image of the list (consecutive video frames repeat each other).
    #[arg(long, default_value_t = 1)]
    pub every: usize,
    /// Children per node, k.
    #[arg(long, default_value_t = VocabularyOptions::default().branching)]
    pub branching: usize,
    /// Levels, L (k^L words).
    #[arg(long, default_value_t = VocabularyOptions::default().depth)]
    pub depth: usize,
}

#[derive(Args, Debug)]
pub struct LocalizeArgs {
    /// Map saved by `egoslam run --map-out`.
    #[arg(long)]
    pub map: PathBuf,
    /// Sequence to localize (TUM/KITTI/EuRoC folder, video or image folder).
    #[arg(long)]
    pub input: PathBuf,
    /// Output folder: trajectory.tum (the map's frame) and report.json.
    #[arg(long, default_value = "localized")]
    pub out: PathBuf,
    /// Calibration of the input; default: the dataset's own.
    #[arg(long)]
    pub calib: Option<PathBuf>,
    /// Ground truth for the report (default: found next to the input).
    #[arg(long)]
    pub gt: Option<PathBuf>,
    /// Frame rate assumed for image folders.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// Vocabulary the map was built with (default: the built-in one).
    #[arg(long)]
    pub vocabulary: Option<PathBuf>,
    /// Rolling-shutter readout of the input's camera, milliseconds (0: a global shutter).
    /// Each frame's pose is then refined with the camera's turn during the readout.
    /// Default: the readout the map's run corrected its frames for (recorded in the map;
    /// 0 in maps that do not know it); `egoslam calibrate-readout` measures it.
    #[arg(long, value_parser = parse_readout_ms)]
    pub rolling_shutter_ms: Option<f64>,
}

/// A readout in milliseconds, 0 to [`crate::calibration::settings::MAX_READOUT_MS`] (`auto` has no
/// meaning for single query frames).
fn parse_readout_ms(text: &str) -> Result<f64, String> {
    use crate::calibration::settings::MAX_READOUT_MS;
    let ms: f64 = text
        .parse()
        .map_err(|_| format!("{text}: not a number of milliseconds"))?;
    if !(0.0..=MAX_READOUT_MS).contains(&ms) {
        return Err(format!("{text}: must be between 0 and {MAX_READOUT_MS} ms"));
    }
    Ok(ms)
}

/// A query's features: GFTT corners, their ORB descriptors, undistorted positions.
pub fn query_features(
    describer: &mut OrbDescriber,
    image: &Mat,
    camera: &PinholeRadtan,
) -> anyhow::Result<QueryFeatures> {
    let corners = detect_corners(image, &QueryCornerOptions::default())?;
    let descriptors = describer.describe(image, &corners)?;
    let mut q = QueryFeatures::default();
    for (c, d) in corners.iter().zip(descriptors) {
        let raw = nalgebra::Point2::new(f64::from(c.x), f64::from(c.y));
        if let (Some(d), Some(ideal)) = (d, camera.undistort_pixel(raw)) {
            q.pixels.push(ideal);
            q.descriptors.push(d);
        }
    }
    Ok(q)
}

fn image_files(inputs: &[PathBuf]) -> anyhow::Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for p in inputs {
        if p.is_dir() {
            let mut inside: Vec<PathBuf> = std::fs::read_dir(p)
                .with_context(|| format!("{}: cannot be listed", p.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| {
                    f.extension().and_then(|e| e.to_str()).is_some_and(|e| {
                        matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg")
                    })
                })
                .collect();
            inside.sort();
            files.extend(inside);
        } else if p.is_file() {
            files.push(p.clone());
        } else {
            bail!("{}: no such image or folder", p.display());
        }
    }
    Ok(files)
}

pub fn vocab_train(args: VocabTrainArgs) -> anyhow::Result<()> {
    let files: Vec<PathBuf> = image_files(&args.images)?
        .into_iter()
        .step_by(args.every.max(1))
        .collect();
    if files.is_empty() {
        bail!("no images found in {:?}", args.images);
    }
    let mut describer = OrbDescriber::new(DescriberOptions::default())?;
    let mut images: Vec<Vec<Descriptor>> = Vec::new();
    for (i, f) in files.iter().enumerate() {
        let image = match egoslam_sources::reader::decode_grey(f) {
            Ok(m) => m,
            Err(e) => {
                tracing::warn!(error = %e, "image skipped");
                continue;
            }
        };
        let corners = detect_corners(&image, &QueryCornerOptions::default())?;
        images.push(
            describer
                .describe(&image, &corners)?
                .into_iter()
                .flatten()
                .collect(),
        );
        if (i + 1) % 50 == 0 || i + 1 == files.len() {
            tracing::info!("described {} of {} images", i + 1, files.len());
        }
    }
    let options = VocabularyOptions {
        branching: args.branching,
        depth: args.depth,
        ..VocabularyOptions::default()
    };
    let started = Instant::now();
    let vocabulary = Vocabulary::train(&images, &options)?;
    write_atomically(&args.out, &vocabulary.to_bytes())?;
    println!(
        "vocabulary {}: {} words from {} descriptors of {} images in {:.1} s (id {:016x})",
        args.out.display(),
        vocabulary.words(),
        images.iter().map(Vec::len).sum::<usize>(),
        images.len(),
        started.elapsed().as_secs_f64(),
        vocabulary.id()
    );
    Ok(())
}

/// The paper's relocalization error (Table 5): the map is aligned to ground truth by its
/// keyframes (Sim(3)), and each localized frame is compared in that frame.
fn relocalization_error(
    keyframes: &[StampedPose],
    localized: &[StampedPose],
    gt: &[StampedPose],
) -> anyhow::Result<serde_json::Value> {
    let ate = absolute_trajectory_error(keyframes, gt, 0.02)
        .map_err(|e| anyhow::anyhow!("map keyframes cannot be aligned to ground truth: {e}"))?;
    // Aligned by the keyframes' orientations as well as positions: a position-only fit of
    // a short, rotation-heavy path leaves the rotation ill-determined.
    let s = &alignment_from_poses(keyframes, gt, 0.02)
        .context("map keyframes cannot be aligned to ground truth by their poses")?;
    let errors = |poses: &[StampedPose]| {
        let (mut position, mut rotation) = (Vec::new(), Vec::new());
        for (e, g) in associate(poses, gt, 0.02) {
            let (e, g) = (&poses[e], &gt[g]);
            position.push((s.apply(&e.position) - g.position).norm());
            let r = nalgebra::UnitQuaternion::from_rotation_matrix(&s.rotation) * e.rotation;
            rotation.push(r.angle_to(&g.rotation).to_degrees());
        }
        (position, rotation)
    };
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied()
    };
    let (mut position, mut rotation) = errors(localized);
    let (mut map_position, mut map_rotation) = errors(keyframes);
    // As `egoslam eval` scores a trajectory: the localized frames aligned on their own.
    let localized_ate = absolute_trajectory_error(localized, gt, 0.02)
        .map_err(|e| anyhow::anyhow!("localized frames cannot be aligned to ground truth: {e}"))?;
    Ok(json!({
        "ate_m": localized_ate.rmse,
        "map_keyframe_ate_m": ate.rmse,
        "map_keyframe_median_position_m": median(&mut map_position),
        "map_keyframe_median_rotation_deg": median(&mut map_rotation),
        "evaluated": position.len(),
        "median_position_m": median(&mut position),
        "median_rotation_deg": median(&mut rotation),
    }))
}

/// Writes `out/trajectory.tum` (atomically): every localized frame, segment after segment.
fn write_trajectory(out: &Path, localized: &BTreeMap<u32, Vec<StampedPose>>) -> anyhow::Result<()> {
    let mut text = String::new();
    for poses in localized.values() {
        text.push_str(&egoslam_export::tum::tum_text(poses));
    }
    write_atomically(&out.join("trajectory.tum"), text.as_bytes())?;
    Ok(())
}

pub fn localize(args: LocalizeArgs) -> anyhow::Result<()> {
    let vocabulary = load_vocabulary(args.vocabulary.as_deref())?;
    let map = read_map(&args.map, &vocabulary)?;
    let layout = detect_layout(&args.input)?;
    let calibration = load_calibration(&layout, args.calib.as_deref())?;
    let mut source = open_source(&args.input, args.fps)?;
    let total = source.len_hint();
    let readout_ms = args
        .rolling_shutter_ms
        .unwrap_or(map.rolling_shutter_s * 1000.0);
    let map_camera = map.camera;
    let relocalizer = Relocalizer::new(vocabulary, map);
    let options = RelocalizerOptions {
        rolling_shutter_s: readout_ms / 1000.0,
        ..RelocalizerOptions::default()
    };
    let mut describer = OrbDescriber::new(DescriberOptions::default())?;
    let keyframe_stamps: Vec<f64> = relocalizer
        .map()
        .keyframes
        .iter()
        .map(|k| k.pose.timestamp)
        .collect();
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let mut localized: BTreeMap<u32, Vec<StampedPose>> = BTreeMap::new();
    let mut failures: BTreeMap<String, u64> = BTreeMap::new();
    let mut query_ms = Vec::new();
    let (mut frames, mut non_keyframes, mut non_keyframes_localized) = (0u64, 0u64, 0u64);
    let mut camera: Option<PinholeRadtan> = None;
    while let Some(frame) = source.next_frame() {
        // Bad frames are skipped and counted by the source (below); an error here means it
        // gave up.
        let frame = frame?;
        let (w, h) = (frame.image.cols() as u32, frame.image.rows() as u32);
        let camera = match camera {
            Some(c) => c,
            None => *camera.insert(crate::calibration::focal::with_the_maps_focal(
                &calibration.camera_for(w, h)?,
                &map_camera,
            )),
        };
        frames += 1;
        let is_keyframe = keyframe_stamps
            .iter()
            .any(|t| (t - frame.timestamp).abs() < 1e-6);
        non_keyframes += u64::from(!is_keyframe);
        let started = Instant::now();
        let result = query_features(&mut describer, &frame.image, &camera).map(|q| {
            relocalizer
                .relocalize(&q, &options)
                .map(|found| relocalizer.refine_by_patches(found, &frame.image, &camera, &options))
        });
        query_ms.push(started.elapsed().as_secs_f64() * 1e3);
        match result? {
            Ok(r) => {
                non_keyframes_localized += u64::from(!is_keyframe);
                localized.entry(r.segment).or_default().push(StampedPose {
                    timestamp: frame.timestamp,
                    ..r.pose
                });
            }
            Err(e) => *failures.entry(e.to_string()).or_default() += 1,
        }
        if frames % 100 == 0 {
            // What is localized so far is kept, so a localization killed on a long input
            // loses at most the last 100 frames (written before the progress line says so).
            write_trajectory(&args.out, &localized)?;
            tracing::info!(frames, total = ?total, "localizing");
        }
    }
    if frames == 0 {
        bail!("{}: no frames", args.input.display());
    }
    write_trajectory(&args.out, &localized)?;
    for (reason, n) in source.skipped().iter() {
        *failures
            .entry(format!("frame skipped ({reason})"))
            .or_default() += n;
    }
    query_ms.sort_by(f64::total_cmp);
    let count: usize = localized.values().map(Vec::len).sum();
    let mut report = json!({
        "map": args.map.display().to_string(),
        "input": args.input.display().to_string(),
        "rolling_shutter_ms": readout_ms,
        "frames": frames,
        "localized": count,
        "non_keyframes": non_keyframes,
        "non_keyframes_localized": non_keyframes_localized,
        "failures": failures,
        "query_ms_median": query_ms[query_ms.len() / 2],
        "query_ms_p90": query_ms[query_ms.len() * 9 / 10],
    });
    println!(
        "localized {count} of {frames} frames ({non_keyframes_localized} of {non_keyframes} non-keyframes); query median {:.1} ms",
        query_ms[query_ms.len() / 2]
    );
    let gt = match &args.gt {
        Some(p) => Some(load_ground_truth(p)?),
        None => layout
            .root()
            .ancestors()
            .take(3)
            .find_map(|d| load_ground_truth(d).ok()),
    };
    // Evaluated on the largest segment (other segments are in frames of their own).
    let segment = localized
        .iter()
        .max_by_key(|(_, v)| v.len())
        .map(|(s, _)| *s);
    if let (Some(gt), Some(segment)) = (gt, segment) {
        let keyframes: Vec<StampedPose> = relocalizer
            .map()
            .keyframes
            .iter()
            .filter(|k| k.segment == segment)
            .map(|k| k.pose)
            .collect();
        match relocalization_error(&keyframes, &localized[&segment], &gt.poses) {
            Ok(e) => {
                let number = |key: &str| e[key].as_f64().unwrap_or(f64::NAN);
                println!(
                    "relocalization error: median {:.4} m, {:.3} deg over {} frames; ATE {:.4} m (map keyframes {:.4} m)",
                    number("median_position_m"),
                    number("median_rotation_deg"),
                    e["evaluated"],
                    number("ate_m"),
                    number("map_keyframe_ate_m"),
                );
                report["accuracy"] = e;
            }
            Err(e) => println!("not evaluated: {e}"),
        }
    }
    write_atomically(
        &args.out.join("report.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    Ok(())
}
