//! The merger's keyframe descriptors and new tracks' patches on disk: an append-only log of
//! length-delimited `KeyframeFeatures` messages beside the checkpoint (docs/durability.md).
//!
//! Descriptors and patches are most of the map's bytes (~45 KB per keyframe). Inside the
//! checkpoint, which is rewritten whole, they would be written again every few seconds;
//! appended once each, they cost O(new keyframes). They stay on disk only: the merger keeps
//! each keyframe's record offset and reads descriptors back when loop closure, segment
//! linking or culling asks for a keyframe's, and patches when a map is saved. The
//! log is flushed and synced before every checkpoint, so it always covers the windows the
//! checkpoint has applied; a torn record at its end (a kill mid-append) is ignored, and the
//! windows after the checkpoint are re-applied from the solver's journal, which re-appends
//! their features.
//!
//! New records wait in memory ([`FeaturesLog::write_pending`]) until the checkpoint or
//! until they outgrow [`PENDING_LIMIT_BYTES`]: most of a head-mounted walk's keyframes are
//! culled soon after they arrive, and a record written and compacted away later is flash
//! wear for nothing (the checkpoint needs them no sooner; the journal covers a kill).

use crate::record_log::{for_each_record, LogReader, RecordLog};
use egoslam_messages::internal::v1 as internal;
use egoslam_relocalization::patch_alignment::Patch;
use egoslam_relocalization::saved_map::{features_from_pb, patches_from_pb};
use egoslam_relocalization::MapFeature;
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// File name in the state folder.
pub const FILE_NAME: &str = "keyframe_features.log";

/// Logs smaller than this are left as they are (8 MiB: ~200 keyframes).
pub const COMPACT_ABOVE_BYTES: u64 = 8 << 20;

/// A log is compacted once it holds this many times the bytes of the records still
/// wanted: the disk it takes stays within this factor of what the map needs, and each
/// compaction rewrites the live records once (the write amplification is 1 / (factor - 1)).
pub const COMPACT_AT_FACTOR: f64 = 1.25;

/// Bytes of new records held in memory before the oldest are written (16 MiB: ~350
/// keyframes, ~15 s of a walk's keyframes), whatever their keyframes' fate by then.
pub const PENDING_LIMIT_BYTES: u64 = 16 << 20;

/// Bytes a record keeps per track when compaction keeps only some of its tracks (a
/// descriptor, its track id and pixel, and a patch).
const BYTES_PER_KEPT_TRACK: u64 = 32 + 10 + 10 + 10 + 100;

/// What compaction keeps of a keyframe's record.
#[derive(Debug, Clone, PartialEq)]
pub enum Keep {
    /// The whole record (a keyframe of the map).
    Whole,
    /// The features and patches of these tracks alone (a culled keyframe's patched
    /// points).
    Tracks(BTreeSet<u64>),
    /// The features without the patches (a keyframe of the map whose patches, pixels of
    /// the wearer's surroundings, are older than the retention allows).
    Features,
    /// Nothing.
    Nothing,
}

/// The tracks whose patch a keyframe's record holds, with each patch's grey level
/// ([`patch_grey`]).
pub type PatchedTracks = Vec<(u64, u8)>;

/// A track's grey level: the centre of its patch (map.ply's colours).
pub fn patch_grey(patch: &Patch) -> u8 {
    use egoslam_relocalization::patch_alignment::PATCH_SIDE;
    let (a, b) = (PATCH_SIDE / 2 - 1, PATCH_SIDE / 2);
    let sum: u32 = [(a, a), (a, b), (b, a), (b, b)]
        .iter()
        .map(|(y, x)| u32::from(patch[y * PATCH_SIDE + x]))
        .sum();
    (sum / 4) as u8
}

/// The tracks of `patches` with their grey levels.
pub fn patched_tracks(patches: &[(u64, Patch)]) -> Vec<(u64, u8)> {
    patches.iter().map(|(t, p)| (*t, patch_grey(p))).collect()
}

/// The features log: where each keyframe's latest record is.
pub struct FeaturesLog {
    path: std::path::PathBuf,
    log: RecordLog,
    /// keyframe -> (byte offset, bytes) of its latest record.
    records: BTreeMap<u64, (u64, u64)>,
    /// keyframe -> bytes of the patches in its latest record (those with any).
    patch_bytes: BTreeMap<u64, u64>,
    /// keyframe -> its latest record, appended but not yet written (newer than `records`).
    pending: BTreeMap<u64, internal::KeyframeFeatures>,
    /// Encoded bytes of `pending`.
    pending_bytes: u64,
}

/// A record's bytes in the log (length prefix included).
fn logged_len(record: &internal::KeyframeFeatures) -> u64 {
    use prost::Message;
    let bytes = record.encoded_len();
    (prost::length_delimiter_len(bytes) + bytes) as u64
}

/// The bytes a record's patches take (pixels and track ids).
fn patch_bytes_of(record: &internal::KeyframeFeatures) -> u64 {
    (record.patches.len() + 10 * record.patch_track_ids.len()) as u64
}

impl FeaturesLog {
    /// Opens `dir/keyframe_features.log` for appending (created if absent) and reads which
    /// keyframes it describes and the tracks each holds a patch of, later records
    /// replacing earlier ones (a resumed merger's).
    pub fn open(dir: &Path) -> crate::Result<(Self, BTreeMap<u64, PatchedTracks>)> {
        let path = dir.join(FILE_NAME);
        let mut records = BTreeMap::new();
        let mut patch_bytes = BTreeMap::new();
        let mut descriptions = BTreeMap::new();
        let mut ends = Vec::new();
        for_each_record::<internal::KeyframeFeatures>(&path, |at, r| {
            match features_from_pb(&r).zip(patches_from_pb(&r)) {
                Some((_, patches)) => {
                    descriptions.insert(r.keyframe_id, patched_tracks(&patches));
                    records.insert(r.keyframe_id, (at, 0));
                    match patch_bytes_of(&r) {
                        0 => patch_bytes.remove(&r.keyframe_id),
                        b => patch_bytes.insert(r.keyframe_id, b),
                    };
                    ends.push(at);
                }
                None => tracing::warn!(
                    keyframe = r.keyframe_id,
                    "inconsistent features in the log skipped"
                ),
            }
        })?;
        let mut log = RecordLog::open(&path)?;
        let end = log.len_bytes()?;
        // A record's size: up to the next record's offset (or the end of the log).
        ends.push(end);
        ends.sort_unstable();
        for (at, bytes) in records.values_mut() {
            let next = ends[ends.partition_point(|e| e <= at)..]
                .first()
                .copied()
                .unwrap_or(end);
            *bytes = next - *at;
        }
        Ok((
            Self {
                path,
                log,
                records,
                patch_bytes,
                pending: BTreeMap::new(),
                pending_bytes: 0,
            },
            descriptions,
        ))
    }

    /// Hands what was written to the kernel, so that reads see it.
    pub fn flush(&mut self) -> crate::Result<()> {
        self.log.flush()
    }

    /// Keyframe `id`'s described tracks as its latest record holds them; `None` for a
    /// keyframe without one or an unreadable record.
    pub fn features_of(&self, id: u64) -> crate::Result<Option<Vec<MapFeature>>> {
        if let Some(record) = self.pending.get(&id) {
            return Ok(features_from_pb(record));
        }
        let Some((at, _)) = self.records.get(&id) else {
            return Ok(None);
        };
        let record: internal::KeyframeFeatures = LogReader::open(&self.path)?.read_at(*at)?;
        Ok(features_from_pb(&record))
    }

    /// Takes `record` as keyframe `record.keyframe_id`'s latest, held in memory until
    /// [`FeaturesLog::write_pending`] writes what is still wanted of it.
    pub fn append(&mut self, record: &internal::KeyframeFeatures) {
        self.pending_bytes += logged_len(record);
        if let Some(old) = self.pending.insert(record.keyframe_id, record.clone()) {
            self.pending_bytes -= logged_len(&old);
        }
    }

    /// Writes what `keep` keeps of the pending records, oldest keyframe first, until at most
    /// `limit` bytes of them are left in memory (0: all, before a checkpoint); a record
    /// kept whole, or partly, is written once, and one kept not at all never (buffered:
    /// [`FeaturesLog::sync`] makes it durable). Returns the bytes written.
    pub fn write_pending(&mut self, keep: impl Fn(u64) -> Keep, limit: u64) -> crate::Result<u64> {
        let mut written = 0;
        while self.pending_bytes > limit {
            let Some((keyframe, record)) = self.pending.pop_first() else {
                break;
            };
            self.pending_bytes -= logged_len(&record);
            let Some(record) = kept_part(record, keep(keyframe)) else {
                continue;
            };
            let bytes = logged_len(&record);
            let at = self.log.append(&record)?;
            self.records.insert(keyframe, (at, bytes));
            match patch_bytes_of(&record) {
                0 => self.patch_bytes.remove(&keyframe),
                b => self.patch_bytes.insert(keyframe, b),
            };
            written += bytes;
        }
        Ok(written)
    }

    /// Makes everything written durable (not the pending records: write those first).
    pub fn sync(&mut self) -> crate::Result<()> {
        self.log.sync()
    }

    /// Empties the log (a new stream starts a new map).
    pub fn truncate(&mut self) -> crate::Result<()> {
        self.records.clear();
        self.patch_bytes.clear();
        self.pending.clear();
        self.pending_bytes = 0;
        self.log.truncate()
    }

    /// The patches of `keyframes` (those the log has a record of), read from disk.
    pub fn patches(
        &mut self,
        keyframes: impl IntoIterator<Item = u64>,
    ) -> crate::Result<BTreeMap<u64, Vec<(u64, Patch)>>> {
        let mut reader = self.log.reader()?;
        let mut out = BTreeMap::new();
        for keyframe in keyframes {
            let record: internal::KeyframeFeatures = match self.pending.get(&keyframe) {
                Some(record) => record.clone(),
                None => match self.records.get(&keyframe) {
                    Some((at, _)) => reader.read_at(*at)?,
                    None => continue,
                },
            };
            if let Some(patches) = patches_from_pb(&record).filter(|p| !p.is_empty()) {
                out.insert(keyframe, patches);
            }
        }
        Ok(out)
    }

    /// Rewrites the log with what `keep` keeps of each keyframe's latest record when it
    /// holds more than [`COMPACT_AT_FACTOR`] times their size and at least
    /// [`COMPACT_ABOVE_BYTES`]: culled keyframes' records go, so the log grows with the
    /// map, not with the time walked. Records are copied one at a time. Returns the bytes
    /// written (0 when not due). Call it before a checkpoint: the log must cover every
    /// keyframe the checkpoint holds, and the windows after it re-append theirs when
    /// replayed, and after [`FeaturesLog::write_pending`] (it rewrites the written records).
    pub fn compact_if_due(&mut self, keep: impl Fn(u64) -> Keep) -> crate::Result<u64> {
        let size = self.log.len_bytes()?;
        if size < COMPACT_ABOVE_BYTES {
            return Ok(0);
        }
        let decisions: Vec<(u64, u64, Keep)> = self
            .records
            .iter()
            .map(|(k, (at, _))| (*k, *at, keep(*k)))
            .filter(|(_, _, keep)| *keep != Keep::Nothing)
            .collect();
        let live: u64 = crate::record_log::HEADER_LEN
            + decisions
                .iter()
                .map(|(k, _, keep)| {
                    let whole = self.records.get(k).map_or(0, |(_, bytes)| *bytes);
                    match keep {
                        Keep::Tracks(t) => BYTES_PER_KEPT_TRACK * t.len() as u64,
                        Keep::Features => {
                            whole.saturating_sub(self.patch_bytes.get(k).copied().unwrap_or(0))
                        }
                        _ => whole,
                    }
                })
                .sum::<u64>();
        if (size as f64) <= COMPACT_AT_FACTOR * live as f64 {
            return Ok(0);
        }
        let mut records = BTreeMap::new();
        let mut patch_bytes = BTreeMap::new();
        self.log.rewrite(|reader, writer| {
            for (keyframe, at, keep) in decisions {
                let record: internal::KeyframeFeatures = reader.read_at(at)?;
                let Some(record) = kept_part(record, keep) else {
                    continue;
                };
                let bytes = logged_len(&record);
                records.insert(keyframe, (writer.append(&record)?, bytes));
                if let b @ 1.. = patch_bytes_of(&record) {
                    patch_bytes.insert(keyframe, b);
                }
            }
            Ok(())
        })?;
        self.records = records;
        self.patch_bytes = patch_bytes;
        let after = self.log.len_bytes()?;
        tracing::info!(before = size, after, "keyframe features log compacted");
        Ok(after)
    }
}

impl egoslam_merger::KeyframeFeatureSource for FeaturesLog {
    fn is_described(&self, id: u64) -> bool {
        self.pending.contains_key(&id) || self.records.contains_key(&id)
    }

    fn features(&self, id: u64) -> Option<Vec<MapFeature>> {
        self.features_of(id).unwrap_or_else(|e| {
            tracing::warn!(keyframe = id, error = %e, "keyframe descriptors unreadable");
            None
        })
    }
}

/// What `keep` keeps of `record` (`None`: nothing).
fn kept_part(
    mut record: internal::KeyframeFeatures,
    keep: Keep,
) -> Option<internal::KeyframeFeatures> {
    match keep {
        Keep::Whole => {}
        Keep::Tracks(tracks) => record = only_tracks(&record, &tracks),
        Keep::Features => {
            record.patch_track_ids.clear();
            record.patches.clear();
        }
        Keep::Nothing => return None,
    }
    Some(record)
}

/// `record` with the features and patches of `tracks` alone.
fn only_tracks(
    record: &internal::KeyframeFeatures,
    tracks: &BTreeSet<u64>,
) -> internal::KeyframeFeatures {
    let mut out = internal::KeyframeFeatures {
        keyframe_id: record.keyframe_id,
        ..Default::default()
    };
    for (i, track) in record.track_ids.iter().enumerate() {
        let descriptor = record.descriptors.get(32 * i..32 * (i + 1));
        if let (true, Some(d), Some(x), Some(y)) = (
            tracks.contains(track),
            descriptor,
            record.x.get(i),
            record.y.get(i),
        ) {
            out.track_ids.push(*track);
            out.descriptors.extend_from_slice(d);
            out.x.push(*x);
            out.y.push(*y);
        }
    }
    let side = record.patches.len() / record.patch_track_ids.len().max(1);
    for (i, track) in record.patch_track_ids.iter().enumerate() {
        if let (true, Some(p)) = (
            tracks.contains(track),
            record.patches.get(side * i..side * (i + 1)),
        ) {
            out.patch_track_ids.push(*track);
            out.patches.extend_from_slice(p);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use egoslam_relocalization::saved_map::features_to_pb;
    use prost::Message;

    fn feature(k: u64) -> MapFeature {
        MapFeature {
            track_id: k,
            descriptor: [k as u8; 32],
            pixel: nalgebra::Point2::new(1.0, 2.0),
        }
    }

    /// Writes every pending record whole.
    fn write_all(log: &mut FeaturesLog) {
        log.write_pending(|_| Keep::Whole, 0).expect("write");
    }

    #[test]
    fn records_wait_in_memory_and_those_culled_meanwhile_are_never_written() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (mut log, _) = FeaturesLog::open(dir.path()).expect("open");
        // 100 keyframes of 500 features (~21 KB each).
        for k in 0..100u64 {
            let f: Vec<MapFeature> = (0..500).map(|i| feature(k * 1000 + i)).collect();
            log.append(&features_to_pb(k, &f, &[(k * 1000 + 7, [k as u8; 100])]));
        }
        assert_eq!(
            log.log.len_bytes().expect("len"),
            crate::record_log::HEADER_LEN
        );
        // Read back from memory as from disk.
        assert_eq!(
            log.features_of(42).expect("read").expect("pending")[3],
            feature(42003)
        );
        assert_eq!(
            log.patches([42]).expect("patches")[&42],
            vec![(42007, [42; 100])]
        );
        use egoslam_merger::KeyframeFeatureSource;
        assert!(log.is_described(99) && !log.is_described(100));
        // Over a limit of about half of them, the oldest go first: the culled ones not at
        // all, keyframe 2 with its one wanted track.
        let keep = |k: u64| match k {
            2 => Keep::Tracks(BTreeSet::from([2007])),
            k if k % 4 == 0 => Keep::Whole,
            _ => Keep::Nothing,
        };
        let newest_half: u64 = log.pending.range(50..).map(|(_, r)| logged_len(r)).sum();
        let kept_whole: u64 = (0..50)
            .filter(|k| k % 4 == 0)
            .map(|k| logged_len(&log.pending[&k]))
            .sum();
        let written = log.write_pending(keep, newest_half).expect("write");
        assert_eq!(log.pending.len(), 50);
        assert_eq!(log.pending.keys().next(), Some(&50));
        let partial = logged_len(&features_to_pb(2, &[feature(2007)], &[(2007, [2; 100])]));
        assert_eq!(written, kept_whole + partial);
        assert_eq!(
            written,
            log.log.len_bytes().expect("len") - crate::record_log::HEADER_LEN
        );
        // The rest before a checkpoint; what was written comes back after a restart.
        log.write_pending(keep, 0).expect("write");
        assert!(log.pending.is_empty() && log.pending_bytes == 0);
        log.sync().expect("sync");
        let (back_log, back) = FeaturesLog::open(dir.path()).expect("reopen");
        assert_eq!(back.len(), 26);
        assert_eq!(back[&2], [(2007, 2)]);
        assert_eq!(
            back_log.features_of(96).expect("read").expect("kept").len(),
            500
        );
        assert!(back_log.features_of(97).expect("read").is_none());
    }

    #[test]
    fn compaction_keeps_the_live_keyframes_once_and_appending_goes_on() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (mut log, old) = FeaturesLog::open(dir.path()).expect("open");
        assert!(old.is_empty());
        // 800 keyframes of 500 features (~21 KB each): every fourth stays whole, and of
        // keyframe 2 (culled) only track 7 with its patch.
        for k in 0..800u64 {
            let f: Vec<MapFeature> = (0..500).map(|i| feature(k * 1000 + i)).collect();
            let p = vec![(k * 1000 + 7, [k as u8; 100]), (k * 1000 + 8, [1; 100])];
            log.append(&features_to_pb(k, &f, &p));
        }
        write_all(&mut log);
        let keep = |k: u64| match k {
            2 => Keep::Tracks(BTreeSet::from([2007])),
            k if k % 4 == 0 => Keep::Whole,
            _ => Keep::Nothing,
        };
        let before = log.log.len_bytes().expect("len");
        assert!(before > COMPACT_ABOVE_BYTES);
        let after = log.compact_if_due(keep).expect("compact");
        assert!(after > 0 && after < before / 3, "{after} of {before}");
        assert_eq!(log.log.len_bytes().expect("len"), after);
        assert_eq!(log.compact_if_due(keep).expect("again"), 0);
        log.append(&features_to_pb(800, &[feature(800)], &[]));
        // Patches are read back by offset, before and after a restart.
        let patches = log.patches([2, 8, 9, 800]).expect("patches");
        assert_eq!(patches.keys().copied().collect::<Vec<_>>(), [2, 8]);
        assert_eq!(patches[&2], vec![(2007, [2; 100])]);
        assert_eq!(patches[&8][1], (8008, [1; 100]));
        write_all(&mut log);
        log.sync().expect("sync");
        let (mut back_log, back) = FeaturesLog::open(dir.path()).expect("reopen");
        assert_eq!(back.len(), 202);
        let features = |k: u64| back_log.features_of(k).expect("read").expect("features");
        assert_eq!(features(8).len(), 500);
        assert_eq!(features(8)[3], feature(8003));
        assert_eq!(back[&8], [(8007, 8), (8008, 1)]);
        assert_eq!(features(2), vec![feature(2007)]);
        assert!(back.contains_key(&800) && !back.contains_key(&1));
        assert!(back_log.features_of(1).expect("read").is_none());
        assert_eq!(back_log.patches([8]).expect("patches")[&8], patches[&8]);
        // The sizes read back on opening drive the next compaction as before.
        assert_eq!(back_log.compact_if_due(keep).expect("again"), 0);
    }

    #[test]
    fn patches_past_retention_leave_and_the_features_stay() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (mut log, _) = FeaturesLog::open(dir.path()).expect("open");
        // 700 keyframes of 100 features and 100 patches (~15 KB each, two thirds patches).
        for k in 0..700u64 {
            let f: Vec<MapFeature> = (0..100).map(|i| feature(k * 1000 + i)).collect();
            let p: Vec<(u64, Patch)> = (0..100).map(|i| (k * 1000 + i, [3; 100])).collect();
            log.append(&features_to_pb(k, &f, &p));
        }
        write_all(&mut log);
        let all_whole = |_: u64| Keep::Whole;
        assert_eq!(log.compact_if_due(all_whole).expect("not due"), 0);
        // The oldest half's patches are past retention: the log shrinks by their bytes.
        let keep = |k: u64| if k < 350 { Keep::Features } else { Keep::Whole };
        let before = log.log.len_bytes().expect("len");
        assert!(before > COMPACT_ABOVE_BYTES);
        let after = log.compact_if_due(keep).expect("compact");
        assert!(
            after > 0 && (after as f64) < 0.72 * before as f64,
            "{after} of {before}"
        );
        assert_eq!(log.compact_if_due(keep).expect("again"), 0, "settled");
        log.sync().expect("sync");
        let (mut back, patched) = FeaturesLog::open(dir.path()).expect("reopen");
        assert_eq!(back.features_of(5).expect("read").expect("kept").len(), 100);
        assert!(patched[&5].is_empty(), "no patch left of keyframe 5");
        assert_eq!(patched[&500].len(), 100);
        let patches = back.patches([5, 500]).expect("patches");
        assert_eq!(patches.keys().copied().collect::<Vec<_>>(), [500]);
    }

    #[test]
    fn records_come_back_later_ones_win_and_a_torn_tail_is_dropped() {
        let dir = tempfile::tempdir().expect("tempdir");
        let record = |k: u64, fill: u8| internal::KeyframeFeatures {
            keyframe_id: k,
            track_ids: vec![1, 2],
            descriptors: vec![fill; 64],
            x: vec![1.0, 2.0],
            y: vec![3.0, 4.0],
            patch_track_ids: vec![2],
            patches: vec![fill; 100],
        };
        let (mut log, _) = FeaturesLog::open(dir.path()).expect("open");
        log.append(&record(0, 1));
        write_all(&mut log);
        log.append(&record(1, 2));
        log.append(&record(0, 3));
        write_all(&mut log);
        log.sync().expect("sync");
        let (mut reopened, back) = FeaturesLog::open(dir.path()).expect("read");
        assert_eq!(back.len(), 2);
        let features = reopened.features_of(0).expect("read").expect("features");
        assert_eq!(features[0].descriptor, [3; 32]);
        assert_eq!(
            reopened.patches([1]).expect("patches")[&1],
            vec![(2, [2; 100])]
        );
        // A kill mid-append leaves half a record.
        let path = dir.path().join(FILE_NAME);
        let mut bytes = std::fs::read(&path).expect("bytes");
        bytes.extend_from_slice(&record(2, 4).encode_length_delimited_to_vec()[..20]);
        std::fs::write(&path, &bytes).expect("write");
        assert_eq!(FeaturesLog::open(dir.path()).expect("read").1.len(), 2);
        log.truncate().expect("truncate");
        assert!(FeaturesLog::open(dir.path()).expect("read").1.is_empty());
    }
}
