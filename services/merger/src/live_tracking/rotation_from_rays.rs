//! A turn in place seen in the tracks' rays: the rotation between two frames that sent the
//! rays of their shared tracks onto each other.

use egoslam_geometry::{rotation_aligning, BearingPair};
use nalgebra::{UnitQuaternion, Vector3};
use rustc_hash::FxHashMap;

/// The rotation `R` (camera now -> camera before) that best takes the rays of now onto the
/// rays of before for the tracks both have, and how many agree within `threshold_rad`:
/// RANSAC over pairs of tracks (two rays fix a rotation), then Kabsch on those that agree
/// with the best pair, twice. A group of tracks moving together (a near surface, a
/// moving object) would pull a least-squares fit over all of them off every track.
/// `None` with fewer than 3 shared tracks.
pub(super) fn rotation_between(
    before: &FxHashMap<u64, Vector3<f64>>,
    now: &FxHashMap<u64, Vector3<f64>>,
    threshold_rad: f64,
) -> Option<(UnitQuaternion<f64>, usize)> {
    /// Pairs drawn: with half the tracks agreeing, 64 draws all miss a good pair with
    /// probability 0.75^64 < 1e-7.
    const DRAWS: usize = 64;
    // `(now, before)`: the pairs `rotation_aligning` turns the first onto the second of.
    let mut pairs: Vec<(u64, BearingPair)> = now
        .iter()
        .filter_map(|(t, r)| before.get(t).map(|b| (*t, (*r, *b))))
        .collect();
    if pairs.len() < 3 {
        return None;
    }
    // Track order, so that the draws (and the result) do not depend on the hash order.
    pairs.sort_by_key(|(t, _)| *t);
    let fit = |used: &[BearingPair]| UnitQuaternion::from_rotation_matrix(&rotation_aligning(used));
    let min_cos = threshold_rad.cos();
    let agreeing = |rotation: &UnitQuaternion<f64>| -> Vec<BearingPair> {
        pairs
            .iter()
            .filter(|(_, (r, b))| b.dot(&(rotation * r)) >= min_cos)
            .map(|(_, pair)| *pair)
            .collect()
    };
    let mut state = pairs.len() as u64 ^ 0x9e37_79b9_7f4a_7c15;
    let mut draw = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 33) as usize % pairs.len()
    };
    let mut best: Option<(UnitQuaternion<f64>, usize)> = None;
    for _ in 0..DRAWS {
        let (i, j) = (draw(), draw());
        if i == j {
            continue;
        }
        let rotation = fit(&[pairs[i].1, pairs[j].1]);
        let support = agreeing(&rotation).len();
        if best.is_none_or(|(_, n)| support > n) {
            best = Some((rotation, support));
        }
    }
    let (mut rotation, _) = best?;
    for _ in 0..2 {
        let used = agreeing(&rotation);
        if used.len() < 3 {
            return None;
        }
        rotation = fit(&used);
    }
    Some((rotation, agreeing(&rotation).len()))
}
