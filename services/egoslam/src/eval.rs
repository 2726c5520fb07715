//! `egoslam eval`: ATE of a TUM trajectory against ground truth.

use crate::cli::EvalArgs;
use egoslam_geometry::{absolute_trajectory_error, AteReport, StampedPose};
use egoslam_sources::ground_truth::read_tum_file;
use egoslam_sources::load_ground_truth;

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

pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    let estimate = read_tum_file(&args.estimate)?;
    let gt = load_ground_truth(&args.ground_truth)?;
    let report = evaluate(&estimate, &gt.poses, args.max_dt)?;
    println!("{}", summary(&report));
    println!("ground truth: {}", gt.description);
    Ok(())
}
