//! Segment linking: a global loop closure after a tracking break (issue 7; the paper notes
//! that "relocalization also facilitates global loop closures").
//!
//! When a break started a new map segment, the new segment's keyframes are relocalized
//! against the older segments with their own descriptors (no image needed). Keyframes that
//! land in the same older segment give, for each of them, its pose in both frames, and the
//! relocalization inliers that are points of the new segment too give 3-D/3-D pairs. From
//! those the similarity new -> old is estimated the way windows are chained
//! ([`align_shared`]: rotation from the keyframe orientations, scale from camera-to-point
//! distance ratios), checked against every keyframe, and the new segment is merged into
//! the old one.

use crate::map::MapBuilder;
use crate::window_alignment::{align_shared, transform_pose};
use egoslam_geometry::{PinholeRadtan, Similarity, StampedPose};
use egoslam_relocalization::{
    BowVector, KeyframeDatabase, MapFeature, MapKeyframe, QueryFeatures, RelocalizationMap,
    Relocalizer, RelocalizerOptions, Vocabulary,
};
use nalgebra::{Point2, Vector3};
use rayon::prelude::*;
use std::collections::{BTreeMap, BTreeSet, HashMap};

/// When a link is accepted; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkOptions {
    /// Keyframes of the new segment that must relocalize, consistently, into the same older
    /// segment (default 3: one keyframe can be a wrong place that looks alike; three that
    /// agree on one similarity cannot, by chance).
    pub min_keyframes: usize,
    /// Largest rotation between a keyframe's relocalized orientation and its orientation
    /// mapped by the link, degrees (default 3: relocalization is within ~1.5 deg of the map
    /// on TUM, docs/relocalization.md).
    pub max_rotation_deg: f64,
    /// Largest position disagreement, as a fraction of the median camera-to-point distance
    /// (default 0.05: 5 cm at 1 m, the scale of the relocalization error).
    pub max_position_fraction: f64,
    /// Keyframes of the segment relocalized per attempt, evenly spread over it (default 12:
    /// 3 must agree, and each query costs ~20 ms; the segment is tried after each of its
    /// first windows, so all of them would make linking the merger's largest cost).
    pub max_queries: usize,
    /// Query only the segment's newest this-many keyframes (default `None`: the whole
    /// segment). A segment past its first windows is retried with its newest keyframes:
    /// a walk that comes back to a place the older map saw links there (a loop closure).
    pub only_newest: Option<usize>,
    pub relocalizer: RelocalizerOptions,
}

impl Default for LinkOptions {
    fn default() -> Self {
        Self {
            min_keyframes: 3,
            max_rotation_deg: 3.0,
            max_position_fraction: 0.05,
            max_queries: 12,
            only_newest: None,
            // A link is a similarity from relocalized positions; a frame placed by
            // rotation at a keyframe's centre has none of its own. Tentative poses
            // (weak appearance matches confirmed by projection) were measured on
            // `localize` only, not on linking: off until they are.
            relocalizer: RelocalizerOptions {
                place_by_rotation: false,
                tentative: None,
                ..RelocalizerOptions::default()
            },
        }
    }
}

/// A link found between two segments.
#[derive(Debug, Clone, PartialEq)]
pub struct SegmentLink {
    /// The newer segment, merged into `to`.
    pub from: u32,
    pub to: u32,
    /// Maps `from`'s frame onto `to`'s.
    pub transform: Similarity,
    /// Keyframes of `from` that relocalized consistently.
    pub keyframes: usize,
    /// 3-D/3-D pairs that gave the scale.
    pub shared_points: usize,
}

/// One relocalized keyframe of the new segment.
struct Relocalized {
    in_new: StampedPose,
    in_old: StampedPose,
    segment: u32,
    /// The older keyframe whose matches gave the pose.
    old_keyframe: u64,
    /// (new-segment point, old-segment point).
    pairs: Vec<(Vector3<f64>, Vector3<f64>)>,
    /// Distances from the relocalized camera to its inlier old points.
    depths: Vec<f64>,
    /// The query keyframe's id and, per inlier, (old point's track, the query's undistorted
    /// pixel of it).
    sightings: (u64, Vec<(u64, Point2<f64>)>),
}

fn query_of(features: &[MapFeature]) -> QueryFeatures {
    QueryFeatures {
        pixels: features
            .iter()
            .map(|f| Point2::new(f64::from(f.pixel.x), f64::from(f.pixel.y)))
            .collect(),
        descriptors: features.iter().map(|f| f.descriptor).collect(),
    }
}

/// Where relocalization inside the map finds the keyframes' described tracks: a map in
/// memory, or a store that reads them from disk when asked (a long run keeps its
/// descriptors there: ~48 KB per keyframe, most of a map's bytes).
pub trait KeyframeFeatureSource {
    /// Whether keyframe `id` has descriptors.
    fn is_described(&self, id: u64) -> bool;
    /// Keyframe `id`'s described tracks.
    fn features(&self, id: u64) -> Option<Vec<MapFeature>>;
}

impl KeyframeFeatureSource for BTreeMap<u64, Vec<MapFeature>> {
    fn is_described(&self, id: u64) -> bool {
        self.contains_key(&id)
    }

    fn features(&self, id: u64) -> Option<Vec<MapFeature>> {
        self.get(&id).cloned()
    }
}

/// What relocalizing keyframes against the map needs: the map, every keyframe's
/// descriptors, their bag-of-words index, the ideal camera of the undistorted pixels and
/// the vocabulary. Segment linking, loop closure and the relocalized chaining scale all
/// query the same five.
#[derive(Clone, Copy)]
pub struct RelocalizationSources<'a> {
    pub map: &'a MapBuilder,
    pub features: &'a dyn KeyframeFeatureSource,
    pub database: &'a KeyframeDatabase,
    pub camera: &'a PinholeRadtan,
    pub vocabulary: &'a Vocabulary,
}

impl RelocalizationSources<'_> {
    /// The keyframes of `segment` that have descriptors, with their poses, in id order.
    pub(crate) fn described_keyframes(&self, segment: u32) -> Vec<(u64, StampedPose)> {
        self.map
            .keyframes()
            .filter(|(id, s, _)| *s == segment && self.features.is_described(*id))
            .map(|(id, _, pose)| (id, *pose))
            .collect()
    }

    /// The map point of `track` if it is in `segment`.
    pub(crate) fn segment_point(&self, segment: u32, track: u64) -> Option<Vector3<f64>> {
        self.map
            .point(track)
            .filter(|(s, _)| *s == segment)
            .map(|(_, x)| *x)
    }
}

/// Searches a link from `segment` to an older segment; `None` when its keyframes do not
/// relocalize consistently enough.
pub fn find_link(
    sources: &RelocalizationSources,
    segment: u32,
    options: &LinkOptions,
) -> Option<SegmentLink> {
    let _span = tracing::info_span!("find_link", segment).entered();
    let mut young = sources.described_keyframes(segment);
    if let Some(n) = options.only_newest {
        young.drain(..young.len().saturating_sub(n));
    }
    let stride = young.len().div_ceil(options.max_queries.max(1)).max(1);
    let queries: Vec<(u64, StampedPose)> = young.iter().step_by(stride).copied().collect();
    let older = OlderKeyframes {
        query_point: &|track| sources.segment_point(segment, track),
        accept: &|_, s| s != segment,
    };
    let agreement = relocalize_consistently(sources, &queries, &older, options)?;
    Some(SegmentLink {
        from: segment,
        to: agreement.to,
        transform: agreement.transform,
        keyframes: agreement.keyframes,
        shared_points: agreement.shared_points,
    })
}

/// Which keyframes the queries may be relocalized against, and where the queries' own
/// points are.
pub(crate) struct OlderKeyframes<'a> {
    /// A query keyframe's track -> its point in the queries' frame, if triangulated.
    pub query_point: &'a dyn Fn(u64) -> Option<Vector3<f64>>,
    /// `(keyframe id, its segment)` -> whether it may be a match. The index is asked for
    /// its best among these alone: where the best-scoring keyframes are refused (a loop's
    /// recent past), drawing a fixed number first and filtering after left none.
    pub accept: &'a dyn Fn(u64, u32) -> bool,
}

/// What the queries agreed on.
pub(crate) struct Agreement {
    /// The segment they relocalized into.
    pub to: u32,
    /// Maps the queries' frame onto `to`'s.
    pub transform: Similarity,
    /// Query keyframes that agree.
    pub keyframes: usize,
    /// 3-D/3-D pairs that gave the scale.
    pub shared_points: usize,
    /// The older keyframes they were relocalized against.
    pub old_keyframes: Vec<u64>,
    /// `(query keyframe, old track, undistorted pixel)`: where the agreeing queries see
    /// the older points they matched.
    pub sightings: Vec<(u64, u64, Point2<f64>)>,
}

/// Relocalizes the `queries` (keyframes with their poses in their own frame) against the
/// keyframes `older` accepts, and returns the similarity the largest group of them that
/// lands in one segment agrees on (at least `options.min_keyframes`, each within the
/// rotation and position tolerances), or `None`.
pub(crate) fn relocalize_consistently(
    sources: &RelocalizationSources,
    queries: &[(u64, StampedPose)],
    older: &OlderKeyframes,
    options: &LinkOptions,
) -> Option<Agreement> {
    let RelocalizationSources {
        map,
        features,
        database,
        camera,
        vocabulary,
    } = *sources;
    // The older keyframes worth matching: each query's best candidates in the whole map's
    // index, with their neighbours. A relocalizer over these few is cheap; one over the
    // whole older map cost seconds per attempt on a 7,000-keyframe walk.
    let older_ids: Vec<u64> = map
        .keyframes()
        .filter(|(id, s, _)| (older.accept)(*id, *s))
        .map(|(id, _, _)| id)
        .collect();
    // Bags of words as the index holds them, computed only for keyframes it lacks.
    let bag_of = |id: u64, features: &[MapFeature]| -> BowVector {
        database.bag(id).cloned().unwrap_or_else(|| {
            let descriptors: Vec<_> = features.iter().map(|f| f.descriptor).collect();
            vocabulary.bag_of_words(&descriptors)
        })
    };
    // Each query's features and bag, read once for the candidate search and the
    // relocalization below.
    let described: Vec<(u64, StampedPose, Vec<MapFeature>, BowVector)> = queries
        .iter()
        .filter_map(|&(id, in_new)| {
            let query = features.features(id)?;
            let bow = bag_of(id, &query);
            Some((id, in_new, query, bow))
        })
        .collect();
    let mut chosen = BTreeSet::new();
    for (_, _, _, bow) in &described {
        let candidates = database.query_where(
            bow,
            options.relocalizer.candidates,
            |id| matches!(map.keyframe(id), Some((s, _)) if (older.accept)(id, s)),
        );
        for c in candidates {
            let at = older_ids.partition_point(|k| *k < c.keyframe_id);
            let lo = at.saturating_sub(options.relocalizer.neighbours);
            let hi = (at + options.relocalizer.neighbours + 1).min(older_ids.len());
            chosen.extend(&older_ids[lo..hi]);
        }
    }
    let mut candidate_bags = KeyframeDatabase::new();
    let candidates: Vec<MapKeyframe> = chosen
        .iter()
        .filter_map(|&id| {
            let (s, pose) = map.keyframe(id)?;
            let described = features.features(id)?;
            candidate_bags.add(id, &bag_of(id, &described));
            Some(MapKeyframe {
                keyframe_id: id,
                segment: s,
                pose: *pose,
                features: described,
                // Queries here are keyframes' own tracks, already where their points are.
                patches: Vec::new(),
            })
        })
        .collect();
    if candidates.is_empty() {
        return None;
    }
    let points: HashMap<u64, (u32, Vector3<f64>)> = candidates
        .iter()
        .flat_map(|k| k.features.iter().map(move |f| (k.segment, f.track_id)))
        .filter_map(|(ks, track)| {
            let (s, x) = map.point(track)?;
            (s == ks).then_some((track, (s, *x)))
        })
        .collect();
    let relocalizer = Relocalizer::with_database(
        vocabulary.clone(),
        RelocalizationMap {
            camera: *camera,
            keyframes: candidates,
            points,
            // The pipeline's keyframe features are corrected already.
            rolling_shutter_s: 0.0,
        },
        candidate_bags,
    );
    // The queries are relocalized independently, on every core: an attempt relocalizes
    // up to a window of keyframes (~20 ms each), and the end of a stream waits for its
    // last window's attempt with the other core idle.
    let relocalized: Vec<Option<_>> = described
        .par_iter()
        .map(|(_, _, kf_features, bow)| {
            let query = query_of(kf_features);
            relocalizer
                .relocalize_bag(&query, bow, &options.relocalizer)
                .ok()
        })
        .collect();
    let mut found: Vec<Relocalized> = Vec::new();
    for ((id, in_new, kf_features, _), r) in described.into_iter().zip(relocalized) {
        let Some(r) = r else {
            continue;
        };
        let pairs = r
            .inliers
            .iter()
            .filter_map(|(old_track, qi)| {
                let x_new = (older.query_point)(kf_features[*qi].track_id)?;
                let (_, x_old) = relocalizer.map().points.get(old_track)?;
                Some((x_new, *x_old))
            })
            .collect();
        let depths = r
            .inliers
            .iter()
            .filter_map(|(old_track, _)| relocalizer.map().points.get(old_track))
            .map(|(_, x)| (x - r.pose.position).norm())
            .collect();
        let sightings = r
            .inliers
            .iter()
            .map(|(old_track, qi)| {
                let p = kf_features[*qi].pixel;
                (*old_track, Point2::new(f64::from(p.x), f64::from(p.y)))
            })
            .collect();
        found.push(Relocalized {
            in_new,
            in_old: r.pose,
            segment: r.segment,
            old_keyframe: r.keyframe_id,
            pairs,
            depths,
            sightings: (id, sightings),
        });
    }
    // The older segment most keyframes relocalized into.
    let mut votes: BTreeMap<u32, usize> = BTreeMap::new();
    for f in &found {
        *votes.entry(f.segment).or_default() += 1;
    }
    tracing::debug!(
        relocalized = found.len(),
        ?votes,
        "keyframes of the segment relocalized"
    );
    let (&to, _) = votes.iter().max_by_key(|(_, n)| **n)?;
    let mut group: Vec<&Relocalized> = found.iter().filter(|f| f.segment == to).collect();
    for _ in 0..2 {
        if group.len() < options.min_keyframes {
            return None;
        }
        let (transform, shared) = link_transform(&group);
        let depth = median_depth(&group)?;
        let consistent: Vec<&Relocalized> = group
            .iter()
            .copied()
            .filter(|f| {
                let mapped = transform_pose(&transform, &f.in_new);
                mapped.rotation.angle_to(&f.in_old.rotation).to_degrees()
                    <= options.max_rotation_deg
                    && (mapped.position - f.in_old.position).norm()
                        <= options.max_position_fraction * depth
            })
            .collect();
        tracing::debug!(
            to,
            relocalized = group.len(),
            consistent = consistent.len(),
            shared,
            "link candidate"
        );
        if consistent.len() == group.len() {
            return Some(Agreement {
                to,
                transform,
                keyframes: group.len(),
                shared_points: shared,
                old_keyframes: group.iter().map(|f| f.old_keyframe).collect(),
                sightings: group
                    .iter()
                    .flat_map(|f| {
                        let (keyframe, seen) = &f.sightings;
                        seen.iter()
                            .map(move |(track, pixel)| (*keyframe, *track, *pixel))
                    })
                    .collect(),
            });
        }
        group = consistent;
    }
    None
}

fn link_transform(group: &[&Relocalized]) -> (Similarity, usize) {
    let new: Vec<StampedPose> = group.iter().map(|f| f.in_new).collect();
    let old: Vec<StampedPose> = group.iter().map(|f| f.in_old).collect();
    let mut seen = BTreeSet::new();
    let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = group
        .iter()
        .flat_map(|f| f.pairs.iter())
        .filter(|(a, _)| seen.insert([a.x.to_bits(), a.y.to_bits(), a.z.to_bits()]))
        .copied()
        .collect();
    (align_shared(&new, &old, &pairs).0, pairs.len())
}

/// Median distance from the relocalized cameras to their inlier old points: the scene's
/// scale in the old segment's units.
fn median_depth(group: &[&Relocalized]) -> Option<f64> {
    crate::median(
        group
            .iter()
            .flat_map(|f| f.depths.iter().copied())
            .collect(),
    )
}

impl MapBuilder {
    /// Merges segment `link.from` into `link.to`: its keyframes and points are mapped by the
    /// link's similarity and relabelled, and new windows continue in `to` if they were
    /// continuing `from`.
    pub fn merge_segment(&mut self, link: &SegmentLink) {
        for (segment, pose) in self.keyframes.values_mut() {
            if *segment == link.from {
                *segment = link.to;
                *pose = transform_pose(&link.transform, pose);
            }
        }
        for (_, (segment, x)) in self.points.iter_mut() {
            if *segment == link.from {
                *segment = link.to;
                *x = link.transform.apply(x);
            }
        }
        if self.current_segment == Some(link.from) {
            self.current_segment = Some(link.to);
        }
    }

    /// Segments that still hold keyframes (created segments minus those merged away).
    pub fn live_segments(&self) -> usize {
        self.keyframes
            .values()
            .map(|(s, _)| *s)
            .collect::<BTreeSet<_>>()
            .len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::WindowInput;
    use nalgebra::{Rotation3, UnitQuaternion};

    #[test]
    fn merging_maps_the_segment_and_continues_in_the_old_one() {
        let pose = |x: f64| StampedPose {
            timestamp: x,
            position: Vector3::new(x, 0.0, 0.0),
            rotation: UnitQuaternion::identity(),
        };
        let mut map = MapBuilder::new();
        let window = |ids: std::ops::Range<u64>, track: u64| WindowInput {
            poses: ids.map(|i| (i, pose(i as f64))).collect(),
            points: vec![(track, Vector3::new(0.0, 0.0, 5.0))],
            ..WindowInput::default()
        };
        map.add_window(&window(0..3, 100));
        map.break_segment();
        map.add_window(&window(10..13, 200));
        assert_eq!(map.live_segments(), 2);
        let link = SegmentLink {
            from: 1,
            to: 0,
            transform: Similarity {
                scale: 2.0,
                rotation: Rotation3::from_euler_angles(0.0, 0.3, 0.0),
                translation: Vector3::new(1.0, 2.0, 3.0),
            },
            keyframes: 3,
            shared_points: 0,
        };
        map.merge_segment(&link);
        assert_eq!(map.live_segments(), 1);
        let (segment, p) = map.keyframe(11).expect("keyframe");
        assert_eq!(segment, 0);
        assert!((p.position - link.transform.apply(&Vector3::new(11.0, 0.0, 0.0))).norm() < 1e-12);
        let (segment, x) = map.point(200).expect("point");
        assert_eq!(segment, 0);
        assert!((x - link.transform.apply(&Vector3::new(0.0, 0.0, 5.0))).norm() < 1e-12);
        assert_eq!(
            map.keyframe(1).expect("kept").1.position,
            Vector3::new(1.0, 0.0, 0.0)
        );
        // The next window sharing keyframes with the merged part aligns to segment 0.
        let next = map.add_window(&window(11..15, 300));
        assert!(
            matches!(next, crate::WindowOutcome::Aligned { segment: 0, .. }),
            "{next:?}"
        );
    }
}
