//! Reading frames, one at a time, from any [`Layout`].

use crate::error::{data_lines, parse_floats, read_text};
use crate::frame_stream::FrameStream;
use crate::layout::is_image;
use crate::{detect_layout, Layout, SourceError};
use opencv::core::{Mat, Scalar, CV_8UC1};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc, videoio};
use std::path::{Path, PathBuf};

/// One decoded greyscale frame.
pub struct Frame {
    /// 0-based position in the stream.
    pub index: u64,
    /// Capture time in seconds (the dataset's own clock).
    pub timestamp: f64,
    /// 8-bit single-channel image.
    pub image: Mat,
    /// File (or `video#frame`) the frame came from, for error messages.
    pub source: String,
}

/// A stream of frames. `next_frame` returns `None` at the end of the stream.
pub trait FrameSource: Send {
    /// Number of frames when known in advance (for progress), else `None`.
    fn len_hint(&self) -> Option<usize>;
    /// The next frame, or the error that stops the stream.
    fn next_frame(&mut self) -> Option<Result<Frame, SourceError>>;
    /// The layout this source reads.
    fn layout(&self) -> &Layout;
}

/// A list of `(timestamp, image file)` read in order (TUM, KITTI, EuRoC, image folders).
struct IndexedSource {
    layout: Layout,
    entries: Vec<(f64, PathBuf)>,
    next: usize,
}

/// True when a PNG or JPEG file lacks its end marker. libjpeg decodes a truncated file
/// "successfully" (grey bottom rows, a warning on stderr); tracking on such a frame would
/// silently corrupt the map, so it is refused here.
fn is_truncated(bytes: &[u8]) -> bool {
    let tail = &bytes[bytes.len().saturating_sub(32)..];
    if bytes.starts_with(&[0xFF, 0xD8]) {
        return !tail.windows(2).any(|w| w == [0xFF, 0xD9]);
    }
    if bytes.starts_with(b"\x89PNG") {
        return !tail.windows(4).any(|w| w == b"IEND");
    }
    false
}

/// Decodes an image file to 8-bit grey, naming the file on any failure.
pub fn decode_grey(path: &Path) -> Result<Mat, SourceError> {
    let bytes = std::fs::read(path).map_err(|e| SourceError::io(path, e))?;
    if bytes.is_empty() || is_truncated(&bytes) {
        return Err(SourceError::BadImage { path: path.into() });
    }
    // A Mat header over the file bytes: OpenCV decodes from them without another copy.
    let opencv_error = |e: opencv::Error| SourceError::OpenCv {
        path: path.into(),
        message: e.to_string(),
    };
    if let Some(img) = decode_grey_png(&bytes) {
        return Ok(img);
    }
    let buf = Mat::from_slice(&bytes).map_err(opencv_error)?;
    let img = imgcodecs::imdecode(&buf, imgcodecs::IMREAD_GRAYSCALE).map_err(opencv_error)?;
    if img.empty() || img.cols() <= 0 || img.rows() <= 0 {
        return Err(SourceError::BadImage { path: path.into() });
    }
    Ok(img)
}

/// An 8-bit greyscale PNG (the rendered sequences, KITTI) decoded by the `png` crate, which
/// inflates it ~2x faster than OpenCV's libpng and zlib; `None` for anything else (colour,
/// 16 bits, interlaced, or an error), which OpenCV then decodes or refuses. PNG is lossless,
/// so the pixels are the same either way.
fn decode_grey_png(bytes: &[u8]) -> Option<Mat> {
    if !bytes.starts_with(b"\x89PNG") {
        return None;
    }
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes))
        .read_info()
        .ok()?;
    let info = reader.info();
    let grey = info.color_type == png::ColorType::Grayscale
        && info.bit_depth == png::BitDepth::Eight
        && !info.interlaced;
    let (width, height) = (
        i32::try_from(info.width).ok()?,
        i32::try_from(info.height).ok()?,
    );
    if !grey || width <= 0 || height <= 0 {
        return None;
    }
    // Inflated straight into the frame's buffer: one row of `width` bytes per image row.
    let mut image =
        Mat::new_rows_cols_with_default(height, width, CV_8UC1, Scalar::all(0.0)).ok()?;
    let buffer = image.data_bytes_mut().ok()?;
    if reader.output_buffer_size()? != buffer.len() {
        return None;
    }
    let size = buffer.len();
    let out = reader.next_frame(buffer).ok()?;
    (out.line_size == width as usize && out.buffer_size() == size).then_some(image)
}

impl FrameSource for IndexedSource {
    fn len_hint(&self) -> Option<usize> {
        Some(self.entries.len())
    }

    fn next_frame(&mut self) -> Option<Result<Frame, SourceError>> {
        let (timestamp, path) = self.entries.get(self.next)?.clone();
        let index = self.next as u64;
        self.next += 1;
        Some(decode_grey(&path).map(|image| Frame {
            index,
            timestamp,
            image,
            source: path.display().to_string(),
        }))
    }

    fn layout(&self) -> &Layout {
        &self.layout
    }
}

struct VideoSource {
    layout: Layout,
    /// A live camera: frames stamped with the wall clock, never a known length.
    live: bool,
    file: PathBuf,
    capture: videoio::VideoCapture,
    fps: f64,
    frames: Option<usize>,
    next: u64,
    grey: Mat,
    /// Live camera: wall-clock time and monotonic instant of the first frame.
    clock: Option<(f64, std::time::Instant)>,
}

impl FrameSource for VideoSource {
    fn len_hint(&self) -> Option<usize> {
        self.frames
    }

    fn next_frame(&mut self) -> Option<Result<Frame, SourceError>> {
        let mut bgr = Mat::default();
        match self.capture.read(&mut bgr) {
            Ok(true) if !bgr.empty() => {}
            Ok(_) => return None,
            Err(e) => {
                return Some(Err(SourceError::OpenCv {
                    path: self.file.clone(),
                    message: format!("frame {}: {e}", self.next),
                }))
            }
        }
        let conv = if bgr.channels() == 1 {
            bgr.copy_to(&mut self.grey)
        } else {
            imgproc::cvt_color_def(&bgr, &mut self.grey, imgproc::COLOR_BGR2GRAY)
        };
        if let Err(e) = conv {
            return Some(Err(SourceError::OpenCv {
                path: self.file.clone(),
                message: e.to_string(),
            }));
        }
        let index = self.next;
        self.next += 1;
        let timestamp = if self.live {
            // Wall-clock time at the first frame plus the monotonic clock since: a step of
            // the system clock (NTP, a suspended box) must not send stamps backwards, which
            // would have every frame skipped until the clock caught up.
            let (wall0, mono0) = *self.clock.get_or_insert_with(|| {
                let wall = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0.0, |d| d.as_secs_f64());
                (wall, std::time::Instant::now())
            });
            wall0 + mono0.elapsed().as_secs_f64()
        } else {
            index as f64 / self.fps
        };
        Some(Ok(Frame {
            index,
            timestamp,
            image: std::mem::take(&mut self.grey),
            source: format!("{}#{index}", self.file.display()),
        }))
    }

    fn layout(&self) -> &Layout {
        &self.layout
    }
}

fn tum_entries(dir: &Path) -> Result<Vec<(f64, PathBuf)>, SourceError> {
    let index = dir.join("rgb.txt");
    let text = read_text(&index)?;
    data_lines(&text)
        .map(|(n, line)| {
            let mut parts = line.split_whitespace();
            let (Some(t), Some(file)) = (parts.next(), parts.next()) else {
                return Err(SourceError::parse(
                    &index,
                    n,
                    "expected 'timestamp filename'",
                ));
            };
            let t = t
                .parse::<f64>()
                .map_err(|_| SourceError::parse(&index, n, format!("bad timestamp {t:?}")))?;
            Ok((t, dir.join(file)))
        })
        .collect()
}

fn kitti_entries(dir: &Path) -> Result<Vec<(f64, PathBuf)>, SourceError> {
    let times = dir.join("times.txt");
    let text = read_text(&times)?;
    data_lines(&text)
        .enumerate()
        .map(|(i, (n, line))| {
            let v = parse_floats(&times, n, line)?;
            let t = *v
                .first()
                .ok_or_else(|| SourceError::parse(&times, n, "empty line"))?;
            Ok((t, dir.join("image_0").join(format!("{i:06}.png"))))
        })
        .collect()
}

fn euroc_entries(cam_dir: &Path) -> Result<Vec<(f64, PathBuf)>, SourceError> {
    let csv = cam_dir.join("data.csv");
    let text = read_text(&csv)?;
    data_lines(&text)
        .map(|(n, line)| {
            let mut parts = line.split(',').map(str::trim);
            let (Some(ns), Some(file)) = (parts.next(), parts.next()) else {
                return Err(SourceError::parse(
                    &csv,
                    n,
                    "expected 'timestamp_ns,filename'",
                ));
            };
            let ns = ns
                .parse::<u64>()
                .map_err(|_| SourceError::parse(&csv, n, format!("bad timestamp {ns:?}")))?;
            Ok((ns as f64 * 1e-9, cam_dir.join("data").join(file)))
        })
        .collect()
}

fn folder_entries(dir: &Path, fps: f64) -> Result<Vec<(f64, PathBuf)>, SourceError> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| SourceError::io(dir, e))?
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| p.is_file() && is_image(p))
        .collect();
    files.sort();
    Ok(files
        .into_iter()
        .enumerate()
        .map(|(i, p)| (i as f64 / fps, p))
        .collect())
}

/// The image files of a sequence with their timestamps, in order (for exports that name
/// the images); `None` for a video or a camera, whose frames are not files.
pub fn image_files(layout: &Layout, fps: f64) -> Result<Option<Vec<(f64, PathBuf)>>, SourceError> {
    Ok(Some(match layout {
        Layout::Tum { dir } => tum_entries(dir)?,
        Layout::Kitti { dir } => kitti_entries(dir)?,
        Layout::Euroc { cam_dir } => euroc_entries(cam_dir)?,
        Layout::ImageFolder { dir } => folder_entries(dir, fps)?,
        Layout::Video { .. } | Layout::Camera { .. } => return Ok(None),
    }))
}

/// Opens the sequence at `path` (any supported layout) as a [`FrameStream`], which skips and
/// counts the frames that cannot be used. `fps` sets the timestamps of image folders (which
/// carry none) and is the fallback for videos that report no rate.
pub fn open_source(path: &Path, fps: f64) -> Result<FrameStream, SourceError> {
    open_frames(path, fps).map(FrameStream::new)
}

/// The frames at `path` as they are listed, bad ones included.
fn open_frames(path: &Path, fps: f64) -> Result<Box<dyn FrameSource>, SourceError> {
    let layout = detect_layout(path)?;
    let entries = match &layout {
        Layout::Video { file } | Layout::Camera { device: file } => {
            let live = matches!(layout, Layout::Camera { .. });
            let backend = if live {
                videoio::CAP_V4L2
            } else {
                videoio::CAP_ANY
            };
            let capture = videoio::VideoCapture::from_file(file, backend).map_err(|e| {
                SourceError::OpenCv {
                    path: file.clone(),
                    message: e.to_string(),
                }
            })?;
            if !capture.is_opened().unwrap_or(false) {
                let message = if live {
                    "cannot open the camera (busy, no permission: is the user in group video?)"
                } else {
                    "cannot open video (unknown codec or not a video)"
                };
                return Err(SourceError::OpenCv {
                    path: file.clone(),
                    message: message.into(),
                });
            }
            let reported = capture.get(videoio::CAP_PROP_FPS).unwrap_or(0.0);
            let count = capture.get(videoio::CAP_PROP_FRAME_COUNT).unwrap_or(0.0);
            return Ok(Box::new(VideoSource {
                file: file.clone(),
                layout: layout.clone(),
                capture,
                fps: if reported > 0.0 && reported.is_finite() {
                    reported
                } else {
                    fps
                },
                frames: (count >= 1.0 && !live).then_some(count as usize),
                live,
                next: 0,
                grey: Mat::default(),
                clock: None,
            }));
        }
        // Every other layout lists its image files.
        _ => image_files(&layout, fps)?.unwrap_or_default(),
    };
    if entries.is_empty() {
        return Err(SourceError::Empty {
            path: layout.root().into(),
        });
    }
    Ok(Box::new(IndexedSource {
        layout,
        entries,
        next: 0,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::shared_test_data as shared;

    /// The `png` crate's decoding of a grey PNG gives OpenCV's pixels; a colour PNG is
    /// left to OpenCV.
    #[test]
    fn grey_pngs_decode_to_opencvs_pixels_and_colour_ones_are_left_to_it() {
        let mut state = 3u32;
        let mut noise = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 24) as u8
        };
        let values: Vec<u8> = (0..97 * 61).map(|_| noise()).collect();
        let image = Mat::new_rows_cols_with_data(61, 97, &values)
            .expect("image")
            .try_clone()
            .expect("owned");
        let mut encoded = opencv::core::Vector::<u8>::new();
        imgcodecs::imencode(".png", &image, &mut encoded, &opencv::core::Vector::new())
            .expect("encodes");
        let bytes = encoded.to_vec();
        let ours = decode_grey_png(&bytes).expect("a grey PNG");
        let theirs = imgcodecs::imdecode(
            &Mat::from_slice(&bytes).expect("buffer"),
            imgcodecs::IMREAD_GRAYSCALE,
        )
        .expect("decodes");
        assert_eq!((ours.cols(), ours.rows()), (97, 61));
        assert_eq!(
            ours.data_bytes().expect("pixels"),
            theirs.data_bytes().expect("pixels")
        );
        let mut colour = Mat::default();
        opencv::imgproc::cvt_color_def(&image, &mut colour, opencv::imgproc::COLOR_GRAY2BGR)
            .expect("colour");
        imgcodecs::imencode(".png", &colour, &mut encoded, &opencv::core::Vector::new())
            .expect("encodes");
        assert!(decode_grey_png(&encoded.to_vec()).is_none());
        assert!(decode_grey_png(&bytes[..bytes.len() / 2]).is_none());
    }

    fn check(sub: &str, frames: usize, size: (i32, i32), first_t: f64) {
        let Some(d) = shared(sub) else { return };
        let mut src = open_source(&d, 30.0).expect("opens");
        assert_eq!(src.len_hint(), Some(frames));
        let f = src.next_frame().expect("one frame").expect("decodes");
        assert_eq!((f.image.cols(), f.image.rows()), size);
        assert_eq!(f.image.channels(), 1);
        assert!((f.timestamp - first_t).abs() < 1e-6, "{}", f.timestamp);
        let mut n = 1;
        let mut last = f.timestamp;
        while let Some(f) = src.next_frame() {
            let f = f.expect("decodes");
            assert!(f.timestamp > last);
            last = f.timestamp;
            n += 1;
        }
        assert_eq!(n, frames);
    }

    #[test]
    fn reads_tum() {
        check("tum_fr1_rpy", 120, (640, 480), 1305031229.528748);
    }

    #[test]
    fn reads_kitti() {
        check("kitti_odometry_00", 150, (1241, 376), 0.0);
    }

    #[test]
    fn reads_euroc() {
        check("euroc_v1_01", 95, (752, 480), 1403715273.262143);
    }

    #[test]
    fn reads_video_and_image_folder_written_here() {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut writer = videoio::VideoWriter::new(
            dir.path().join("clip.avi"),
            videoio::VideoWriter::fourcc('M', 'J', 'P', 'G').expect("fourcc"),
            25.0,
            opencv::core::Size::new(64, 48),
            false,
        )
        .expect("writer");
        let folder = dir.path().join("images");
        std::fs::create_dir(&folder).expect("mkdir");
        for i in 0..5 {
            let img =
                Mat::new_rows_cols_with_default(48, 64, opencv::core::CV_8UC1, (i * 40).into())
                    .expect("mat");
            writer.write(&img).expect("write frame");
            imgcodecs::imwrite_def(folder.join(format!("{i:03}.png")), &img).expect("png");
        }
        writer.release().expect("close");
        let mut video = open_source(&dir.path().join("clip.avi"), 30.0).expect("video opens");
        let mut n = 0;
        while let Some(f) = video.next_frame() {
            let f = f.expect("frame");
            assert_eq!(
                (f.image.cols(), f.image.rows(), f.image.channels()),
                (64, 48, 1)
            );
            assert!((f.timestamp - n as f64 / 25.0).abs() < 1e-9);
            n += 1;
        }
        assert_eq!(n, 5);
        let mut images = open_source(&folder, 10.0).expect("folder opens");
        assert_eq!(images.len_hint(), Some(5));
        let second = images
            .next_frame()
            .and_then(|_| images.next_frame())
            .expect("two")
            .expect("decodes");
        assert!((second.timestamp - 0.1).abs() < 1e-12);
    }

    #[test]
    fn truncated_and_empty_inputs_name_the_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        let good =
            Mat::new_rows_cols_with_default(48, 64, opencv::core::CV_8UC1, 7.into()).expect("mat");
        let png = dir.path().join("000.png");
        imgcodecs::imwrite_def(&png, &good).expect("png");
        let bytes = std::fs::read(&png).expect("read");
        std::fs::write(&png, &bytes[..bytes.len() / 3]).expect("truncate");
        let mut src = open_frames(dir.path(), 30.0).expect("folder");
        let err = src
            .next_frame()
            .expect("one")
            .err()
            .expect("truncated fails");
        assert!(err.to_string().contains("000.png"), "{err}");

        let tum = dir.path().join("tum");
        std::fs::create_dir(&tum).expect("mkdir");
        std::fs::write(tum.join("rgb.txt"), "# header only\n").expect("write");
        let err = open_source(&tum, 30.0).err().expect("empty");
        assert!(err.to_string().contains("empty sequence"), "{err}");
        std::fs::write(tum.join("rgb.txt"), "1.0 rgb/missing.png\n").expect("write");
        let err = open_frames(&tum, 30.0)
            .expect("lists")
            .next_frame()
            .expect("one")
            .err()
            .expect("missing");
        assert!(err.to_string().contains("missing.png"), "{err}");
    }
}
