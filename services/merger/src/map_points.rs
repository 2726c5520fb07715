//! The map's points, recording which ones changed: the merger publishes the points new or
//! moved after each window, and finding them by comparing every point of a map that grows
//! all day would cost more per window the longer it runs. Reads as the `BTreeMap` it
//! wraps; every write goes through a method that records the point (one that can touch
//! them all records "all").

use nalgebra::Vector3;
use std::collections::{BTreeMap, BTreeSet};
use std::ops::Deref;

/// Changes recorded one by one up to this many, or as many as there are points, before
/// the record becomes [`Changed::All`].
const RECORD_BEFORE_ALL: usize = 4096;

/// track id -> (segment, position).
#[derive(Debug, Clone, Default)]
pub struct MapPoints {
    points: BTreeMap<u64, (u32, Vector3<f64>)>,
    changed: Changed,
}

/// The points changed since the last [`MapPoints::take_changed`].
#[derive(Debug, Clone, PartialEq)]
pub enum Changed {
    All,
    Some(BTreeSet<u64>),
}

impl Default for Changed {
    /// A map made from parts (new, or resumed from a checkpoint): every point is new to
    /// whoever follows its changes.
    fn default() -> Self {
        Self::All
    }
}

impl PartialEq for MapPoints {
    /// Equal when they hold the same points (what changed is not content).
    fn eq(&self, other: &Self) -> bool {
        self.points == other.points
    }
}

impl MapPoints {
    pub fn insert(&mut self, track: u64, point: (u32, Vector3<f64>)) {
        self.points.insert(track, point);
        self.record(track);
    }

    pub fn remove(&mut self, track: &u64) -> Option<(u32, Vector3<f64>)> {
        let removed = self.points.remove(track)?;
        self.record(*track);
        Some(removed)
    }

    pub fn get_mut(&mut self, track: &u64) -> Option<&mut (u32, Vector3<f64>)> {
        if self.points.contains_key(track) {
            self.record(*track);
        }
        self.points.get_mut(track)
    }

    /// Every point, to change: all are recorded as changed.
    pub fn iter_mut(&mut self) -> impl Iterator<Item = (&u64, &mut (u32, Vector3<f64>))> {
        self.changed = Changed::All;
        self.points.iter_mut()
    }

    /// The points changed (inserted, moved or removed) since the last call.
    pub fn take_changed(&mut self) -> Changed {
        std::mem::replace(&mut self.changed, Changed::Some(BTreeSet::new()))
    }

    fn record(&mut self, track: u64) {
        if let Changed::Some(changed) = &mut self.changed {
            changed.insert(track);
            // Nobody took them (nothing publishes): "all" says as much in no memory.
            if changed.len() > self.points.len().max(RECORD_BEFORE_ALL) {
                self.changed = Changed::All;
            }
        }
    }
}

impl Deref for MapPoints {
    type Target = BTreeMap<u64, (u32, Vector3<f64>)>;
    fn deref(&self) -> &Self::Target {
        &self.points
    }
}

impl From<BTreeMap<u64, (u32, Vector3<f64>)>> for MapPoints {
    fn from(points: BTreeMap<u64, (u32, Vector3<f64>)>) -> Self {
        Self {
            points,
            changed: Changed::All,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_write_is_recorded_and_an_untaken_record_stays_small() {
        let at = |x: f64| (0, Vector3::new(x, 0.0, 1.0));
        let mut points = MapPoints::from(BTreeMap::from([(1, at(0.0)), (2, at(1.0))]));
        assert_eq!(points.take_changed(), Changed::All, "new to its followers");
        assert_eq!(points.take_changed(), Changed::Some(BTreeSet::new()));
        points.insert(3, at(2.0));
        if let Some((_, x)) = points.get_mut(&1) {
            x.x = 0.5;
        }
        points.remove(&2);
        points.remove(&9); // not there: nothing changed
        assert_eq!(
            points.take_changed(),
            Changed::Some(BTreeSet::from([1, 2, 3]))
        );
        for (_, (segment, _)) in points.iter_mut() {
            *segment = 1;
        }
        assert_eq!(points.take_changed(), Changed::All);
        // Points come and go while nothing takes the record: it turns into "all".
        for track in 0..=RECORD_BEFORE_ALL as u64 {
            points.insert(track, at(0.0));
            points.remove(&track);
        }
        assert_eq!(points.take_changed(), Changed::All);
    }
}
