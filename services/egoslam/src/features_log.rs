//! The merger's keyframe descriptors (and new tracks' patches) on disk: an append-only log of length-delimited
//! `KeyframeFeatures` messages beside the checkpoint (docs/durability.md).
//!
//! Descriptors are most of the map's bytes (~40 KB per keyframe). Inside the checkpoint,
//! which is rewritten whole, they made a 12,000-frame walk write 363 MB every 5 s (103 s of
//! its run); appended once each, they cost O(new keyframes). The log is flushed and synced
//! before every checkpoint, so it always covers the windows the checkpoint has applied; a
//! torn record at its end (a kill mid-append) is ignored, and the windows after the
//! checkpoint are re-applied from the solver's journal, which re-appends their features.

use crate::record_log::{read_records, RecordLog};
use egoslam_messages::v1 as pb;
use egoslam_relocalization::patch_alignment::Patch;
use egoslam_relocalization::saved_map::{features_from_pb, features_to_pb, patches_from_pb};
use egoslam_relocalization::MapFeature;
use prost::Message;
use std::collections::BTreeMap;
use std::path::Path;

/// File name in the output folder.
pub const FILE_NAME: &str = "keyframe_features.log";

/// Opens `dir/keyframe_features.log` for appending (created if absent).
pub fn open(dir: &Path) -> anyhow::Result<RecordLog> {
    RecordLog::open(&dir.join(FILE_NAME))
}

/// Rewrites the log with the records of `features` (each map of them; and their `patches`) alone when it
/// holds more than 1.5 times their size and at least [`COMPACT_ABOVE_BYTES`]: culled keyframes'
/// records go, so the log grows with the map, not with the time walked. Returns the bytes
/// written (0 when not due). Call it before a checkpoint: the log must cover every keyframe
/// the checkpoint holds, and the windows after it re-append theirs when replayed.
pub fn compact_if_due<const N: usize>(
    log: &mut RecordLog,
    features: [&BTreeMap<u64, Vec<MapFeature>>; N],
    patches: &BTreeMap<u64, Vec<(u64, Patch)>>,
) -> anyhow::Result<u64> {
    let size = log.len_bytes()?;
    if size < COMPACT_ABOVE_BYTES {
        return Ok(0);
    }
    let records: Vec<pb::KeyframeFeatures> = features
        .iter()
        .flat_map(|f| f.iter())
        .map(|(k, f)| features_to_pb(*k, f, patches.get(k).map_or(&[], Vec::as_slice)))
        .collect();
    let live: u64 = crate::record_log::HEADER_LEN
        + records
            .iter()
            .map(|r| (prost::length_delimiter_len(r.encoded_len()) + r.encoded_len()) as u64)
            .sum::<u64>();
    if 2 * size <= 3 * live {
        return Ok(0);
    }
    log.replace_with(&records)?;
    tracing::info!(
        before = size,
        after = live,
        "keyframe features log compacted"
    );
    Ok(live)
}

/// Logs smaller than this are left as they are (8 MiB: ~200 keyframes).
pub const COMPACT_ABOVE_BYTES: u64 = 8 << 20;

/// Features (keyframe -> described tracks) and patches (keyframe -> tracks first described in
/// it) of the log at `dir`, later records replacing earlier ones.
pub type Descriptions = (
    BTreeMap<u64, Vec<MapFeature>>,
    BTreeMap<u64, Vec<(u64, Patch)>>,
);

/// The features and patches in the log at `dir`.
pub fn read(dir: &Path) -> anyhow::Result<Descriptions> {
    let (mut features, mut patches) = (BTreeMap::new(), BTreeMap::new());
    for r in read_records::<pb::KeyframeFeatures>(&dir.join(FILE_NAME))? {
        match features_from_pb(&r).zip(patches_from_pb(&r)) {
            Some((f, p)) => {
                features.insert(r.keyframe_id, f);
                patches.insert(r.keyframe_id, p);
            }
            None => tracing::warn!(
                keyframe = r.keyframe_id,
                "inconsistent features in the log skipped"
            ),
        }
    }
    Ok((features, patches))
}

#[cfg(test)]
mod tests {
    use super::*;
    use prost::Message;

    #[test]
    fn compaction_keeps_the_live_keyframes_once_and_appending_goes_on() {
        let dir = tempfile::tempdir().expect("tempdir");
        let feature = |k: u64| MapFeature {
            track_id: k,
            descriptor: [k as u8; 32],
            pixel: nalgebra::Point2::new(1.0, 2.0),
        };
        let mut log = open(dir.path()).expect("open");
        // 800 keyframes of 500 features (~21 KB each), of which 200 stay.
        let mut features = BTreeMap::new();
        let mut patches = BTreeMap::new();
        for k in 0..800u64 {
            let f: Vec<MapFeature> = (0..500).map(|_| feature(k)).collect();
            let p = vec![(k, [k as u8; 100])];
            log.append(&features_to_pb(k, &f, &p)).expect("append");
            if k % 4 == 0 {
                features.insert(k, f);
                patches.insert(k, p);
            }
        }
        let before = log.len_bytes().expect("len");
        assert!(before > COMPACT_ABOVE_BYTES);
        let after = compact_if_due(&mut log, [&features], &patches).expect("compact");
        assert!(after > 0 && after < before / 3, "{after} of {before}");
        assert_eq!(log.len_bytes().expect("len"), after);
        assert_eq!(
            compact_if_due(&mut log, [&features], &patches).expect("again"),
            0
        );
        log.append(&features_to_pb(800, &[feature(800)], &[]))
            .expect("append");
        log.sync().expect("sync");
        let (back, back_patches) = read(dir.path()).expect("read");
        assert_eq!(back.len(), 201);
        assert_eq!(back[&8], features[&8]);
        assert_eq!(back_patches[&8], patches[&8]);
        assert!(back.contains_key(&800) && !back.contains_key(&1));
    }

    #[test]
    fn records_come_back_later_ones_win_and_a_torn_tail_is_dropped() {
        let dir = tempfile::tempdir().expect("tempdir");
        let record = |k: u64, fill: u8| pb::KeyframeFeatures {
            keyframe_id: k,
            track_ids: vec![1, 2],
            descriptors: vec![fill; 64],
            x: vec![1.0, 2.0],
            y: vec![3.0, 4.0],
            patch_track_ids: vec![2],
            patches: vec![fill; 100],
        };
        let mut log = open(dir.path()).expect("open");
        log.append(&record(0, 1)).expect("append");
        log.append(&record(1, 2)).expect("append");
        log.append(&record(0, 3)).expect("append");
        log.sync().expect("sync");
        let (back, patches) = read(dir.path()).expect("read");
        assert_eq!(back.len(), 2);
        assert_eq!(back[&0][0].descriptor, [3; 32]);
        assert_eq!(patches[&1], vec![(2, [2; 100])]);
        // A kill mid-append leaves half a record.
        let path = dir.path().join(FILE_NAME);
        let mut bytes = std::fs::read(&path).expect("bytes");
        bytes.extend_from_slice(&record(2, 4).encode_length_delimited_to_vec()[..20]);
        std::fs::write(&path, &bytes).expect("write");
        assert_eq!(read(dir.path()).expect("read").0.len(), 2);
        log.truncate().expect("truncate");
        assert!(read(dir.path()).expect("read").0.is_empty());
    }
}
