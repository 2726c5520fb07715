//! The frontend's last tracked frame, kept so that a restarted frontend continues its
//! tracks (egoslam_frontend's `Tracker::resume_from`) instead of splitting the map.
//!
//! Written after every frame, so it lives in memory-backed storage, never on the flash:
//! systemd's `RuntimeDirectory=` (`$RUNTIME_DIRECTORY`), else `/dev/shm`. Where neither
//! exists nothing is kept, and a restart is healed by relocalization alone. The file is
//! replaced atomically (write, then rename), so a frontend killed mid-write leaves the
//! previous frame's.
//!
//! Format (little-endian): the line `egoslam frontend resume v1\n`, then width and height
//! (u32), frame id (u64), timestamp (f64), track count (u32), per track its id (u64) and
//! raw pixel (2 x f32), then the grey pixels row by row.

use anyhow::{bail, Context};
use opencv::core::{Mat, Point2f, CV_8UC1};
use opencv::prelude::*;
use std::io::Write;
use std::path::{Path, PathBuf};

const MAGIC: &[u8] = b"egoslam frontend resume v1\n";

/// Where the frontend of bus namespace `namespace` keeps its last frame, if anywhere.
pub fn path(namespace: &str) -> Option<PathBuf> {
    let dir = egoslam_durability::memory_backed_dir()?;
    Some(dir.join(egoslam_durability::memory_backed_name(
        namespace,
        "frontend.resume",
    )))
}

/// A frame read back from the file.
pub struct SavedFrame {
    pub frame_id: u64,
    pub timestamp_s: f64,
    pub image: Mat,
    pub tracks: Vec<(u64, Point2f)>,
}

/// Writes the frame (`image`: 8-bit grey, continuous) and its tracks.
pub fn save(
    path: &Path,
    frame_id: u64,
    timestamp_s: f64,
    image: &impl MatTraitConst,
    tracks: impl ExactSizeIterator<Item = (u64, Point2f)>,
) -> anyhow::Result<()> {
    let pixels = image.data_bytes().context("resume frame: pixel access")?;
    let mut bytes = Vec::with_capacity(MAGIC.len() + 32 + tracks.len() * 16);
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&(image.cols() as u32).to_le_bytes());
    bytes.extend_from_slice(&(image.rows() as u32).to_le_bytes());
    bytes.extend_from_slice(&frame_id.to_le_bytes());
    bytes.extend_from_slice(&timestamp_s.to_le_bytes());
    bytes.extend_from_slice(&(tracks.len() as u32).to_le_bytes());
    for (id, p) in tracks {
        bytes.extend_from_slice(&id.to_le_bytes());
        bytes.extend_from_slice(&p.x.to_le_bytes());
        bytes.extend_from_slice(&p.y.to_le_bytes());
    }
    let partial = path.with_extension("resume.partial");
    let mut file = std::fs::File::create(&partial)
        .with_context(|| format!("creating {}", partial.display()))?;
    // The pixels straight from the frame (shared memory), not through another buffer.
    file.write_all(&bytes)
        .and_then(|()| file.write_all(pixels))
        .with_context(|| format!("writing {}", partial.display()))?;
    std::fs::rename(&partial, path).with_context(|| format!("replacing {}", path.display()))
}

/// Reads the bytes in order, failing on a short file.
struct Reader<'a> {
    bytes: &'a [u8],
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> anyhow::Result<&'a [u8]> {
        if self.bytes.len() < n {
            bail!("truncated");
        }
        let (head, rest) = self.bytes.split_at(n);
        self.bytes = rest;
        Ok(head)
    }

    fn array<const N: usize>(&mut self) -> anyhow::Result<[u8; N]> {
        Ok(self.take(N)?.try_into()?)
    }
}

/// Reads the file back; an error says why it cannot be used (the frontend then starts
/// fresh tracks).
pub fn load(path: &Path) -> anyhow::Result<SavedFrame> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let mut r = Reader { bytes: &bytes };
    if r.take(MAGIC.len())? != MAGIC {
        bail!(
            "{}: not an egoslam frontend resume file of version 1",
            path.display()
        );
    }
    let width = u32::from_le_bytes(r.array()?);
    let height = u32::from_le_bytes(r.array()?);
    let frame_id = u64::from_le_bytes(r.array()?);
    let timestamp_s = f64::from_le_bytes(r.array()?);
    let count = u32::from_le_bytes(r.array()?) as usize;
    if count > r.bytes.len() / 16 {
        bail!(
            "{}: {count} tracks in a file of {} bytes",
            path.display(),
            bytes.len()
        );
    }
    let mut tracks = Vec::with_capacity(count);
    for _ in 0..count {
        let id = u64::from_le_bytes(r.array()?);
        let x = f32::from_le_bytes(r.array()?);
        let y = f32::from_le_bytes(r.array()?);
        if !(x.is_finite() && y.is_finite()) {
            bail!("{}: track {id} at a non-finite position", path.display());
        }
        tracks.push((id, Point2f::new(x, y)));
    }
    let pixels = r.bytes;
    if width == 0 || height == 0 || pixels.len() as u64 != u64::from(width) * u64::from(height) {
        bail!(
            "{}: {} pixel bytes for {width}x{height}",
            path.display(),
            pixels.len()
        );
    }
    let rows = i32::try_from(height)?;
    let mut image =
        Mat::new_rows_cols_with_default(rows, i32::try_from(width)?, CV_8UC1, 0.into())?;
    image.data_bytes_mut()?.copy_from_slice(pixels);
    Ok(SavedFrame {
        frame_id,
        timestamp_s,
        image,
        tracks,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_saved_frame_reads_back_and_a_damaged_one_is_refused() {
        let dir = tempfile::tempdir().expect("tempdir");
        let file = dir.path().join("f.resume");
        let mut image = Mat::new_rows_cols_with_default(3, 4, CV_8UC1, 0.into()).expect("mat");
        image
            .data_bytes_mut()
            .expect("bytes")
            .iter_mut()
            .enumerate()
            .for_each(|(i, b)| *b = i as u8);
        let tracks = vec![(7, Point2f::new(1.5, 2.0)), (9, Point2f::new(3.0, 0.5))];
        save(&file, 42, 1.25, &image, tracks.iter().copied()).expect("save");
        let back = load(&file).expect("load");
        assert_eq!((back.frame_id, back.timestamp_s), (42, 1.25));
        assert_eq!(back.tracks, tracks);
        assert_eq!(
            back.image.data_bytes().expect("bytes"),
            image.data_bytes().expect("bytes")
        );
        let bytes = std::fs::read(&file).expect("read");
        for cut in [0, 10, MAGIC.len() + 20, bytes.len() - 1] {
            std::fs::write(&file, &bytes[..cut]).expect("write");
            assert!(load(&file).is_err(), "cut at {cut}");
        }
        let mut wrong = bytes.clone();
        wrong[MAGIC.len() - 2] = b'9';
        std::fs::write(&file, &wrong).expect("write");
        assert!(load(&file).is_err());
    }
}
