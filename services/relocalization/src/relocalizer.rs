//! Relocalization of a frame in a map without any tracking prior (paper, section 5
//! "Relocalization"): bag-of-words candidates from the vocabulary tree, descriptor matches
//! to the candidates' map points, PnP in RANSAC, outliers rejected with the candidates'
//! known poses, then a pose-only refinement on the matches found by projecting the points
//! of the candidates and their neighbours, trusted only where it stayed near its start.
//! A frame no group places this way gets a second chance: placement by rotation, then
//! weak appearance poses that the matching by projection must confirm
//! (`relocalizer/confirmation.rs`).

use crate::absolute_pose::{solve_pnp, PnpError, PnpOptions};
use crate::descriptors::{hamming, hamming_all, pack, Descriptor};
use crate::keyframe_database::KeyframeDatabase;
use crate::patch_alignment::AlignmentOptions;
pub use crate::relocalization_map::{MapFeature, MapKeyframe, QueryFeatures, RelocalizationMap};
use crate::rolling_shutter_pose::{refine_rolling_shutter_pose, RollingShutterPoseOptions};
use crate::vocabulary::{BowVector, Vocabulary};
use egoslam_geometry::StampedPose;
use nalgebra::{Point2, Vector3};
use std::collections::{BTreeMap, HashMap};

/// Settings; defaults commented with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelocalizerOptions {
    /// Keyframes tried per query, best bag-of-words score first (default 5: neighbouring
    /// keyframes of a video look alike, so the right place is almost always among the top
    /// few). Their points are matched together, one RANSAC per map segment.
    pub candidates: usize,
    /// Largest Hamming distance of an accepted match (default 64 of 256 bits: ORB-SLAM's
    /// strict threshold is 50, its loose one 100).
    pub max_hamming: u32,
    /// Lowe's ratio test: best distance below this fraction of the second best (default
    /// 0.8, Lowe 2004).
    pub ratio: f32,
    /// PnP from scratch (defaults: 15 inliers making 15 % of the matches within 4 px, 1000
    /// RANSAC draws: the matches come from appearance alone, so far more outliers than along
    /// tracks; 1000 AP3P draws find an all-inlier sample at 20 % inliers with p > 0.8 and
    /// cost ~5 ms).
    pub pnp: PnpOptions,
    /// Keyframes on each side of a candidate whose points join the matching by projection
    /// (default 2: a candidate's neighbours see the same place, and together they hold more
    /// of its points than the candidate alone, whose tracks are only those alive at that
    /// frame; in the appearance matching they doubled the cost for no gain).
    pub neighbours: usize,
    /// Descriptors of one point compared per query (default 3: from the best-ranked
    /// keyframes seeing it; measured on TUM fr1_rpy, 1 loses 5 % of the relocalized frames
    /// and all of them (~10 per point) doubles the query time for 1 % more).
    pub descriptors_per_point: usize,
    /// Matching by projection after the first pose: search radius, pixels (default 8: the
    /// first pose is within a few pixels when right) and largest Hamming distance (default
    /// 80: the position already constrains the match, so a looser bound than `max_hamming`).
    pub projection_radius_px: f64,
    pub max_projection_hamming: u32,
    /// Inlier threshold of the final refinement, pixels (default 3).
    pub refine_threshold_px: f64,
    /// How far the refinement by projection may move the pose it started from: largest
    /// turn, degrees (default 2), and largest shift as a fraction of its inliers' median
    /// depth (default 0.04). Beyond, the refined pose is not used: a right start is
    /// already near (tentative hypotheses on the TUM clip and the rendered egomotion
    /// profile moved at most 0.97 deg and 0.026), while on that profile a wrong
    /// tentative one moved 3.3 deg and 0.064, and two strict ones were taken 57 and 176
    /// deg away (the second with its points behind the camera), 2.2 and 4.1 m off the
    /// ground truth.
    pub max_refinement_turn_deg: f64,
    pub max_refinement_shift_of_depth: f64,
    /// Largest angle between the found camera's optical axis and that of the candidate
    /// keyframe viewing most like it, degrees (default 60: a frame that looks like a keyframe
    /// views the same surfaces from a similar direction; a pose that does not is a wrong
    /// match that RANSAC happened to support).
    pub max_view_angle_deg: f64,
    /// Patch alignment of the inliers ([`Relocalizer::refine_by_patches`]).
    pub alignment: AlignmentOptions,
    /// Inlier threshold of the pose solved on aligned positions, pixels (default 1.5: they
    /// agree with the map as its own observations do, 0.3-0.8 px RMS).
    pub aligned_threshold_px: f64,
    /// Inliers aligned at most, evenly spaced through them (default 150: on the Aria replay
    /// 1.13 cm median against 1.11 cm aligning every inlier, at 2.4 ms per query against
    /// 9 ms on the 1000-keyframe bench).
    pub max_aligned: usize,
    /// Where a candidate keyframe turned in place and has no points
    /// ([`crate::rotation_relocalization`]): largest angle between a query bearing turned by
    /// the rotation and its keyframe bearing, in pixels at the focal length (default 2: a
    /// pure rotation explains a match to the tracker's precision, parallax of a few
    /// centimetres at 2 m does not), and the least share of the matches it must explain
    /// (default 0.5).
    pub rotation_threshold_px: f64,
    pub rotation_min_inlier_ratio: f64,
    /// Whether a frame no candidate's points can place may be placed by rotation at a
    /// keyframe that turned in place (default true). Its position is then the keyframe's,
    /// which says nothing about where the frame is beyond that: uses that need a position
    /// from the points (segment linking, scale) turn it off.
    pub place_by_rotation: bool,
    /// The query frames' rolling-shutter readout, seconds (default 0: a global shutter).
    /// A query frame has no tracks for the frontend's correction; with a readout its pose
    /// is refined together with the camera's turn during the readout
    /// ([`crate::rolling_shutter_pose`]), and the points are searched for and aligned
    /// where the turning camera sees them (`relocalizer/turn.rs`).
    pub rolling_shutter_s: f64,
    /// Settings of that refinement.
    pub rolling_shutter: RollingShutterPoseOptions,
    /// A second chance for a frame no candidate group placed ([`TentativePoseOptions`]);
    /// `None` turns it off.
    pub tentative: Option<TentativePoseOptions>,
}

impl Default for RelocalizerOptions {
    fn default() -> Self {
        Self {
            candidates: 5,
            max_hamming: 64,
            ratio: 0.8,
            pnp: PnpOptions {
                min_inliers: 15,
                min_inlier_ratio: 0.15,
                ransac_threshold_px: 4.0,
                ransac_iterations: 1000,
            },
            neighbours: 2,
            descriptors_per_point: 3,
            projection_radius_px: 8.0,
            max_projection_hamming: 80,
            refine_threshold_px: 3.0,
            max_refinement_turn_deg: 2.0,
            max_refinement_shift_of_depth: 0.04,
            max_view_angle_deg: 60.0,
            alignment: AlignmentOptions::default(),
            aligned_threshold_px: 1.5,
            max_aligned: 150,
            rotation_threshold_px: 2.0,
            rotation_min_inlier_ratio: 0.5,
            place_by_rotation: true,
            rolling_shutter_s: 0.0,
            rolling_shutter: RollingShutterPoseOptions::default(),
            tentative: Some(TentativePoseOptions::default()),
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
    /// Inlier matches of the final refinement: `(map track, query feature index)`.
    pub inliers: Vec<(u64, usize)>,
    /// The camera's angular velocity during the rolling-shutter readout (camera frame,
    /// rad/s; `pose` is the middle row's): zero with a global shutter or when the readout's
    /// refinement did not hold.
    pub angular_velocity: Vector3<f64>,
}

/// A map ready for queries: the map, its vocabulary and the keyframes' inverted index.
pub struct Relocalizer {
    vocabulary: Vocabulary,
    map: RelocalizationMap,
    database: KeyframeDatabase,
    index: HashMap<u64, usize>,
    /// track id -> (keyframe index, index in its patches, the track's pixel there): where
    /// each point's patch was cut, found once here rather than per query.
    patch_index: HashMap<u64, (usize, usize, Point2<f64>)>,
    /// Per keyframe, per feature: where its track's point is in `point_positions`, or
    /// `NO_POINT`. The matching loops visit ~30,000 features per query; a hash lookup of
    /// each in `map.points` was a third of the projection search.
    feature_points: Vec<Vec<u32>>,
    point_positions: Vec<Vector3<f64>>,
}

/// A feature whose track has no map point.
const NO_POINT: u32 = u32::MAX;

impl Relocalizer {
    /// Indexes every keyframe of `map` with `vocabulary`.
    pub fn new(vocabulary: Vocabulary, map: RelocalizationMap) -> Self {
        let mut database = KeyframeDatabase::new();
        for k in &map.keyframes {
            let descriptors: Vec<Descriptor> = k.features.iter().map(|f| f.descriptor).collect();
            database.add(k.keyframe_id, &vocabulary.bag_of_words(&descriptors));
        }
        Self::with_database(vocabulary, map, database)
    }

    /// [`Self::new`] with the keyframes' bags of words already indexed in `database` (made
    /// with `vocabulary`): every keyframe of `map` and no other, else a query finds a
    /// keyframe the map does not hold (skipped) or misses one it does.
    pub fn with_database(
        vocabulary: Vocabulary,
        map: RelocalizationMap,
        database: KeyframeDatabase,
    ) -> Self {
        let _span =
            tracing::info_span!("index_keyframes", keyframes = map.keyframes.len()).entered();
        let mut index = HashMap::new();
        let mut patch_index = HashMap::new();
        let (mut dense, mut point_positions) = (HashMap::new(), Vec::new());
        let feature_points = map
            .keyframes
            .iter()
            .map(|k| {
                k.features
                    .iter()
                    .map(|f| match map.points.get(&f.track_id) {
                        Some((_, x)) => *dense.entry(f.track_id).or_insert_with(|| {
                            point_positions.push(*x);
                            (point_positions.len() - 1) as u32
                        }),
                        None => NO_POINT,
                    })
                    .collect()
            })
            .collect();
        for (i, k) in map.keyframes.iter().enumerate() {
            index.insert(k.keyframe_id, i);
            if !k.patches.is_empty() {
                let pixels: HashMap<u64, Point2<f64>> = k
                    .features
                    .iter()
                    .map(|f| (f.track_id, f.pixel.cast::<f64>()))
                    .collect();
                for (j, (track, _)) in k.patches.iter().enumerate() {
                    if let Some(&pixel) = pixels.get(track) {
                        patch_index.entry(*track).or_insert((i, j, pixel));
                    }
                }
            }
        }
        Self {
            vocabulary,
            map,
            database,
            index,
            patch_index,
            feature_points,
            point_positions,
        }
    }

    /// The map queried.
    pub fn map(&self) -> &RelocalizationMap {
        &self.map
    }

    /// The keyframes whose points are matched by projection for a group of candidates: the
    /// candidates (best first), then their `neighbours` on each side in keyframe order,
    /// within the segment.
    fn local_keyframes(&self, group: &[usize], neighbours: usize) -> Vec<usize> {
        let mut out: Vec<usize> = group.to_vec();
        for &i in group {
            let segment = self.map.keyframes[i].segment;
            let lo = i.saturating_sub(neighbours);
            let hi = (i + neighbours).min(self.map.keyframes.len() - 1);
            for j in lo..=hi {
                if self.map.keyframes[j].segment == segment && !out.contains(&j) {
                    out.push(j);
                }
            }
        }
        out
    }

    /// Query features matched to the map points seen by `keyframes`: nearest neighbour
    /// under `max_hamming` passing Lowe's ratio test, each point used once.
    /// Returns `(track, query feature)` pairs.
    fn match_appearance(
        &self,
        query: &QueryFeatures,
        keyframes: &[usize],
        options: &RelocalizerOptions,
    ) -> Vec<(u64, usize)> {
        // One descriptor per point, from the first keyframe listing it (candidates come
        // first, best first): a track lives over many keyframes, so this cuts the
        // comparisons several-fold at no loss, the descriptors of one track being alike.
        let mut seen: HashMap<u64, usize> = HashMap::new();
        let (mut tracks, mut packed) = (Vec::new(), Vec::new());
        for (f, &point) in keyframes.iter().flat_map(|&k| {
            self.map.keyframes[k]
                .features
                .iter()
                .zip(&self.feature_points[k])
        }) {
            if point == NO_POINT {
                continue;
            }
            let n = seen.entry(f.track_id).or_default();
            *n += 1;
            if *n <= options.descriptors_per_point {
                tracks.push(f.track_id);
                packed.push(pack(&f.descriptor));
            }
        }
        // Ordered maps for the results: the order of the correspondences handed to RANSAC
        // decides its samples, and a HashMap's differs from process to process (the same
        // input gave a different map every run).
        let mut by_track: BTreeMap<u64, (u32, usize)> = BTreeMap::new();
        let mut distances = Vec::with_capacity(packed.len());
        for (qi, qd) in query.descriptors.iter().enumerate() {
            hamming_all(&pack(qd), &packed, &mut distances);
            let (mut best, mut second, mut best_track) = (u32::MAX, u32::MAX, u64::MAX);
            for (&d, &track) in distances.iter().zip(&tracks) {
                if track == best_track {
                    best = best.min(d);
                } else if d < best {
                    second = best;
                    best = d;
                    best_track = track;
                } else if d < second {
                    second = d;
                }
            }
            if best > options.max_hamming || (best as f32) >= options.ratio * second as f32 {
                continue;
            }
            match by_track.get(&best_track) {
                Some((d, _)) if *d <= best => {}
                _ => {
                    by_track.insert(best_track, (best, qi));
                }
            }
        }
        by_track.into_iter().map(|(t, (_, qi))| (t, qi)).collect()
    }

    /// Matches by projection (as ORB-SLAM's search by projection): every map point seen by
    /// `keyframes` is projected with `pose`, and the closest descriptor among the query
    /// features within `options.projection_radius_px` is taken.
    fn match_projection(
        &self,
        query: &QueryFeatures,
        keyframes: &[usize],
        pose: &StampedPose,
        options: &RelocalizerOptions,
    ) -> Vec<(u64, usize)> {
        let r_cw = pose.rotation.inverse();
        let camera = &self.map.camera;
        self.match_projected(
            query,
            keyframes,
            |x| camera.project_undistorted(&(r_cw * (x - pose.position))),
            options,
        )
    }

    /// [`Self::match_projection`] with the points placed in the query by `project` (an
    /// undistorted pixel).
    fn match_projected(
        &self,
        query: &QueryFeatures,
        keyframes: &[usize],
        project: impl Fn(&Vector3<f64>) -> Option<Point2<f64>>,
        options: &RelocalizerOptions,
    ) -> Vec<(u64, usize)> {
        // A dense grid of the query's features over their bounding box: looked up 9 times
        // per projected point, so a hash map here cost more than the distances. Cells of
        // 16 px (at least the search radius, so the 3x3 block around a projection holds
        // every feature in reach), coarser only if the features spread over more than
        // 4096 px, so that the grid stays under 256 x 256 cells whatever the input.
        let valid = |p: &Point2<f64>| p.x.is_finite() && p.y.is_finite();
        let (mut lo, mut hi) = (
            Point2::new(f64::MAX, f64::MAX),
            Point2::new(f64::MIN, f64::MIN),
        );
        for p in query.pixels.iter().filter(|p| valid(p)) {
            (lo.x, lo.y, hi.x, hi.y) = (lo.x.min(p.x), lo.y.min(p.y), hi.x.max(p.x), hi.y.max(p.y));
        }
        if lo.x > hi.x {
            return Vec::new();
        }
        let size = 16f64
            .max(options.projection_radius_px)
            .max((hi.x - lo.x).max(hi.y - lo.y) / 254.0);
        // Cells on multiples of their size, as the hash grid's were: the features are then
        // visited in the same order, and ties in distance go the same way.
        let lo = Point2::new((lo.x / size).floor() * size, (lo.y / size).floor() * size);
        let cell_of = |p: &Point2<f64>| {
            (
                ((p.x - lo.x) / size).floor() as i64,
                ((p.y - lo.y) / size).floor() as i64,
            )
        };
        let (cols, rows) = (cell_of(&hi).0 + 1, cell_of(&hi).1 + 1);
        let mut grid: Vec<Vec<usize>> = vec![Vec::new(); (cols * rows) as usize];
        for (i, p) in query.pixels.iter().enumerate().filter(|(_, p)| valid(p)) {
            let (x, y) = cell_of(p);
            grid[(y * cols + x) as usize].push(i);
        }
        let cell = |x: i64, y: i64| -> &[usize] {
            if x < 0 || y < 0 || x >= cols || y >= rows {
                return &[];
            }
            &grid[(y * cols + x) as usize]
        };
        let radius = options.projection_radius_px;
        let mut best_of_query: BTreeMap<usize, (u32, u64)> = BTreeMap::new();
        for &k in keyframes {
            for (f, &point) in self.map.keyframes[k]
                .features
                .iter()
                .zip(&self.feature_points[k])
            {
                let Some(x) = self.point_positions.get(point as usize) else {
                    continue;
                };
                let Some(px) = project(x) else {
                    continue;
                };
                let (cx, cy) = cell_of(&px);
                let mut best = (u32::MAX, usize::MAX);
                for gx in cx - 1..=cx + 1 {
                    for gy in cy - 1..=cy + 1 {
                        for &qi in cell(gx, gy) {
                            if (query.pixels[qi] - px).norm() > radius {
                                continue;
                            }
                            let d = hamming(&query.descriptors[qi], &f.descriptor);
                            if d < best.0 {
                                best = (d, qi);
                            }
                        }
                    }
                }
                if best.0 <= options.max_projection_hamming {
                    let slot = best_of_query
                        .entry(best.1)
                        .or_insert((u32::MAX, f.track_id));
                    if best.0 < slot.0 {
                        *slot = (best.0, f.track_id);
                    }
                }
            }
        }
        best_of_query
            .into_iter()
            .map(|(qi, (_, track))| (track, qi))
            .collect()
    }

    /// `(point, query pixel)` of `(track, query feature)` matches.
    fn correspondences(
        &self,
        query: &QueryFeatures,
        matches: &[(u64, usize)],
    ) -> Vec<(Vector3<f64>, Point2<f64>)> {
        matches
            .iter()
            .filter_map(|(t, qi)| Some((self.map.points.get(t)?.1, query.pixels[*qi])))
            .collect()
    }

    /// `pose` refined on its inlier `pairs` with the camera's turn during a rolling-shutter
    /// readout (`RelocalizerOptions::rolling_shutter_s`), and that turn's angular velocity;
    /// `pose` itself and no turn with a global shutter or when the refinement does not hold.
    fn unrolled(
        &self,
        pose: StampedPose,
        pairs: impl Iterator<Item = (Vector3<f64>, Point2<f64>)>,
        options: &RelocalizerOptions,
    ) -> (StampedPose, Vector3<f64>) {
        if options.rolling_shutter_s <= 0.0 {
            return (pose, Vector3::zeros());
        }
        let pairs: Vec<_> = pairs.collect();
        refine_rolling_shutter_pose(
            &self.map.camera,
            &pairs,
            &pose,
            options.rolling_shutter_s,
            &options.rolling_shutter,
        )
        .map_or((pose, Vector3::zeros()), |r| (r.pose, r.angular_velocity))
    }

    /// Relocalizes one frame.
    pub fn relocalize(
        &self,
        query: &QueryFeatures,
        options: &RelocalizerOptions,
    ) -> Result<Relocalization, RelocalizationError> {
        let bow = self.vocabulary.bag_of_words(&query.descriptors);
        self.relocalize_bag(query, &bow, options)
    }

    /// [`Self::relocalize`] of a query whose bag of words (`bow`, of its descriptors with
    /// this relocalizer's vocabulary) is known already.
    pub fn relocalize_bag(
        &self,
        query: &QueryFeatures,
        bow: &BowVector,
        options: &RelocalizerOptions,
    ) -> Result<Relocalization, RelocalizationError> {
        if query.descriptors.is_empty() {
            return Err(RelocalizationError::NoFeatures);
        }
        let candidates = self.database.query(bow, options.candidates);
        if candidates.is_empty() {
            return Err(RelocalizationError::NoCandidates);
        }
        // Candidates grouped by segment, best group first: poses of different segments are
        // in different frames and cannot be pooled.
        let mut groups: Vec<(u32, Vec<usize>)> = Vec::new();
        for c in &candidates {
            let Some(&i) = self.index.get(&c.keyframe_id) else {
                continue;
            };
            let segment = self.map.keyframes[i].segment;
            match groups.iter_mut().find(|(s, _)| *s == segment) {
                Some((_, g)) => g.push(i),
                None => groups.push((segment, vec![i])),
            }
        }
        let camera = &self.map.camera;
        // The appearance PnP accepts down to the tentative minimum; what falls short of
        // the strict one waits in `tentative` until everything else has failed.
        let strict = options.pnp;
        let appearance = PnpOptions {
            min_inliers: options.tentative.map_or(strict.min_inliers, |t| {
                t.min_inliers.min(strict.min_inliers)
            }),
            ..strict
        };
        let mut best_inliers = 0;
        let mut tentative = Vec::new();
        for (segment, group) in &groups {
            // Both matchers return only tracks with a map point (`feature_points`), so the
            // correspondences line up with the matches index for index.
            let matches = self.match_appearance(query, group, options);
            let correspondences = self.correspondences(query, &matches);
            let solved = solve_pnp(camera, &correspondences, None, &appearance);
            tracing::debug!(
                segment,
                matches = correspondences.len(),
                result = ?solved.as_ref().map(|s| s.inliers.len()),
                "candidate group"
            );
            let solution = match solved {
                Ok(solution) => solution,
                Err(PnpError::TooFewInliers { inliers, .. }) => {
                    // Reported in `NoPose`: "0 inliers" had hidden a pose short of the
                    // minimum (the TUM clip's frames 43-50: 4-12 of 28-58).
                    best_inliers = best_inliers.max(inliers);
                    continue;
                }
                Err(_) => continue,
            };
            best_inliers = best_inliers.max(solution.inliers.len());
            let hypothesis = Hypothesis {
                segment: *segment,
                group,
                matches,
                correspondences,
                solution,
            };
            let needed = strict.inliers_needed(hypothesis.correspondences.len());
            if hypothesis.solution.inliers.len() < needed {
                tentative.push(hypothesis);
                continue;
            }
            if let Some(found) = self.place(query, &hypothesis, None, options) {
                return Ok(self.rotation_if_better(query, &candidates, found, options));
            }
        }
        if let Some(found) = self.second_chance(query, &candidates, options, tentative) {
            return Ok(found);
        }
        Err(RelocalizationError::NoPose {
            tried: candidates.len(),
            best_inliers,
        })
    }
}

mod patches;
mod turn;

mod confirmation;
use confirmation::Hypothesis;
pub use confirmation::TentativePoseOptions;
