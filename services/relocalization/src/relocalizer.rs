//! Relocalization of a frame in a map without any tracking prior (paper, section 5
//! "Relocalization"): bag-of-words candidates from the vocabulary tree, descriptor matches
//! to the candidates' map points, outliers rejected with the candidates' known poses, PnP in
//! RANSAC, then a pose-only refinement on every candidate's inlier matches.

use crate::absolute_pose::{solve_pnp, PnpOptions};
use crate::descriptors::{hamming, Descriptor};
use crate::keyframe_database::KeyframeDatabase;
use crate::vocabulary::Vocabulary;
use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Point2, Vector3};
use std::collections::HashMap;

/// A keyframe feature that is a map point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapFeature {
    pub track_id: u64,
    pub descriptor: Descriptor,
    /// Undistorted pixel in the keyframe.
    pub pixel: Point2<f32>,
}

/// A keyframe of a relocalization map.
#[derive(Debug, Clone, PartialEq)]
pub struct MapKeyframe {
    pub keyframe_id: u64,
    /// Map segment of the keyframe (poses of different segments are in different frames).
    pub segment: u32,
    /// world_from_camera, in the segment's frame.
    pub pose: StampedPose,
    pub features: Vec<MapFeature>,
}

/// What relocalization searches: keyframes with described features and the points.
#[derive(Debug, Clone, PartialEq)]
pub struct RelocalizationMap {
    /// Ideal pinhole camera of the undistorted pixels.
    pub camera: PinholeRadtan,
    pub keyframes: Vec<MapKeyframe>,
    /// track id -> (segment, position).
    pub points: HashMap<u64, (u32, Vector3<f64>)>,
}

/// A query frame's features (undistorted pixels and their descriptors, same order).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct QueryFeatures {
    pub pixels: Vec<Point2<f64>>,
    pub descriptors: Vec<Descriptor>,
}

/// Settings; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelocalizerOptions {
    /// Keyframes tried per query, best bag-of-words score first (default 5: neighbouring
    /// keyframes of a video look alike, so the right place is almost always among the top
    /// few; each costs one matching pass and one RANSAC).
    pub candidates: usize,
    /// Largest Hamming distance of an accepted match (default 64 of 256 bits: ORB-SLAM's
    /// strict threshold is 50, its loose one 100).
    pub max_hamming: u32,
    /// Lowe's ratio test: best distance below this fraction of the second best (default
    /// 0.8, Lowe 2004).
    pub ratio: f32,
    /// PnP from scratch (defaults: 15 inliers making 25 % of the matches within 4 px: the
    /// matches come from appearance alone, so more outliers than along tracks).
    pub pnp: PnpOptions,
    /// Largest angle between the found camera's optical axis and that of the candidate
    /// keyframe it was matched to, degrees (default 60: a frame that looks like a keyframe
    /// views the same surfaces from a similar direction; a pose that does not is a wrong
    /// match that RANSAC happened to support).
    pub max_view_angle_deg: f64,
}

impl Default for RelocalizerOptions {
    fn default() -> Self {
        Self {
            candidates: 5,
            max_hamming: 64,
            ratio: 0.8,
            pnp: PnpOptions {
                min_inliers: 15,
                min_inlier_ratio: 0.25,
                ransac_threshold_px: 4.0,
                ransac_iterations: 300,
            },
            max_view_angle_deg: 60.0,
        }
    }
}

/// Why a frame was not relocalized.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RelocalizationError {
    /// The query has no described features (a dark or textureless frame).
    #[error("the frame has no described features")]
    NoFeatures,
    /// No keyframe shares a visual word with the frame.
    #[error("no keyframe shares a visual word with the frame")]
    NoCandidates,
    /// Candidates were found, but none gave a supported, consistent pose.
    #[error("{tried} candidate keyframes, best pose had {best_inliers} inliers")]
    NoPose { tried: usize, best_inliers: usize },
}

/// A relocalized frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Relocalization {
    /// world_from_camera in the segment's frame.
    pub pose: StampedPose,
    pub segment: u32,
    /// The candidate keyframe whose matches gave the pose.
    pub keyframe_id: u64,
    /// Inlier correspondences of the final refinement.
    pub inliers: usize,
}

/// A map ready for queries: the map, its vocabulary and the keyframes' inverted index.
pub struct Relocalizer {
    vocabulary: Vocabulary,
    map: RelocalizationMap,
    database: KeyframeDatabase,
    index: HashMap<u64, usize>,
}

impl Relocalizer {
    /// Indexes every keyframe of `map` with `vocabulary`.
    pub fn new(vocabulary: Vocabulary, map: RelocalizationMap) -> Self {
        let _span =
            tracing::info_span!("index_keyframes", keyframes = map.keyframes.len()).entered();
        let mut database = KeyframeDatabase::new();
        let mut index = HashMap::new();
        for (i, k) in map.keyframes.iter().enumerate() {
            let descriptors: Vec<Descriptor> = k.features.iter().map(|f| f.descriptor).collect();
            database.add(k.keyframe_id, &vocabulary.bag_of_words(&descriptors));
            index.insert(k.keyframe_id, i);
        }
        Self {
            vocabulary,
            map,
            database,
            index,
        }
    }

    /// The map queried.
    pub fn map(&self) -> &RelocalizationMap {
        &self.map
    }

    /// `(map point, query pixel, query feature index)` for the query features matched to a
    /// keyframe's features (nearest neighbour under `max_hamming` passing the ratio test,
    /// each keyframe feature used once).
    fn match_keyframe(
        &self,
        query: &QueryFeatures,
        keyframe: &MapKeyframe,
        options: &RelocalizerOptions,
    ) -> Vec<(Vector3<f64>, Point2<f64>, usize)> {
        let mut taken: HashMap<usize, (u32, usize)> = HashMap::new();
        for (qi, qd) in query.descriptors.iter().enumerate() {
            let (mut best, mut second, mut best_j) = (u32::MAX, u32::MAX, 0);
            for (j, f) in keyframe.features.iter().enumerate() {
                let d = hamming(qd, &f.descriptor);
                if d < best {
                    second = best;
                    best = d;
                    best_j = j;
                } else if d < second {
                    second = d;
                }
            }
            if best > options.max_hamming || (best as f32) >= options.ratio * second as f32 {
                continue;
            }
            match taken.get(&best_j) {
                Some((d, _)) if *d <= best => {}
                _ => {
                    taken.insert(best_j, (best, qi));
                }
            }
        }
        taken
            .into_iter()
            .filter_map(|(j, (_, qi))| {
                let f = &keyframe.features[j];
                let (segment, x) = self.map.points.get(&f.track_id)?;
                (*segment == keyframe.segment).then_some((*x, query.pixels[qi], qi))
            })
            .collect()
    }

    /// Relocalizes one frame.
    pub fn relocalize(
        &self,
        query: &QueryFeatures,
        options: &RelocalizerOptions,
    ) -> Result<Relocalization, RelocalizationError> {
        if query.descriptors.is_empty() {
            return Err(RelocalizationError::NoFeatures);
        }
        let bow = self.vocabulary.bag_of_words(&query.descriptors);
        let candidates = self.database.query(&bow, options.candidates);
        if candidates.is_empty() {
            return Err(RelocalizationError::NoCandidates);
        }
        let camera = &self.map.camera;
        let mut best: Option<(usize, &MapKeyframe, StampedPose)> = None;
        let mut best_inliers = 0;
        let mut matched = Vec::new();
        for c in &candidates {
            let Some(keyframe) = self
                .index
                .get(&c.keyframe_id)
                .map(|&i| &self.map.keyframes[i])
            else {
                continue;
            };
            let matches = self.match_keyframe(query, keyframe, options);
            let correspondences: Vec<_> = matches.iter().map(|(x, p, _)| (*x, *p)).collect();
            if let Ok(solution) = solve_pnp(camera, &correspondences, None, &options.pnp) {
                let axis = |p: &StampedPose| p.rotation * Vector3::z();
                let angle = axis(&solution.pose)
                    .angle(&axis(&keyframe.pose))
                    .to_degrees();
                best_inliers = best_inliers.max(solution.inliers.len());
                if angle <= options.max_view_angle_deg
                    && best
                        .as_ref()
                        .is_none_or(|(n, _, _)| solution.inliers.len() > *n)
                {
                    best = Some((solution.inliers.len(), keyframe, solution.pose));
                }
            }
            matched.push((keyframe, matches));
        }
        let Some((ransac_inliers, keyframe, pose)) = best else {
            return Err(RelocalizationError::NoPose {
                tried: candidates.len(),
                best_inliers,
            });
        };
        // Pose-only refinement on the matches of every candidate of the same segment that
        // agree with the pose (one match per query feature).
        let mut seen = std::collections::HashSet::new();
        let pooled: Vec<(Vector3<f64>, Point2<f64>)> = matched
            .iter()
            .filter(|(k, _)| k.segment == keyframe.segment)
            .flat_map(|(_, m)| m.iter())
            .filter(|(_, _, qi)| seen.insert(*qi))
            .map(|(x, p, _)| (*x, *p))
            .collect();
        let refine = PnpOptions {
            min_inlier_ratio: 0.0,
            ransac_iterations: 50,
            ..options.pnp
        };
        let (pose, inliers) = match solve_pnp(camera, &pooled, Some(&pose), &refine) {
            Ok(s) if s.inliers.len() >= options.pnp.min_inliers => (s.pose, s.inliers.len()),
            _ => (pose, ransac_inliers),
        };
        Ok(Relocalization {
            pose,
            segment: keyframe.segment,
            keyframe_id: keyframe.keyframe_id,
            inliers,
        })
    }
}
