//! Redundant keyframes leave the map (Mur-Artal et al., "ORB-SLAM", T-RO 2015, section
//! VI-E): a keyframe whose map points are nearly all seen by enough other keyframes adds
//! nothing the refinements or relocalization need, and keeping it makes memory, the
//! checkpoint and every map-wide step grow with the time walked instead of with the
//! ground covered. The head-mounted walks this runs on make keyframes at 0.4-0.8 per frame
//! (head turns fire the flow rule), so most of them are redundant.
//!
//! What is removed: the keyframe's pose, its observations (kept and weak), and points no
//! keyframe observes any more. Its frame (and the frames posed against it) are handed to
//! the caller, who keeps them relative to the keyframes around ([`CulledKeyframe`]).

use crate::map::MapBuilder;
use egoslam_geometry::StampedPose;
use std::collections::{BTreeSet, HashMap};

/// When a keyframe is redundant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeyframeCullingOptions {
    /// Fraction of its points that must be seen by [`Self::other_views`] other keyframes
    /// (ORB-SLAM: 90 %).
    pub redundant_fraction: f64,
    /// ORB-SLAM: 3.
    pub other_views: usize,
    /// Keyframes this many ids before the oldest candidate, and every one after it, count
    /// as other views (the tracks of a walk's keyframes live a few windows; a point seen
    /// again much later through a loop sighting is not counted, which only keeps more).
    pub neighbourhood: u64,
    /// The rule for places mapped before ([`crate::keyframe_coverage`]); `None`: only the
    /// covisibility rule.
    pub revisits: Option<crate::keyframe_coverage::CoverageOptions>,
    /// A map of at most this many keyframes is kept whole: it is small (~100 MB in the
    /// merger), and relocalization against a saved map is most accurate with every
    /// keyframe (culled, the rendered walks' median relocalization error rose by a
    /// quarter, and one TUM frame was relocalized a kilometre off).
    pub min_map_keyframes: usize,
    /// A point left with fewer views than this by a culled keyframe leaves the map, with
    /// its last observation (default 2: one view gives it no parallax, so no refinement
    /// can move it and no pose rests on it; ORB-SLAM drops a point at two, Mur-Artal et al.
    /// 2015, `MapPoint::EraseObservation`). Otherwise the survivors of culling keep every
    /// point their culled neighbours shared with them, and the map's points keep growing
    /// at its keyframe ceiling.
    pub min_point_views: usize,
}

impl Default for KeyframeCullingOptions {
    fn default() -> Self {
        Self {
            redundant_fraction: 0.9,
            other_views: 3,
            neighbourhood: 300,
            revisits: Some(Default::default()),
            min_map_keyframes: 600,
            min_point_views: 2,
        }
    }
}

/// A keyframe taken out of the map, with what its frames need to stay posed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CulledKeyframe {
    pub keyframe_id: u64,
    pub segment: u32,
    pub pose: StampedPose,
}

/// The outcome of one culling pass.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CullingReport {
    pub culled: Vec<CulledKeyframe>,
    /// Points left without any observation, removed.
    pub removed_points: usize,
}

impl MapBuilder {
    /// Culls the redundant keyframes among `candidates` (oldest first, so that the counts
    /// of the later ones see the earlier removals). A keyframe is kept when it is the first
    /// or last of its segment (the frames around it need a keyframe on each side), when it
    /// observes no point and no older keyframe covers it, or when fewer than
    /// `redundant_fraction` of its points are seen by `other_views` other keyframes and no
    /// older keyframe covers it ([`crate::keyframe_coverage`]).
    pub fn cull_keyframes(
        &mut self,
        candidates: &[u64],
        options: &KeyframeCullingOptions,
    ) -> CullingReport {
        let mut report = CullingReport::default();
        let (Some(&oldest), Some(&newest)) = (candidates.iter().min(), candidates.iter().max())
        else {
            return report;
        };
        if self.keyframes.len() <= options.min_map_keyframes {
            return report;
        }
        let first_nearby = oldest.saturating_sub(options.neighbourhood);
        let mut views = ViewCounts::of(self, candidates, first_nearby);
        let older = options
            .revisits
            .map(|r| crate::keyframe_coverage::OlderKeyframes::of(self, newest, &r));
        for &id in candidates {
            let Some(&(segment, pose)) = self.keyframes.get(&id) else {
                continue;
            };
            if !self.has_neighbours_in(segment, id) {
                continue;
            }
            let tracks: Vec<u64> = self
                .observations
                .range((id, 0)..=(id, u64::MAX))
                .map(|((_, t), _)| *t)
                .filter(|t| self.points.contains_key(t))
                .collect();
            let seen_elsewhere = tracks
                .iter()
                .filter(|t| views.nearby(**t) > options.other_views)
                .count();
            // A keyframe without points is never redundant by its points (it may be what
            // poses the frames of a turn on the spot), but on a revisit it is covered like
            // the others: there the neighbours culled before it took its points along.
            let redundant = !tracks.is_empty()
                && (seen_elsewhere as f64) >= options.redundant_fraction * tracks.len() as f64;
            let covered = || {
                older
                    .as_ref()
                    .is_some_and(|older| older.cover(self, id, segment, &pose))
            };
            if !redundant && !covered() {
                continue;
            }
            self.cull_one(id, &mut views, options.min_point_views, &mut report);
        }
        self.drop_weak_views(&report);
        report
    }

    /// Removes keyframe `id` into `report`.
    fn cull_one(
        &mut self,
        id: u64,
        views: &mut ViewCounts,
        min_point_views: usize,
        report: &mut CullingReport,
    ) {
        let Some(&(segment, pose)) = self.keyframes.get(&id) else {
            return;
        };
        report.removed_points += self.remove_keyframe(id, views, min_point_views);
        report.culled.push(CulledKeyframe {
            keyframe_id: id,
            segment,
            pose,
        });
    }

    /// Removes the keyframes `ids` (chosen otherwise, e.g. by
    /// [`MapBuilder::over_budget_keyframes`]), as [`Self::cull_keyframes`] removes the
    /// redundant ones.
    pub fn remove_keyframes(
        &mut self,
        ids: &[u64],
        options: &KeyframeCullingOptions,
    ) -> CullingReport {
        let mut report = CullingReport::default();
        let Some(&oldest) = ids.iter().min() else {
            return report;
        };
        let first_nearby = oldest.saturating_sub(options.neighbourhood);
        let mut views = ViewCounts::of(self, ids, first_nearby);
        for &id in ids {
            self.cull_one(id, &mut views, options.min_point_views, &mut report);
        }
        self.drop_weak_views(&report);
        report
    }

    fn drop_weak_views(&mut self, report: &CullingReport) {
        if report.culled.is_empty() {
            return;
        }
        let culled: BTreeSet<u64> = report.culled.iter().map(|c| c.keyframe_id).collect();
        self.weak.retain(|_, views| {
            views.retain(|k, _| !culled.contains(k));
            !views.is_empty()
        });
    }

    /// Whether keyframe `id` has keyframes of `segment` both before and after it.
    fn has_neighbours_in(&self, segment: u32, id: u64) -> bool {
        let before = self
            .keyframes
            .range(..id)
            .next_back()
            .is_some_and(|(_, (s, _))| *s == segment);
        let after = self
            .keyframes
            .range(id + 1..)
            .next()
            .is_some_and(|(_, (s, _))| *s == segment);
        before && after
    }

    /// Removes keyframe `id` and its observations, and the points it leaves with fewer
    /// than `min_views` views (with their last observations); returns how many points were
    /// removed.
    fn remove_keyframe(&mut self, id: u64, views: &mut ViewCounts, min_views: usize) -> usize {
        self.keyframes.remove(&id);
        let seen_again: Vec<(u64, u64)> = self
            .seen_again
            .range((id, 0)..=(id, u64::MAX))
            .map(|(k, _)| *k)
            .collect();
        for key in seen_again {
            self.seen_again.remove(&key);
        }
        let keys: Vec<(u64, u64)> = self
            .observations
            .range((id, 0)..=(id, u64::MAX))
            .map(|(k, _)| *k)
            .collect();
        let mut removed = 0;
        for &(_, track) in &keys {
            self.observations.remove(&(id, track));
            let left = views.remove_view(track, id);
            if left.len() >= min_views || !self.points.contains_key(&track) {
                continue;
            }
            for keyframe in left {
                self.observations.remove(&(*keyframe, track));
            }
            views.forget(track);
            self.points.remove(&track);
            removed += 1;
        }
        removed
    }
}

/// How many keyframes observe each track of the keyframes looked at: those from the
/// neighbourhood's first keyframe on (the covisibility rule counts only these), and all of
/// them (a point leaves the map only when no keyframe at all observes it: a revisit
/// keyframe's loop sightings of an old point are often its only views near the candidates,
/// and the old keyframes that made the point still see it).
struct ViewCounts {
    /// track -> (views from the neighbourhood's first keyframe on, every keyframe that
    /// observes it).
    counts: HashMap<u64, (usize, Vec<u64>)>,
}

impl ViewCounts {
    fn of(map: &MapBuilder, keyframes: &[u64], first_nearby: u64) -> Self {
        let mut counts: HashMap<u64, (usize, Vec<u64>)> = HashMap::new();
        for &id in keyframes {
            for ((_, track), _) in map.observations.range((id, 0)..=(id, u64::MAX)) {
                counts.insert(*track, (0, Vec::new()));
            }
        }
        for (keyframe, track) in map.observations.keys() {
            if let Some((nearby, all)) = counts.get_mut(track) {
                all.push(*keyframe);
                if *keyframe >= first_nearby {
                    *nearby += 1;
                }
            }
        }
        Self { counts }
    }

    /// Keyframes from the neighbourhood's first on that observe `track`.
    fn nearby(&self, track: u64) -> usize {
        self.counts.get(&track).map_or(0, |c| c.0)
    }

    /// Takes `keyframe`'s view of `track` away (the keyframes looked at are all in the
    /// neighbourhood); returns the keyframes that still observe it.
    fn remove_view(&mut self, track: u64, keyframe: u64) -> &[u64] {
        let Some((nearby, all)) = self.counts.get_mut(&track) else {
            return &[];
        };
        *nearby = nearby.saturating_sub(1);
        all.retain(|k| *k != keyframe);
        all
    }

    /// `track` left the map: no view of it is counted any more.
    fn forget(&mut self, track: u64) {
        self.counts.remove(&track);
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::map::MapParts;
    use nalgebra::{Point2, UnitQuaternion, Vector3};
    use std::collections::BTreeMap;

    /// The rules on maps of any size.
    pub(crate) fn any_size() -> KeyframeCullingOptions {
        KeyframeCullingOptions {
            min_map_keyframes: 0,
            ..Default::default()
        }
    }

    fn pose(t: f64) -> StampedPose {
        StampedPose {
            timestamp: t,
            position: Vector3::new(t, 0.0, 0.0),
            rotation: UnitQuaternion::identity(),
        }
    }

    /// Keyframes 0..n in one segment; keyframe k observes tracks `tracks(k)`.
    fn map(n: u64, tracks: impl Fn(u64) -> Vec<u64>) -> MapBuilder {
        let mut parts = MapParts::default();
        for k in 0..n {
            parts.keyframes.insert(k, (0, pose(k as f64)));
            for t in tracks(k) {
                parts
                    .points
                    .insert(t, (0, Vector3::new(t as f64, 1.0, 5.0)));
                parts.observations.insert((k, t), Point2::new(1.0, 2.0));
            }
        }
        MapBuilder::from_parts(parts)
    }

    #[test]
    fn keyframes_whose_points_others_see_go_and_the_ends_and_unique_views_stay() {
        // Every keyframe sees the same 20 tracks, keyframe 5 also 10 of its own.
        let mut m = map(10, |k| {
            let mut t: Vec<u64> = (0..20).collect();
            if k == 5 {
                t.extend(100..110);
            }
            t
        });
        let report = m.cull_keyframes(&(0..10).collect::<Vec<_>>(), &any_size());
        let culled: Vec<u64> = report.culled.iter().map(|c| c.keyframe_id).collect();
        // 0 and 9 end the segment; 5's own tracks are a third of its points. Keyframe 8,
        // the last culled, still had 3 others (0, 5, 9) seeing its points.
        assert!(!culled.contains(&0) && !culled.contains(&9) && !culled.contains(&5));
        let kept: Vec<u64> = m.keyframes().map(|(id, _, _)| id).collect();
        assert_eq!(kept.len() + culled.len(), 10);
        assert_eq!(kept, vec![0, 5, 9], "culled {culled:?}");
        for t in 0..20 {
            let views = m.observations.keys().filter(|(_, x)| *x == t).count();
            assert_eq!(views, 3, "track {t}");
        }
        assert_eq!(report.removed_points, 0);
        assert_eq!(m.points().count(), 30);
    }

    #[test]
    fn an_old_point_a_culled_revisit_keyframe_sighted_stays_with_the_keyframes_that_made_it() {
        // Keyframes 0..5 made tracks 0..20; keyframes 400..410, a revisit far past the
        // neighbourhood, see tracks 1000..1020 and keyframe 405 also sighted old track 3.
        let mut m = map(411, |k| match k {
            0..=4 => (0..20).collect(),
            400..=410 => (1000..1020).collect(),
            _ => Vec::new(),
        });
        m.observations.insert((405, 3), Point2::new(4.0, 4.0));
        let report = m.cull_keyframes(&[405], &any_size());
        assert_eq!(
            report.culled.len(),
            1,
            "20 of its 21 points are seen by 10 others"
        );
        assert_eq!(report.removed_points, 0);
        assert!(m.point(3).is_some(), "keyframes 0..5 still observe track 3");
        assert_eq!(m.points().count(), 40);
    }

    #[test]
    fn a_point_a_culled_keyframe_leaves_with_one_view_goes_with_that_view() {
        // Keyframes 0..6 see tracks 0..20; keyframes 2 and 3 alone also see track 50.
        let tracks = |k| {
            let mut t: Vec<u64> = (0..20).collect();
            if k == 2 || k == 3 {
                t.push(50);
            }
            t
        };
        let mut m = map(6, tracks);
        let report = m.cull_keyframes(&[2], &any_size());
        assert_eq!(report.culled.len(), 1);
        assert_eq!(report.removed_points, 1);
        assert!(m.point(50).is_none());
        assert!(
            !m.observations.contains_key(&(3, 50)),
            "keyframe 3's lone view went too"
        );
        assert_eq!(m.observations.range((3, 0)..(4, 0)).count(), 20);
        let keep_single = KeyframeCullingOptions {
            min_point_views: 1,
            ..any_size()
        };
        let mut m = map(6, tracks);
        let report = m.cull_keyframes(&[2], &keep_single);
        assert_eq!((report.culled.len(), report.removed_points), (1, 0));
        assert!(m.point(50).is_some());
        assert!(m.observations.contains_key(&(3, 50)));
    }

    #[test]
    fn a_point_only_the_culled_keyframe_saw_goes_with_it_and_weak_views_too() {
        // Keyframes 0..6 see tracks 0..20; keyframe 2 alone sees track 50 (1 of 21 points,
        // under the 10 % it may own).
        let mut m = map(6, |k| {
            let mut t: Vec<u64> = (0..20).collect();
            if k == 2 {
                t.push(50);
            }
            t
        });
        let mut weak = BTreeMap::new();
        weak.insert(2, Point2::new(3.0, 3.0));
        m.weak.insert(77, weak);
        let report = m.cull_keyframes(&[2], &any_size());
        assert_eq!(report.culled.len(), 1);
        assert_eq!(report.culled[0].keyframe_id, 2);
        assert_eq!(report.culled[0].pose, pose(2.0));
        assert_eq!(report.removed_points, 1);
        assert!(m.point(50).is_none() && m.keyframe(2).is_none());
        assert!(m.weak.is_empty());
    }
}
