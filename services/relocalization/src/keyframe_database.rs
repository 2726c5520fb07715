//! Inverted index of keyframe bags of words (Nister and Stewenius 2006, section 4; Sivic and
//! Zisserman's "Video Google", ICCV 2003): each word lists the keyframes containing it, so a
//! query touches only keyframes that share a word with it, and its cost grows with the
//! number of matching entries, not with the map.

use crate::vocabulary::BowVector;
use std::collections::HashMap;

/// A keyframe returned by a query, best first.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    pub keyframe_id: u64,
    /// L1 similarity in [0, 1] (1: identical bags of words).
    pub score: f32,
}

/// Keyframes searchable by bag of words.
#[derive(Debug, Clone, Default)]
pub struct KeyframeDatabase {
    /// The keyframe of each entry (a removed keyframe's entry is reused by a later one, so
    /// the entries follow the keyframes indexed at once, not all ever added: a day's
    /// stream makes hundreds of thousands, of which the map keeps a few thousand).
    keyframes: Vec<u64>,
    /// Entries of removed keyframes, free for the next ones.
    free: Vec<u32>,
    /// keyframe id -> index into `keyframes`, of the keyframes indexed now.
    entries: HashMap<u64, u32>,
    /// word -> (index into `keyframes`, weight).
    inverted: HashMap<u32, Vec<(u32, f32)>>,
    /// keyframe id -> its bag of words, of the keyframes indexed now: what removes it, and
    /// what a relocalizer over a few of them indexes again without computing them anew
    /// (a loop attempt's ~50-100 candidates, each ~500 descriptors down the tree).
    bags: HashMap<u64, BowVector>,
}

impl KeyframeDatabase {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a keyframe's (L1-normalised) bag of words (replacing the one it had).
    pub fn add(&mut self, keyframe_id: u64, bow: &BowVector) {
        self.remove(keyframe_id);
        self.bags.insert(keyframe_id, bow.clone());
        let index = match self.free.pop() {
            Some(index) => {
                self.keyframes[index as usize] = keyframe_id;
                index
            }
            None => {
                self.keyframes.push(keyframe_id);
                (self.keyframes.len() - 1) as u32
            }
        };
        self.entries.insert(keyframe_id, index);
        for &(word, weight) in bow {
            self.inverted.entry(word).or_default().push((index, weight));
        }
    }

    /// Takes a keyframe out of the index; its entries go, so the index's size follows the
    /// keyframes kept, not those ever added.
    pub fn remove(&mut self, keyframe_id: u64) {
        let (Some(index), Some(bow)) = (
            self.entries.remove(&keyframe_id),
            self.bags.remove(&keyframe_id),
        ) else {
            return;
        };
        for &(word, _) in &bow {
            if let Some(list) = self.inverted.get_mut(&word) {
                list.retain(|(entry, _)| *entry != index);
                if list.is_empty() {
                    self.inverted.remove(&word);
                }
            }
        }
        self.free.push(index);
    }

    /// Entries the index holds, in use or free (what a query's score arrays span).
    pub fn entries(&self) -> usize {
        self.keyframes.len()
    }

    /// Whether keyframe `keyframe_id` is indexed now.
    pub fn contains(&self, keyframe_id: u64) -> bool {
        self.entries.contains_key(&keyframe_id)
    }

    /// The bag of words keyframe `keyframe_id` is indexed with, if it is.
    pub fn bag(&self, keyframe_id: u64) -> Option<&BowVector> {
        self.bags.get(&keyframe_id)
    }

    /// Number of keyframes indexed.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether no keyframe is indexed.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The `max_results` keyframes most similar to `bow` by the L1 score
    /// `1 - |q - d|_1 / 2 = sum over shared words of (|q_i| + |d_i| - |q_i - d_i|) / 2`,
    /// which needs only the shared words.
    pub fn query(&self, bow: &BowVector, max_results: usize) -> Vec<Candidate> {
        self.query_where(bow, max_results, |_| true)
    }

    /// [`Self::query`] among the keyframes `accept` takes: they are chosen before the
    /// best are kept, so a query whose best matches are all refused (a loop's recent past,
    /// which always scores best) still gets its `max_results`.
    pub fn query_where(
        &self,
        bow: &BowVector,
        max_results: usize,
        accept: impl Fn(u64) -> bool,
    ) -> Vec<Candidate> {
        // Scores by entry in a dense array: a query against a map of thousands of
        // keyframes adds up hundreds of thousands of word matches, and a hash map's
        // lookups were most of the query's cost.
        let mut scores = vec![0.0f32; self.keyframes.len()];
        let mut touched = vec![false; self.keyframes.len()];
        let mut found: Vec<u32> = Vec::new();
        for &(word, q) in bow {
            let Some(list) = self.inverted.get(&word) else {
                continue;
            };
            for &(entry, d) in list {
                let e = entry as usize;
                if !touched[e] {
                    touched[e] = true;
                    found.push(entry);
                }
                scores[e] += q.abs() + d.abs() - (q - d).abs();
            }
        }
        let mut out: Vec<Candidate> = found
            .into_iter()
            .map(|entry| Candidate {
                keyframe_id: self.keyframes[entry as usize],
                score: 0.5 * scores[entry as usize],
            })
            .filter(|c| accept(c.keyframe_id))
            .collect();
        out.sort_by(|a, b| {
            b.score
                .total_cmp(&a.score)
                .then(a.keyframe_id.cmp(&b.keyframe_id))
        });
        out.truncate(max_results);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_identical_bag_scores_one_and_disjoint_bags_are_not_returned() {
        let mut db = KeyframeDatabase::new();
        db.add(7, &vec![(1, 0.5), (4, 0.5)]);
        db.add(8, &vec![(1, 0.25), (9, 0.75)]);
        db.add(9, &vec![(2, 1.0)]);
        let got = db.query(&vec![(1, 0.5), (4, 0.5)], 5);
        assert_eq!(got.len(), 2);
        assert_eq!(got[0].keyframe_id, 7);
        assert!((got[0].score - 1.0).abs() < 1e-6);
        assert_eq!(got[1].keyframe_id, 8);
        assert!((got[1].score - 0.25).abs() < 1e-6);
        assert_eq!(db.query(&vec![(1, 1.0)], 1).len(), 1);
        assert_eq!(db.len(), 3);
        assert_eq!(db.bag(7), Some(&vec![(1, 0.5), (4, 0.5)]));
        db.remove(7);
        assert_eq!(db.bag(7), None);
        let got = db.query(&vec![(1, 0.5), (4, 0.5)], 5);
        assert_eq!(got.len(), 1);
        assert_eq!(got[0].keyframe_id, 8);
        assert_eq!(db.len(), 2);
        assert!(!db.contains(7) && db.contains(8));
        assert!(!db.inverted.contains_key(&4), "an emptied word's list goes");
    }

    #[test]
    fn a_filtered_query_returns_the_best_accepted_even_below_refused_ones() {
        let mut db = KeyframeDatabase::new();
        // Keyframes 10..20 match the query best and are refused; 1 and 2 match less.
        for k in 10..20 {
            db.add(k, &vec![(1, 0.5), (4, 0.5)]);
        }
        db.add(1, &vec![(1, 0.5), (9, 0.5)]);
        db.add(2, &vec![(1, 0.2), (9, 0.8)]);
        let query = vec![(1, 0.5), (4, 0.5)];
        assert!(db.query(&query, 2).iter().all(|c| c.keyframe_id >= 10));
        let got = db.query_where(&query, 2, |k| k < 10);
        let ids: Vec<u64> = got.iter().map(|c| c.keyframe_id).collect();
        assert_eq!(ids, vec![1, 2]);
        assert!((got[0].score - 0.5).abs() < 1e-6 && (got[1].score - 0.2).abs() < 1e-6);
    }

    #[test]
    fn the_index_follows_the_keyframes_kept_not_those_ever_added() {
        let mut db = KeyframeDatabase::new();
        // A long stream: 10 keyframes indexed at a time, 1000 added over it.
        for k in 0..1000u64 {
            db.add(k, &vec![((k % 7) as u32, 0.5), (100 + (k % 3) as u32, 0.5)]);
            if k >= 10 {
                db.remove(k - 10);
            }
        }
        assert_eq!(db.len(), 10);
        assert!(db.entries() <= 11, "{} entries", db.entries());
        // The reused entries answer for their new keyframes.
        let last = 999u64;
        let got = db.query(
            &vec![((last % 7) as u32, 0.5), (100 + (last % 3) as u32, 0.5)],
            1,
        );
        assert_eq!(got[0].keyframe_id, 999);
        assert!((got[0].score - 1.0).abs() < 1e-6);
        assert!(db.query(&vec![(5000, 1.0)], 3).is_empty());
    }
}
