//! The check on translation averaging's direction refinement (docs/solver.md, "A
//! collapse in the direction refinement"): the refinement's objective does not change when
//! a group of cameras, with the points only they see, is scaled about a point, so bad
//! directions inside a group can shrink it against the rest. This measures how much a
//! group was rescaled, so that [`crate::translation_averaging::average_translations`] can
//! keep the LUD positions instead.

use crate::translation_averaging::{DirectionConstraint, Endpoints};
use nalgebra::Vector3;

/// How much `refined` rescaled one part of the cameras against another, compared with
/// `initial`: each camera's local scale is the median distance to the cameras it has
/// direction constraints with, the ratio refined / initial of that scale is taken per
/// camera, and the 90th percentile of those ratios over the 10th is returned (1 for a
/// refinement that moved cameras about without rescaling a group of them). Percentiles,
/// not the extremes: single cameras' local scales move a lot (largest over smallest was up
/// to 180 on sound windows), while a tenth of the cameras moving together is what a
/// collapse looks like. Measured over ~500 windows of 13 sequences (rendered walks, head
/// shakes, TUM, KITTI): 10.3 at most but one sound window at 48.7, against 3,628 for the
/// window whose 20 of 25 cameras collapsed. `None` with fewer than two cameras with a
/// local scale.
pub fn refinement_rescale(
    cameras: usize,
    constraints: &[DirectionConstraint],
    initial: &[Vector3<f64>],
    refined: &[Vector3<f64>],
) -> Option<f64> {
    let mut neighbours: Vec<Vec<usize>> = vec![Vec::new(); cameras];
    for c in constraints {
        if let Endpoints::Cameras { i, j } = c.endpoints {
            if i < cameras && j < cameras && i != j {
                neighbours[i].push(j);
                neighbours[j].push(i);
            }
        }
    }
    let local_scale = |x: &[Vector3<f64>], k: usize| {
        let mut d: Vec<f64> = neighbours[k]
            .iter()
            .map(|&j| (x[j] - x[k]).norm())
            .collect();
        d.sort_by(f64::total_cmp);
        d.get(d.len() / 2).copied()
    };
    let mut ratios: Vec<f64> = (0..cameras)
        .filter_map(|k| {
            let (a, b) = (local_scale(initial, k)?, local_scale(refined, k)?);
            (a > 1e-12 && b.is_finite()).then(|| b / a)
        })
        .collect();
    if ratios.len() < 2 {
        return None;
    }
    ratios.sort_by(f64::total_cmp);
    let at = |f: f64| ratios[((ratios.len() - 1) as f64 * f).round() as usize];
    Some(at(0.9) / at(0.1).max(1e-300))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_group_of_cameras_shrunk_against_the_rest_is_told_from_a_global_rescale() {
        // 25 cameras along a walk, each constrained to its next three (a window's chain and
        // local loop closures).
        let initial: Vec<Vector3<f64>> = (0..25)
            .map(|k| Vector3::new(0.1 * k as f64, 0.02 * (k as f64).sin(), 0.0))
            .collect();
        let constraints: Vec<DirectionConstraint> = (0..25)
            .flat_map(|i| (i + 1..(i + 4).min(25)).map(move |j| (i, j)))
            .map(|(i, j)| DirectionConstraint {
                endpoints: Endpoints::Cameras { i, j },
                direction: Vector3::x(),
                weight: 1.0,
            })
            .collect();
        let rescale = |refined: &[Vector3<f64>]| {
            refinement_rescale(25, &constraints, &initial, refined).expect("measurable")
        };
        // Scaled as a whole and moved about by a few per cent: no group rescaled.
        let jittered: Vec<_> = initial
            .iter()
            .enumerate()
            .map(|(k, c)| 3.0 * c + Vector3::new(0.01 * (k as f64 * 1.7).cos(), 0.0, 0.0))
            .collect();
        assert!(rescale(&jittered) < 2.0, "{}", rescale(&jittered));
        // The first 20 cameras shrunk 1000x towards the 20th (the collapsed window).
        let collapsed: Vec<_> = initial
            .iter()
            .map(|c| {
                if c.x < 1.95 {
                    initial[19] + (c - initial[19]) * 1e-3
                } else {
                    *c
                }
            })
            .collect();
        assert!(rescale(&collapsed) > 100.0, "{}", rescale(&collapsed));
        // One camera alone, however far off, is not a group.
        let mut one_off = initial.clone();
        one_off[7] += Vector3::new(0.0, 5.0, 0.0);
        assert!(rescale(&one_off) < 30.0, "{}", rescale(&one_off));
        assert_eq!(
            refinement_rescale(1, &[], &initial[..1], &initial[..1]),
            None
        );
    }
}
