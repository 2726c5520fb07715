//! Loop closure inside a map segment: a walk that comes back to a place it mapped long ago
//! is relocalized against that older part of its own map, and the drift accumulated in
//! between is spread over the keyframes of the loop.
//!
//! Detection is segment linking's (section 5 of the paper, "relocalization also
//! facilitates global loop closures"; [`crate::segment_linking`]): the newest keyframes
//! are relocalized by their descriptors against keyframes of the same segment at least
//! `min_age_keyframes` older, and at least three must agree on one similarity. That
//! similarity maps the newest keyframes from where the chained windows put them onto where
//! the old map says they are.
//!
//! Correction: the classic distribution of the loop error along the loop (as in the
//! initialisation of ORB-SLAM's essential-graph optimisation, Mur-Artal et al. 2015,
//! and in Strasdat et al., "Scale Drift-Aware Large Scale Monocular SLAM", RSS 2010, with
//! Sim(3) so that scale drift is corrected too). Keyframe k of the loop, at fraction
//! `a` of the loop's path, turns by `a` of the loop's rotation and scales by `scale^a`
//! (each step of the chain is re-integrated with those), and the position left over at
//! the end is spread linearly. Keyframes before the loop do not move; points move with
//! the keyframe that first saw them. The newest keyframes' sightings of the old points
//! they were relocalized against are kept as observations of those points (as ORB-SLAM's
//! loop fusion makes the old map points the new keyframes' own): the background
//! refinement then adjusts the result against the observations, the loop among them, so
//! it does not pull the loop open again toward the chain. A scale change beyond drift is a break in the chain, not
//! drift: the keyframes after the one where the map's walking pace jumps (within 1.5x of
//! the loop's factor) take that jump as a step, a second jump takes what the first leaves
//! beyond 1.25x, and the rest is spread as drift ([`crate::scale_break`]); where the pace
//! shows no such jump, a strong loop takes it as a step after the last loop's keyframes
//! (`break_since_last_loop`), and any other is refused.

use crate::map::MapBuilder;
use crate::refinement_rebase::Moves;
use crate::scale_break::{
    locate_scale_break, locate_second_break, strongest_pace_jump, ScaleBreak, ScaleBreakOptions,
};
use crate::segment_linking::{
    relocalize_consistently, LinkOptions, OlderKeyframes, RelocalizationSources,
};
use egoslam_geometry::{Similarity, StampedPose};
use nalgebra::{Rotation3, UnitQuaternion, Vector3};
use std::collections::BTreeMap;

/// When a loop is looked for and accepted; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoopOptions {
    /// Only keyframes at least this many keyframes older than the newest may close a loop
    /// (default 300, ~15 s of walking at the rendered walk's ~19 keyframes/s): the recent
    /// past always matches and carries the same drift, so it closes nothing.
    pub min_age_keyframes: u64,
    /// Newest keyframes queried per attempt (default 12, as segment linking: 3 must agree).
    pub newest_keyframes: usize,
    /// A correction that moves the newest keyframe by less than this fraction of the
    /// loop's path is not applied (default 0.002: below the drift the windows themselves
    /// leave, so applying it would only add the relocalization's own noise).
    pub min_correction_fraction: f64,
    /// A correction that moves the newest keyframe by more than this fraction of the
    /// loop's path is refused (default 0.35), unless the loop undoes a scale break as a
    /// step. Drift since the last closed loop is a few to ~25 % of the path walked (the
    /// rendered corridor's loops: 4-25 %); a match that asks for 69 % (measured: a wall
    /// of one corridor leg taken for another's, 78 shared points) is a wrong place.
    pub max_correction_fraction: f64,
    /// Fewest 3-D/3-D pairs (a newest keyframe's map point matched to an old one) the
    /// loop's scale must rest on (default 30). With fewer, the scale would come from the
    /// queried keyframes' centres, a few decimetres of walking relocalized with centimetre
    /// noise: on the 12,000-frame walk that gave loop scales of 0.01 and 37 and wrecked
    /// the map.
    pub min_shared_points: usize,
    /// Largest scale change a loop may spread as drift, as a factor either way (default
    /// 1.5). Drift along a loop is gradual: on rendered walks whose map kept its scale,
    /// loops corrected it by 0.97-0.99. A loop that asks for 37x (measured on the
    /// 12,000-frame walk, where one window had broken the chain's scale) is not drift;
    /// spreading it along the loop would distort all of it. Such a loop is applied as a
    /// step where the map's pace shows the break (`scale_break`) or after the last loop
    /// (`break_since_last_loop`), and refused and logged otherwise.
    pub max_scale_change: f64,
    /// How a break is located ([`crate::scale_break`]).
    pub scale_break: ScaleBreakOptions,
    /// A scale change beyond drift that the map's pace does not place is applied as a step
    /// after the last loop's keyframes (`break_since_last_loop`) when every queried
    /// keyframe agrees on it with at least this many pairs (default 300: ten times
    /// `min_shared_points`; revisits of the rendered corridor give 300-1,500)...
    pub min_step_shared_points: usize,
    /// ... and it is at most this factor either way (default 10: an hour of the rendered
    /// corridor walked back and forth broke the chain 7x at a window that shared nothing
    /// with the map, and every loop after asked for 6-10x with 650-1,400 pairs; a weak
    /// join at a turn was measured 3x off; beyond an order of magnitude is a wrong place).
    pub max_step_scale: f64,
    /// Acceptance of the relocalized group (rotation and position tolerances, keyframes
    /// that must agree); segment linking's defaults.
    pub link: LinkOptions,
}

impl Default for LoopOptions {
    fn default() -> Self {
        Self {
            min_age_keyframes: 300,
            newest_keyframes: 12,
            min_correction_fraction: 0.002,
            max_correction_fraction: 0.35,
            min_shared_points: 30,
            max_scale_change: 1.5,
            scale_break: ScaleBreakOptions::default(),
            min_step_shared_points: 300,
            max_step_scale: 10.0,
            link: LinkOptions::default(),
        }
    }
}

/// A loop found in a segment.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopClosure {
    pub segment: u32,
    /// The oldest keyframe the newest ones were relocalized against: the loop starts
    /// after it (it and everything before it stay where they are).
    pub anchor_keyframe: u64,
    /// Maps the newest keyframes from where they are onto where the old map puts them.
    pub transform: Similarity,
    /// Newest keyframes that agreed.
    pub keyframes: usize,
    /// 3-D/3-D pairs that gave the scale.
    pub shared_points: usize,
    /// When the scale change is a break, not drift (`LoopOptions::max_scale_change`):
    /// where the break is and the part of the correction it accounts for, and a second
    /// break for what a first leaves beyond drift ([`crate::scale_break`]); the rest is
    /// spread along the loop as drift. Empty: all of it is drift.
    pub scale_steps: Vec<ScaleStep>,
    /// `(newest keyframe, old track, undistorted pixel)`: the older points the agreeing
    /// newest keyframes matched, where they see them. Kept as observations, they are the
    /// loop's constraint in a later bundle adjustment of the map (without them the
    /// refinement sees only the chain and pulls the loop open again).
    pub sightings: Vec<(u64, u64, nalgebra::Point2<f64>)>,
}

/// A scale break a loop undoes as a step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScaleStep {
    /// The last keyframe before the break: those after it take `factor`.
    pub after_keyframe: u64,
    /// The scale correction of the break itself (the inverse of the map's pace ratio
    /// there).
    pub factor: f64,
}

/// Why a loop that was found was not applied.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum LoopNotApplied {
    #[error("the loop holds fewer than two keyframes after its anchor")]
    TooShort,
    #[error("correction {correction} below the minimum share of the loop's path {path}")]
    TooSmall { correction: f64, path: f64 },
    #[error(
        "correction {correction} beyond the share of the loop's path {path} drift can explain"
    )]
    TooLarge { correction: f64, path: f64 },
}

/// What closing a loop did.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopReport {
    /// Keyframes moved (those after the anchor).
    pub keyframes: usize,
    /// Points moved with them.
    pub points: usize,
    /// How far the newest keyframe moved, in map units, and the loop's path length.
    pub correction: f64,
    pub path: f64,
    /// Each moved keyframe's move, as a similarity of the map.
    pub keyframe_moves: Moves,
    /// Each moved point and the keyframe whose move it followed.
    pub point_owners: BTreeMap<u64, u64>,
}

/// Looks for a loop closed by the newest keyframes of `segment`; `None` when none of its
/// older keyframes relocalize them consistently.
pub fn find_loop(
    sources: &RelocalizationSources,
    segment: u32,
    options: &LoopOptions,
) -> Option<LoopClosure> {
    let _span = tracing::info_span!("find_loop", segment).entered();
    let mut newest = sources.described_keyframes(segment);
    newest.drain(..newest.len().saturating_sub(options.newest_keyframes));
    let first_query = newest.first()?.0;
    let cutoff = first_query.checked_sub(options.min_age_keyframes)?;
    let accept = |id: u64, s: u32| s == segment && id < cutoff;
    let older = OlderKeyframes {
        query_point: &|track| sources.segment_point(segment, track),
        accept: &accept,
    };
    let agreement = relocalize_consistently(sources, &newest, &older, &options.link)?;
    if agreement.shared_points < options.min_shared_points {
        tracing::debug!(
            shared_points = agreement.shared_points,
            "loop refused: too few shared points for its scale"
        );
        return None;
    }
    let scale = agreement.transform.scale;
    let anchor_keyframe = agreement.old_keyframes.iter().copied().min()?;
    let scale_steps = if scale_is_drift(scale, options.max_scale_change) {
        Vec::new()
    } else {
        // Not drift: a break, if the map's pace shows one step of that factor.
        let looped: Vec<(u64, StampedPose)> = sources
            .map
            .keyframes()
            .filter(|(id, s, _)| *s == segment && *id >= anchor_keyframe)
            .map(|(id, _, p)| (id, *p))
            .collect();
        let found = locate_scale_break(&looped, scale, &options.scale_break).or_else(|| {
            break_since_last_loop(
                sources.map,
                segment,
                anchor_keyframe,
                scale,
                &agreement,
                options,
            )
        });
        let Some(found) = found else {
            let strongest = strongest_pace_jump(&looped, scale, &options.scale_break);
            tracing::warn!(
                scale,
                shared_points = agreement.shared_points,
                keyframes = looped.len(),
                strongest_pace_ratio = strongest.map(|s| s.pace_ratio),
                strongest_after_keyframe = strongest.map(|s| s.after_keyframe),
                "loop refused: its scale change is not drift, and no single break in the map's pace explains it"
            );
            return None;
        };
        tracing::info!(
            scale,
            after_keyframe = found.after_keyframe,
            pace_ratio = found.pace_ratio,
            "loop corrects a scale break as a step"
        );
        let mut steps = vec![ScaleStep {
            after_keyframe: found.after_keyframe,
            factor: 1.0 / found.pace_ratio,
        }];
        if let Some(second) = locate_second_break(&looped, scale, &found, &options.scale_break) {
            tracing::info!(
                after_keyframe = second.after_keyframe,
                pace_ratio = second.pace_ratio,
                "loop corrects a second scale break as a step"
            );
            steps.push(ScaleStep {
                after_keyframe: second.after_keyframe,
                factor: 1.0 / second.pace_ratio,
            });
        }
        steps
    };
    Some(LoopClosure {
        segment,
        anchor_keyframe,
        transform: agreement.transform,
        keyframes: agreement.keyframes,
        shared_points: agreement.shared_points,
        scale_steps,
        sightings: agreement.sightings,
    })
}

/// A scale break the map's pace does not show, placed where the chain left the last loop:
/// when a loop closed in this segment after `anchor`, the keyframes up to it were on the
/// older map's scale, and the chain since (a few seconds on revisited ground) carries all
/// of this loop's scale change: typically a turn or a stop whose windows shared nothing
/// with the map. Only for a loop every queried keyframe agrees on, resting on at least
/// `min_step_shared_points` pairs, and only within `max_step_scale` either way.
fn break_since_last_loop(
    map: &MapBuilder,
    segment: u32,
    anchor: u64,
    scale: f64,
    agreement: &crate::segment_linking::Agreement,
    options: &LoopOptions,
) -> Option<ScaleBreak> {
    let (pinned_segment, pinned) = map.loop_pinned?;
    let strong = agreement.keyframes >= options.newest_keyframes
        && agreement.shared_points >= options.min_step_shared_points
        && scale.max(1.0 / scale) <= options.max_step_scale;
    (pinned_segment == segment && pinned >= anchor && strong).then(|| {
        tracing::info!(
            scale,
            after_keyframe = pinned,
            "loop corrects the chain since the last loop as a step"
        );
        ScaleBreak {
            after_keyframe: pinned,
            pace_ratio: 1.0 / scale,
        }
    })
}

/// How one keyframe of the loop moved: its centre, and the turn and scale about it that
/// its points follow.
struct KeyframeMove {
    before: Vector3<f64>,
    after: Vector3<f64>,
    rotation: Rotation3<f64>,
    scale: f64,
}

impl KeyframeMove {
    /// The move as a similarity of the map: `x -> after + scale * rotation * (x - before)`.
    fn as_similarity(&self) -> Similarity {
        Similarity {
            scale: self.scale,
            rotation: self.rotation,
            translation: self.after - self.scale * (self.rotation * self.before),
        }
    }
}

/// Whether a loop's scale correction is within `max_change` either way (drift), not a
/// broken chain (see `LoopOptions::max_scale_change`).
fn scale_is_drift(scale: f64, max_change: f64) -> bool {
    scale.is_finite() && scale > 0.0 && scale.ln().abs() <= max_change.ln()
}

impl MapBuilder {
    /// Spreads the loop's correction over the keyframes after its anchor (see the module
    /// documentation); nothing changes when the correction is outside
    /// `min_correction_fraction`..`max_correction_fraction` of the loop's path or the loop
    /// has < 2 keyframes.
    pub fn close_loop(
        &mut self,
        closure: &LoopClosure,
        options: &LoopOptions,
    ) -> Result<LoopReport, LoopNotApplied> {
        // Keyframes an earlier loop put onto the older map stay there: the drift to
        // correct is the chain's since then.
        let start = match self.loop_pinned {
            Some((segment, keyframe)) if segment == closure.segment => {
                closure.anchor_keyframe.max(keyframe)
            }
            _ => closure.anchor_keyframe,
        };
        let ids: Vec<u64> = self
            .keyframes
            .range(start..)
            .filter(|(_, (s, _))| *s == closure.segment)
            .map(|(id, _)| *id)
            .collect();
        if ids.len() < 2 {
            return Err(LoopNotApplied::TooShort);
        }
        let old: Vec<StampedPose> = ids.iter().map(|id| self.keyframes[id].1).collect();
        let mut along = vec![0.0; old.len()];
        for k in 1..old.len() {
            along[k] = along[k - 1] + (old[k].position - old[k - 1].position).norm();
        }
        let path = along[old.len() - 1];
        let newest = old[old.len() - 1];
        let target = closure.transform.apply(&newest.position);
        let correction = (target - newest.position).norm();
        if path <= 0.0 || correction < options.min_correction_fraction * path {
            return Err(LoopNotApplied::TooSmall { correction, path });
        }
        if closure.scale_steps.is_empty() && correction > options.max_correction_fraction * path {
            return Err(LoopNotApplied::TooLarge { correction, path });
        }
        let turn = UnitQuaternion::from_rotation_matrix(&closure.transform.rotation);
        // The breaks' steps, and the rest of the scale correction as drift.
        let steps_log_scale: f64 = closure.scale_steps.iter().map(|s| s.factor.ln()).sum();
        let drift_log_scale = closure.transform.scale.ln() - steps_log_scale;
        // Rotation and scale per keyframe, and the chain re-integrated with them.
        let share = |k: usize| along[k] / path;
        let turn_at = |k: usize| UnitQuaternion::identity().slerp(&turn, share(k));
        let scale_at = |k: usize| {
            let stepped: f64 = closure
                .scale_steps
                .iter()
                .filter(|s| ids[k] > s.after_keyframe)
                .map(|s| s.factor)
                .product();
            stepped * (share(k) * drift_log_scale).exp()
        };
        let mut centres = vec![old[0].position];
        for k in 1..old.len() {
            let step = old[k].position - old[k - 1].position;
            centres.push(centres[k - 1] + scale_at(k) * (turn_at(k) * step));
        }
        let residual = target - centres[old.len() - 1];
        let mut moved: BTreeMap<u64, KeyframeMove> = BTreeMap::new();
        // The anchor (k = 0) stays exactly where it is.
        for (k, id) in ids.iter().enumerate().skip(1) {
            let centre = centres[k] + share(k) * residual;
            let rotation = turn_at(k);
            if let Some((_, p)) = self.keyframes.get_mut(id) {
                moved.insert(
                    *id,
                    KeyframeMove {
                        before: p.position,
                        after: centre,
                        rotation: rotation.to_rotation_matrix(),
                        scale: scale_at(k),
                    },
                );
                p.position = centre;
                p.rotation = rotation * p.rotation;
            }
        }
        // Each point follows the first keyframe of the loop that observed it. Observations
        // are ordered by keyframe, so only those from the loop on are read (not the whole
        // map's), and the first seen per track is its earliest.
        let mut first_seen: BTreeMap<u64, u64> = BTreeMap::new();
        for (kf, track) in self.observations.range((ids[1], 0)..).map(|(k, _)| k) {
            if moved.contains_key(kf) {
                first_seen.entry(*track).or_insert(*kf);
            }
        }
        let mut point_owners = BTreeMap::new();
        for (track, kf) in first_seen {
            let (Some((s, x)), Some(m)) = (self.points.get_mut(&track), moved.get(&kf)) else {
                continue;
            };
            if *s != closure.segment {
                continue;
            }
            *x = m.after + m.scale * (m.rotation * (*x - m.before));
            point_owners.insert(track, kf);
        }
        self.loop_pinned = ids.last().map(|id| (closure.segment, *id));
        // A stretch waiting for its scale from the walking pace has it from the old map
        // now: the loop put its newest keyframes where the map saw them.
        if let Some(p) = self.provisional.filter(|p| p.segment == closure.segment) {
            tracing::debug!(
                first_keyframe = p.first_keyframe,
                "provisional scale settled by a loop"
            );
            self.provisional = None;
        }
        let keyframe_moves = moved
            .iter()
            .map(|(id, m)| (*id, m.as_similarity()))
            .collect();
        Ok(LoopReport {
            keyframes: ids.len() - 1,
            points: point_owners.len(),
            correction,
            path,
            keyframe_moves,
            point_owners,
        })
    }
    /// Keeps a closed loop's sightings (`LoopClosure::sightings`) as observations of the
    /// old points, where both keyframe and point are in `segment` and the keyframe has no
    /// observation of that track yet; returns how many were added. Separate from
    /// [`Self::close_loop`] so that the merger can add them after it measured the
    /// window's cross-window error, which compares what windows chained and would read a
    /// loop's own residual as drift.
    pub fn add_loop_sightings(
        &mut self,
        segment: u32,
        sightings: &[(u64, u64, nalgebra::Point2<f64>)],
    ) -> usize {
        let mut added = 0;
        for &(keyframe, track, pixel) in sightings {
            let point_in = self.points.get(&track).map(|(s, _)| *s);
            let keyframe_in = self.keyframes.get(&keyframe).map(|(s, _)| *s);
            if point_in == Some(segment) && keyframe_in == Some(segment) {
                if let std::collections::btree_map::Entry::Vacant(e) =
                    self.observations.entry((keyframe, track))
                {
                    e.insert(pixel);
                    added += 1;
                }
            }
        }
        added
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::WindowInput;
    use nalgebra::Point2;

    /// A square loop of side 10 walked twice, keyframes every 0.5 m, facing along the path.
    fn square_pose(i: u64) -> StampedPose {
        let s = 0.5 * i as f64 % 40.0;
        let (side, t) = ((s / 10.0) as u32, s % 10.0);
        let (x, z, yaw) = match side {
            0 => (t, 0.0, 0.0),
            1 => (10.0, t, std::f64::consts::FRAC_PI_2),
            2 => (10.0 - t, 10.0, std::f64::consts::PI),
            _ => (0.0, 10.0 - t, -std::f64::consts::FRAC_PI_2),
        };
        StampedPose {
            timestamp: i as f64,
            position: Vector3::new(x, 0.0, z),
            rotation: UnitQuaternion::from_euler_angles(0.0, yaw, 0.0),
        }
    }

    #[test]
    fn a_strong_loop_steps_after_the_last_loop_and_no_other_does() {
        let map = |pinned: Option<(u32, u64)>| {
            MapBuilder::from_parts(crate::map::MapParts {
                loop_pinned: pinned,
                ..crate::map::MapParts::default()
            })
        };
        let agreement =
            |keyframes: usize, shared_points: usize| crate::segment_linking::Agreement {
                to: 0,
                transform: Similarity::identity(),
                keyframes,
                shared_points,
                old_keyframes: vec![10],
                sightings: Vec::new(),
            };
        let options = LoopOptions::default();
        let strong = agreement(12, 800);
        let step = break_since_last_loop(&map(Some((0, 500))), 0, 10, 0.33, &strong, &options)
            .expect("a step after the last loop");
        assert_eq!(step.after_keyframe, 500);
        assert!((step.pace_ratio - 1.0 / 0.33).abs() < 1e-12);
        let none =
            |m: &MapBuilder, anchor: u64, scale: f64, a: &crate::segment_linking::Agreement| {
                break_since_last_loop(m, 0, anchor, scale, a, &options).is_none()
            };
        assert!(none(&map(None), 10, 0.33, &strong), "no loop before");
        assert!(
            none(&map(Some((1, 500))), 10, 0.33, &strong),
            "another segment's"
        );
        assert!(
            none(&map(Some((0, 5))), 10, 0.33, &strong),
            "before the anchor"
        );
        // The hour-long looped corridor's break: the chain 7x too small, loops of 650-1,400
        // pairs asking for it.
        let seven = break_since_last_loop(&map(Some((0, 500))), 0, 10, 7.0, &strong, &options);
        assert!(seven.is_some_and(|s| (s.pace_ratio - 1.0 / 7.0).abs() < 1e-12));
        assert!(none(&map(Some((0, 500))), 10, 0.05, &strong), "beyond 10x");
        assert!(
            none(&map(Some((0, 500))), 10, 0.33, &agreement(12, 100)),
            "few pairs"
        );
        assert!(
            none(&map(Some((0, 500))), 10, 0.33, &agreement(9, 800)),
            "not all agree"
        );
    }

    #[test]
    fn a_scale_change_beyond_drift_is_refused() {
        for ok in [0.97, 0.99, 1.0, 1.2, 1.49, 1.0 / 1.49] {
            assert!(scale_is_drift(ok, 1.5), "{ok}");
        }
        for broken in [37.0, 0.0104, 1.6, 0.6, 0.0, f64::NAN, f64::INFINITY] {
            assert!(!scale_is_drift(broken, 1.5), "{broken}");
        }
    }

    #[test]
    fn a_drifted_loop_is_pulled_back_and_the_start_stays() {
        // 81 keyframes: twice around; the chained map drifted in yaw, scale and position
        // so that keyframe 80 (truly where keyframe 0 is) is off. The loop closure's
        // similarity (as relocalization would give it) maps the drifted keyframe 80 onto
        // keyframe 0's true pose.
        let n = 81u64;
        let drift = |i: u64| {
            let a = i as f64 / (n - 1) as f64;
            Similarity {
                scale: 1.0 + 0.1 * a,
                rotation: Rotation3::from_euler_angles(0.0, 0.05 * a, 0.0),
                translation: Vector3::new(0.3 * a, 0.1 * a, -0.2 * a),
            }
        };
        let mut map = MapBuilder::new();
        let drifted = |i: u64| crate::window_alignment::transform_pose(&drift(i), &square_pose(i));
        map.add_window(&WindowInput {
            poses: (0..n).map(|i| (i, drifted(i))).collect(),
            points: vec![(7, drifted(79).position + Vector3::new(0.0, 0.0, 2.0))],
            observations: vec![(79, 7, Point2::new(320.0, 240.0))],
            ..WindowInput::default()
        });
        let truth_end = square_pose(n - 1);
        let closure = LoopClosure {
            segment: 0,
            anchor_keyframe: 0,
            transform: drift(n - 1).inverse(),
            keyframes: 3,
            shared_points: 50,
            scale_steps: Vec::new(),
            // Keyframe 80 sees point 7; track 99 is no point; keyframe 79's own
            // observation of 7 stays as the window measured it.
            sightings: vec![
                (80, 7, Point2::new(300.0, 200.0)),
                (80, 99, Point2::new(10.0, 10.0)),
                (79, 7, Point2::new(1.0, 1.0)),
            ],
        };
        let before: f64 = (0..n)
            .map(|i| (drifted(i).position - square_pose(i).position).norm_squared())
            .sum::<f64>();
        let unclosed = map.to_parts();
        let report = map
            .close_loop(&closure, &LoopOptions::default())
            .expect("closed");
        assert_eq!(report.keyframes, 80);
        assert_eq!(report.points, 1);
        assert_eq!(map.add_loop_sightings(0, &closure.sightings), 1);
        assert_eq!(map.observations[&(80, 7)], Point2::new(300.0, 200.0));
        assert_eq!(map.observations[&(79, 7)], Point2::new(320.0, 240.0));
        assert!(!map.observations.contains_key(&(80, 99)));
        let (_, end) = map.keyframe(n - 1).expect("end");
        assert!((end.position - truth_end.position).norm() < 1e-9);
        assert!(end.rotation.angle_to(&truth_end.rotation) < 1e-9);
        assert_eq!(map.keyframe(0).expect("start").1, &drifted(0));
        let after: f64 = (0..n)
            .map(|i| {
                (map.keyframe(i).expect("kf").1.position - square_pose(i).position).norm_squared()
            })
            .sum::<f64>();
        assert!(
            after < 0.05 * before,
            "sum of squared errors {before} -> {after}"
        );
        // The point moved with keyframe 79, the first that saw it: the same direction in
        // that camera, its distance scaled by the loop's scale there (between 1/1.1 and 1).
        let (_, x) = map.point(7).expect("point");
        let (_, k79) = map.keyframe(79).expect("kf");
        let seen_after = k79.rotation.inverse() * (x - k79.position);
        let k79_before = drifted(79);
        let seen_before = k79_before.rotation.inverse() * (Vector3::new(0.0, 0.0, 2.0));
        assert!(seen_after.normalize().dot(&seen_before.normalize()) > 1.0 - 1e-12);
        let ratio = seen_after.norm() / seen_before.norm();
        assert!(ratio > 1.0 / 1.1 - 1e-9 && ratio < 1.0, "{ratio}");
        // A correction below the threshold is not applied.
        let tiny = LoopClosure {
            transform: Similarity::identity(),
            ..closure
        };
        let mut fresh = MapBuilder::from_parts(unclosed.clone());
        assert!(matches!(
            fresh.close_loop(&tiny, &LoopOptions::default()),
            Err(LoopNotApplied::TooSmall { .. })
        ));
        // One that would move the newest keyframe by half the loop's path is a wrong place.
        let far = LoopClosure {
            transform: Similarity {
                scale: 1.0,
                rotation: Rotation3::identity(),
                translation: Vector3::new(20.0, 0.0, 0.0),
            },
            ..tiny
        };
        let mut fresh = MapBuilder::from_parts(unclosed.clone());
        assert!(matches!(
            fresh.close_loop(&far, &LoopOptions::default()),
            Err(LoopNotApplied::TooLarge { .. })
        ));
        assert_eq!(fresh.to_parts(), unclosed);
    }

    #[test]
    fn a_scale_break_is_undone_as_a_step_where_spreading_would_bend_the_loop() {
        // The chain's scale broke after keyframe 40: everything after it is 1.6 times too
        // far from it. The loop's similarity maps those keyframes back exactly.
        let (n, last_before, factor) = (81u64, 40u64, 1.6);
        let pivot = square_pose(last_before).position;
        let broken = |i: u64| {
            let mut p = square_pose(i);
            if i > last_before {
                p.position = pivot + factor * (p.position - pivot);
            }
            p
        };
        let build = || {
            let mut map = MapBuilder::new();
            map.add_window(&WindowInput {
                poses: (0..n).map(|i| (i, broken(i))).collect(),
                points: vec![(7, broken(79).position + Vector3::new(0.0, 0.0, 2.0))],
                observations: vec![(79, 7, Point2::new(320.0, 240.0))],
                ..WindowInput::default()
            });
            map
        };
        let closure = LoopClosure {
            segment: 0,
            anchor_keyframe: 0,
            transform: Similarity {
                scale: 1.0 / factor,
                rotation: Rotation3::identity(),
                translation: pivot * (1.0 - 1.0 / factor),
            },
            keyframes: 3,
            shared_points: 50,
            scale_steps: vec![ScaleStep {
                after_keyframe: last_before,
                factor: 1.0 / factor,
            }],
            sightings: Vec::new(),
        };
        let error = |map: &MapBuilder| {
            (0..n)
                .map(|i| {
                    let p = map.keyframe(i).expect("kf").1.position;
                    (p - square_pose(i).position).norm()
                })
                .fold(0.0, f64::max)
        };
        let mut stepped = build();
        stepped
            .close_loop(&closure, &LoopOptions::default())
            .expect("closed");
        assert!(error(&stepped) < 1e-9, "{}", error(&stepped));
        // The point seen first after the break came back with its keyframe.
        let truth_point = square_pose(79).position + Vector3::new(0.0, 0.0, 2.0) / factor;
        let point = stepped.points().find(|(t, _, _)| *t == 7).expect("point").2;
        assert!((point - truth_point).norm() < 1e-9);
        let mut spread = build();
        let as_drift = LoopClosure {
            scale_steps: Vec::new(),
            ..closure.clone()
        };
        spread
            .close_loop(&as_drift, &LoopOptions::default())
            .expect("closed");
        assert!(error(&spread) > 0.5, "{}", error(&spread));
        // A loop asking for 5 % more than the break: the step stays the break's, the rest
        // is spread as drift, and the newest keyframe lands where the loop puts it.
        let mut with_drift = build();
        let more = LoopClosure {
            transform: Similarity {
                scale: 0.95 / factor,
                ..closure.transform
            },
            ..closure
        };
        let newest_before = with_drift.keyframe(n - 1).expect("kf").1.position;
        with_drift
            .close_loop(&more, &LoopOptions::default())
            .expect("closed");
        let kf = |i: u64| with_drift.keyframe(i).expect("kf").1.position;
        let newest_target = more.transform.apply(&newest_before);
        assert!((kf(n - 1) - newest_target).norm() < 1e-9);
        // Across the break consecutive steps keep their lengths (0.5 m on the square):
        // the step undid the break, the drift's share changes them by well under 1 %.
        let step = |i: u64| (kf(i) - kf(i - 1)).norm();
        let ratio = step(last_before + 1) / step(last_before);
        assert!((ratio - 1.0).abs() < 0.01, "{ratio}");
    }

    #[test]
    fn a_later_loop_leaves_what_an_earlier_loop_put_onto_the_map() {
        // Keyframes 0-80 go around the square once. The first loop (anchored at 0)
        // closes at 40 and pins it; then the chain drifts again from 40 on and a second
        // loop, relocalized against keyframe 0 once more, closes at 80.
        let n = 81u64;
        let drift_after = |i: u64| {
            let a = i.saturating_sub(40) as f64 / 40.0;
            Similarity {
                scale: 1.0,
                rotation: Rotation3::from_euler_angles(0.0, 0.04 * a, 0.0),
                translation: Vector3::new(0.2 * a, 0.0, -0.1 * a),
            }
        };
        let truth = |i: u64| square_pose(i);
        let mut map = MapBuilder::new();
        let drifted = |i: u64| crate::window_alignment::transform_pose(&drift_after(i), &truth(i));
        map.add_window(&WindowInput {
            poses: (0..=40).map(|i| (i, truth(i))).collect(),
            ..WindowInput::default()
        });
        let small = Similarity {
            scale: 1.0,
            rotation: Rotation3::identity(),
            translation: Vector3::new(0.0, 0.0, 0.05),
        };
        // The first loop moves keyframe 40 by 5 cm (still drift), and pins it.
        let first = LoopClosure {
            segment: 0,
            anchor_keyframe: 0,
            transform: small,
            keyframes: 3,
            shared_points: 50,
            scale_steps: Vec::new(),
            sightings: Vec::new(),
        };
        map.close_loop(&first, &LoopOptions::default())
            .expect("first loop closed");
        let pinned: Vec<StampedPose> = (0..=40).map(|i| *map.keyframe(i).expect("kf").1).collect();
        map.add_window(&WindowInput {
            poses: (39..n)
                .map(|i| {
                    let mut p = drifted(i);
                    p.position += pinned[39].position - truth(39).position;
                    (i, p)
                })
                .collect(),
            ..WindowInput::default()
        });
        let second = LoopClosure {
            anchor_keyframe: 0,
            transform: drift_after(n - 1).inverse(),
            ..first
        };
        let report = map
            .close_loop(&second, &LoopOptions::default())
            .expect("second loop closed");
        assert_eq!(report.keyframes, 40, "spread over 41-80 only");
        for (i, before) in pinned.iter().enumerate() {
            assert_eq!(
                map.keyframe(i as u64).expect("kf").1,
                before,
                "keyframe {i}"
            );
        }
        assert_eq!(map.loop_pinned, Some((0, n - 1)));
    }
}
