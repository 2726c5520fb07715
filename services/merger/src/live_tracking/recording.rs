//! A text record of what the live tracker was given, one line per input in the order the
//! tracker took them (a map, the first frame of a stream, a frame), so that a real-time run's
//! live poses can be replayed exactly offline (`EGOSLAM_DUMP_LIVE=FILE egoslam run ...`,
//! then `cargo run --release -p egoslam-merger --example live_replay FILE`). In a real-time
//! run the maps arrive when the solver and merger are done with them, which no offline run
//! reproduces; the record keeps that order.
//!
//! Lines (whitespace-separated numbers): `M segment pace fx fy cx cy width height t x y z
//! qx qy qz qw n` then `n` times `id x y z` (a map: its newest keyframe's pose, `pace` NaN
//! when unknown); `O segment t fx fy cx cy width height n` then `n` times `id u v` (a
//! stream's first frame); `F t n` then `n` times `id u v` (a frame). Only the pinhole
//! intrinsics are kept: the tracker works on undistorted positions.

use super::{FrameTracks, MapView};
use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::{Point2, Quaternion, UnitQuaternion, Vector3};
use std::fmt::Write;

/// One recorded input of the tracker.
#[derive(Debug, Clone)]
pub enum Recorded {
    Map(MapView),
    Origin {
        segment: u32,
        camera: PinholeRadtan,
        timestamp: f64,
        tracks: FrameTracks,
    },
    Frame {
        timestamp: f64,
        tracks: FrameTracks,
    },
}

/// Why a line is not a record.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RecordingError {
    #[error("line {line}: {reason}")]
    Malformed { line: usize, reason: String },
}

fn write_camera(out: &mut String, c: &PinholeRadtan) {
    let _ = write!(
        out,
        " {} {} {} {} {} {}",
        c.fx, c.fy, c.cx, c.cy, c.width, c.height
    );
}

fn write_tracks(out: &mut String, tracks: &[(u64, Point2<f64>)]) {
    let _ = write!(out, " {}", tracks.len());
    for (id, px) in tracks {
        let _ = write!(out, " {id} {} {}", px.x, px.y);
    }
}

/// The line of a map view; `None` without a camera or a keyframe (the tracker ignores it).
pub fn map_line(view: &MapView) -> Option<String> {
    let (camera, k) = (view.camera?, view.newest_keyframe?);
    let mut out = format!("M {} {}", view.segment, view.pace.unwrap_or(f64::NAN));
    write_camera(&mut out, &camera);
    let q = k.rotation.coords;
    let p = k.position;
    let _ = write!(
        out,
        " {} {} {} {} {} {} {} {} {}",
        k.timestamp,
        p.x,
        p.y,
        p.z,
        q.x,
        q.y,
        q.z,
        q.w,
        view.points.len()
    );
    // Track order, so that two records of one run compare equal.
    let mut points: Vec<_> = view.points.iter().collect();
    points.sort_by_key(|(id, _)| **id);
    for (id, x) in points {
        let _ = write!(out, " {id} {} {} {}", x.x, x.y, x.z);
    }
    Some(out)
}

/// The line of a stream's first frame.
pub fn origin_line(
    segment: u32,
    camera: &PinholeRadtan,
    timestamp: f64,
    tracks: &[(u64, Point2<f64>)],
) -> String {
    let mut out = format!("O {segment} {timestamp}");
    write_camera(&mut out, camera);
    write_tracks(&mut out, tracks);
    out
}

/// The line of a frame.
pub fn frame_line(timestamp: f64, tracks: &[(u64, Point2<f64>)]) -> String {
    let mut out = format!("F {timestamp}");
    write_tracks(&mut out, tracks);
    out
}

/// Field `i` of a record's `fields` read as a `T` (`what` it is, for the error).
fn parse_field<T: std::str::FromStr>(
    fields: &[&str],
    i: usize,
    what: &str,
    line: usize,
) -> Result<T, RecordingError> {
    let reason = match fields.get(i) {
        Some(field) => match field.parse() {
            Ok(value) => return Ok(value),
            Err(_) => format!("field {i} is not {what}"),
        },
        None => format!("field {i} ({what}) missing"),
    };
    Err(RecordingError::Malformed { line, reason })
}

/// Reads the record on line `line` (numbered for the error only).
pub fn parse_line(text: &str, line: usize) -> Result<Recorded, RecordingError> {
    let malformed = |reason: &str| RecordingError::Malformed {
        line,
        reason: reason.to_string(),
    };
    let fields: Vec<&str> = text.split_whitespace().collect();
    let number = |i: usize| parse_field::<f64>(&fields, i, "a number", line);
    let id = |i: usize| parse_field::<u64>(&fields, i, "a track id", line);
    let count = |i: usize| parse_field::<usize>(&fields, i, "a count", line);
    let small = |i: usize| parse_field::<u32>(&fields, i, "a segment or an image size", line);
    let camera = |i: usize| -> Result<PinholeRadtan, RecordingError> {
        PinholeRadtan::new(
            small(i + 4)?,
            small(i + 5)?,
            [number(i)?, number(i + 1)?, number(i + 2)?, number(i + 3)?],
            [0.0; 5],
        )
        .map_err(|e| malformed(&e.to_string()))
    };
    let tracks = |i: usize| -> Result<FrameTracks, RecordingError> {
        (0..count(i)?)
            .map(|k| {
                let j = i + 1 + 3 * k;
                Ok((id(j)?, Point2::new(number(j + 1)?, number(j + 2)?)))
            })
            .collect()
    };
    match fields.first() {
        Some(&"M") => {
            let pace = number(2)?;
            let newest_keyframe = StampedPose {
                timestamp: number(9)?,
                position: Vector3::new(number(10)?, number(11)?, number(12)?),
                rotation: UnitQuaternion::from_quaternion(Quaternion::new(
                    number(16)?,
                    number(13)?,
                    number(14)?,
                    number(15)?,
                )),
            };
            let points = (0..count(17)?)
                .map(|k| {
                    let j = 18 + 4 * k;
                    Ok((
                        id(j)?,
                        Vector3::new(number(j + 1)?, number(j + 2)?, number(j + 3)?),
                    ))
                })
                .collect::<Result<_, RecordingError>>()?;
            Ok(Recorded::Map(MapView {
                camera: Some(camera(3)?),
                segment: small(1)?,
                points,
                newest_keyframe: Some(newest_keyframe),
                pace: (!pace.is_nan()).then_some(pace),
            }))
        }
        Some(&"O") => Ok(Recorded::Origin {
            segment: small(1)?,
            timestamp: number(2)?,
            camera: camera(3)?,
            tracks: tracks(9)?,
        }),
        Some(&"F") => Ok(Recorded::Frame {
            timestamp: number(1)?,
            tracks: tracks(2)?,
        }),
        _ => Err(malformed("not a map (M), origin (O) or frame (F)")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_read_back_as_written() {
        let camera =
            PinholeRadtan::new(640, 480, [500.0, 501.0, 320.5, 240.25], [0.0; 5]).expect("camera");
        let tracks = vec![(7, Point2::new(10.5, 20.25)), (9, Point2::new(-1.0, 3.0))];
        let view = MapView {
            camera: Some(camera),
            segment: 2,
            points: [(7, Vector3::new(1.0, 2.0, 3.5))].into_iter().collect(),
            newest_keyframe: Some(StampedPose {
                timestamp: 1.25,
                position: Vector3::new(0.5, -0.25, 2.0),
                rotation: UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3),
            }),
            pace: None,
        };
        let Recorded::Map(read) = parse_line(&map_line(&view).expect("a map"), 1).expect("map")
        else {
            panic!("not a map")
        };
        assert_eq!(read.segment, 2);
        assert_eq!(read.points, view.points);
        assert_eq!(read.pace, None);
        let (a, b) = (
            read.newest_keyframe.expect("pose"),
            view.newest_keyframe.expect("pose"),
        );
        assert!(a.rotation.angle_to(&b.rotation) < 1e-12 && a.position == b.position);
        assert_eq!(
            read.camera.map(|c| (c.fx, c.cy, c.width)),
            Some((500.0, 240.25, 640))
        );
        let Recorded::Frame {
            timestamp,
            tracks: read,
        } = parse_line(&frame_line(3.5, &tracks), 2).expect("frame")
        else {
            panic!("not a frame")
        };
        assert_eq!((timestamp, read), (3.5, tracks.clone()));
        let Recorded::Origin {
            segment,
            tracks: read,
            ..
        } = parse_line(&origin_line(4, &camera, 0.0, &tracks), 3).expect("origin")
        else {
            panic!("not an origin")
        };
        assert_eq!((segment, read), (4, tracks));
        assert!(matches!(
            parse_line("F 1.0 2 7 1.0", 9),
            Err(RecordingError::Malformed { line: 9, .. })
        ));
    }
}
