//! Map points seen again by a new keyframe (beyond the paper; ORB-SLAM's search by
//! projection and point fusion, Mur-Artal et al. 2015). The tracker follows a corner only
//! while it stays in view: a head that turns away and back starts new tracks on the same
//! corners, so the map holds the place twice and nothing ties the two sightings together
//! but the chain of windows between them, whose rotation and scale drift. Each new
//! keyframe's described tracks are matched, by projection and descriptor, to the points
//! of older keyframes that viewed the same place from a similar pose; each match is kept
//! as a sighting of the old point in the new keyframe at the new track's pixel
//! (`MapBuilder::seen_again`), which the background refinement (crate::refinement) adds
//! to its observations and so adjusts across the revisit.

use crate::map::MapBuilder;
use crate::segment_linking::KeyframeFeatureSource;
use egoslam_geometry::{PinholeRadtan, StampedPose};
use egoslam_relocalization::absolute_pose::{solve_pnp, PnpOptions};
use egoslam_relocalization::{hamming, MapFeature};
use nalgebra::{Point2, Vector3};
use std::collections::{BTreeMap, HashMap};

/// Settings; defaults with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReassociationOptions {
    /// Older keyframes searched are at least this many keyframes before the new one
    /// (default 20, a window: nearer ones share its live tracks already).
    pub min_keyframe_gap: u64,
    /// ... and at most this many (default 300, the age from which loop closure searches,
    /// `LoopOptions::min_age_keyframes`): a place seen again after longer has drifted by
    /// more than a bundle adjustment from the chained poses can take in; loop closure
    /// corrects it first.
    pub max_keyframe_gap: u64,
    /// A new keyframe is searched only when it sees at least this many points of its own
    /// window (default 50): one that turned in place (a rotation-only window, no points)
    /// has a position only by its neighbours', and its sightings alone would place it.
    pub min_own_points: usize,
    /// Older keyframes searched per new keyframe, nearest in viewing direction first
    /// (default 4).
    pub reference_keyframes: usize,
    /// Largest angle between the two optical axes, degrees (default 30: ORB descriptors
    /// hold over about that change of view).
    pub max_view_angle_deg: f64,
    /// Largest distance between the two centres, as a fraction of the new keyframe's
    /// median point depth (default 0.3).
    pub max_centre_distance_of_depth: f64,
    /// Search radius around an old point's projection, pixels (default 10: the drift
    /// between two sightings a few seconds apart, ~1 deg at 500 px).
    pub radius_px: f64,
    /// Largest Hamming distance of a match (default 50 of 256 bits, ORB-SLAM's strict
    /// threshold) and Lowe's ratio to the second best in the radius (default 0.8).
    pub max_hamming: u32,
    pub ratio: f32,
    /// The matches of one keyframe must agree on one pose (PnP in RANSAC from the
    /// keyframe's): at least this many (default 20) making this share of them (default
    /// 0.3), within this many pixels (default 3). On tum_fr1_rpy (blur, rolling shutter)
    /// 33-65 % of a keyframe's matches agreed at 2 px and 65-91 % at 4 px; the wrong
    /// matches on the rendered walks' repeated textures do not agree: without this test
    /// the rendered corridor and street ended 16x and 31x worse.
    pub min_agreeing: usize,
    pub min_agreeing_share: f64,
    pub agreement_px: f64,
    /// That pose may differ from the keyframe's by this turn, degrees (default 2), and
    /// this shift as a fraction of the keyframe's median point depth (default 0.05): the
    /// drift between two sightings, not another place.
    pub max_drift_deg: f64,
    pub max_drift_of_depth: f64,
}

impl Default for ReassociationOptions {
    fn default() -> Self {
        Self {
            min_keyframe_gap: 20,
            max_keyframe_gap: 300,
            min_own_points: 50,
            reference_keyframes: 4,
            max_view_angle_deg: 30.0,
            max_centre_distance_of_depth: 0.3,
            radius_px: 10.0,
            max_hamming: 50,
            ratio: 0.8,
            min_agreeing: 20,
            min_agreeing_share: 0.3,
            agreement_px: 3.0,
            max_drift_deg: 2.0,
            max_drift_of_depth: 0.05,
        }
    }
}

/// What one pass did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ReassociationReport {
    /// New keyframes searched (posed, described, with points).
    pub keyframes: usize,
    /// Sightings of old points kept.
    pub sightings: usize,
    /// Each sighting's reprojection error with the map as it is, pixels: the
    /// drift between the two sightings.
    pub residuals_px: Vec<f64>,
}

/// The optical axis of a world_from_camera pose.
fn axis(pose: &StampedPose) -> Vector3<f64> {
    pose.rotation * Vector3::z()
}

impl MapBuilder {
    /// Matches the described tracks of `keyframes` (new to the map) to the points of older
    /// keyframes of their segment, and keeps each match as a sighting of the old point
    /// (`MapBuilder::seen_again`).
    pub fn reassociate_points(
        &mut self,
        camera: &PinholeRadtan,
        features: &dyn KeyframeFeatureSource,
        keyframes: &[u64],
        options: &ReassociationOptions,
    ) -> ReassociationReport {
        let mut report = ReassociationReport::default();
        let mut cache: HashMap<u64, Option<Vec<MapFeature>>> = HashMap::new();
        let mut added: Vec<((u64, u64), Point2<f64>)> = Vec::new();
        for &k in keyframes {
            let Some(&(segment, pose)) = self.keyframes.get(&k) else {
                continue;
            };
            if self.turns_in_place(k) {
                continue;
            }
            let Some(depth) = self.observed_depth_of(k, &pose, options.min_own_points) else {
                continue;
            };
            // Before the keyframe's descriptors are read from the features log: most new
            // keyframes of a walk have no older view of their place.
            let references = self.reference_keyframes(k, segment, &pose, depth, options);
            if references.is_empty() {
                continue;
            }
            let Some(new_features) = features.features(k) else {
                continue;
            };
            report.keyframes += 1;
            let grid = FeatureGrid::new(&new_features, options.radius_px);
            let r_cw = pose.rotation.inverse();
            // Per new feature, the old point matched to it with the least distance:
            // (distance, old track).
            let mut best: BTreeMap<usize, (u32, u64)> = BTreeMap::new();
            for j in references {
                let old = cache.entry(j).or_insert_with(|| features.features(j));
                let Some(old) = old.as_ref() else { continue };
                for f in old {
                    let track = f.track_id;
                    let Some((s, x)) = self.points.get(&track) else {
                        continue;
                    };
                    if *s != segment
                        || self.observations.contains_key(&(k, track))
                        || self.seen_again.contains_key(&(k, track))
                    {
                        continue;
                    }
                    let Some(px) = camera.project_undistorted(&(r_cw * (x - pose.position))) else {
                        continue;
                    };
                    let (mut first, mut second, mut at) = (u32::MAX, u32::MAX, usize::MAX);
                    for i in grid.near(&px, options.radius_px) {
                        if new_features[i].track_id == track {
                            continue;
                        }
                        let d = hamming(&f.descriptor, &new_features[i].descriptor);
                        if d < first {
                            (second, first, at) = (first, d, i);
                        } else if d < second {
                            second = d;
                        }
                    }
                    if at == usize::MAX
                        || first > options.max_hamming
                        || first as f32 >= options.ratio * second as f32
                    {
                        continue;
                    }
                    let slot = best.entry(at).or_insert((u32::MAX, track));
                    if first < slot.0 {
                        *slot = (first, track);
                    }
                }
            }
            let mut taken = std::collections::HashSet::new();
            let matches: Vec<(u64, Point2<f64>)> = best
                .into_iter()
                .filter(|(_, (_, track))| taken.insert(*track))
                .map(|(i, (_, track))| (track, new_features[i].pixel.cast::<f64>()))
                .collect();
            for (track, px) in self.agreeing_matches(camera, &pose, depth, &matches, options) {
                if let Some(seen) = self
                    .points
                    .get(&track)
                    .and_then(|(_, x)| camera.project_undistorted(&(r_cw * (x - pose.position))))
                {
                    report.residuals_px.push((seen - px).norm());
                }
                added.push(((k, track), px));
            }
        }
        report.sightings = added.len();
        for (key, px) in added {
            self.seen_again.entry(key).or_insert(px);
        }
        report
    }

    /// The matches (old point, pixel in the new keyframe) that one pose of the keyframe
    /// explains, where that pose is near `pose`: each match passed on its own, but a
    /// repeated texture passes too; the sightings of one place agree on one pose, shifted
    /// from the keyframe's by the drift between them at most.
    fn agreeing_matches(
        &self,
        camera: &PinholeRadtan,
        pose: &StampedPose,
        depth: f64,
        matches: &[(u64, Point2<f64>)],
        options: &ReassociationOptions,
    ) -> Vec<(u64, Point2<f64>)> {
        let pairs: Vec<(Vector3<f64>, Point2<f64>)> = matches
            .iter()
            .filter_map(|(t, px)| Some((self.points.get(t)?.1, *px)))
            .collect();
        if pairs.len() != matches.len() {
            return Vec::new();
        }
        let pnp = PnpOptions {
            min_inliers: options.min_agreeing,
            min_inlier_ratio: options.min_agreeing_share,
            ransac_threshold_px: options.agreement_px,
            ransac_iterations: 100,
        };
        let solved = solve_pnp(camera, &pairs, Some(pose), &pnp);
        let Ok(solution) = solved else {
            return Vec::new();
        };
        let turn = solution.pose.rotation.angle_to(&pose.rotation).to_degrees();
        let shift = (solution.pose.position - pose.position).norm();
        if turn > options.max_drift_deg || shift > options.max_drift_of_depth * depth {
            return Vec::new();
        }
        solution.inliers.iter().map(|&i| matches[i]).collect()
    }

    /// Whether keyframe `id` shares its centre with the keyframe before or after it (a
    /// window without parallax puts all its keyframes at one centre).
    fn turns_in_place(&self, id: u64) -> bool {
        let Some((segment, pose)) = self.keyframes.get(&id) else {
            return false;
        };
        let same =
            |(_, (s, p)): (&u64, &(u32, StampedPose))| s == segment && pose.shares_centre_with(p);
        self.keyframes.range(..id).next_back().is_some_and(same)
            || self.keyframes.range(id + 1..).next().is_some_and(same)
    }

    /// Older keyframes of `segment` that viewed what keyframe `id` views, nearest in
    /// viewing direction first.
    fn reference_keyframes(
        &self,
        id: u64,
        segment: u32,
        pose: &StampedPose,
        depth: f64,
        options: &ReassociationOptions,
    ) -> Vec<u64> {
        let max_angle = options.max_view_angle_deg.to_radians();
        let mut near: Vec<(f64, u64)> = self
            .keyframes
            .range(
                id.saturating_sub(options.max_keyframe_gap)
                    ..id.saturating_sub(options.min_keyframe_gap),
            )
            .filter(|(_, (s, p))| {
                *s == segment
                    && (p.position - pose.position).norm()
                        <= options.max_centre_distance_of_depth * depth
            })
            .filter(|(j, _)| !self.turns_in_place(**j))
            .map(|(j, (_, p))| (axis(p).angle(&axis(pose)), *j))
            .filter(|(angle, _)| *angle <= max_angle)
            .collect();
        near.sort_by(|a, b| a.0.total_cmp(&b.0));
        near.into_iter()
            .take(options.reference_keyframes)
            .map(|(_, j)| j)
            .collect()
    }
}

/// A keyframe's features in square cells of at least the search radius.
struct FeatureGrid {
    cells: HashMap<(i64, i64), Vec<usize>>,
    size: f64,
    pixels: Vec<Point2<f64>>,
}

impl FeatureGrid {
    fn new(features: &[MapFeature], radius: f64) -> Self {
        let size = radius.max(1.0);
        let pixels: Vec<Point2<f64>> = features.iter().map(|f| f.pixel.cast::<f64>()).collect();
        let mut cells: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
        for (i, p) in pixels.iter().enumerate() {
            if p.x.is_finite() && p.y.is_finite() {
                cells
                    .entry(((p.x / size).floor() as i64, (p.y / size).floor() as i64))
                    .or_default()
                    .push(i);
            }
        }
        Self {
            cells,
            size,
            pixels,
        }
    }

    /// Features within `radius` of `p`.
    fn near<'a>(&'a self, p: &'a Point2<f64>, radius: f64) -> impl Iterator<Item = usize> + 'a {
        let (cx, cy) = (
            (p.x / self.size).floor() as i64,
            (p.y / self.size).floor() as i64,
        );
        (cx - 1..=cx + 1)
            .flat_map(move |x| (cy - 1..=cy + 1).map(move |y| (x, y)))
            .filter_map(|c| self.cells.get(&c))
            .flatten()
            .copied()
            .filter(move |&i| (self.pixels[i] - p).norm() <= radius)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::MapParts;
    use egoslam_relocalization::Descriptor;
    use nalgebra::UnitQuaternion;

    fn camera() -> PinholeRadtan {
        PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera")
    }

    fn pose(x: f64, yaw_deg: f64) -> StampedPose {
        StampedPose {
            timestamp: 0.0,
            position: Vector3::new(x, 0.0, 0.0),
            rotation: UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw_deg.to_radians()),
        }
    }

    /// A distinct descriptor per index (bits far apart from every other index's).
    fn descriptor(i: usize) -> Descriptor {
        let mut d = [0u8; 32];
        let mut state = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        for byte in &mut d {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            *byte = state as u8;
        }
        d
    }

    /// The corners: an 8 x 8 grid 3-3.7 m ahead.
    fn corner(i: usize) -> Vector3<f64> {
        let (row, column) = ((i / 8) as f64, (i % 8) as f64);
        Vector3::new(-0.7 + 0.2 * column, -0.5 + 0.14 * row, 3.0 + 0.1 * column)
    }

    /// An old keyframe 0 seeing 64 points 3 m ahead (tracks 1000..), and a new keyframe 100
    /// 5 cm to the side and 5 deg turned, whose own tracks (2000..) are on the same
    /// corners: at the old points' projections, with the old descriptors but
    /// `flipped_bits` bits.
    fn revisit(
        flipped_bits: usize,
    ) -> (MapBuilder, BTreeMap<u64, Vec<MapFeature>>, Vec<Point2<f64>>) {
        let camera = camera();
        let (old, new) = (pose(0.0, 0.0), pose(0.05, 5.0));
        let mut parts = MapParts::default();
        parts.keyframes.insert(0, (0, old));
        parts.keyframes.insert(100, (0, new));
        let mut features = BTreeMap::new();
        let (mut old_features, mut new_features, mut pixels) = (Vec::new(), Vec::new(), Vec::new());
        for i in 0..64 {
            let x = corner(i);
            let track = 1000 + i as u64;
            parts.points.insert(track, (0, x));
            let seen_old = camera
                .project_undistorted(&(old.rotation.inverse() * (x - old.position)))
                .expect("in front");
            parts.observations.insert((0, track), seen_old);
            old_features.push(MapFeature {
                track_id: track,
                descriptor: descriptor(i),
                pixel: seen_old.cast::<f32>(),
            });
            let seen_new = camera
                .project_undistorted(&(new.rotation.inverse() * (x - new.position)))
                .expect("in front");
            let mut d = descriptor(i);
            for b in 0..flipped_bits {
                d[b / 8] ^= 1 << (b % 8);
            }
            new_features.push(MapFeature {
                track_id: 2000 + i as u64,
                descriptor: d,
                pixel: seen_new.cast::<f32>(),
            });
            pixels.push(seen_new);
        }
        // The new keyframe's own points (for its depth): the same corners as new tracks.
        for (i, f) in new_features.iter().enumerate() {
            let x = corner(i);
            parts.points.insert(f.track_id, (0, x));
            parts
                .observations
                .insert((100, f.track_id), f.pixel.cast::<f64>());
        }
        features.insert(0, old_features);
        features.insert(100, new_features);
        (MapBuilder::from_parts(parts), features, pixels)
    }

    #[test]
    fn a_revisited_corner_becomes_an_observation_of_the_old_point() {
        let (mut map, features, pixels) = revisit(10);
        let report = map.reassociate_points(
            &camera(),
            &features,
            &[100],
            &ReassociationOptions::default(),
        );
        assert_eq!(report.keyframes, 1);
        assert_eq!(report.sightings, 64);
        for (i, px) in pixels.iter().enumerate() {
            let seen = map.seen_again.get(&(100, 1000 + i as u64)).expect("linked");
            assert!((seen - px).norm() < 1e-3, "{seen} vs {px}");
            // Kept apart: the window observations decide which points are published.
            assert!(!map.observations.contains_key(&(100, 1000 + i as u64)));
        }
    }

    #[test]
    fn other_corners_and_other_views_are_left_alone() {
        // Descriptors 60 bits apart: another corner, however near its pixel.
        let (mut map, features, _) = revisit(60);
        let options = ReassociationOptions::default();
        let report = map.reassociate_points(&camera(), &features, &[100], &options);
        assert_eq!(report.sightings, 0);
        // The same corners from a view turned 40 deg away are not searched.
        let (mut map, features, _) = revisit(10);
        map.keyframes.insert(100, (0, pose(0.05, 40.0)));
        let report = map.reassociate_points(&camera(), &features, &[100], &options);
        assert_eq!((report.keyframes, report.sightings), (0, 0));
        // Matches no one pose explains (each corner 8.5 px off its projection, one way or
        // the other, as a repeated texture would give) are refused together.
        let (mut map, mut features, _) = revisit(10);
        for (i, f) in features.get_mut(&100).expect("new").iter_mut().enumerate() {
            let offset = if i % 2 == 0 { 6.0 } else { -6.0 };
            f.pixel += nalgebra::Vector2::new(offset, offset);
        }
        let report = map.reassociate_points(&camera(), &features, &[100], &options);
        assert_eq!((report.keyframes, report.sightings), (1, 0));
        // Nor from a keyframe of the same window.
        let near = ReassociationOptions {
            min_keyframe_gap: 101,
            ..options
        };
        let (mut map, features, _) = revisit(10);
        let report = map.reassociate_points(&camera(), &features, &[100], &near);
        assert_eq!(report.sightings, 0);
    }
}
