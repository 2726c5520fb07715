//! map.ply: the map's points as a binary little-endian PLY (ply-rs-bw), with per point its
//! grey level from the images, the keyframes that see it and its relative standard
//! deviation (docs/merger.md, "Published points"). MeshLab, CloudCompare, Open3D and
//! Blender read it; the extra properties are ignored by viewers that do not know them.

use crate::ExportError;
use ply_rs_bw::ply::{
    Addable, ElementDef, Encoding, Ply, PropertyAccess, PropertyAccessResult, PropertyDef,
    PropertyType, ScalarType,
};
use std::path::Path;

/// One point of map.ply.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapPlyPoint {
    pub position: [f32; 3],
    /// RGB (a grey level from the grey frames the pipeline tracks: r = g = b).
    pub colour: [u8; 3],
    /// Keyframes with an inlier observation of the point.
    pub views: u32,
    /// Standard deviation over the distance to the nearest viewing keyframe; NaN when the
    /// views do not fix the point.
    pub relative_std: f32,
}

impl PropertyAccess for MapPlyPoint {
    fn new() -> Self {
        Self {
            position: [0.0; 3],
            colour: [0; 3],
            views: 0,
            relative_std: f32::NAN,
        }
    }

    fn set_float(&mut self, name: &str, value: f32) -> PropertyAccessResult {
        match name {
            "x" => self.position[0] = value,
            "y" => self.position[1] = value,
            "z" => self.position[2] = value,
            "relative_std" => self.relative_std = value,
            _ => return PropertyAccessResult::Ignored,
        }
        PropertyAccessResult::Set
    }

    fn set_uchar(&mut self, name: &str, value: u8) -> PropertyAccessResult {
        match name {
            "red" => self.colour[0] = value,
            "green" => self.colour[1] = value,
            "blue" => self.colour[2] = value,
            _ => return PropertyAccessResult::Ignored,
        }
        PropertyAccessResult::Set
    }

    fn set_uint(&mut self, name: &str, value: u32) -> PropertyAccessResult {
        if name != "views" {
            return PropertyAccessResult::Ignored;
        }
        self.views = value;
        PropertyAccessResult::Set
    }

    fn get_float(&self, name: &str) -> Option<f32> {
        match name {
            "x" => Some(self.position[0]),
            "y" => Some(self.position[1]),
            "z" => Some(self.position[2]),
            "relative_std" => Some(self.relative_std),
            _ => None,
        }
    }

    fn get_uchar(&self, name: &str) -> Option<u8> {
        match name {
            "red" => Some(self.colour[0]),
            "green" => Some(self.colour[1]),
            "blue" => Some(self.colour[2]),
            _ => None,
        }
    }

    fn get_uint(&self, name: &str) -> Option<u32> {
        (name == "views").then_some(self.views)
    }
}

/// The points as PLY bytes (binary little-endian).
pub fn to_bytes(points: Vec<MapPlyPoint>, comment: &str) -> Result<Vec<u8>, ExportError> {
    let mut ply = Ply::<MapPlyPoint>::new();
    ply.header.encoding = Encoding::BinaryLittleEndian;
    ply.header.comments.push(comment.to_string());
    let mut vertex = ElementDef::new("vertex".to_string());
    let scalar =
        |name: &str, t: ScalarType| PropertyDef::new(name.to_string(), PropertyType::Scalar(t));
    for name in ["x", "y", "z"] {
        vertex.properties.add(scalar(name, ScalarType::Float));
    }
    for name in ["red", "green", "blue"] {
        vertex.properties.add(scalar(name, ScalarType::UChar));
    }
    vertex.properties.add(scalar("views", ScalarType::UInt));
    vertex
        .properties
        .add(scalar("relative_std", ScalarType::Float));
    ply.header.elements.add(vertex);
    ply.payload.insert("vertex".to_string(), points);
    let mut bytes = Vec::new();
    ply_rs_bw::writer::Writer::new()
        .write_ply(&mut bytes, &mut ply)
        .map_err(|source| ExportError::Write {
            path: "map.ply".into(),
            source,
        })?;
    Ok(bytes)
}

/// The points of a map.ply (binary or ASCII; properties it lacks keep their defaults).
pub fn read(path: &Path) -> Result<Vec<MapPlyPoint>, ExportError> {
    let read_error = |source: std::io::Error| ExportError::Read {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::open(path).map_err(read_error)?;
    let mut reader = std::io::BufReader::new(file);
    let ply = ply_rs_bw::parser::Parser::<MapPlyPoint>::new()
        .read_ply(&mut reader)
        .map_err(|e| {
            read_error(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                e.to_string(),
            ))
        })?;
    Ok(ply.payload.get("vertex").cloned().unwrap_or_default())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_are_written_in_binary_and_read_back() {
        let points = vec![
            MapPlyPoint {
                position: [1.5, -2.0, 3.25],
                colour: [200, 200, 200],
                views: 4,
                relative_std: 0.01,
            },
            MapPlyPoint {
                position: [0.0, 0.5, -1.0],
                colour: [7, 7, 7],
                views: 2,
                relative_std: f32::NAN,
            },
        ];
        let bytes = to_bytes(points.clone(), "egoslam map points").expect("bytes");
        let header_end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .expect("header");
        let header = String::from_utf8_lossy(&bytes[..header_end]);
        assert!(
            header.contains("format binary_little_endian 1.0"),
            "{header}"
        );
        assert!(header.contains("element vertex 2"), "{header}");
        assert_eq!(bytes.len() - header_end - 11, 2 * (12 + 3 + 4 + 4));
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("map.ply");
        std::fs::write(&path, &bytes).expect("write");
        let back = read(&path).expect("read");
        assert_eq!(back[0], points[0]);
        assert_eq!(back[1].position, points[1].position);
        assert!(back[1].relative_std.is_nan());
    }

    #[test]
    fn an_ascii_ply_of_positions_reads_too() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("old.ply");
        std::fs::write(
            &path,
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n",
        )
        .expect("write");
        let back = read(&path).expect("read");
        assert_eq!(back.len(), 1);
        assert_eq!(back[0].position, [1.0, 2.0, 3.0]);
    }
}
