//! Loops closed while a background refinement runs. The refinement works on a copy of the
//! map taken when it started; a loop closed meanwhile moves keyframes and points of that
//! copy. Folding the result as it is would put them back where the chain had them, so loops
//! could not be closed at all while a refinement runs (on a corridor walked back and
//! forth, one loop per 30 windows: the length of a 1,500-keyframe job). Instead, each
//! loop's moves are recorded as similarities of the map and replayed onto the refined
//! result at the fold: a keyframe or point the loop moved by `C` takes `C` of its refined
//! value, and what the refinement carries rigidly (keyframes and points it did not know)
//! is carried in the corrected frame (`C T C^-1`), as if the loop had been closed after
//! the refinement.

use egoslam_geometry::Similarity;
use std::collections::BTreeMap;

/// The corrections made since a refinement started, per keyframe and per point.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LoopCorrections {
    keyframes: BTreeMap<u64, Similarity>,
    points: BTreeMap<u64, Similarity>,
}

/// How one keyframe or point of a closed loop moved, as a similarity of the map.
pub type Moves = BTreeMap<u64, Similarity>;

impl LoopCorrections {
    pub fn is_empty(&self) -> bool {
        self.keyframes.is_empty()
    }

    /// The correction keyframe `id` has taken: its own, or, for a keyframe after the newest
    /// one a loop moved, that one's (it was chained onto the corrected map); the identity
    /// before.
    pub fn of_keyframe(&self, id: u64) -> Similarity {
        if let Some(c) = self.keyframes.get(&id) {
            return *c;
        }
        match self.keyframes.last_key_value() {
            Some((newest, c)) if id > *newest => *c,
            _ => Similarity::identity(),
        }
    }

    /// The correction a point the refinement knew has taken (the identity when no loop
    /// moved it).
    pub fn of_known_point(&self, track: u64) -> Similarity {
        self.points
            .get(&track)
            .copied()
            .unwrap_or_else(Similarity::identity)
    }

    /// The correction of the map's newest part, which points made since it was corrected
    /// were triangulated in.
    pub fn newest(&self) -> Similarity {
        self.keyframes
            .last_key_value()
            .map_or_else(Similarity::identity, |(_, c)| *c)
    }

    /// Records a loop's moves on top of those recorded before. `point_owners`: the keyframe
    /// whose move each point followed; a point first moved now whose earlier correction is
    /// unknown takes that keyframe's earlier one (it was made after the earlier loop).
    pub fn record(&mut self, keyframe_moves: &Moves, point_owners: &BTreeMap<u64, u64>) {
        let earlier: BTreeMap<u64, Similarity> = keyframe_moves
            .keys()
            .map(|id| (*id, self.of_keyframe(*id)))
            .collect();
        for (track, owner) in point_owners {
            let Some(m) = keyframe_moves.get(owner) else {
                continue;
            };
            let before = self
                .points
                .get(track)
                .copied()
                .or_else(|| earlier.get(owner).copied())
                .unwrap_or_else(Similarity::identity);
            self.points.insert(*track, m.compose(&before));
        }
        for (id, m) in keyframe_moves {
            let before = earlier
                .get(id)
                .copied()
                .unwrap_or_else(Similarity::identity);
            self.keyframes.insert(*id, m.compose(&before));
        }
    }
}

/// `t` seen in the frame `c` corrected into: `c t c^-1`.
pub fn conjugated(t: &Similarity, c: &Similarity) -> Similarity {
    c.compose(t).compose(&c.inverse())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};

    fn shift(x: f64, scale: f64, yaw: f64) -> Similarity {
        Similarity {
            scale,
            rotation: Rotation3::from_euler_angles(0.0, yaw, 0.0),
            translation: Vector3::new(x, 0.0, 0.0),
        }
    }

    fn close(a: &Vector3<f64>, b: &Vector3<f64>) -> bool {
        (a - b).norm() < 1e-12
    }

    #[test]
    fn keyframes_after_the_newest_moved_take_its_correction() {
        let mut c = LoopCorrections::default();
        let moves: Moves = [(10, shift(1.0, 1.0, 0.0)), (12, shift(2.0, 1.1, 0.1))].into();
        c.record(&moves, &BTreeMap::new());
        let x = Vector3::new(0.5, 0.2, 3.0);
        assert!(close(&c.of_keyframe(5).apply(&x), &x), "before the loop");
        assert!(close(&c.of_keyframe(10).apply(&x), &moves[&10].apply(&x)));
        assert!(close(&c.of_keyframe(20).apply(&x), &moves[&12].apply(&x)));
    }

    #[test]
    fn a_second_loop_composes_with_what_the_first_implied() {
        let mut c = LoopCorrections::default();
        let first: Moves = [(10, shift(1.0, 1.0, 0.2))].into();
        c.record(&first, &[(100, 10)].into());
        // Keyframe 30 and point 200 were made after the first loop, on the corrected map.
        let second: Moves = [(30, shift(-0.5, 0.9, -0.1))].into();
        c.record(&second, &[(200, 30), (100, 30)].into());
        let x = Vector3::new(0.5, 0.2, 3.0);
        let expected = second[&30].apply(&first[&10].apply(&x));
        assert!(close(&c.of_keyframe(30).apply(&x), &expected));
        assert!(close(&c.of_known_point(200).apply(&x), &expected));
        assert!(close(&c.of_known_point(100).apply(&x), &expected));
        assert!(close(&c.of_known_point(7).apply(&x), &x), "never moved");
    }

    #[test]
    fn a_carry_conjugated_by_the_correction_commutes_with_it() {
        let t = shift(0.3, 1.02, 0.05);
        let c = shift(-2.0, 0.8, 0.4);
        let x = Vector3::new(1.0, -0.5, 2.0);
        // Refine then correct == correct then carry in the corrected frame.
        let refined_then_corrected = c.apply(&t.apply(&x));
        let corrected_then_carried = conjugated(&t, &c).apply(&c.apply(&x));
        assert!(close(&refined_then_corrected, &corrected_then_carried));
    }
}
