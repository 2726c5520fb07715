//! Reading and writing saved maps and vocabularies (the file side of
//! egoslam_relocalization::saved_map; format in docs/relocalization.md).

use crate::write_atomically;
use egoslam_geometry::PinholeRadtan;
use egoslam_merger::KeyframeFeatureSource;
use egoslam_merger::MergerState;
use egoslam_relocalization::patch_alignment::Patch;
use egoslam_relocalization::MapFeature;
use egoslam_relocalization::{
    decode_map, default_vocabulary, encode_map, MapKeyframe, RelocalizationMap, Vocabulary,
};
use egoslam_relocalization::{SavedMapError, VocabularyError};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

/// Why a map or vocabulary file could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum MapFileError {
    #[error("{what} {}: cannot be read", path.display())]
    Read {
        what: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{what} {}: not a file", path.display())]
    NotAFile { what: &'static str, path: PathBuf },
    #[error("{what} {}: {bytes} bytes, more than the {MAX_FILE_BYTES} accepted", path.display())]
    TooLarge {
        what: &'static str,
        path: PathBuf,
        bytes: u64,
    },
    #[error("vocabulary {}", path.display())]
    Vocabulary {
        path: PathBuf,
        #[source]
        source: VocabularyError,
    },
    #[error("the built-in vocabulary")]
    BuiltInVocabulary(#[source] VocabularyError),
    #[error("map {}", path.display())]
    Map {
        path: PathBuf,
        #[source]
        source: SavedMapError,
    },
    #[error(
        "map {} was built for vocabulary {map:016x}, not {given:016x} (pass the same --vocabulary as the run that saved it)",
        path.display()
    )]
    OtherVocabulary { path: PathBuf, map: u64, given: u64 },
    #[error("map {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: crate::DurabilityError,
    },
}

/// Largest map or vocabulary file read (a bound on what is read from outside: 4 GiB holds
/// ~100,000 keyframes with their descriptors).
const MAX_FILE_BYTES: u64 = 4 << 30;

fn read_bounded(path: &Path, what: &'static str) -> Result<Vec<u8>, MapFileError> {
    let read = |source| MapFileError::Read {
        what,
        path: path.to_path_buf(),
        source,
    };
    let meta = std::fs::metadata(path).map_err(read)?;
    if !meta.is_file() {
        return Err(MapFileError::NotAFile {
            what,
            path: path.to_path_buf(),
        });
    }
    if meta.len() > MAX_FILE_BYTES {
        return Err(MapFileError::TooLarge {
            what,
            path: path.to_path_buf(),
            bytes: meta.len(),
        });
    }
    std::fs::read(path).map_err(read)
}

/// The vocabulary at `path`, or the built-in one.
pub fn load_vocabulary(path: Option<&Path>) -> Result<Vocabulary, MapFileError> {
    match path {
        Some(p) => Vocabulary::from_bytes(&read_bounded(p, "vocabulary")?).map_err(|source| {
            MapFileError::Vocabulary {
                path: p.to_path_buf(),
                source,
            }
        }),
        None => default_vocabulary().map_err(MapFileError::BuiltInVocabulary),
    }
}

/// The relocalization map of the merger's state: every keyframe of the map with its
/// described tracks (read from `features`), the points, the `patches` of their tracks, and
/// the rolling-shutter readout its frames were corrected for (`rolling_shutter_s`, 0 when
/// a global shutter or not known).
pub fn relocalization_map(
    state: &MergerState,
    features: &dyn KeyframeFeatureSource,
    patches: &BTreeMap<u64, Vec<(u64, Patch)>>,
    camera: &PinholeRadtan,
    rolling_shutter_s: f64,
) -> RelocalizationMap {
    let points: HashMap<u64, (u32, nalgebra::Vector3<f64>)> = state
        .map
        .points()
        .map(|(track, segment, x)| (track, (segment, *x)))
        .collect();
    // Culled keyframes keep the patches of their points (merger/keyframe_culling.rs), at
    // the pose their frame keeps, with those tracks' features.
    let frame_poses = egoslam_merger::session::frames::frame_poses(&state.map, &state.frames, ..);
    let culled = state
        .patched_tracks
        .iter()
        .filter(|(id, _)| state.map.keyframe(**id).is_none())
        .filter_map(|(id, patched)| {
            let frame = state.frames.keyframe_frames.get(id)?;
            let (segment, pose) = frame_poses.get(frame)?;
            Some(MapKeyframe {
                keyframe_id: *id,
                segment: *segment,
                pose: *pose,
                features: patched_features(features.features(*id)?, patched),
                patches: Vec::new(),
            })
        });
    let mut keyframes: Vec<MapKeyframe> = state
        .map
        .keyframes()
        .map(|(id, segment, pose)| MapKeyframe {
            keyframe_id: id,
            segment,
            pose: *pose,
            // Every described track: all of them make the keyframe's bag of words, those
            // that are points give the matches.
            features: features.features(id).unwrap_or_default(),
            patches: Vec::new(),
        })
        .chain(culled)
        .collect();
    keyframes.sort_by_key(|k| k.keyframe_id);
    for k in &mut keyframes {
        // Only for points: the other tracks' patches are never looked up.
        if let Some(patches) = patches.get(&k.keyframe_id) {
            k.patches = patches
                .iter()
                .filter(|(track, _)| points.contains_key(track))
                .copied()
                .collect();
        }
    }
    RelocalizationMap {
        camera: *camera,
        keyframes,
        points,
        rolling_shutter_s,
    }
}

/// Those of a culled keyframe's `features` whose tracks it keeps a patch of: what the saved
/// relocalization map needs of it.
fn patched_features(features: Vec<MapFeature>, patched_tracks: &[(u64, u8)]) -> Vec<MapFeature> {
    let patched: std::collections::BTreeSet<u64> = patched_tracks.iter().map(|(t, _)| *t).collect();
    features
        .into_iter()
        .filter(|f| patched.contains(&f.track_id))
        .collect()
}

/// Writes the map file atomically.
pub fn write_map(
    path: &Path,
    map: &RelocalizationMap,
    vocabulary: &Vocabulary,
    source: &str,
) -> Result<(), MapFileError> {
    let bytes = encode_map(map, vocabulary.id(), source);
    write_atomically(path, &bytes).map_err(|source| MapFileError::Write {
        path: path.to_path_buf(),
        source,
    })?;
    tracing::info!(
        path = %path.display(),
        keyframes = map.keyframes.len(),
        points = map.points.len(),
        bytes = bytes.len(),
        "map saved"
    );
    Ok(())
}

/// The first keyframe and track id free above those of the map file at `path` (the file's
/// vocabulary is not checked: the merger reads it with its own).
pub fn next_free_id(path: &Path) -> Result<u64, MapFileError> {
    let (map, _) = decode(path)?;
    Ok(egoslam_merger::next_free_id(&map))
}

/// Makes the saved `map` the start of `state`'s map (egoslam_merger::base_map): its
/// keyframes and points; returns each keyframe's descriptors and patches, which belong in
/// the features log. Its keyframes are never culled: they are the map being extended.
pub fn extend_state(state: &mut MergerState, map: RelocalizationMap) -> Vec<MapKeyframe> {
    state.map = egoslam_merger::MapBuilder::from_parts(egoslam_merger::MapParts::from_saved(&map));
    state.culling_checked_before = egoslam_merger::next_free_id(&map);
    for k in &map.keyframes {
        if !k.patches.is_empty() {
            let tracks = crate::features_log::patched_tracks(&k.patches);
            state.patched_tracks.insert(k.keyframe_id, tracks);
        }
    }
    map.keyframes
}

/// The map in the file at `path` and the id of the vocabulary it was made for.
fn decode(path: &Path) -> Result<(RelocalizationMap, u64), MapFileError> {
    let bytes = read_bounded(path, "map")?;
    decode_map(&bytes).map_err(|source| MapFileError::Map {
        path: path.to_path_buf(),
        source,
    })
}

/// Reads a map file and checks that it was made for `vocabulary`.
pub fn read_map(path: &Path, vocabulary: &Vocabulary) -> Result<RelocalizationMap, MapFileError> {
    let (map, vocabulary_id) = decode(path)?;
    if vocabulary_id != vocabulary.id() {
        return Err(MapFileError::OtherVocabulary {
            path: path.to_path_buf(),
            map: vocabulary_id,
            given: vocabulary.id(),
        });
    }
    Ok(map)
}
