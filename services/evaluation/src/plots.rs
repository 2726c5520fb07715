//! `egoslam eval --alignment sim3|se3 --plot DIR`: the estimate aligned to the ground truth,
//! its error per pose as JSON, and two plots (plotters, SVG): the trajectories seen from
//! above (the ground truth's plane of largest spread) with the estimate coloured by its
//! error, and the error over time.

use anyhow::Context;
use egoslam_geometry::{associate, rigid_alignment, umeyama, Similarity, StampedPose};
use nalgebra::{Matrix3, Vector3};
use serde_json::json;
use std::path::Path;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Alignment {
    /// Rotation, translation and scale (Umeyama): a monocular estimate has no scale.
    Sim3,
    /// Rotation and translation only: the estimate's scale is judged too.
    Se3,
}

/// One matched pose after alignment.
pub struct AlignedPose {
    pub timestamp: f64,
    pub estimate: Vector3<f64>,
    pub truth: Vector3<f64>,
    pub error: f64,
}

/// The estimate's positions aligned onto the ground truth's, pose by pose.
pub fn aligned(
    estimate: &[StampedPose],
    truth: &[StampedPose],
    max_dt: f64,
    alignment: Alignment,
) -> anyhow::Result<(Similarity, Vec<AlignedPose>)> {
    let pairs = associate(estimate, truth, max_dt);
    let src: Vec<Vector3<f64>> = pairs.iter().map(|(e, _)| estimate[*e].position).collect();
    let dst: Vec<Vector3<f64>> = pairs.iter().map(|(_, g)| truth[*g].position).collect();
    let similarity = match alignment {
        Alignment::Sim3 => umeyama(&src, &dst),
        Alignment::Se3 => rigid_alignment(&src, &dst),
    }
    .context("aligning the estimate to the ground truth")?;
    let mut poses: Vec<AlignedPose> = pairs
        .iter()
        .zip(src.iter().zip(&dst))
        .map(|((e, _), (s, d))| {
            let moved = similarity.apply(s);
            AlignedPose {
                timestamp: estimate[*e].timestamp,
                estimate: moved,
                truth: *d,
                error: (moved - d).norm(),
            }
        })
        .collect();
    poses.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp));
    Ok((similarity, poses))
}

/// The root mean square of the errors.
pub fn rmse(poses: &[AlignedPose]) -> f64 {
    (poses.iter().map(|p| p.error * p.error).sum::<f64>() / poses.len().max(1) as f64).sqrt()
}

/// The two axes of the ground truth's largest spread (its floor plane for a walk).
fn top_view_axes(poses: &[AlignedPose]) -> (Vector3<f64>, Vector3<f64>) {
    let n = poses.len().max(1) as f64;
    let mean = poses.iter().map(|p| p.truth).sum::<Vector3<f64>>() / n;
    let covariance = poses
        .iter()
        .map(|p| (p.truth - mean) * (p.truth - mean).transpose())
        .sum::<Matrix3<f64>>()
        / n;
    let eigen = covariance.symmetric_eigen();
    let mut order = [0usize, 1, 2];
    order.sort_by(|a, b| eigen.eigenvalues[*b].total_cmp(&eigen.eigenvalues[*a]));
    (
        eigen.eigenvectors.column(order[0]).into_owned(),
        eigen.eigenvectors.column(order[1]).into_owned(),
    )
}

/// Green (no error) through yellow to red (the largest error).
fn error_colour(error: f64, largest: f64) -> plotters::style::RGBColor {
    let f = if largest > 0.0 {
        (error / largest).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let (r, g) = if f < 0.5 {
        (2.0 * f, 1.0)
    } else {
        (1.0, 2.0 * (1.0 - f))
    };
    plotters::style::RGBColor((r * 220.0) as u8, (g * 180.0) as u8, 40)
}

fn plot_top_view(path: &Path, poses: &[AlignedPose]) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let (u, v) = top_view_axes(poses);
    let project = |p: &Vector3<f64>| (p.dot(&u), p.dot(&v));
    let all: Vec<(f64, f64)> = poses
        .iter()
        .flat_map(|p| [project(&p.truth), project(&p.estimate)])
        .collect();
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for (x, y) in &all {
        (x0, x1, y0, y1) = (x0.min(*x), x1.max(*x), y0.min(*y), y1.max(*y));
    }
    // Equal scales on both axes: a top view must not be stretched.
    let half = ((x1 - x0).max(y1 - y0) / 2.0 * 1.05).max(1e-3);
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    let root = SVGBackend::new(path, (800, 800)).into_drawing_area();
    root.fill(&WHITE)?;
    let largest = poses.iter().map(|p| p.error).fold(0.0, f64::max);
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!(
                "top view: ground truth (grey), estimate coloured by error (red = {largest:.3} m)"
            ),
            ("sans-serif", 16),
        )
        .margin(10)
        .x_label_area_size(30)
        .y_label_area_size(50)
        .build_cartesian_2d(cx - half..cx + half, cy - half..cy + half)?;
    chart.configure_mesh().x_desc("m").y_desc("m").draw()?;
    chart.draw_series(LineSeries::new(
        poses.iter().map(|p| project(&p.truth)),
        RGBColor(120, 120, 120).stroke_width(2),
    ))?;
    chart.draw_series(poses.windows(2).map(|w| {
        let colour = error_colour(w[1].error, largest);
        PathElement::new(
            vec![project(&w[0].estimate), project(&w[1].estimate)],
            colour.stroke_width(2),
        )
    }))?;
    root.present()?;
    Ok(())
}

fn plot_error(path: &Path, poses: &[AlignedPose]) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let t0 = poses.first().map_or(0.0, |p| p.timestamp);
    let t1 = poses.last().map_or(1.0, |p| p.timestamp).max(t0 + 1e-3);
    let largest = poses.iter().map(|p| p.error).fold(1e-6, f64::max);
    let root = SVGBackend::new(path, (900, 400)).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!("position error after alignment (RMSE {:.4} m)", rmse(poses)),
            ("sans-serif", 16),
        )
        .margin(10)
        .x_label_area_size(30)
        .y_label_area_size(50)
        .build_cartesian_2d(0.0..t1 - t0, 0.0..largest * 1.05)?;
    chart
        .configure_mesh()
        .x_desc("time (s)")
        .y_desc("error (m)")
        .draw()?;
    chart.draw_series(LineSeries::new(
        poses.iter().map(|p| (p.timestamp - t0, p.error)),
        RED.stroke_width(2),
    ))?;
    root.present()?;
    Ok(())
}

/// Writes eval.json, trajectory.svg and error.svg into `dir` (created).
pub fn write(
    dir: &Path,
    alignment: Alignment,
    similarity: &Similarity,
    poses: &[AlignedPose],
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let q = nalgebra::UnitQuaternion::from_rotation_matrix(&similarity.rotation);
    let report = json!({
        "alignment": match alignment { Alignment::Sim3 => "sim3", Alignment::Se3 => "se3" },
        "matched": poses.len(),
        "ate_rmse_m": rmse(poses),
        "scale": similarity.scale,
        "rotation_xyzw": [q.i, q.j, q.k, q.w],
        "translation": [similarity.translation.x, similarity.translation.y, similarity.translation.z],
        "poses": poses.iter().map(|p| json!({
            "timestamp": p.timestamp,
            "estimate": [p.estimate.x, p.estimate.y, p.estimate.z],
            "ground_truth": [p.truth.x, p.truth.y, p.truth.z],
            "error_m": p.error,
        })).collect::<Vec<_>>(),
    });
    egoslam_durability::write_atomically(
        &dir.join("eval.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    plot_top_view(&dir.join("trajectory.svg"), poses)?;
    plot_error(&dir.join("error.svg"), poses)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, UnitQuaternion};

    fn walk(scale: f64, transform: &Similarity) -> Vec<StampedPose> {
        (0..50)
            .map(|i| {
                let a = f64::from(i) * 0.12;
                StampedPose {
                    timestamp: f64::from(i) * 0.1,
                    position: transform
                        .apply(&(Vector3::new(a.cos() * 2.0, a.sin() * 2.0, 0.05 * a) * scale)),
                    rotation: UnitQuaternion::identity(),
                }
            })
            .collect()
    }

    #[test]
    fn sim3_forgives_the_scale_se3_does_not_and_the_plots_are_written() {
        let truth = walk(1.0, &Similarity::identity());
        let moved = Similarity {
            scale: 1.0,
            rotation: Rotation3::from_euler_angles(0.1, 0.2, 0.7),
            translation: Vector3::new(3.0, -1.0, 2.0),
        };
        let half = walk(0.5, &moved);
        let (s, poses) = aligned(&half, &truth, 0.02, Alignment::Sim3).expect("sim3");
        assert!(rmse(&poses) < 1e-9 && (s.scale - 2.0).abs() < 1e-9);
        let (s, poses) = aligned(&half, &truth, 0.02, Alignment::Se3).expect("se3");
        assert_eq!(s.scale, 1.0);
        assert!(rmse(&poses) > 0.5, "{}", rmse(&poses));
        let dir = tempfile::tempdir().expect("tempdir");
        write(dir.path(), Alignment::Se3, &s, &poses).expect("write");
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.path().join("eval.json")).expect("json"))
                .expect("valid");
        assert_eq!(report["alignment"], "se3");
        assert_eq!(report["poses"].as_array().map(Vec::len), Some(50));
        let ate = report["ate_rmse_m"].as_f64().expect("ate");
        assert!((ate - rmse(&poses)).abs() < 1e-12);
        for plot in ["trajectory.svg", "error.svg"] {
            let svg = std::fs::read_to_string(dir.path().join(plot)).expect("svg");
            assert!(
                svg.starts_with("<svg") && svg.contains("polyline"),
                "{plot}"
            );
        }
    }
}
