//! A saved map as the start of a run's map (multi-session): a wearer's home or office is
//! mapped once, and the next day's run extends that map instead of starting anew.
//!
//! The saved map's keyframes, points and the keyframes' sightings of those points become
//! the map's older segments; the run's first window starts a segment of its own, which
//! segment linking ([`crate::segment_linking`]) merges into the saved map's segment once
//! enough of its keyframes relocalize there, consistently. From then on the run's poses are
//! in the saved map's frame and scale, and loops close against the saved keyframes as
//! against the run's own. The run's keyframe and track ids must start above the saved
//! map's ([`next_free_id`]): ids order keyframes in time, and the saved ones are older.

use crate::map::MapParts;
use egoslam_relocalization::RelocalizationMap;
use nalgebra::Point2;

/// The smallest id above every keyframe and track id of `map` (points and described
/// tracks): where the run's own ids start.
pub fn next_free_id(map: &RelocalizationMap) -> u64 {
    let keyframes = map.keyframes.iter().map(|k| k.keyframe_id);
    let described = map
        .keyframes
        .iter()
        .flat_map(|k| k.features.iter().map(|f| f.track_id));
    let tracks = map.points.keys().copied();
    keyframes
        .chain(described)
        .chain(tracks)
        .max()
        .map_or(0, |id| id + 1)
}

impl MapParts {
    /// The map state of a saved map: its keyframes and points in their segments, and every
    /// keyframe's feature of a point of its segment as an observation (what the refinements
    /// adjust against). New windows start a new segment.
    pub fn from_saved(map: &RelocalizationMap) -> Self {
        let mut parts = Self::default();
        for (track, (segment, x)) in &map.points {
            parts.points.insert(*track, (*segment, *x));
        }
        for k in &map.keyframes {
            parts.keyframes.insert(k.keyframe_id, (k.segment, k.pose));
            for f in &k.features {
                if matches!(map.points.get(&f.track_id), Some((s, _)) if *s == k.segment) {
                    let pixel = Point2::new(f64::from(f.pixel.x), f64::from(f.pixel.y));
                    parts
                        .observations
                        .insert((k.keyframe_id, f.track_id), pixel);
                }
            }
        }
        parts.segments = map
            .keyframes
            .iter()
            .map(|k| k.segment)
            .chain(map.points.values().map(|(s, _)| *s))
            .max()
            .map_or(0, |s| s + 1);
        parts.current_segment = None;
        parts
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::{MapBuilder, WindowInput, WindowOutcome};
    use egoslam_geometry::{PinholeRadtan, StampedPose};
    use egoslam_relocalization::{MapFeature, MapKeyframe};
    use nalgebra::{Point2, UnitQuaternion, Vector3};

    fn keyframe(id: u64, segment: u32, tracks: &[u64]) -> MapKeyframe {
        MapKeyframe {
            keyframe_id: id,
            segment,
            pose: StampedPose {
                timestamp: id as f64,
                position: Vector3::new(id as f64, 0.0, 0.0),
                rotation: UnitQuaternion::identity(),
            },
            features: tracks
                .iter()
                .map(|t| MapFeature {
                    track_id: *t,
                    descriptor: [0; 32],
                    pixel: Point2::new(*t as f32, 1.0),
                })
                .collect(),
            patches: Vec::new(),
        }
    }

    #[test]
    fn the_saved_map_becomes_older_segments_and_the_run_starts_its_own() {
        let camera =
            PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera");
        let saved = RelocalizationMap {
            camera,
            // Keyframe 7 describes track 3 (a point of segment 1, not its own) and 40
            // (no point): neither is an observation.
            keyframes: vec![keyframe(5, 0, &[1, 2]), keyframe(7, 0, &[2, 3, 40])],
            points: [
                (1, (0, Vector3::new(0.0, 0.0, 5.0))),
                (2, (0, Vector3::new(1.0, 0.0, 5.0))),
                (3, (1, Vector3::new(2.0, 0.0, 5.0))),
            ]
            .into_iter()
            .collect(),
            rolling_shutter_s: 0.0,
        };
        assert_eq!(next_free_id(&saved), 41);
        let parts = MapParts::from_saved(&saved);
        let observed: Vec<(u64, u64)> = parts.observations.keys().copied().collect();
        assert_eq!(observed, vec![(5, 1), (5, 2), (7, 2)]);
        assert_eq!(parts.observations[&(7, 2)], Point2::new(2.0, 1.0));
        assert_eq!(parts.segments, 2);
        let mut map = MapBuilder::from_parts(parts);
        let pose = |t: f64| StampedPose {
            timestamp: t,
            position: Vector3::zeros(),
            rotation: UnitQuaternion::identity(),
        };
        let outcome = map.add_window(&WindowInput {
            poses: vec![(41, pose(41.0)), (42, pose(42.0))],
            ..WindowInput::default()
        });
        assert_eq!(outcome, WindowOutcome::NewSegment { segment: 2 });
        assert_eq!(map.keyframe(5).map(|(s, _)| s), Some(0));
    }
}
