//! `egoslam synth`: renders a sequence with ground truth to the TUM layout (rgb/, rgb.txt,
//! depth/, depth.txt, groundtruth.txt, camera.yaml), which `egoslam run` reads like any
//! TUM folder. Scenes, paths and image formation: `egoslam_synth`; docs/synth.md.

use anyhow::{bail, Context};
use clap::{Args, ValueEnum};
use egoslam_durability::write_atomically;
use egoslam_export::camera_yaml::camera_yaml;
use egoslam_export::tum::tum_text;
use egoslam_geometry::{LensModel, PinholeRadtan};
use egoslam_synth::paths::aria_head_trajectory;
use egoslam_synth::placement::place_in_free_space;
use egoslam_synth::{
    readout_poses, render_fisheye_frame, render_frame, CameraPath, Photo, RenderOptions,
    RobustnessEvent, Scene, WalkerOptions,
};
use opencv::core::Vector;
use opencv::prelude::*;
use std::path::PathBuf;
use std::time::Instant;

/// Closest a replayed head may come to a rendered surface, metres (0.3: a head turned to a
/// wall stays a forearm's length away; nearer, the texture is a featureless blur).
const REPLAY_CLEARANCE_M: f64 = 0.3;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum PathKind {
    /// Paper: 2.0 m straight towards the planes.
    Frontal,
    /// Paper: 4.0 m sideways past the planes.
    LeftRight,
    /// Paper: a 3.7 m walk with head motion.
    Egomotion,
    /// A head-mounted walk around a room: scans, glances, sharp and 360 deg turns, stops.
    Walker,
    /// A recorded head trajectory (`--trajectory`): Aria MPS / HOT3D CSV or TUM file.
    Replay,
    /// Robustness: a walk with a 60 deg head turn in place (no translation) 3 s in.
    PureRotation,
    /// Robustness: a walk with a 360 deg turn on the spot.
    Spin,
    /// Robustness: a walk with the camera perfectly still for 5 s.
    Static,
    /// Robustness: a walk with a fast head shake (+-20 deg at 3 Hz for 2 s).
    Shake,
    /// Robustness: a walk with 1 s of darkness.
    Dark,
    /// Robustness: the walker stops in a 2 s blackout, then walks on (tracking lost;
    /// relocalization links the map).
    Blackout,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SceneKind {
    /// The paper's textured planes (1.28, 2.56, 5.12 m at 3.5, 5, 8 m) and a background.
    Planes,
    /// A 16 x 16 m room with a central block and boxes.
    Room,
    /// A 2.2 m wide indoor corridor in a ring around an 8 x 8 m core.
    Corridor,
    /// An outdoor street around a 12 m high block: facades across, parked cars, sky.
    Street,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SynthLens {
    /// A pinhole without distortion.
    Pinhole,
    /// An ideal equidistant fisheye (Kannala-Brandt with k1..k4 zero), rendered from a
    /// cube map.
    Equidistant,
}

#[derive(Args, Debug)]
pub struct SynthArgs {
    /// Output folder (created; existing rendered files are replaced).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, value_enum, default_value = "walker")]
    pub path: PathKind,
    /// Scene; default: planes for the paper's profiles, room otherwise.
    #[arg(long, value_enum)]
    pub scene: Option<SceneKind>,
    /// Recorded trajectory for `--path replay`.
    #[arg(long)]
    pub trajectory: Option<PathBuf>,
    #[arg(long, default_value_t = 300)]
    pub frames: usize,
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Focal length, pixels (default 500: ~65 deg horizontal field of view at 640 px).
    #[arg(long, default_value_t = 500.0)]
    pub focal: f64,
    /// Lens: a pinhole, or a fisheye whose `--focal` is pixels per radian at the centre
    /// (equidistant at 260 px/rad: 141 deg across 640 px, 176 deg across the diagonal).
    #[arg(long, value_enum, default_value_t = SynthLens::Pinhole)]
    pub lens: SynthLens,
    /// Sensor noise, grey levels.
    #[arg(long, default_value_t = 2.0)]
    pub noise: f64,
    /// Sub-frame poses per frame for motion blur (1: none).
    #[arg(long, default_value_t = 1)]
    pub blur_samples: usize,
    /// Rolling shutter: milliseconds from the first row's exposure to the last's (0: a
    /// global shutter). Head-mounted RGB cameras read out in 10-30 ms. With
    /// `--blur-samples` each row is also blurred over its own exposure.
    #[arg(long, default_value_t = 0.0)]
    pub rolling_shutter_ms: f64,
    /// Relative exposure drift amplitude (0.2 = +-20 %).
    #[arg(long, default_value_t = 0.0)]
    pub exposure_drift: f64,
    /// Walker speed, m/s.
    #[arg(long, default_value_t = 1.2)]
    pub speed: f64,
    /// Texture seed: the same seed gives the same frames.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// Gap, pixels, between consecutive blur sub-poses' images in the median frame above which
/// the blur is ghost copies rather than a smear. Measured on the rendered 300-frame walk
/// (global shutter; keyframe ATE over 4.9 m, 1.7 cm unblurred): 3 sub-poses, median gap
/// 7.2 px, 1.05 m; 5, 4.4 px, 13.4 cm; 9, 2.4 px, 1.1 cm.
const MAX_BLUR_GHOST_PX: f64 = 3.0;

/// Largest image distance, pixels at `focal`, that the head's turn puts between two
/// consecutive blur sub-poses of a frame (the turn dominates a head's image motion; the
/// walk's translation is left out).
fn blur_ghost_px(sub_poses: &[egoslam_geometry::StampedPose], focal: f64) -> f64 {
    sub_poses
        .windows(2)
        .map(|w| w[0].rotation.angle_to(&w[1].rotation) * focal)
        .fold(0.0, f64::max)
}

/// Path samples per frame interval with a rolling shutter.
const ROLLING_SHUTTER_SUBSAMPLES: usize = 32;

/// The photographs hung in the corridor and street scenes: frames of the TUM RGB-D
/// benchmark (CC BY 4.0, services/synth/photos/LICENSE.txt), built into the binary.
const PHOTOS: [(&str, &[u8]); 2] = [
    (
        "tum_fr1_rpy_frame000.jpg",
        include_bytes!("../../../synth/photos/tum_fr1_rpy_frame000.jpg"),
    ),
    (
        "tum_fr1_rpy_frame059.jpg",
        include_bytes!("../../../synth/photos/tum_fr1_rpy_frame059.jpg"),
    ),
];

/// Decodes [`PHOTOS`] (grey).
fn photos() -> anyhow::Result<Vec<std::sync::Arc<Photo>>> {
    PHOTOS
        .iter()
        .map(|(name, bytes)| {
            let image = opencv::imgcodecs::imdecode(
                &Vector::<u8>::from_slice(bytes),
                opencv::imgcodecs::IMREAD_GRAYSCALE,
            )
            .with_context(|| format!("decoding the built-in photograph {name}"))?;
            let (w, h) = (image.cols() as usize, image.rows() as usize);
            let pixels = image.data_bytes()?.to_vec();
            Ok(std::sync::Arc::new(
                Photo::from_grey(w, h, &pixels)
                    .with_context(|| format!("the built-in photograph {name}"))?,
            ))
        })
        .collect()
}

/// Writes a one-channel PNG (8-bit grey or 16-bit depth) with the `png` crate's fdeflate
/// path: at OpenCV's fastest zlib level libpng's row filtering and zlib had been a quarter
/// of `egoslam synth`'s time; the pixels are the same either way.
fn write_png(
    path: &std::path::Path,
    width: u32,
    height: u32,
    depth: png::BitDepth,
    bytes: &[u8],
) -> anyhow::Result<()> {
    let mut encoded = Vec::with_capacity(bytes.len() / 2);
    let mut encoder = png::Encoder::new(&mut encoded, width, height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(depth);
    // Grey frames: fdeflate (300 walker frames: 48 MB against libpng's 50 MB). Depth is
    // smooth and fdeflate's fixed tables do badly on it (27 MB): zlib level 1 writes 14 MB
    // (level 3: 8.6 MB in ~0.6 s more per 300 frames; libpng level 1: 12 MB).
    encoder.set_compression(png::Compression::Fast);
    if depth == png::BitDepth::Sixteen {
        encoder.set_deflate_compression(png::DeflateCompression::Level(1));
    } else {
        // Noise-grained grey frames: the Paeth filter on every row instead of the adaptive
        // choice, whose trial of each filter per row was ~5 % of all samples (perf; the
        // writer ~17 %). 300 frames: 48 MB against 47 MB, 5.6 instead of 6.3 s on 2 cores
        // (one run each).
        encoder.set_filter(png::Filter::Paeth);
    }
    let encoding = || format!("{}: encoding", path.display());
    let mut writer = encoder.write_header().with_context(encoding)?;
    writer.write_image_data(bytes).with_context(encoding)?;
    writer.finish().with_context(encoding)?;
    std::fs::write(path, &encoded).with_context(|| format!("{}: could not write", path.display()))
}

pub fn run(args: SynthArgs) -> anyhow::Result<()> {
    if args.frames < 2 || args.fps.is_nan() || args.fps <= 0.0 {
        bail!("--frames must be >= 2 and --fps > 0");
    }
    let camera = PinholeRadtan::new(
        args.width,
        args.height,
        [
            args.focal,
            args.focal,
            f64::from(args.width) / 2.0,
            f64::from(args.height) / 2.0,
        ],
        [0.0; 5],
    )?
    .with_lens(match args.lens {
        SynthLens::Pinhole => LensModel::RadialTangential,
        SynthLens::Equidistant => LensModel::Equidistant,
    })?;
    let path = match args.path {
        PathKind::Frontal => CameraPath::Frontal,
        PathKind::LeftRight => CameraPath::LeftRight,
        PathKind::Egomotion => CameraPath::Egomotion,
        PathKind::Walker => CameraPath::Walker(WalkerOptions {
            speed: args.speed,
            ..WalkerOptions::default()
        }),
        PathKind::Replay => {
            let file = args
                .trajectory
                .as_ref()
                .context("--path replay needs --trajectory FILE")?;
            let text = std::fs::read_to_string(file)
                .with_context(|| format!("reading {}", file.display()))?;
            let poses = if text.starts_with('#') || !text.contains(',') {
                egoslam_sources::ground_truth::read_tum_file(file)?
            } else {
                aria_head_trajectory(&text).with_context(|| file.display().to_string())?
            };
            CameraPath::Replay(poses)
        }
        PathKind::PureRotation => CameraPath::Event(RobustnessEvent::PureRotation),
        PathKind::Spin => CameraPath::Event(RobustnessEvent::Spin),
        PathKind::Static => CameraPath::Event(RobustnessEvent::Static),
        PathKind::Shake => CameraPath::Event(RobustnessEvent::Shake),
        PathKind::Dark => CameraPath::Event(RobustnessEvent::Dark),
        PathKind::Blackout => CameraPath::Event(RobustnessEvent::Blackout),
    };
    let dark = match args.path {
        PathKind::Dark => Some(RobustnessEvent::Dark.window()),
        PathKind::Blackout => Some(RobustnessEvent::Blackout.window()),
        _ => None,
    };
    let scene_kind = args.scene.unwrap_or(match args.path {
        PathKind::Frontal | PathKind::LeftRight | PathKind::Egomotion => SceneKind::Planes,
        _ => SceneKind::Room,
    });
    let scene = match scene_kind {
        SceneKind::Planes => Scene::paper_planes(args.seed),
        SceneKind::Room => Scene::room(args.seed),
        SceneKind::Corridor => Scene::corridor(args.seed, &photos()?),
        SceneKind::Street => Scene::street(args.seed, &photos()?),
    };
    let rolling = args.rolling_shutter_ms > 0.0;
    if !args.rolling_shutter_ms.is_finite()
        || args.rolling_shutter_ms < 0.0
        || args.rolling_shutter_ms > 1000.0 / args.fps
    {
        bail!(
            "--rolling-shutter-ms {}: must be between 0 and the frame interval ({:.1} ms)",
            args.rolling_shutter_ms,
            1000.0 / args.fps
        );
    }
    // With both, each row's exposure (half the frame interval, as the global shutter's)
    // is blurred: the poses then span the readout and one exposure.
    let readout_s = args.rolling_shutter_ms / 1000.0;
    let row_exposure_s = if rolling && args.blur_samples > 1 {
        RenderOptions::default().shutter / args.fps
    } else {
        0.0
    };
    let options = RenderOptions {
        noise_sigma: args.noise,
        blur_samples: args.blur_samples.max(1),
        exposure_drift: args.exposure_drift,
        rolling_shutter: rolling,
        rolling_exposure: row_exposure_s / (readout_s + row_exposure_s).max(1e-12),
        // One rendering thread more than cores: the PNG writer below takes a core for
        // ~10 ms at a time, and with one thread per core the other core then sat idle at
        // the end of each frame (300 frames on 2 cores: 168-173 % CPU and 6.3-7.5 s with
        // 2 threads, 187-188 % and 5.8-6.9 s with 3, same images).
        threads: RenderOptions::default().threads + 1,
        ..RenderOptions::default()
    };
    // Sub-frame poses: the path sampled `blur_samples` times finer (a rolling shutter:
    // 32 times, so that a 30 ms readout at 30 fps spans ~29 poses to interpolate rows in).
    let sub = if rolling {
        ROLLING_SHUTTER_SUBSAMPLES
    } else {
        options.blur_samples
    };
    let mut fine = path.poses((args.frames - 1) * sub + 1, args.fps * sub as f64);
    if matches!(args.path, PathKind::Replay) {
        // A recorded trajectory is turned to keep clear of the rendered room's surfaces
        // (egoslam_synth::placement: the Aria sample walked through a box otherwise).
        let (placed, yaw, clearance) = place_in_free_space(&fine, &scene, REPLAY_CLEARANCE_M);
        tracing::info!(
            turned_deg = yaw.to_degrees(),
            clearance_m = clearance,
            "replayed trajectory placed"
        );
        if clearance < REPLAY_CLEARANCE_M {
            tracing::warn!(
                clearance_m = clearance,
                "the replayed trajectory comes closer than {REPLAY_CLEARANCE_M} m to a surface at every heading"
            );
        }
        fine = placed;
    }
    let poses: Vec<_> = fine.iter().step_by(sub).copied().collect();
    if poses.len() < args.frames {
        tracing::warn!(
            frames = poses.len(),
            "the recorded trajectory is shorter than --frames"
        );
    }
    let out = &args.out;
    for dir in ["rgb", "depth"] {
        std::fs::create_dir_all(out.join(dir))
            .with_context(|| format!("creating {}", out.join(dir).display()))?;
    }
    let (mut rgb_index, mut depth_index) = (
        String::from("# timestamp filename (rendered by egoslam synth)\n"),
        String::from("# timestamp filename (16-bit, depth in metres x 5000)\n"),
    );
    let started = Instant::now();
    let mut last_progress = Instant::now();
    // Per frame, the widest gap between consecutive blur sub-poses, pixels.
    let mut ghosts: Vec<f64> = Vec::new();
    let mut render_s = 0.0;
    // PNG encoding runs on its own thread while the next frame renders.
    let (to_writer, frames_in) = std::sync::mpsc::sync_channel::<(usize, egoslam_synth::Frame)>(4);
    let (rgb_dir, depth_dir) = (out.join("rgb"), out.join("depth"));
    let writer = std::thread::spawn(move || -> anyhow::Result<()> {
        for (i, frame) in frames_in {
            let name = format!("{i:06}.png");
            let (w, h) = (frame.width, frame.height);
            write_png(
                &rgb_dir.join(&name),
                w,
                h,
                png::BitDepth::Eight,
                &frame.grey,
            )?;
            let depth = frame.depth_png_samples();
            write_png(&depth_dir.join(&name), w, h, png::BitDepth::Sixteen, &depth)?;
        }
        Ok(())
    });
    for (i, pose) in poses.iter().enumerate() {
        // The sub-frame poses of the exposure (the readout, or the open shutter), centred
        // on the frame time (the ground-truth pose is the middle row's); at the ends of
        // the sequence a readout takes the path's end poses and an open shutter is
        // clipped; without either, the frame's own pose.
        let shutter = if rolling {
            // As finely as the path is sampled, the first and last rows at the readout's
            // ends exactly (and their exposures' ends, with blur).
            let span_s = readout_s + row_exposure_s;
            let samples = (span_s * args.fps * sub as f64).ceil() as usize + 1;
            readout_poses(&fine, pose.timestamp, span_s, samples)
        } else {
            let half = if sub > 1 {
                ((sub as f64 * options.shutter) / 2.0).round() as usize
            } else {
                0
            };
            let centre = i * sub;
            fine[centre.saturating_sub(half)..(centre + half + 1).min(fine.len())].to_vec()
        };
        let render_start = Instant::now();
        let in_dark =
            dark.is_some_and(|(start, length)| (start..start + length).contains(&pose.timestamp));
        let frame_options = RenderOptions {
            exposure_scale: if in_dark { 0.03 } else { 1.0 },
            ..options
        };
        if options.blur_samples > 1 {
            ghosts.push(if rolling {
                let row =
                    readout_poses(&fine, pose.timestamp, row_exposure_s, options.blur_samples);
                blur_ghost_px(&row, args.focal)
            } else {
                blur_ghost_px(&shutter, args.focal)
            });
        }
        let frame = if camera.lens.is_fisheye() {
            render_fisheye_frame(&scene, &camera, &shutter, i as u64, &frame_options)?
        } else {
            render_frame(&scene, &camera, &shutter, i as u64, &frame_options)
        };
        render_s += render_start.elapsed().as_secs_f64();
        if to_writer.send((i, frame)).is_err() {
            break; // the writer failed: its error is reported below
        }
        let name = format!("{i:06}.png");
        rgb_index.push_str(&format!("{:.6} rgb/{name}\n", pose.timestamp));
        depth_index.push_str(&format!("{:.6} depth/{name}\n", pose.timestamp));
        if last_progress.elapsed().as_secs_f64() > 2.0 {
            last_progress = Instant::now();
            let fps = (i + 1) as f64 / started.elapsed().as_secs_f64();
            tracing::info!(
                "synth: {}/{} frames ({fps:.1} frames/s)",
                i + 1,
                poses.len()
            );
        }
    }
    drop(to_writer);
    ghosts.sort_by(f64::total_cmp);
    let median_ghost = ghosts.get(ghosts.len() / 2).copied().unwrap_or(0.0);
    if let Some(widest) = ghosts.last() {
        tracing::info!(
            median_px = median_ghost,
            max_px = widest,
            "motion blur: gap between consecutive sub-poses' images"
        );
    }
    if median_ghost > MAX_BLUR_GHOST_PX {
        tracing::warn!(
            "motion blur from {} sub-poses leaves copies of the image {:.1} px apart in the median frame: ghosts rather than a smear, which real video does not have and which broke tracking on a rendered walk; use --blur-samples {} or more",
            options.blur_samples,
            median_ghost,
            (options.blur_samples as f64 * median_ghost / MAX_BLUR_GHOST_PX).ceil()
        );
    }
    match writer.join() {
        Ok(result) => result?,
        Err(_) => bail!("the PNG writer thread panicked"),
    }
    write_atomically(&out.join("rgb.txt"), rgb_index.as_bytes())?;
    write_atomically(&out.join("depth.txt"), depth_index.as_bytes())?;
    write_atomically(&out.join("groundtruth.txt"), tum_text(&poses).as_bytes())?;
    write_atomically(
        &out.join("camera.yaml"),
        camera_yaml(&camera, std::path::Path::new("egoslam synth")).as_bytes(),
    )?;
    let length: f64 = poses
        .windows(2)
        .map(|w| (w[1].position - w[0].position).norm())
        .sum();
    let licence = match scene_kind {
        SceneKind::Corridor | SceneKind::Street => {
            "Licence: Apache-2.0, as egoslam, except the pictures seen in it: frames of the TUM RGB-D benchmark (fr1_rpy; J. Sturm et al., IROS 2012, https://cvg.cit.tum.de/data/datasets/rgbd-dataset), CC BY 4.0 (services/synth/photos/LICENSE.txt)."
        }
        SceneKind::Planes | SceneKind::Room => {
            "Licence: Apache-2.0, as egoslam (no third-party content)."
        }
    };
    let about = format!(
        "Rendered by egoslam synth: path {:?}, scene {:?}, {} frames at {} fps, {}x{} f={}, noise {}, blur {}, exposure drift {}, seed {}, rolling shutter {} ms; path length {:.2} m; renderer revision {}.\n{licence}\n",
        args.path, scene_kind, poses.len(), args.fps, args.width, args.height, args.focal, args.noise, options.blur_samples, args.exposure_drift, args.seed, args.rolling_shutter_ms, length, egoslam_synth::RENDER_REVISION
    );
    write_atomically(&out.join("SOURCE.txt"), about.as_bytes())?;
    tracing::info!(
        frames = poses.len(),
        path_m = length,
        seconds = started.elapsed().as_secs_f64(),
        render_seconds = render_s,
        "synth finished"
    );
    println!(
        "{} frames, {length:.2} m of path; {}",
        poses.len(),
        out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The frames are read back by OpenCV (the pipeline's decoder): grey levels and 16-bit
    /// depth (big-endian in the file) must come back exactly.
    #[test]
    fn png_frames_read_back_exactly_through_opencv() {
        let dir = tempfile::tempdir().expect("temporary directory");
        let (w, h) = (37u32, 5u32);
        let grey: Vec<u8> = (0..w * h).map(|i| (i * 7 % 256) as u8).collect();
        let depth: Vec<u16> = (0..w * h).map(|i| (i * 1013 % 65536) as u16).collect();
        let depth_bytes: Vec<u8> = depth.iter().flat_map(|d| d.to_be_bytes()).collect();
        let (grey_path, depth_path) = (dir.path().join("g.png"), dir.path().join("d.png"));
        write_png(&grey_path, w, h, png::BitDepth::Eight, &grey).expect("grey written");
        write_png(&depth_path, w, h, png::BitDepth::Sixteen, &depth_bytes).expect("depth");
        let read = |p: &std::path::Path| {
            opencv::imgcodecs::imread(
                p.to_str().expect("UTF-8 path"),
                opencv::imgcodecs::IMREAD_UNCHANGED,
            )
            .expect("decoded")
        };
        let g = read(&grey_path);
        assert_eq!(
            (g.cols(), g.rows(), g.typ()),
            (37, 5, opencv::core::CV_8UC1)
        );
        assert_eq!(g.data_bytes().expect("bytes"), &grey[..]);
        let d = read(&depth_path);
        assert_eq!(d.typ(), opencv::core::CV_16UC1);
        assert_eq!(d.data_typed::<u16>().expect("u16"), &depth[..]);
    }
}
