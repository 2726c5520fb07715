//! Vocabulary tree over binary descriptors (Nister and Stewenius, "Scalable Recognition with
//! a Vocabulary Tree", CVPR 2006; binary k-majority clustering as in DBoW2, Galvez-Lopez and
//! Tardos, "Bags of Binary Words for Fast Place Recognition", T-RO 2012).
//!
//! Hierarchical k-means with Hamming distance: each node's descriptors are split into
//! `branching` clusters whose centres are bitwise majorities, down to `depth` levels. The
//! leaves are the words; each word carries an inverse document frequency learnt from the
//! training images. A descriptor's word is found by descending to the nearest child at each
//! level (`branching * depth` Hamming distances), so a 1000-feature frame is quantised in
//! well under a millisecond.

use crate::descriptors::{hamming, Descriptor};

/// Training settings; defaults give 10^4 words, DBoW2's smallest published vocabulary size
/// that still separates places well.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VocabularyOptions {
    /// Children per node, k (default 10, Nister and Stewenius' choice).
    pub branching: usize,
    /// Levels below the root, L (default 4: 10^4 leaves).
    pub depth: usize,
    /// k-majority iterations per node (default 10; assignments rarely change after ~6).
    pub iterations: usize,
    /// Seed of the k-means++ initialisation (training is deterministic for a seed).
    pub seed: u64,
}

impl Default for VocabularyOptions {
    fn default() -> Self {
        Self {
            branching: 10,
            depth: 4,
            iterations: 10,
            seed: 1,
        }
    }
}

/// Why a vocabulary could not be trained or read.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum VocabularyError {
    /// Training needs at least `branching` descriptors.
    #[error("{found} training descriptors, need at least {needed}")]
    TooFewDescriptors { found: usize, needed: usize },
    /// Options out of range.
    #[error("branching must be 2-255 and depth 1-8 (got {branching}, {depth})")]
    BadOptions { branching: usize, depth: usize },
    /// The bytes do not start with the vocabulary magic.
    #[error("not an egoslam vocabulary (bad magic)")]
    BadMagic,
    /// The file is of a format version this build does not read.
    #[error("vocabulary format version {found}, this build reads {supported}")]
    UnsupportedVersion { found: u32, supported: u32 },
    /// The file ends early.
    #[error("vocabulary truncated: {needed} bytes needed, {found} present")]
    Truncated { needed: usize, found: usize },
    /// The checksum does not match the content.
    #[error("vocabulary checksum mismatch (corrupt file)")]
    ChecksumMismatch,
    /// The tree structure is inconsistent.
    #[error("malformed vocabulary: {0}")]
    Malformed(String),
}

#[derive(Debug, Clone, PartialEq)]
struct Node {
    centre: Descriptor,
    /// Index of the first child; 0 for a leaf (the root is never a child).
    first_child: u32,
    children: u8,
    /// Word index for leaves.
    word: u32,
}

/// A sparse bag-of-words vector: `(word, weight)` sorted by word, L1-normalised.
pub type BowVector = Vec<(u32, f32)>;

/// A trained vocabulary tree.
#[derive(Debug, Clone, PartialEq)]
pub struct Vocabulary {
    branching: u8,
    depth: u8,
    nodes: Vec<Node>,
    /// Inverse document frequency per word, ln(N / n_i).
    idf: Vec<f32>,
}

/// Deterministic generator for the k-means++ draws (SplitMix64).
struct SplitMix(u64);
impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e3779b97f4a7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58476d1ce4e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d049bb133111eb);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// Bitwise majority of a set of descriptors.
fn majority(all: &[Descriptor], members: &[usize]) -> Descriptor {
    let mut counts = [0u32; 256];
    for &m in members {
        for (byte, bits) in all[m].iter().enumerate() {
            for bit in 0..8 {
                counts[byte * 8 + bit] += u32::from((bits >> bit) & 1);
            }
        }
    }
    let mut out = [0u8; 32];
    let half = members.len() as u32;
    for (i, c) in counts.iter().enumerate() {
        if 2 * c > half {
            out[i / 8] |= 1 << (i % 8);
        }
    }
    out
}

/// k-majority clustering of `members` (k-means++ seeding, Arthur and Vassilvitskii 2007).
fn cluster(
    all: &[Descriptor],
    members: &[usize],
    k: usize,
    iterations: usize,
    rng: &mut SplitMix,
) -> Vec<(Descriptor, Vec<usize>)> {
    let mut centres = vec![all[members[rng.below(members.len())]]];
    let mut nearest: Vec<u64> = members
        .iter()
        .map(|&m| u64::from(hamming(&all[m], &centres[0])).pow(2))
        .collect();
    while centres.len() < k {
        let total: u64 = nearest.iter().sum();
        if total == 0 {
            break; // every member equals a centre already
        }
        let mut draw = rng.next() % total;
        let mut pick = 0;
        for (i, d) in nearest.iter().enumerate() {
            if draw < *d {
                pick = i;
                break;
            }
            draw -= d;
        }
        let c = all[members[pick]];
        for (n, &m) in nearest.iter_mut().zip(members) {
            *n = (*n).min(u64::from(hamming(&all[m], &c)).pow(2));
        }
        centres.push(c);
    }
    let mut assignment = vec![usize::MAX; members.len()];
    for _ in 0..iterations.max(1) {
        let mut changed = false;
        for (a, &m) in assignment.iter_mut().zip(members) {
            let best = (0..centres.len())
                .min_by_key(|&c| hamming(&all[m], &centres[c]))
                .unwrap_or(0);
            changed |= *a != best;
            *a = best;
        }
        let mut groups = vec![Vec::new(); centres.len()];
        for (a, &m) in assignment.iter().zip(members) {
            groups[*a].push(m);
        }
        for (c, g) in centres.iter_mut().zip(&groups) {
            if !g.is_empty() {
                *c = majority(all, g);
            }
        }
        if !changed {
            break;
        }
    }
    let mut groups = vec![Vec::new(); centres.len()];
    for (a, &m) in assignment.iter().zip(members) {
        groups[*a].push(m);
    }
    centres
        .into_iter()
        .zip(groups)
        .filter(|(_, g)| !g.is_empty())
        .collect()
}

const MAGIC: &[u8; 8] = b"EGOVOCAB";
const FORMAT_VERSION: u32 = 1;
const HEADER: usize = 8 + 4 + 1 + 1 + 4;
const NODE_BYTES: usize = 32 + 4 + 1 + 4;

/// FNV-1a, 64 bit: the checksum and identity of a vocabulary file.
pub fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf29ce484222325u64, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x100000001b3)
    })
}

impl Vocabulary {
    /// Trains a vocabulary on the descriptors of a set of images (one list per image; the
    /// images give the inverse document frequencies).
    pub fn train(
        images: &[Vec<Descriptor>],
        options: &VocabularyOptions,
    ) -> Result<Self, VocabularyError> {
        if !(2..=255).contains(&options.branching) || !(1..=8).contains(&options.depth) {
            return Err(VocabularyError::BadOptions {
                branching: options.branching,
                depth: options.depth,
            });
        }
        let all: Vec<Descriptor> = images.iter().flatten().copied().collect();
        if all.len() < options.branching {
            return Err(VocabularyError::TooFewDescriptors {
                found: all.len(),
                needed: options.branching,
            });
        }
        let _span = tracing::info_span!("train_vocabulary", descriptors = all.len()).entered();
        let mut rng = SplitMix(options.seed);
        let mut nodes = vec![Node {
            centre: [0; 32],
            first_child: 0,
            children: 0,
            word: 0,
        }];
        // Breadth-first, so that children of a node are contiguous.
        let mut queue = std::collections::VecDeque::from([(
            0usize,
            (0..all.len()).collect::<Vec<_>>(),
            0usize,
        )]);
        while let Some((node, members, level)) = queue.pop_front() {
            if level >= options.depth || members.len() <= options.branching {
                continue;
            }
            let clusters = cluster(
                &all,
                &members,
                options.branching,
                options.iterations,
                &mut rng,
            );
            if clusters.len() < 2 {
                continue;
            }
            nodes[node].first_child = nodes.len() as u32;
            nodes[node].children = clusters.len() as u8;
            for (centre, group) in clusters {
                queue.push_back((nodes.len(), group, level + 1));
                nodes.push(Node {
                    centre,
                    first_child: 0,
                    children: 0,
                    word: 0,
                });
            }
        }
        let mut vocabulary = Self {
            branching: options.branching as u8,
            depth: options.depth as u8,
            nodes,
            idf: Vec::new(),
        };
        let words = vocabulary.number_words();
        let mut documents = vec![0u32; words];
        for image in images {
            let mut seen: Vec<u32> = image.iter().map(|d| vocabulary.word(d)).collect();
            seen.sort_unstable();
            seen.dedup();
            for w in seen {
                documents[w as usize] += 1;
            }
        }
        let n = images.len().max(1) as f32;
        vocabulary.idf = documents
            .iter()
            .map(|&d| (n / d.max(1) as f32).ln())
            .collect();
        Ok(vocabulary)
    }

    /// Numbers the leaves in node order; returns the word count.
    fn number_words(&mut self) -> usize {
        let mut words = 0u32;
        for node in self.nodes.iter_mut().skip(1) {
            if node.children == 0 {
                node.word = words;
                words += 1;
            }
        }
        if self.nodes.len() == 1 {
            self.nodes[0].word = 0;
            words = 1;
        }
        words as usize
    }

    /// Number of words (leaves).
    pub fn words(&self) -> usize {
        self.idf.len()
    }

    /// The word of a descriptor: descend to the nearest child at each level.
    pub fn word(&self, d: &Descriptor) -> u32 {
        let mut node = &self.nodes[0];
        while node.children > 0 {
            let first = node.first_child as usize;
            let children = &self.nodes[first..first + node.children as usize];
            node = children
                .iter()
                .min_by_key(|c| hamming(d, &c.centre))
                .unwrap_or(&children[0]);
        }
        node.word
    }

    /// TF-IDF bag of words of an image's descriptors, L1-normalised (Nister and Stewenius'
    /// weighting; the L1 norm is the one their scoring uses).
    pub fn bag_of_words(&self, descriptors: &[Descriptor]) -> BowVector {
        let mut words: Vec<u32> = descriptors.iter().map(|d| self.word(d)).collect();
        words.sort_unstable();
        let mut bow: BowVector = Vec::new();
        for w in words {
            let weight = self.idf.get(w as usize).copied().unwrap_or(0.0);
            match bow.last_mut() {
                Some((last, v)) if *last == w => *v += weight,
                _ => bow.push((w, weight)),
            }
        }
        let norm: f32 = bow.iter().map(|(_, v)| v.abs()).sum();
        if norm > 0.0 {
            for (_, v) in &mut bow {
                *v /= norm;
            }
        }
        bow.retain(|(_, v)| *v > 0.0);
        bow
    }

    /// The file bytes: magic, version, shape, nodes, then an FNV-1a checksum of all before.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER + self.nodes.len() * NODE_BYTES + 8);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        out.push(self.branching);
        out.push(self.depth);
        out.extend_from_slice(&(self.nodes.len() as u32).to_le_bytes());
        for (i, n) in self.nodes.iter().enumerate() {
            out.extend_from_slice(&n.centre);
            out.extend_from_slice(&n.first_child.to_le_bytes());
            out.push(n.children);
            let idf = if n.children == 0 && i > 0 {
                self.idf.get(n.word as usize).copied().unwrap_or(0.0)
            } else {
                0.0
            };
            out.extend_from_slice(&idf.to_le_bytes());
        }
        let sum = fnv1a(&out);
        out.extend_from_slice(&sum.to_le_bytes());
        out
    }

    /// Identity of the vocabulary (its checksum): saved maps name the vocabulary they were
    /// built with, and a localizer refuses a different one.
    pub fn id(&self) -> u64 {
        let bytes = self.to_bytes();
        let tail = &bytes[bytes.len() - 8..];
        u64::from_le_bytes(tail.try_into().unwrap_or([0; 8]))
    }

    /// Reads [`Vocabulary::to_bytes`] output, checking magic, version, length, checksum and
    /// tree structure.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, VocabularyError> {
        if bytes.len() < 8 || &bytes[..8] != MAGIC {
            return Err(VocabularyError::BadMagic);
        }
        if bytes.len() < HEADER {
            return Err(VocabularyError::Truncated {
                needed: HEADER,
                found: bytes.len(),
            });
        }
        let u32_at =
            |i: usize| u32::from_le_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
        let version = u32_at(8);
        if version != FORMAT_VERSION {
            return Err(VocabularyError::UnsupportedVersion {
                found: version,
                supported: FORMAT_VERSION,
            });
        }
        let (branching, depth) = (bytes[12], bytes[13]);
        let count = u32_at(14) as usize;
        let needed = count
            .checked_mul(NODE_BYTES)
            .and_then(|n| n.checked_add(HEADER + 8))
            .ok_or_else(|| VocabularyError::Malformed(format!("{count} nodes")))?;
        if bytes.len() < needed {
            return Err(VocabularyError::Truncated {
                needed,
                found: bytes.len(),
            });
        }
        let body = &bytes[..needed - 8];
        let stored = u64::from_le_bytes(bytes[needed - 8..needed].try_into().unwrap_or([0; 8]));
        if fnv1a(body) != stored {
            return Err(VocabularyError::ChecksumMismatch);
        }
        if count == 0 {
            return Err(VocabularyError::Malformed("no nodes".into()));
        }
        let mut nodes = Vec::with_capacity(count);
        let mut idf_of_node = Vec::with_capacity(count);
        for i in 0..count {
            let at = HEADER + i * NODE_BYTES;
            let mut centre = [0u8; 32];
            centre.copy_from_slice(&bytes[at..at + 32]);
            let first_child = u32_at(at + 32);
            let children = bytes[at + 36];
            let idf = f32::from_le_bytes([
                bytes[at + 37],
                bytes[at + 38],
                bytes[at + 39],
                bytes[at + 40],
            ]);
            // Children must come after their parent and inside the table (no cycles).
            if children > 0
                && (first_child as usize <= i || first_child as usize + children as usize > count)
            {
                return Err(VocabularyError::Malformed(format!(
                    "node {i}: children out of range"
                )));
            }
            if !idf.is_finite() {
                return Err(VocabularyError::Malformed(format!(
                    "node {i}: weight not finite"
                )));
            }
            nodes.push(Node {
                centre,
                first_child,
                children,
                word: 0,
            });
            idf_of_node.push(idf);
        }
        let mut vocabulary = Self {
            branching,
            depth,
            nodes,
            idf: Vec::new(),
        };
        let words = vocabulary.number_words();
        let mut idf = vec![0.0; words];
        for (i, n) in vocabulary.nodes.iter().enumerate() {
            if n.children == 0 && (i > 0 || count == 1) {
                idf[n.word as usize] = idf_of_node[i];
            }
        }
        vocabulary.idf = idf;
        Ok(vocabulary)
    }
}

/// The vocabulary built into egoslam (vocabulary/default.vocab; how it was trained and on
/// what: vocabulary/README.md), so that relocalization needs no download.
pub fn default_vocabulary() -> Result<Vocabulary, VocabularyError> {
    Vocabulary::from_bytes(include_bytes!("../vocabulary/default.vocab"))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Descriptors drawn around `centres` prototypes with `flips` random bit flips.
    fn images(
        prototypes: usize,
        per_image: usize,
        images: usize,
        seed: u64,
    ) -> Vec<Vec<Descriptor>> {
        let mut rng = SplitMix(seed);
        let protos: Vec<Descriptor> = (0..prototypes)
            .map(|_| {
                let mut d = [0u8; 32];
                for b in &mut d {
                    *b = rng.next() as u8;
                }
                d
            })
            .collect();
        (0..images)
            .map(|_| {
                (0..per_image)
                    .map(|_| {
                        let mut d = protos[rng.below(prototypes)];
                        for _ in 0..8 {
                            let bit = rng.below(256);
                            d[bit / 8] ^= 1 << (bit % 8);
                        }
                        d
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn training_separates_prototypes_and_round_trips_through_bytes() {
        let data = images(100, 200, 20, 5);
        let options = VocabularyOptions {
            branching: 5,
            depth: 3,
            ..VocabularyOptions::default()
        };
        let v = Vocabulary::train(&data, &options).expect("train");
        assert!(v.words() >= 60 && v.words() <= 125, "{} words", v.words());
        // Noisy copies of one prototype land in few words; different images share words.
        let again = Vocabulary::train(&data, &options).expect("train");
        assert_eq!(v, again, "training is deterministic for a seed");
        let bytes = v.to_bytes();
        let back = Vocabulary::from_bytes(&bytes).expect("read");
        assert_eq!(back.words(), v.words());
        for d in data[0].iter().take(50) {
            assert_eq!(back.word(d), v.word(d));
        }
        assert_eq!(back.bag_of_words(&data[3]), v.bag_of_words(&data[3]));
        let bow = v.bag_of_words(&data[3]);
        let l1: f32 = bow.iter().map(|(_, w)| w).sum();
        assert!((l1 - 1.0).abs() < 1e-4);
        assert!(bow.windows(2).all(|w| w[0].0 < w[1].0));
    }

    #[test]
    fn corrupt_truncated_and_foreign_files_are_refused() {
        let v =
            Vocabulary::train(&images(20, 50, 5, 9), &VocabularyOptions::default()).expect("train");
        let bytes = v.to_bytes();
        assert_eq!(
            Vocabulary::from_bytes(b"PNG\x89...."),
            Err(VocabularyError::BadMagic)
        );
        assert!(matches!(
            Vocabulary::from_bytes(&bytes[..bytes.len() - 3]),
            Err(VocabularyError::Truncated { .. })
        ));
        let mut flipped = bytes.clone();
        flipped[HEADER + 5] ^= 0x10;
        assert_eq!(
            Vocabulary::from_bytes(&flipped),
            Err(VocabularyError::ChecksumMismatch)
        );
        let mut newer = bytes.clone();
        newer[8] = 2;
        assert_eq!(
            Vocabulary::from_bytes(&newer),
            Err(VocabularyError::UnsupportedVersion {
                found: 2,
                supported: 1
            })
        );
        assert_eq!(
            Vocabulary::train(&[vec![[0; 32]; 3]], &VocabularyOptions::default()),
            Err(VocabularyError::TooFewDescriptors {
                found: 3,
                needed: 10
            })
        );
    }
}
