//! The chaining scale of a window that nothing visual links to the map: the wearer's
//! walking pace, assumed the same just before and just after the boundary.
//!
//! A window normally takes its scale from the points it shares with the map
//! ([`crate::window_alignment::align_shared`]), or from its keyframes relocalized in the map
//! ([`crate::relocalized_scale`]). Across a sharp corner turn while walking (~250 deg/s on
//! the rendered 12,000-frame walk) no track lives through, and the keyframes in the turn
//! see almost nothing: the five keyframes a window shared with the map had 0-10 inlier
//! observations on either side, so their centres were noise. Their Umeyama scale was off
//! by 5.6x there and the scene-depth ratio ([`crate::scene_depth`]; a different wall after
//! the turn) by 2.5x, and the map's metres-per-unit jumped by as much for the rest of the
//! walk.
//!
//! What is well measured on either side is the motion: the map's keyframes before the turn
//! and the window's after it, each seeing hundreds of points. A person walks at a nearly
//! constant pace through a turn and resumes it after a short stop (the constant-velocity
//! assumption of monocular visual odometry, e.g. ORB-SLAM's motion model; here only its
//! speed, over ~1-2 s on each side). So the scale is the ratio of the two paces, map units
//! per second over window units per second. It is a prior, not a measurement: it is used
//! only when no point and no relocalization measures the scale, and only when both sides
//! clearly move (a camera standing still on either side has no pace to compare).

use crate::map::{MapBuilder, WindowInput};
use crate::scene_depth::window_scene_depth;
use egoslam_geometry::{Similarity, StampedPose};
use nalgebra::Rotation3;

/// A new segment's walking pace, map units per second: its scale is set so that its first
/// window walks one unit per second ([`new_segment_gauge`]). A monocular map's scale is a
/// free choice; this one is known before the first window is solved, so the live tracker
/// walks a new stream's first frames in the map's units
/// (`LiveTracker::begin_at_origin`), and a map unit is about a metre of walking.
pub const NEW_SEGMENT_PACE: f64 = 1.0;

/// When and how the pace is measured; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpeedContinuityOptions {
    /// Inlier observations a keyframe needs for its centre to count (default 30: the turn's
    /// keyframes with 0-10 are what this must skip).
    pub min_observations: usize,
    /// Well-observed keyframes used on each side (default 30: ~1-2 s of walking, a few
    /// strides, so that the step bob averages out).
    pub keyframes: usize,
    /// Longest time between two counted keyframes for their distance to count as a step,
    /// seconds (default 0.5: across a gap, e.g. a stop whose keyframes see nothing, the
    /// straight line is not the path).
    pub max_step_s: f64,
    /// Shortest total time of moving steps on each side, seconds (default 0.5).
    pub min_span_s: f64,
    /// Map keyframes older than this before the window are not used, seconds (default 20:
    /// longer than the stops of a walk, after which the pace before the stop is the one to
    /// resume; with 5 s a 4 s stop on the 12,000-frame walk left no pace on the map's side).
    pub max_age_s: f64,
    /// Slowest step that counts as moving, in median scene depths per second (default
    /// 0.05: walking at 1.2 m/s is 0.4 before a wall 3 m away and 0.06 on a street 20 m
    /// wide; a standing head sways ~0.01-0.02).
    pub min_speed_depths_per_s: f64,
}

impl Default for SpeedContinuityOptions {
    fn default() -> Self {
        Self {
            min_observations: 30,
            keyframes: 30,
            max_step_s: 0.5,
            min_span_s: 0.5,
            max_age_s: 20.0,
            min_speed_depths_per_s: 0.05,
        }
    }
}

/// The pace of `poses` (in time order) while moving: the median speed of the steps between
/// consecutive poses at most `max_step_s` apart that are at least `min_speed` fast; `None`
/// when those steps span less than `min_span_s`. Steps slower than `min_speed` are the
/// wearer standing (a stop inside the span would otherwise halve a mean speed: on the
/// rendered 1,500-frame walk a 2 s stop did, and the map's scale doubled).
pub fn walking_pace(
    poses: &[&StampedPose],
    min_speed: f64,
    options: &SpeedContinuityOptions,
) -> Option<f64> {
    let mut speeds = Vec::new();
    let mut time = 0.0;
    for pair in poses.windows(2) {
        let dt = pair[1].timestamp - pair[0].timestamp;
        if dt > 0.0 && dt <= options.max_step_s {
            let speed = (pair[1].position - pair[0].position).norm() / dt;
            if speed.is_finite() && speed >= min_speed {
                speeds.push(speed);
                time += dt;
            }
        }
    }
    if time < options.min_span_s {
        return None;
    }
    crate::median(speeds)
}

/// The window's pace over its first well-observed keyframes, in window units per second.
pub(crate) fn window_pace(
    window: &WindowInput,
    min_speed: f64,
    options: &SpeedContinuityOptions,
) -> Option<f64> {
    well_seen_pace(
        &window.poses,
        &window.observation_counts(),
        min_speed,
        options,
    )
}

/// The pace of the first of `poses` that have `min_observations` in `seen` (observations
/// per keyframe), in their units per second: [`window_pace`] over a part of a window.
pub(crate) fn well_seen_pace(
    poses: &[(u64, StampedPose)],
    seen: &std::collections::HashMap<u64, usize>,
    min_speed: f64,
    options: &SpeedContinuityOptions,
) -> Option<f64> {
    let poses: Vec<&StampedPose> = poses
        .iter()
        .filter(|(id, _)| seen.get(id).copied().unwrap_or(0) >= options.min_observations)
        .map(|(_, p)| p)
        .take(options.keyframes)
        .collect();
    walking_pace(&poses, min_speed, options)
}

/// [`window_pace`] with steps counted as moving from
/// [`SpeedContinuityOptions::min_speed_depths_per_s`] of the window's scene depth; `None`
/// without a depth or a clear walk.
fn window_walking_pace(window: &WindowInput, options: &SpeedContinuityOptions) -> Option<f64> {
    let depth = window_scene_depth(window)?;
    window_pace(window, options.min_speed_depths_per_s * depth, options)
}

/// The transform that puts a window starting a new segment into the segment's gauge: its
/// first keyframe where the window has it, scaled about it so that the window walks at
/// [`NEW_SEGMENT_PACE`]; the identity when the window does not clearly walk (its scale is
/// then the solver's).
pub(crate) fn new_segment_gauge(window: &WindowInput) -> Similarity {
    let pace = window_walking_pace(window, &SpeedContinuityOptions::default());
    let (Some(pace), Some((_, first))) = (pace, window.poses.first()) else {
        return Similarity::identity();
    };
    let scale = NEW_SEGMENT_PACE / pace;
    if !(scale.is_finite() && scale > 0.0) {
        return Similarity::identity();
    }
    Similarity {
        scale,
        rotation: Rotation3::identity(),
        translation: first.position * (1.0 - scale),
    }
}

impl MapBuilder {
    /// The segment's pace over its newest well-observed keyframes before keyframe
    /// `before_id` (posed `before` in the window), in map units per second.
    pub(crate) fn recent_pace(
        &self,
        segment: u32,
        (before_id, before): (u64, &StampedPose),
        min_speed: f64,
        options: &SpeedContinuityOptions,
    ) -> Option<f64> {
        // Keyframe ids follow time: past the age limit every older keyframe is older still.
        let mut poses: Vec<&StampedPose> = self
            .keyframes
            .range(..before_id)
            .rev()
            .take_while(|(_, (_, p))| before.timestamp - p.timestamp <= options.max_age_s)
            .filter(|(_, (s, _))| *s == segment)
            .filter(|(id, _)| self.observed_points(**id) >= options.min_observations)
            .map(|(_, (_, p))| p)
            .take(options.keyframes)
            .collect();
        poses.reverse();
        walking_pace(&poses, min_speed, options)
    }

    /// The scale (map units per window unit) that gives `window` the pace the segment had
    /// just before it; `None` unless both sides clearly move
    /// ([`SpeedContinuityOptions::min_speed_depths_per_s`]).
    pub fn speed_continuity_scale(
        &self,
        segment: u32,
        window: &WindowInput,
        options: &SpeedContinuityOptions,
    ) -> Option<f64> {
        let (first_id, first) = window.poses.first()?;
        let map_pace = self.segment_walking_pace(segment, (*first_id, first), options);
        let window_pace = window_walking_pace(window, options);
        tracing::debug!(?map_pace, ?window_pace, "speed continuity");
        Some(map_pace? / window_pace?)
    }

    /// [`Self::recent_pace`] with steps counted as moving from
    /// [`SpeedContinuityOptions::min_speed_depths_per_s`] of the segment's recent scene
    /// depth; `None` without a depth or a clear walk.
    fn segment_walking_pace(
        &self,
        segment: u32,
        before: (u64, &StampedPose),
        options: &SpeedContinuityOptions,
    ) -> Option<f64> {
        let depth = self.recent_scene_depth(segment)?;
        self.recent_pace(
            segment,
            before,
            options.min_speed_depths_per_s * depth,
            options,
        )
    }

    /// The segment's walking pace up to and including keyframe `newest` (map units per
    /// second, as [`Self::speed_continuity_scale`] measures the map's side); `None` while
    /// it has not clearly moved.
    pub fn recent_walking_pace(&self, segment: u32, newest: u64) -> Option<f64> {
        let (_, pose) = self.keyframes.get(&newest)?;
        self.segment_walking_pace(
            segment,
            (newest + 1, pose),
            &SpeedContinuityOptions::default(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::ScaleSource;
    use crate::WindowOutcome;
    use nalgebra::{UnitQuaternion, Vector3};

    fn pose(t: f64, x: f64) -> StampedPose {
        StampedPose {
            timestamp: t,
            position: Vector3::new(x, 0.0, 0.0),
            rotation: UnitQuaternion::identity(),
        }
    }

    /// Keyframes `ids` at 20 per second walking along x at `pace` (window units per second),
    /// each seeing 60 points `depth` ahead (track ids from `tracks`); `blind` of the first
    /// ones see nothing and sit at `blind_x` (a turn's keyframes: noise).
    fn walk(
        ids: std::ops::Range<u64>,
        pace: f64,
        depth: f64,
        tracks: u64,
        blind: usize,
    ) -> WindowInput {
        let poses: Vec<(u64, StampedPose)> = ids
            .clone()
            .enumerate()
            .map(|(i, id)| {
                let t = id as f64 * 0.05;
                let x = if i < blind { 5.0 * i as f64 } else { pace * t };
                (id, pose(t, x))
            })
            .collect();
        let points: Vec<(u64, Vector3<f64>)> = (0..60)
            .map(|k| (tracks + k, Vector3::new(k as f64 * 0.1 * depth, 0.2, depth)))
            .collect();
        WindowInput::seeing_all(poses, points, blind)
    }

    /// The scale a chained window got and what gave it.
    fn chained(outcome: WindowOutcome) -> (f64, ScaleSource) {
        match outcome {
            WindowOutcome::Aligned {
                transform,
                scale_source,
                ..
            } => (transform.scale, scale_source),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn across_a_blind_turn_the_window_gets_the_pace_of_the_map() {
        let mut map = MapBuilder::new();
        map.add_window(&walk(0..30, NEW_SEGMENT_PACE, 3.0, 1000, 0));
        // A new segment walks one unit per second. After the turn, in a frame 4x smaller:
        // the same pace is 0.25 units/s. The five
        // keyframes shared with the map saw nothing (in the map too they would be noise),
        // and no point is shared.
        let after = walk(25..45, 0.25, 0.75, 5000, 5);
        let (scale, source) = chained(map.add_window(&after));
        assert_eq!(source, ScaleSource::WalkingPace);
        assert!((scale - 4.0).abs() < 1e-9, "{scale}");
    }

    #[test]
    fn points_shared_through_keyframes_one_side_barely_sees_do_not_give_the_scale() {
        let mut map = MapBuilder::new();
        map.add_window(&walk(0..30, NEW_SEGMENT_PACE, 3.0, 1000, 0));
        // The window shares all 60 of the map's points, but triangulated them from the
        // shared keyframes it hardly sees: their positions say half the true scale (the
        // points at 1.5 where 0.75 is right). The pace says 4.
        let mut after = walk(25..45, 0.25, 1.5, 1000, 5);
        after.poses[..5]
            .iter_mut()
            .enumerate()
            .for_each(|(i, (id, p))| {
                *p = pose(
                    *id as f64 * 0.05,
                    0.25 * *id as f64 * 0.05 + 0.001 * i as f64,
                )
            });
        assert!(map.lacks_shared_points(&after));
        let (scale, source) = chained(map.add_window(&after));
        assert_eq!(source, ScaleSource::WalkingPace);
        assert!((scale - 4.0).abs() < 1e-9, "{scale}");
        // Seen well on both sides, the same points do give it.
        let mut map = MapBuilder::new();
        map.add_window(&walk(0..30, NEW_SEGMENT_PACE, 3.0, 1000, 0));
        let firm = walk(25..45, 0.25, 0.75, 1000, 0);
        assert!(!map.lacks_shared_points(&firm));
        assert_eq!(chained(map.add_window(&firm)).1, ScaleSource::SharedPoints);
    }

    #[test]
    fn shared_points_that_say_the_pace_jumped_several_fold_are_overruled_by_it() {
        // Firmly joined (60 points, every keyframe sees them all), but the window pulled
        // its points 10x towards the shared keyframes: their scale says ~40 where the pace
        // says 4. Such a window is broken; the pace is the wearer's.
        let pulled = |factor: f64| {
            let mut w = walk(25..45, 0.25, 0.75, 1000, 0);
            let centre = w.poses[..5]
                .iter()
                .map(|(_, p)| p.position)
                .sum::<Vector3<f64>>()
                / 5.0;
            for (_, x) in &mut w.points {
                *x = centre + factor * (*x - centre);
            }
            w
        };
        let mut map = MapBuilder::new();
        map.add_window(&walk(0..30, NEW_SEGMENT_PACE, 3.0, 1000, 0));
        let broken = pulled(0.1);
        assert!(!map.lacks_shared_points(&broken));
        let (scale, source) = chained(map.add_window(&broken));
        assert_eq!(source, ScaleSource::WalkingPace);
        assert!((scale - 4.0).abs() < 1e-9, "{scale}");
        // Pulled by half, within what a pace may change: the points decide.
        let mut map = MapBuilder::new();
        map.add_window(&walk(0..30, NEW_SEGMENT_PACE, 3.0, 1000, 0));
        let (scale, source) = chained(map.add_window(&pulled(0.5)));
        assert_eq!(source, ScaleSource::SharedPoints);
        assert!(scale > 6.0, "{scale}");
    }

    #[test]
    fn a_stop_inside_the_span_does_not_slow_the_pace() {
        let options = SpeedContinuityOptions::default();
        // 1 s walking at 1.2, then 1 s standing.
        let poses: Vec<StampedPose> = (0..40)
            .map(|i| {
                let t = i as f64 * 0.05;
                pose(t, 1.2 * t.min(1.0))
            })
            .collect();
        let refs: Vec<&StampedPose> = poses.iter().collect();
        let pace = walking_pace(&refs, 0.1, &options).expect("moving for 1 s");
        assert!((pace - 1.2).abs() < 1e-9, "{pace}");
        // Standing throughout: no pace, whatever the scale of the map.
        let standing: Vec<StampedPose> = (0..40).map(|i| pose(i as f64 * 0.05, 0.0)).collect();
        let refs: Vec<&StampedPose> = standing.iter().collect();
        assert_eq!(walking_pace(&refs, 0.1, &options), None);
    }

    #[test]
    fn a_standing_map_gives_no_pace_and_the_window_keeps_the_weaker_evidence() {
        let mut map = MapBuilder::new();
        map.add_window(&walk(0..30, 0.0, 3.0, 1000, 0));
        let after = walk(25..45, 0.25, 0.75, 5000, 5);
        assert_eq!(
            map.speed_continuity_scale(0, &after, &SpeedContinuityOptions::default()),
            None
        );
        assert_eq!(chained(map.add_window(&after)).1, ScaleSource::Weak);
    }

    #[test]
    fn a_new_segment_walks_one_unit_per_second_from_its_first_keyframe() {
        // The solver's frame: 0.3 units/s, the first keyframe off the origin.
        let mut first = walk(0..30, 0.3, 0.9, 1000, 0);
        for (_, p) in &mut first.poses {
            p.position += Vector3::new(0.5, 0.0, 0.0);
        }
        let mut map = MapBuilder::new();
        assert!(matches!(
            map.add_window(&first),
            WindowOutcome::NewSegment { segment: 0 }
        ));
        let at = |id: u64| map.keyframe(id).expect("posed").1;
        assert!((at(0).position - first.poses[0].1.position).norm() < 1e-12);
        let pace = (at(20).position - at(0).position).norm() / (at(20).timestamp - at(0).timestamp);
        assert!((pace - NEW_SEGMENT_PACE).abs() < 1e-9, "{pace}");
        // A window standing in place has no pace: its scale stays the solver's.
        let standing = walk(0..30, 0.0, 0.9, 1000, 0);
        assert_eq!(new_segment_gauge(&standing), Similarity::identity());
    }
}
