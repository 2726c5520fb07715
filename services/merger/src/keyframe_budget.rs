//! A ceiling on the keyframes the map keeps, so that a day of walking fits the memory the
//! service is given. The culling rules ([`crate::keyframe_culling`],
//! [`crate::keyframe_coverage`]) judge each keyframe once, when it leaves the windows; a
//! place walked again while the map there has drifted by more than they allow keeps adding
//! keyframes. Over the ceiling, the keyframes whose place another keyframe covers most
//! closely go first, as the summary maps of Mühlfellner et al. ("Summary maps for lifelong
//! visual localization", JFR 2016) keep a fixed budget by dropping what is best covered
//! elsewhere: the map thins out where it is densest instead of failing where it ends.

use crate::map::MapBuilder;
use nalgebra::Vector3;
use std::collections::BTreeSet;

/// The ceiling and how keyframes are chosen above it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeyframeBudget {
    /// Keyframes the map keeps at most (a window's keyframes, always kept, can pass it).
    pub max_keyframes: usize,
    /// Once over, culled down to this fraction of the ceiling, so that the choice (a pass
    /// over every pair of keyframes) is made once per several windows.
    pub culled_to: f64,
    /// Another keyframe covers a keyframe's place when its optical axis is within this
    /// angle (as [`crate::keyframe_coverage::CoverageOptions::max_angle_deg`]).
    pub max_angle_deg: f64,
    /// A keyframe stays when the kept keyframes on both sides of it would be further apart
    /// than this many ids (the frames between are posed relative to them).
    pub spine: u64,
}

impl Default for KeyframeBudget {
    fn default() -> Self {
        Self {
            max_keyframes: 3000,
            culled_to: 0.95,
            max_angle_deg: 20.0,
            spine: 120,
        }
    }
}

struct Entry {
    id: u64,
    segment: u32,
    centre: Vector3<f64>,
    axis: Vector3<f64>,
    /// Median scene depth of its points; `None` for a keyframe that sees none.
    depth: Option<f64>,
}

impl MapBuilder {
    /// The keyframes older than `before` to cull to bring the map within `budget`, best
    /// covered first (nearest other keyframe of the segment looking the same way, in units
    /// of the keyframe's median scene depth); empty while within it. A chosen keyframe's
    /// coverer is not chosen too, and the first and last keyframe of a segment stay. A
    /// keyframe that sees no point is measured in the depth of its coverer, and covers
    /// nothing: otherwise such keyframes, never chosen, would fill the map past the
    /// ceiling on a long walk.
    pub fn over_budget_keyframes(&self, before: u64, budget: &KeyframeBudget) -> Vec<u64> {
        if self.keyframes.len() <= budget.max_keyframes {
            return Vec::new();
        }
        let target = (budget.max_keyframes as f64 * budget.culled_to) as usize;
        let excess = self.keyframes.len().saturating_sub(target);
        let entries: Vec<Entry> = self
            .keyframes
            .iter()
            .map(|(id, (segment, pose))| Entry {
                id: *id,
                segment: *segment,
                centre: pose.position,
                axis: crate::keyframe_coverage::axis(pose),
                depth: self.observed_depth(*id, pose),
            })
            .collect();
        let cos_max = budget.max_angle_deg.to_radians().cos();
        // (distance in depths to the nearest covering keyframe, keyframe, coverer)
        let mut scored: Vec<(f64, u64, u64)> = entries
            .iter()
            .filter(|e| e.id < before)
            .filter_map(|e| {
                entries
                    .iter()
                    .filter(|o| o.id != e.id && o.segment == e.segment && o.depth.is_some())
                    .filter(|o| o.axis.dot(&e.axis) >= cos_max)
                    .filter_map(|o| {
                        Some(((o.centre - e.centre).norm() / e.depth.or(o.depth)?, o.id))
                    })
                    .min_by(|a, b| a.0.total_cmp(&b.0))
                    .map(|(d, o)| (d, e.id, o))
            })
            .collect();
        scored.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let mut chosen = BTreeSet::new();
        let mut coverers = BTreeSet::new();
        for (_, id, coverer) in scored {
            if chosen.len() >= excess {
                break;
            }
            if coverers.contains(&id) || chosen.contains(&coverer) {
                continue;
            }
            if !self.spine_holds_without(id, &chosen, budget.spine) {
                continue;
            }
            chosen.insert(id);
            coverers.insert(coverer);
        }
        chosen.into_iter().collect()
    }

    /// Whether the kept keyframes around `id`, once `id` and `gone` are removed, are of its
    /// segment and at most `spine` ids apart.
    fn spine_holds_without(&self, id: u64, gone: &BTreeSet<u64>, spine: u64) -> bool {
        let Some((segment, _)) = self.keyframes.get(&id) else {
            return false;
        };
        let kept = |(k, (s, _)): (&u64, &(u32, _))| (!gone.contains(k)).then_some((*k, *s));
        let previous = self.keyframes.range(..id).rev().find_map(kept);
        let next = self.keyframes.range(id + 1..).find_map(kept);
        match (previous, next) {
            (Some((p, sp)), Some((n, sn))) => sp == *segment && sn == *segment && n - p <= spine,
            _ => false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::MapParts;
    use egoslam_geometry::StampedPose;
    use nalgebra::{Point2, UnitQuaternion};

    /// Keyframes 0..n along x, each seeing one point of its own 2 units ahead; `x(k)` is
    /// where keyframe k stands.
    fn map(n: u64, x: impl Fn(u64) -> f64) -> MapBuilder {
        let mut parts = MapParts::default();
        for k in 0..n {
            let pose = StampedPose {
                timestamp: k as f64,
                position: Vector3::new(x(k), 0.0, 0.0),
                rotation: UnitQuaternion::identity(),
            };
            parts.keyframes.insert(k, (0, pose));
            parts.points.insert(k, (0, Vector3::new(x(k), 0.0, 2.0)));
            parts.observations.insert((k, k), Point2::new(1.0, 2.0));
        }
        MapBuilder::from_parts(parts)
    }

    #[test]
    fn within_the_ceiling_nothing_goes_and_over_it_the_best_covered_go_first() {
        // 0..100 a metre apart; 100..110 walk the start again, 1 cm beside 0..10.
        let m = map(110, |k| {
            if k < 100 {
                k as f64
            } else {
                (k - 100) as f64 + 0.01
            }
        });
        let roomy = KeyframeBudget {
            max_keyframes: 110,
            ..Default::default()
        };
        assert!(m.over_budget_keyframes(105, &roomy).is_empty());
        let tight = KeyframeBudget {
            max_keyframes: 105,
            culled_to: 0.9,
            ..Default::default()
        };
        // Down to 94: 16 go. The ten pairs 1 cm apart first (one of each pair, older than
        // 105: 0..10 or 100..105), then keyframes a metre from their neighbours.
        let chosen = m.over_budget_keyframes(105, &tight);
        assert_eq!(chosen.len(), 16, "{chosen:?}");
        let close = chosen
            .iter()
            .filter(|k| **k < 10 || (100..105).contains(*k))
            .count();
        assert_eq!(close, 10, "{chosen:?}");
        assert!(!chosen.contains(&0), "the segment's first stays");
        // A tight spine keeps every other keyframe at least.
        let spine = KeyframeBudget { spine: 2, ..tight };
        let chosen = m.over_budget_keyframes(105, &spine);
        assert!(chosen.windows(2).all(|w| w[1] - w[0] >= 2), "{chosen:?}");
    }

    #[test]
    fn keyframes_without_points_are_culled_in_their_coverers_depth_and_cover_nothing() {
        // 0..100 a metre apart with points; 100..120 walk the start again, 1 cm beside
        // 0..20, without points.
        let mut parts = map(120, |k| {
            if k < 100 {
                k as f64
            } else {
                (k - 100) as f64 + 0.01
            }
        })
        .to_parts();
        parts.observations.retain(|(k, _), _| *k < 100);
        let m = MapBuilder::from_parts(parts);
        let tight = KeyframeBudget {
            max_keyframes: 110,
            culled_to: 1.0,
            ..Default::default()
        };
        // Ten go: the pointless ones beside 1..20 (1 cm in 2-unit depths), not the
        // keyframes with points they stand beside.
        let chosen = m.over_budget_keyframes(119, &tight);
        assert_eq!(chosen.len(), 10, "{chosen:?}");
        assert!(chosen.iter().all(|k| (100..119).contains(k)), "{chosen:?}");
    }
}
