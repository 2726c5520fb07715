//! The saved-map file: a versioned, checksummed envelope around a protobuf `SavedMap`
//! (proto/egoslam/internal/v1/saved_map.proto, docs/relocalization.md).
//!
//! Protobuf alone would decode many corrupt files into a wrong map without complaint, so the
//! envelope states the format version, the payload length and its checksum, and every value
//! is validated before a map is built: a truncated, corrupt or foreign file is an error that
//! names what is wrong, never a panic or a silently wrong map.

use crate::descriptors::Descriptor;
use crate::patch_alignment::{Patch, PATCH_SIDE};
use crate::relocalizer::{MapFeature, MapKeyframe, RelocalizationMap};
use crate::vocabulary::fnv1a;
use egoslam_geometry::{LensModel, PinholeRadtan, StampedPose};
use egoslam_messages::internal::v1 as internal;
use egoslam_messages::v1 as pb;
use nalgebra::{Point2, Quaternion, UnitQuaternion, Vector3};
use prost::Message;
use std::collections::HashMap;

const MAGIC: &[u8; 8] = b"EGOSLMAP";
/// Format version written by this build (the only one it reads).
pub const MAP_FORMAT_VERSION: u32 = 1;
const HEADER: usize = 8 + 4 + 8 + 8;

/// Why a saved map could not be read.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SavedMapError {
    /// The file does not start with the map magic.
    #[error("not an egoslam map (bad magic)")]
    BadMagic,
    /// Written by a build with another format version.
    #[error("map format version {found}, this build reads {supported}")]
    UnsupportedVersion { found: u32, supported: u32 },
    /// The file is shorter than its header says.
    #[error("map truncated: {needed} bytes needed, {found} present")]
    Truncated { needed: u64, found: u64 },
    /// The payload does not match its checksum.
    #[error("map checksum mismatch (corrupt file)")]
    ChecksumMismatch,
    /// The payload is not a valid SavedMap message.
    #[error("map payload does not decode: {0}")]
    Decode(String),
    /// A value is missing or out of range.
    #[error("invalid map: {0}")]
    Invalid(String),
}

/// The descriptors of a keyframe's tracks, and the patches of those first described in it, as
/// the wire message.
pub fn features_to_pb(
    keyframe_id: u64,
    features: &[MapFeature],
    patches: &[(u64, Patch)],
) -> internal::KeyframeFeatures {
    internal::KeyframeFeatures {
        keyframe_id,
        track_ids: features.iter().map(|f| f.track_id).collect(),
        descriptors: features.iter().flat_map(|f| f.descriptor).collect(),
        x: features.iter().map(|f| f.pixel.x).collect(),
        y: features.iter().map(|f| f.pixel.y).collect(),
        patch_track_ids: patches.iter().map(|(t, _)| *t).collect(),
        patches: patches
            .iter()
            .flat_map(|(_, p)| p.iter().copied())
            .collect(),
    }
}

/// The patches of the wire message; `None` when their bytes do not match their tracks.
pub fn patches_from_pb(m: &internal::KeyframeFeatures) -> Option<Vec<(u64, Patch)>> {
    let side = PATCH_SIDE * PATCH_SIDE;
    if m.patches.len() != side * m.patch_track_ids.len() {
        return None;
    }
    m.patch_track_ids
        .iter()
        .zip(m.patches.chunks_exact(side))
        .map(|(t, bytes)| Some((*t, bytes.try_into().ok()?)))
        .collect()
}

/// The wire message back to features; `None` when its lists disagree in length or a pixel
/// is not finite (a corrupt message).
pub fn features_from_pb(m: &internal::KeyframeFeatures) -> Option<Vec<MapFeature>> {
    let n = m.track_ids.len();
    if m.descriptors.len() != 32 * n || m.x.len() != n || m.y.len() != n {
        return None;
    }
    let mut out = Vec::with_capacity(n);
    for (i, chunk) in m.descriptors.chunks_exact(32).enumerate() {
        let (x, y) = (m.x[i], m.y[i]);
        if !(x.is_finite() && y.is_finite()) {
            return None;
        }
        let descriptor: Descriptor = chunk.try_into().ok()?;
        out.push(MapFeature {
            track_id: m.track_ids[i],
            descriptor,
            pixel: Point2::new(x, y),
        });
    }
    Some(out)
}

fn vec3(v: &Vector3<f64>) -> pb::Vec3 {
    pb::Vec3 {
        x: v.x,
        y: v.y,
        z: v.z,
    }
}

/// A lens model as the wire carries it.
pub fn lens_to_pb(lens: LensModel) -> pb::LensModel {
    match lens {
        LensModel::RadialTangential => pb::LensModel::RadialTangential,
        LensModel::Equidistant => pb::LensModel::Equidistant,
        LensModel::DoubleSphere => pb::LensModel::DoubleSphere,
    }
}

/// A camera as the wire carries it.
pub fn intrinsics_to_pb(camera: &PinholeRadtan) -> pb::Intrinsics {
    pb::Intrinsics {
        width: camera.width,
        height: camera.height,
        fx: camera.fx,
        fy: camera.fy,
        cx: camera.cx,
        cy: camera.cy,
        distortion: camera.distortion.to_vec(),
        lens: lens_to_pb(camera.lens) as i32,
    }
}

/// The lens model of a wire value; `None` for one this version does not know.
pub fn lens_from_pb(value: i32) -> Option<LensModel> {
    match pb::LensModel::try_from(value).ok()? {
        pb::LensModel::RadialTangential => Some(LensModel::RadialTangential),
        pb::LensModel::Equidistant => Some(LensModel::Equidistant),
        pb::LensModel::DoubleSphere => Some(LensModel::DoubleSphere),
    }
}

/// The file bytes of a map (`vocabulary_id`: [`crate::Vocabulary::id`] of the vocabulary
/// its descriptors are meant for; `source`: the input it was built from).
pub fn encode_map(map: &RelocalizationMap, vocabulary_id: u64, source: &str) -> Vec<u8> {
    let c = &map.camera;
    let message = internal::SavedMap {
        // The lens model the map's keyframes were undistorted with: what a query from the
        // same camera needs, including a radial term `egoslam run` self-calibrated.
        camera: Some(intrinsics_to_pb(c)),
        vocabulary_id,
        source: source.to_string(),
        rolling_shutter_s: map.rolling_shutter_s,
        keyframes: map
            .keyframes
            .iter()
            .map(|k| internal::SavedKeyframe {
                keyframe_id: k.keyframe_id,
                segment_id: k.segment,
                pose: Some(pb::Pose {
                    timestamp_s: k.pose.timestamp,
                    position: Some(vec3(&k.pose.position)),
                    orientation: Some(pb::Quaternion {
                        x: k.pose.rotation.i,
                        y: k.pose.rotation.j,
                        z: k.pose.rotation.k,
                        w: k.pose.rotation.w,
                    }),
                    segment_id: k.segment,
                    ..Default::default()
                }),
                features: Some(features_to_pb(k.keyframe_id, &k.features, &k.patches)),
            })
            .collect(),
        points: {
            let mut points: Vec<_> = map.points.iter().collect();
            points.sort_by_key(|(t, _)| **t);
            points
                .into_iter()
                .map(|(t, (segment, x))| internal::CheckpointPoint {
                    track_id: *t,
                    segment_id: *segment,
                    position: Some(vec3(x)),
                })
                .collect()
        },
    };
    let payload = message.encode_to_vec();
    let mut out = Vec::with_capacity(HEADER + payload.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&MAP_FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    out.extend_from_slice(&fnv1a(&payload).to_le_bytes());
    out.extend_from_slice(&payload);
    out
}

fn finite3(v: Option<&pb::Vec3>, what: &str) -> Result<Vector3<f64>, SavedMapError> {
    let v = v.ok_or_else(|| SavedMapError::Invalid(format!("{what}: missing position")))?;
    let x = Vector3::new(v.x, v.y, v.z);
    if x.iter().all(|c| c.is_finite()) {
        Ok(x)
    } else {
        Err(SavedMapError::Invalid(format!(
            "{what}: position not finite"
        )))
    }
}

/// A map and the vocabulary id it names, from file bytes.
pub fn decode_map(bytes: &[u8]) -> Result<(RelocalizationMap, u64), SavedMapError> {
    if bytes.len() < 8 || &bytes[..8] != MAGIC {
        return Err(SavedMapError::BadMagic);
    }
    if bytes.len() < HEADER {
        return Err(SavedMapError::Truncated {
            needed: HEADER as u64,
            found: bytes.len() as u64,
        });
    }
    let u64_at = |i: usize| u64::from_le_bytes(bytes[i..i + 8].try_into().unwrap_or([0; 8]));
    let version = u32::from_le_bytes(bytes[8..12].try_into().unwrap_or([0; 4]));
    if version != MAP_FORMAT_VERSION {
        return Err(SavedMapError::UnsupportedVersion {
            found: version,
            supported: MAP_FORMAT_VERSION,
        });
    }
    let length = u64_at(12);
    let needed = length.saturating_add(HEADER as u64);
    if (bytes.len() as u64) < needed {
        return Err(SavedMapError::Truncated {
            needed,
            found: bytes.len() as u64,
        });
    }
    let payload = &bytes[HEADER..needed as usize];
    if fnv1a(payload) != u64_at(20) {
        return Err(SavedMapError::ChecksumMismatch);
    }
    let message =
        internal::SavedMap::decode(payload).map_err(|e| SavedMapError::Decode(e.to_string()))?;
    let c = message
        .camera
        .ok_or_else(|| SavedMapError::Invalid("no camera".into()))?;
    // Maps written before the distortion was recorded carry none.
    let distortion: [f64; 5] = match c.distortion.as_slice() {
        [] => [0.0; 5],
        d => d.try_into().map_err(|_| {
            SavedMapError::Invalid(format!("camera: {} distortion terms, not 5", d.len()))
        })?,
    };
    let lens = lens_from_pb(c.lens).ok_or_else(|| {
        SavedMapError::Invalid(format!(
            "camera: lens model {} unknown to this version",
            c.lens
        ))
    })?;
    let camera = PinholeRadtan::new(c.width, c.height, [c.fx, c.fy, c.cx, c.cy], distortion)
        .and_then(|camera| camera.with_lens(lens))
        .map_err(|e| SavedMapError::Invalid(format!("camera: {e}")))?;
    let readout_s = message.rolling_shutter_s;
    if !(0.0..=0.1).contains(&readout_s) {
        return Err(SavedMapError::Invalid(format!(
            "rolling-shutter readout {readout_s} s"
        )));
    }
    let mut points = HashMap::with_capacity(message.points.len());
    for p in &message.points {
        let x = finite3(p.position.as_ref(), &format!("point {}", p.track_id))?;
        points.insert(p.track_id, (p.segment_id, x));
    }
    let mut keyframes = Vec::with_capacity(message.keyframes.len());
    for k in &message.keyframes {
        let what = format!("keyframe {}", k.keyframe_id);
        let pose = k
            .pose
            .as_ref()
            .ok_or_else(|| SavedMapError::Invalid(format!("{what}: no pose")))?;
        let q = pose
            .orientation
            .as_ref()
            .ok_or_else(|| SavedMapError::Invalid(format!("{what}: no orientation")))?;
        let quaternion = Quaternion::new(q.w, q.x, q.y, q.z);
        if !(quaternion.coords.iter().all(|v| v.is_finite()) && quaternion.norm() > 0.5) {
            return Err(SavedMapError::Invalid(format!("{what}: bad orientation")));
        }
        let inconsistent = || SavedMapError::Invalid(format!("{what}: inconsistent features"));
        let (features, patches) = match &k.features {
            Some(f) => (
                features_from_pb(f).ok_or_else(inconsistent)?,
                patches_from_pb(f).ok_or_else(inconsistent)?,
            ),
            None => (Vec::new(), Vec::new()),
        };
        keyframes.push(MapKeyframe {
            keyframe_id: k.keyframe_id,
            segment: k.segment_id,
            pose: StampedPose {
                timestamp: pose.timestamp_s,
                position: finite3(pose.position.as_ref(), &what)?,
                rotation: UnitQuaternion::from_quaternion(quaternion),
            },
            features,
            patches,
        });
    }
    Ok((
        RelocalizationMap {
            camera,
            keyframes,
            points,
            rolling_shutter_s: readout_s,
        },
        message.vocabulary_id,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small_map() -> RelocalizationMap {
        let camera = PinholeRadtan::new(
            640,
            480,
            [500.0, 500.0, 320.0, 240.0],
            [0.0135, 0.0, 0.0, 0.0, 0.0],
        )
        .expect("camera");
        let keyframes = (0..3u64)
            .map(|k| MapKeyframe {
                keyframe_id: k,
                segment: 0,
                pose: StampedPose {
                    timestamp: k as f64 * 0.1,
                    position: Vector3::new(k as f64, 0.0, 0.0),
                    rotation: UnitQuaternion::from_euler_angles(0.1 * k as f64, 0.0, 0.0),
                },
                features: (0..4u64)
                    .map(|t| MapFeature {
                        track_id: t,
                        descriptor: [t as u8 + k as u8; 32],
                        pixel: Point2::new(10.0 * t as f32, 5.0),
                    })
                    .collect(),
                patches: vec![(k, [k as u8 + 7; PATCH_SIDE * PATCH_SIDE])],
            })
            .collect();
        let points = (0..4u64)
            .map(|t| (t, (0, Vector3::new(t as f64, 1.0, 5.0))))
            .collect();
        RelocalizationMap {
            camera,
            keyframes,
            points,
            rolling_shutter_s: 0.021,
        }
    }

    #[test]
    fn a_map_round_trips_and_damaged_files_are_refused_by_name() {
        let map = small_map();
        let bytes = encode_map(&map, 42, "test");
        let (back, vocabulary) = decode_map(&bytes).expect("decode");
        assert_eq!(vocabulary, 42);
        assert_eq!(back.camera, map.camera, "the lens model too");
        assert_eq!(back.keyframes.len(), 3);
        assert_eq!(back.points, map.points);
        assert_eq!(back.keyframes[2].features, map.keyframes[2].features);
        assert_eq!(back.keyframes[2].patches, map.keyframes[2].patches);
        assert!((back.keyframes[2].pose.position - map.keyframes[2].pose.position).norm() < 1e-12);

        assert_eq!(decode_map(b"GIF89a"), Err(SavedMapError::BadMagic));
        // Every truncation is refused with a named reason (header or payload).
        for cut in [8, 12, 20, HEADER, bytes.len() / 2, bytes.len() - 1] {
            assert!(
                matches!(
                    decode_map(&bytes[..cut]),
                    Err(SavedMapError::Truncated { .. })
                ),
                "cut at {cut}"
            );
        }
        let mut corrupt = bytes.clone();
        let last = corrupt.len() - 10;
        corrupt[last] ^= 0x40;
        assert_eq!(decode_map(&corrupt), Err(SavedMapError::ChecksumMismatch));
        let mut newer = bytes.clone();
        newer[8] = 9;
        assert_eq!(
            decode_map(&newer),
            Err(SavedMapError::UnsupportedVersion {
                found: 9,
                supported: 1
            })
        );
        // A length field claiming more than the file holds (no allocation from it).
        let mut huge = bytes.clone();
        huge[12..20].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(matches!(
            decode_map(&huge),
            Err(SavedMapError::Truncated { .. })
        ));
    }
}
