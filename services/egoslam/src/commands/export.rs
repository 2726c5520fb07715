//! `egoslam export --run OUT --format colmap|nerfstudio --out DIR` (docs/export.md): the
//! map of a finished run (its merger checkpoint) with the input's own image names, in
//! another tool's format (egoslam_export). The images are the input's: COLMAP names them
//! relative to the sequence folder; nerfstudio gets copies beside its transforms.json.

use anyhow::Context;
use clap::{Args, ValueEnum};
use egoslam_export::{ExportModel, MapView};
use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Point2, Vector3};
use opencv::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ExportFormat {
    /// COLMAP text model: cameras.txt, images.txt, points3D.txt.
    Colmap,
    /// nerfstudio: transforms.json, images/, sparse_pc.ply.
    Nerfstudio,
}

#[derive(Args, Debug)]
pub struct ExportArgs {
    /// Output folder of a finished `egoslam run`.
    #[arg(long)]
    pub run: PathBuf,
    #[arg(long, value_enum)]
    pub format: ExportFormat,
    /// Folder to write into (created).
    #[arg(long)]
    pub out: PathBuf,
}

/// The sequence a run read, from its report.
struct RunInput {
    root: PathBuf,
    images: Vec<(f64, PathBuf)>,
}

fn run_input(run: &Path) -> anyhow::Result<RunInput> {
    let path = run.join("report.json");
    let report: serde_json::Value = serde_json::from_slice(
        &std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?,
    )
    .with_context(|| format!("{}: not JSON", path.display()))?;
    let input = report["input"]
        .as_str()
        .with_context(|| format!("{}: no input", path.display()))?;
    let fps = report["fps"].as_f64().unwrap_or(30.0);
    let layout = egoslam_sources::detect_layout(Path::new(input))?;
    let images = egoslam_sources::image_files(&layout, fps)?.with_context(|| {
        format!("{input}: a video or camera; exports name image files, so extract the frames first")
    })?;
    Ok(RunInput {
        root: layout.root().to_path_buf(),
        images,
    })
}

/// The image file of the frame captured at `t` (the nearest within 1 ms).
fn image_at(images: &[(f64, PathBuf)], t: f64) -> Option<&PathBuf> {
    let i = images.partition_point(|(s, _)| *s < t);
    [i.checked_sub(1), Some(i)]
        .into_iter()
        .flatten()
        .filter_map(|j| images.get(j))
        .filter(|(s, _)| (s - t).abs() < 1e-3)
        .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))
        .map(|(_, p)| p)
}

/// Each point's colour: the pixel of its first observation, from the colour image.
fn colour_points(model: &mut ExportModel, files: &[PathBuf]) -> anyhow::Result<()> {
    let mut by_image: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for (p, point) in model.points.iter().enumerate() {
        if let Some((image, _)) = point.track.first() {
            by_image.entry(*image).or_default().push(p);
        }
    }
    for (image, points) in by_image {
        let file = &files[image];
        let name = file.to_string_lossy();
        let mat = opencv::imgcodecs::imread(name.as_ref(), opencv::imgcodecs::IMREAD_COLOR)
            .with_context(|| format!("reading {name}"))?;
        if mat.empty() {
            anyhow::bail!("{name}: not a readable image");
        }
        for p in points {
            let (_, keypoint) = model.points[p].track[0];
            let pixel = model.images[image].keypoints[keypoint].pixel;
            let (x, y) = (pixel.x.round() as i32, pixel.y.round() as i32);
            if x < 0 || y < 0 || x >= mat.cols() || y >= mat.rows() {
                continue;
            }
            let bgr = mat.at_2d::<opencv::core::Vec3b>(y, x)?;
            model.points[p].colour = [bgr[2], bgr[1], bgr[0]];
        }
    }
    Ok(())
}

pub fn run(args: ExportArgs) -> anyhow::Result<()> {
    let checkpoint =
        egoslam_durability::state_dir(&args.run).join(egoslam_durability::checkpoint::FILE_NAME);
    let state = <egoslam_merger::MergerState as egoslam_durability::checkpoint::Checkpoint>::load(
        &checkpoint,
    )?
    .with_context(|| {
        format!(
            "{}: no map (is it a run's output folder?)",
            checkpoint.display()
        )
    })?;
    let camera_file = args.run.join("camera.yaml");
    let calibration = egoslam_sources::calibration::read_calibration_file(&camera_file)?;
    let (Some(width), Some(height)) = (calibration.width, calibration.height) else {
        anyhow::bail!("{}: no image size", camera_file.display());
    };
    let camera: PinholeRadtan = calibration.camera_for(width, height)?;
    let input = run_input(&args.run)?;
    let parts = state.map.to_parts();
    // The largest segment: the others are in frames of their own.
    let mut sizes: BTreeMap<u32, usize> = BTreeMap::new();
    for (segment, _) in parts.keyframes.values() {
        *sizes.entry(*segment).or_default() += 1;
    }
    let segment = sizes
        .iter()
        .max_by_key(|(s, n)| (**n, std::cmp::Reverse(**s)))
        .map(|(s, _)| *s)
        .context("the run's map has no keyframe")?;
    let mut files = Vec::new();
    let mut keyframes: Vec<(u64, String, StampedPose)> = Vec::new();
    for (id, (s, pose)) in &parts.keyframes {
        if *s != segment {
            continue;
        }
        let file = image_at(&input.images, pose.timestamp).with_context(|| {
            format!(
                "no image of {} at t = {:.6}",
                input.root.display(),
                pose.timestamp
            )
        })?;
        let name = file.strip_prefix(&input.root).unwrap_or(file);
        keyframes.push((*id, name.to_string_lossy().into_owned(), *pose));
        files.push(file.clone());
    }
    let points: BTreeMap<u64, Vector3<f64>> = parts
        .points
        .iter()
        .filter(|(_, (s, _))| *s == segment)
        .map(|(id, (_, p))| (*id, *p))
        .collect();
    let observations: BTreeMap<(u64, u64), Point2<f64>> = parts.observations;
    let mut model = ExportModel::from_map(&MapView {
        camera,
        keyframes,
        points: &points,
        observations: &observations,
    });
    colour_points(&mut model, &files)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    match args.format {
        ExportFormat::Colmap => egoslam_export::colmap::write(&model, &args.out)?,
        ExportFormat::Nerfstudio => {
            let relative: Vec<PathBuf> = model
                .images
                .iter()
                .map(|i| Path::new("images").join(&i.name))
                .collect();
            for (file, to) in files.iter().zip(&relative) {
                let to = args.out.join(to);
                if let Some(parent) = to.parent() {
                    std::fs::create_dir_all(parent)
                        .with_context(|| format!("creating {}", parent.display()))?;
                }
                std::fs::copy(file, &to)
                    .with_context(|| format!("copying {} to {}", file.display(), to.display()))?;
            }
            egoslam_export::nerfstudio::write(&model, &args.out, |i| {
                relative[i].to_string_lossy().into_owned()
            })?
        }
    }
    eprintln!(
        "{} images (segment {segment}), {} points -> {}",
        model.images.len(),
        model.points.len(),
        args.out.display()
    );
    Ok(())
}
