//! `egoslam eval` and the accuracy part of `report.json`: ATE (Sim(3)-aligned), RPE over
//! 1 s, and structure error of the map against ground-truth depth where the sequence has
//! depth maps (rendered sequences, docs/synth.md).

pub mod plots;

use anyhow::Context;
use clap::Args;
use egoslam_geometry::{
    absolute_trajectory_error, alignment_from_poses, orientation_error, relative_pose_error,
    structure_error, AteReport, OrientationReport, PinholeRadtan, RpeReport, Similarity,
    StampedPose, StructureReport,
};
use egoslam_sources::ground_truth::read_tum_file;
use egoslam_sources::load_ground_truth;
use nalgebra::Vector3;
use opencv::prelude::*;
use serde_json::json;
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct EvalArgs {
    /// Estimated trajectory, TUM format.
    pub estimate: PathBuf,
    /// Ground truth: TUM file, KITTI poses file, EuRoC csv/TUM file, or a dataset folder.
    pub ground_truth: PathBuf,
    /// Maximum timestamp difference for association, seconds.
    #[arg(long, default_value_t = 0.02)]
    pub max_dt: f64,
    /// How the estimate is aligned to the ground truth: sim3 (rotation, translation and
    /// scale: monocular) or se3 (scale kept: judges the scale too).
    #[arg(long, value_enum, default_value_t = crate::plots::Alignment::Sim3)]
    pub alignment: crate::plots::Alignment,
    /// Write eval.json (errors per pose), trajectory.svg (top view, estimate coloured by
    /// error) and error.svg (error over time) into this folder.
    #[arg(long)]
    pub plot: Option<PathBuf>,
}

/// ATE with the usual failure cases turned into messages.
pub fn evaluate(
    estimate: &[StampedPose],
    ground_truth: &[StampedPose],
    max_dt: f64,
) -> anyhow::Result<AteReport> {
    if estimate.is_empty() {
        anyhow::bail!("the estimate has no poses");
    }
    let spread = estimate
        .iter()
        .map(|p| (p.position - estimate[0].position).norm())
        .fold(0.0, f64::max);
    if spread == 0.0 {
        anyhow::bail!("the estimate does not move (every window was rotation-only): a position error is undefined; the rotations can still be compared");
    }
    absolute_trajectory_error(estimate, ground_truth, max_dt).map_err(|e| {
        anyhow::anyhow!(
            "cannot align estimate and ground truth ({e}); are the timestamps on the same clock?"
        )
    })
}

/// One line a human reads.
pub fn summary(r: &AteReport) -> String {
    format!(
        "ATE RMSE {:.4} m (mean {:.4}, median {:.4}, max {:.4}) over {} poses; ground-truth path {:.3} m; scale {:.4}",
        r.rmse, r.mean, r.median, r.max, r.matched, r.gt_path_length, r.alignment.scale
    )
}

/// RPE over one second, in the estimate's scale brought to metres by the ATE alignment.
pub fn rpe_1s(est: &[StampedPose], gt: &[StampedPose], ate: &AteReport) -> Option<RpeReport> {
    relative_pose_error(est, gt, 0.02, 1.0, ate.alignment.scale)
}

pub fn rpe_summary(r: &RpeReport) -> String {
    let per_metre = r
        .translation_per_metre
        .map_or_else(|| "-".to_string(), |p| format!("{:.2} %", 100.0 * p));
    format!(
        "RPE over {:.0} s: {:.4} m ({per_metre} of the distance), {:.3} deg, {} pairs",
        r.delta_s, r.translation_rmse_m, r.rotation_rmse_deg, r.pairs
    )
}

pub fn orientation_summary(r: &OrientationReport) -> String {
    format!(
        "orientation error RMSE {:.3} deg (median {:.3}, max {:.3}) over {} poses, after the best constant rotation",
        r.rmse_deg, r.median_deg, r.max_deg, r.matched
    )
}

pub fn rpe_json(r: &RpeReport) -> serde_json::Value {
    json!({"delta_s": r.delta_s, "translation_rmse_m": r.translation_rmse_m, "translation_per_metre": r.translation_per_metre, "rotation_rmse_deg": r.rotation_rmse_deg, "pairs": r.pairs})
}

/// Map points of a `map.ply` written by egoslam.
fn read_ply(path: &Path) -> anyhow::Result<Vec<Vector3<f64>>> {
    Ok(egoslam_export::map_ply::read(path)?
        .iter()
        .map(|p| {
            Vector3::new(
                p.position[0].into(),
                p.position[1].into(),
                p.position[2].into(),
            )
        })
        .collect())
}

/// Structure error of `map.ply` against the sequence's depth maps (TUM `depth.txt`, 16-bit
/// PNG, metres x 5000), over up to 40 ground-truth views spread over the sequence.
pub fn structure(
    sequence: &Path,
    map: &Path,
    camera: &PinholeRadtan,
    gt: &[StampedPose],
    alignment: &Similarity,
) -> anyhow::Result<Option<StructureReport>> {
    let index = sequence.join("depth.txt");
    let Ok(text) = std::fs::read_to_string(&index) else {
        return Ok(None);
    };
    let entries: Vec<(f64, String)> = text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let mut it = l.split_whitespace();
            Some((it.next()?.parse().ok()?, it.next()?.to_string()))
        })
        .collect();
    let step = entries.len().div_ceil(40).max(1);
    let mut views = Vec::new();
    let mut paths = Vec::new();
    for (t, file) in entries.iter().step_by(step) {
        let Some(pose) = gt
            .iter()
            .min_by(|a, b| (a.timestamp - t).abs().total_cmp(&(b.timestamp - t).abs()))
        else {
            continue;
        };
        if (pose.timestamp - t).abs() > 0.02 {
            continue;
        }
        views.push(*pose);
        paths.push(sequence.join(file));
    }
    let depths = read_depth_images(&paths)?;
    let points: Vec<Vector3<f64>> = read_ply(map)?.iter().map(|x| alignment.apply(x)).collect();
    // Slices of the decoded images: the lookup runs ~10^6-10^7 times.
    let grids: Vec<(&[u16], usize)> = depths
        .iter()
        .map(|m| Ok((m.data_typed::<u16>()?, m.cols() as usize)))
        .collect::<opencv::Result<_>>()?;
    Ok(structure_error(camera, &points, &views, |v, x, y| {
        let (grid, width) = grids[v];
        let d = *grid.get(y as usize * width + x as usize)?;
        (d > 0).then(|| f64::from(d) / 5000.0)
    }))
}

/// Decodes 16-bit depth images on every core: the run's outputs wait for this at its end,
/// after the services have stopped, so the cores are free.
fn read_depth_images(paths: &[PathBuf]) -> anyhow::Result<Vec<opencv::core::Mat>> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let chunk = paths.len().div_ceil(threads).max(1);
    let read = |path: &PathBuf| -> anyhow::Result<opencv::core::Mat> {
        let image = opencv::imgcodecs::imread(
            path.to_str().context("non-UTF-8 path")?,
            opencv::imgcodecs::IMREAD_ANYDEPTH,
        )?;
        if image.empty() || image.typ() != opencv::core::CV_16UC1 {
            anyhow::bail!("{}: not a 16-bit depth image", path.display());
        }
        Ok(image)
    };
    std::thread::scope(|scope| {
        let workers: Vec<_> = paths
            .chunks(chunk)
            .map(|part| scope.spawn(move || part.iter().map(read).collect::<Vec<_>>()))
            .collect();
        let mut images = Vec::with_capacity(paths.len());
        for worker in workers {
            let part = worker
                .join()
                .map_err(|_| anyhow::anyhow!("a depth reader panicked"))?;
            for image in part {
                images.push(image?);
            }
        }
        Ok(images)
    })
}

/// Fewest keyframes a segment needs to be aligned on its own.
const MIN_SEGMENT_KEYFRAMES: usize = 10;

/// ATE with one Sim(3) per map segment (`keyframe_segments.txt`), pooled over the
/// keyframes: what the map is worth inside its segments when a run has breaks (one
/// alignment over all segments measures mostly how far apart their gauges are). Segments
/// under [`MIN_SEGMENT_KEYFRAMES`] are counted, not aligned. `None` without the file.
pub fn segmentwise_ate(
    estimate: &[StampedPose],
    ground_truth: &[StampedPose],
    segments_file: &Path,
) -> Option<serde_json::Value> {
    let text = std::fs::read_to_string(segments_file).ok()?;
    let micros = |t: f64| (t * 1e6).round() as i64;
    let segment_of: std::collections::HashMap<i64, u32> = text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let mut it = l.split_whitespace();
            Some((micros(it.next()?.parse().ok()?), it.next()?.parse().ok()?))
        })
        .collect();
    let mut groups: std::collections::BTreeMap<u32, Vec<StampedPose>> = Default::default();
    for p in estimate {
        let segment = segment_of.get(&micros(p.timestamp))?;
        groups.entry(*segment).or_default().push(*p);
    }
    let (mut squared, mut matched, mut aligned, mut left_out) = (0.0, 0usize, 0usize, 0usize);
    for poses in groups.values() {
        let report = (poses.len() >= MIN_SEGMENT_KEYFRAMES)
            .then(|| evaluate(poses, ground_truth, 0.02).ok())
            .flatten();
        match report {
            Some(r) => {
                squared += r.rmse * r.rmse * r.matched as f64;
                matched += r.matched;
                aligned += 1;
            }
            None => left_out += poses.len(),
        }
    }
    (matched > 0).then(|| {
        json!({
            "rmse_m": (squared / matched as f64).sqrt(),
            "segments": groups.len(),
            "segments_aligned": aligned,
            "keyframes_not_aligned": left_out,
        })
    })
}

/// The accuracy section of `report.json` (and the lines printed for it).
pub fn accuracy(
    out: &Path,
    sequence: &Path,
    camera: &PinholeRadtan,
    gt: &egoslam_sources::ground_truth::GroundTruth,
) -> anyhow::Result<serde_json::Value> {
    let mut acc = serde_json::Map::new();
    for (key, file) in [
        ("trajectory", "trajectory.tum"),
        ("keyframes", "keyframes.tum"),
        ("live", egoslam_export::tum::LIVE_TRAJECTORY_FILE),
    ] {
        let path = out.join(file);
        if key == "live" && !path.exists() {
            continue; // a run from before live poses (`egoslam eval` on an old folder)
        }
        let est = read_tum_file(&path)?;
        // Defined without positions: kept even where the ATE is not.
        let orientation = orientation_error(&est, &gt.poses, 0.02).map(|o| {
            println!("{key}: {}", orientation_summary(&o));
            json!({"orientation_rmse_deg": o.rmse_deg, "orientation_median_deg": o.median_deg, "orientation_max_deg": o.max_deg})
        });
        match evaluate(&est, &gt.poses, 0.02) {
            Ok(r) => {
                println!("{key}: {}", summary(&r));
                let mut entry = json!({"ate_rmse_m": r.rmse, "ate_mean_m": r.mean, "ate_median_m": r.median, "ate_max_m": r.max, "matched": r.matched, "gt_path_m": r.gt_path_length, "scale": r.alignment.scale});
                if let (Some(serde_json::Value::Object(o)), Some(e)) =
                    (&orientation, entry.as_object_mut())
                {
                    e.extend(o.clone());
                }
                let segments = out.join("keyframe_segments.txt");
                if let (true, Some(seg)) = (
                    key == "keyframes",
                    segmentwise_ate(&est, &gt.poses, &segments),
                ) {
                    if seg["segments"].as_u64() > Some(1) {
                        println!(
                            "{key}: ATE RMSE per segment {:.4} m ({} of {} segments aligned, {} keyframes in short ones)",
                            seg["rmse_m"].as_f64().unwrap_or(f64::NAN),
                            seg["segments_aligned"],
                            seg["segments"],
                            seg["keyframes_not_aligned"]
                        );
                    }
                    entry["ate_segmentwise"] = seg;
                }
                if let Some(rpe) = rpe_1s(&est, &gt.poses, &r) {
                    println!("{key}: {}", rpe_summary(&rpe));
                    entry["rpe"] = rpe_json(&rpe);
                }
                // The map is aligned by the poses' orientations too: position-only alignment
                // leaves a straight trajectory free to turn about itself.
                let by_poses = alignment_from_poses(&est, &gt.poses, 0.02);
                if let (true, Some(alignment)) = (key == "keyframes", by_poses) {
                    if let Some(s) = structure(
                        sequence,
                        &out.join("map.ply"),
                        camera,
                        &gt.poses,
                        &alignment,
                    )? {
                        println!(
                            "map: structure RMSE {:.4} m (median {:.4}, 90th percentile {:.4}) over {} of {} points",
                            s.rmse_m, s.median_m, s.p90_m, s.evaluated, s.points
                        );
                        println!(
                            "map: distance to the surface RMSE {:.4} m (median {:.4}, 90th percentile {:.4})",
                            s.surface_rmse_m, s.surface_median_m, s.surface_p90_m
                        );
                        acc.insert("structure".into(), json!({"rmse_m": s.rmse_m, "median_m": s.median_m, "p90_m": s.p90_m, "evaluated": s.evaluated, "points": s.points, "surface_rmse_m": s.surface_rmse_m, "surface_median_m": s.surface_median_m, "surface_p90_m": s.surface_p90_m}));
                    }
                }
                acc.insert(key.into(), entry);
            }
            Err(e) => {
                println!("{key}: ATE not evaluated: {e}");
                if let Some(o) = orientation {
                    acc.insert(key.into(), o);
                }
            }
        }
    }
    acc.insert("ground_truth".into(), json!(gt.description));
    Ok(serde_json::Value::Object(acc))
}

pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    use crate::plots::{aligned, Alignment};
    let estimate = read_tum_file(&args.estimate)?;
    let gt = load_ground_truth(&args.ground_truth)?;
    if let Some(o) = orientation_error(&estimate, &gt.poses, args.max_dt) {
        println!("{}", orientation_summary(&o));
    }
    let report = evaluate(&estimate, &gt.poses, args.max_dt)?;
    if args.alignment == Alignment::Sim3 {
        println!("{}", summary(&report));
    }
    let (similarity, poses) = aligned(&estimate, &gt.poses, args.max_dt, args.alignment)?;
    if args.alignment == Alignment::Se3 {
        println!(
            "ATE RMSE {:.4} m over {} poses, SE(3)-aligned (the estimate's scale kept; Sim(3) would give {:.4} m at scale {:.4})",
            crate::plots::rmse(&poses),
            poses.len(),
            report.rmse,
            report.alignment.scale
        );
    }
    if let Some(rpe) = rpe_1s(&estimate, &gt.poses, &report) {
        println!("{}", rpe_summary(&rpe));
    }
    println!("ground truth: {}", gt.description);
    if let Some(dir) = &args.plot {
        crate::plots::write(dir, args.alignment, &similarity, &poses)?;
        println!("plots and errors per pose in {}", dir.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, UnitQuaternion};

    fn pose(t: f64, position: Vector3<f64>) -> StampedPose {
        StampedPose {
            timestamp: t,
            position,
            rotation: UnitQuaternion::identity(),
        }
    }

    #[test]
    fn each_segment_gets_its_own_alignment() {
        // A curved 40-pose path; the second half of the estimate is in another gauge
        // (rotated, shifted, half the scale), as after an unhealed break.
        let gt: Vec<StampedPose> = (0..40)
            .map(|i| {
                let a = f64::from(i) * 0.1;
                pose(
                    f64::from(i),
                    Vector3::new(a.cos() * 3.0, a.sin() * 3.0, 0.1 * a),
                )
            })
            .collect();
        let other = Similarity {
            scale: 0.5,
            rotation: Rotation3::from_euler_angles(0.3, -0.2, 1.0),
            translation: Vector3::new(5.0, -2.0, 1.0),
        };
        let est: Vec<StampedPose> = gt
            .iter()
            .enumerate()
            .map(|(i, p)| match i < 20 {
                true => *p,
                false => pose(p.timestamp, other.apply(&p.position)),
            })
            .collect();
        let dir = tempfile::tempdir().expect("tempdir");
        let file = dir.path().join("keyframe_segments.txt");
        let lines: String = (0..40)
            .map(|i| format!("{i}.000000 {}\n", u32::from(i >= 20)))
            .collect();
        std::fs::write(&file, format!("# timestamp segment\n{lines}")).expect("write");
        let whole = evaluate(&est, &gt, 0.02).expect("ate").rmse;
        let seg = segmentwise_ate(&est, &gt, &file).expect("segments");
        assert!(whole > 0.5, "one alignment over two gauges: {whole}");
        assert!(seg["rmse_m"].as_f64().expect("rmse") < 1e-6, "{seg}");
        assert_eq!(seg["segments_aligned"], 2);
        assert!(segmentwise_ate(&est, &gt, &dir.path().join("absent")).is_none());
    }
}
