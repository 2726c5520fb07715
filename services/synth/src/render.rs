//! The renderer: one ray per pixel (pinhole, no distortion) against the scene's planes,
//! band-limited texture lookup, optional motion blur (sub-frame poses over the exposure),
//! exposure drift and sensor noise; depth along the optical axis.

use crate::scene::{Plane, Scene};
use crate::texture::{fast_floor, SampleCache};
use egoslam_geometry::{PinholeRadtan, StampedPose};
use nalgebra::Vector3;

/// Image formation options; defaults commented.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderOptions {
    /// Gaussian sensor noise, grey levels (default 2, a clean indoor camera).
    pub noise_sigma: f64,
    /// Sub-frame poses averaged for motion blur (default 1: no blur). With n > 1, the
    /// exposure spans `shutter` of the frame interval, centred on the frame time.
    pub blur_samples: usize,
    /// Fraction of the frame interval the shutter is open (default 0.5).
    pub shutter: f64,
    /// Peak relative exposure change, slow drift (default 0: constant; 0.2 = +-20 %).
    pub exposure_drift: f64,
    /// Worker threads (default: available parallelism).
    pub threads: usize,
    /// Exposure of this frame relative to normal (default 1; ~0 renders a dark frame:
    /// lens covered, lights off).
    pub exposure_scale: f64,
    /// Rows exposed one after the other (default false: a global shutter). When set, the
    /// poses given to [`render_frame`] run from the first row's exposure to the last
    /// row's, and each row is rendered from the pose interpolated at its place.
    pub rolling_shutter: bool,
    /// With a rolling shutter and `blur_samples` > 1: the share of the poses' time span
    /// that is one row's exposure, `E / (R + E)` for a readout R and an exposure E (default
    /// 0: no blur). The poses then run from the first row's exposure start to the last
    /// row's exposure end, and each row averages `blur_samples` poses over its own
    /// exposure (a head-mounted camera's frames have both the shear and the blur).
    pub rolling_exposure: f64,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            noise_sigma: 2.0,
            blur_samples: 1,
            shutter: 0.5,
            exposure_drift: 0.0,
            threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            exposure_scale: 1.0,
            rolling_shutter: false,
            rolling_exposure: 0.0,
        }
    }
}

/// A rendered frame: grey levels and z-depth in metres (0 where nothing was hit), row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub grey: Vec<u8>,
    pub depth: Vec<f32>,
}

impl Frame {
    /// The depth as TUM's 16-bit depth PNG samples (metres x 5000, rounded, clamped to
    /// 0-65535), big-endian as PNG stores them: the convention `egoslam eval`'s structure
    /// metrics decode (eval.rs divides by 5000), as for real TUM depth.
    pub fn depth_png_samples(&self) -> Vec<u8> {
        let mut bytes = Vec::with_capacity(2 * self.depth.len());
        for z in &self.depth {
            // Depths are >= 0, so adding a half and truncating rounds as `f64::round`
            // does, without its library call (about a twentieth of the PNG writer's time).
            let sample = (f64::from(*z) * 5000.0 + 0.5).clamp(0.0, 65535.0) as u16;
            bytes.extend_from_slice(&sample.to_be_bytes());
        }
        bytes
    }
}

/// Gaussian noise from a per-pixel hash (deterministic for frame and pixel).
fn gaussian(frame: u64, pixel: u64) -> f64 {
    let mut h =
        frame.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ pixel.wrapping_mul(0xD6E8_FEB8_6659_FD93);
    let mut next = || {
        h ^= h >> 33;
        h = h.wrapping_mul(0xFF51_AFD7_ED55_8CCD);
        h ^= h >> 33;
        ((h >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    let (a, b) = (next(), next());
    (-2.0 * a.ln()).sqrt() * cos_turns(b)
}

/// `cos(2 pi b)` for `b` in [0, 1], within a few units in the last place of the library's
/// `(TAU * b).cos()` (a rounded grey level differs only when a value falls within that of
/// a half level: not once in the render bench's 9 million pixels), without its general
/// range reduction, which was a tenth of the renderer's time. The reflections are exact
/// in floating point (Sterbenz), so only the Taylor series of the last eighth of a turn
/// (to the 18th power: its next term is below 1e-20) rounds; its coefficients are
/// constants, so it costs ten multiply-adds.
fn cos_turns(b: f64) -> f64 {
    // cos(2 pi b) = cos(2 pi (1 - b)): fold onto half a turn.
    let half = if b > 0.5 { 1.0 - b } else { b };
    // cos(2 pi h) = -cos(2 pi (1/2 - h)): fold onto a quarter, keeping the sign.
    let (quarter, sign) = if half > 0.25 {
        (0.5 - half, -1.0)
    } else {
        (half, 1.0)
    };
    // Past an eighth of a turn the sine of the complement converges faster.
    let value = if quarter > 0.125 {
        let x = std::f64::consts::TAU * (0.25 - quarter);
        x * taylor(x * x, &SINE_OVER_X)
    } else {
        let x = std::f64::consts::TAU * quarter;
        taylor(x * x, &COSINE)
    };
    sign * value
}

/// Taylor coefficients of `cos x` in powers of `x^2`: `(-1)^n / (2n)!`.
const COSINE: [f64; 10] = taylor_coefficients(0);
/// Taylor coefficients of `sin x / x` in powers of `x^2`: `(-1)^n / (2n + 1)!`.
const SINE_OVER_X: [f64; 10] = taylor_coefficients(1);

/// `(-1)^n / (2n + offset)!` for n = 0..9, formed at compile time.
const fn taylor_coefficients(offset: u64) -> [f64; 10] {
    let mut c = [0.0; 10];
    let mut n = 0;
    while n < 10 {
        let mut factorial = 1u64;
        let mut k = 2;
        while k <= 2 * n as u64 + offset {
            factorial *= k;
            k += 1;
        }
        let sign = if n % 2 == 0 { 1.0 } else { -1.0 };
        c[n] = sign / factorial as f64;
        n += 1;
    }
    c
}

/// `sum_n c[n] x2^n` by Horner's rule (no division per pixel).
fn taylor(x2: f64, c: &[f64; 10]) -> f64 {
    c.iter().rev().fold(0.0, |sum, &cn| sum * x2 + cn)
}

/// A plane expressed for one camera pose so that, for the unnormalised ray
/// `d = (x', y', 1)` of a pixel, the hit `o + t R d` needs three dot products and one
/// division: `t = K / (n_c . d)`, `u = u0 + t (u_c . d)`, `v = v0 + t (v_c . d)`.
struct PlaneInView<'a> {
    plane: &'a Plane,
    n_c: Vector3<f64>,
    u_c: Vector3<f64>,
    v_c: Vector3<f64>,
    k: f64,
    u0: f64,
    v0: f64,
}

impl<'a> PlaneInView<'a> {
    fn new(plane: &'a Plane, pose: &StampedPose) -> Self {
        let rt = pose.rotation.inverse();
        let rel = pose.position - plane.origin;
        Self {
            plane,
            n_c: rt * plane.normal,
            u_c: rt * plane.u_axis,
            v_c: rt * plane.v_axis,
            k: -plane.normal.dot(&rel),
            u0: rel.dot(&plane.u_axis),
            v0: rel.dot(&plane.v_axis),
        }
    }

    /// The pixel box (x0, x1, y0, y1) outside which no ray can meet the rectangle, when all
    /// four corners are in front of the camera (a convex quad projects inside the box of
    /// its corners' projections; one pixel of margin for rounding); `None` otherwise, and
    /// the plane is tested at every pixel. Skipping a plane outside its box changes no
    /// pixel, and most of a room's box faces cover a small part of the image.
    fn image_box(&self, pose: &StampedPose, camera: &PinholeRadtan) -> Option<[f64; 4]> {
        let p = self.plane;
        let rt = pose.rotation.inverse();
        let mut b = [
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        for (a, c) in [
            (0.0, 0.0),
            (p.width, 0.0),
            (0.0, p.height),
            (p.width, p.height),
        ] {
            let corner = rt * (p.origin + p.u_axis * a + p.v_axis * c - pose.position);
            if corner.z <= 0.05 {
                return None;
            }
            let (x, y) = (
                camera.fx * corner.x / corner.z + camera.cx,
                camera.fy * corner.y / corner.z + camera.cy,
            );
            b = [b[0].min(x), b[1].max(x), b[2].min(y), b[3].max(y)];
        }
        Some([b[0] - 1.0, b[1] + 1.0, b[2] - 1.0, b[3] + 1.0])
    }
}

/// Rows per band of work handed to a rendering thread.
const BAND_ROWS: usize = 8;

/// One band of rows of the output buffers.
struct Band<'a> {
    first_row: usize,
    /// Pixels per row.
    row_width: usize,
    radiance: &'a mut [f64],
    depth: &'a mut [f32],
    grey: &'a mut [u8],
}

impl<'a> Band<'a> {
    /// The band's rows, one band each.
    fn rows(&mut self) -> impl Iterator<Item = Band<'_>> {
        let first = self.first_row;
        self.radiance
            .chunks_mut(self.row_width)
            .zip(self.depth.chunks_mut(self.row_width))
            .zip(self.grey.chunks_mut(self.row_width))
            .enumerate()
            .map(move |(r, ((radiance, depth), grey))| Band {
                first_row: first + r,
                row_width: radiance.len(),
                radiance,
                depth,
                grey,
            })
    }
}

/// The planes `pose` can see, each with its pixel box ([`PlaneInView::image_box`]).
fn planes_seen<'s>(
    scene: &'s Scene,
    pose: &StampedPose,
    camera: &PinholeRadtan,
) -> Vec<(PlaneInView<'s>, Option<[f64; 4]>)> {
    let r = pose.rotation.to_rotation_matrix();
    scene
        .facing(&pose.position, &(r * Vector3::z()))
        .into_iter()
        .map(|p| {
            let view = PlaneInView::new(p, pose);
            let image_box = view.image_box(pose, camera);
            (view, image_box)
        })
        .collect()
}

/// The poses a rolling shutter exposes its rows from: `samples` (at least 2) poses evenly
/// spaced in time over `readout_s` centred on `centre_s`, interpolated in `path` (sorted
/// by time; times beyond its ends take its end poses). Given to [`render_frame`] with
/// [`RenderOptions::rolling_shutter`], the first row is exposed at `centre_s - readout_s
/// / 2` and the last at `centre_s + readout_s / 2` exactly, whatever the path's sampling
/// (taking whole path samples instead rounded a 20 ms readout to 20.8 ms at 30 fps).
pub fn readout_poses(
    path: &[StampedPose],
    centre_s: f64,
    readout_s: f64,
    samples: usize,
) -> Vec<StampedPose> {
    let n = samples.max(2);
    (0..n)
        .filter_map(|k| {
            let t = centre_s + readout_s * (k as f64 / (n - 1) as f64 - 0.5);
            pose_at_time(path, t)
        })
        .collect()
}

/// The pose of `path` (sorted by time) at time `t`, interpolated between the samples
/// either side (clamped at its ends); `None` for an empty path.
pub(crate) fn pose_at_time(path: &[StampedPose], t: f64) -> Option<StampedPose> {
    let after = path.partition_point(|p| p.timestamp <= t);
    let (a, b) = match (after.checked_sub(1), path.get(after)) {
        (Some(i), Some(b)) => (&path[i], b),
        (Some(i), None) => {
            return Some(StampedPose {
                timestamp: t,
                ..path[i]
            })
        }
        (None, Some(b)) => return Some(StampedPose { timestamp: t, ..*b }),
        (None, None) => return None,
    };
    let f = (t - a.timestamp) / (b.timestamp - a.timestamp);
    Some(StampedPose {
        timestamp: t,
        position: a.position + (b.position - a.position) * f,
        rotation: a.rotation.slerp(&b.rotation, f),
    })
}

/// The pose a fraction `at` in [0, 1] along `poses` (equally spaced in time): centres
/// interpolated linearly, orientations by slerp.
fn interpolate(poses: &[StampedPose], at: f64) -> StampedPose {
    let x = at.clamp(0.0, 1.0) * (poses.len() - 1) as f64;
    let k = (x.floor() as usize).min(poses.len().saturating_sub(2));
    let (a, b) = (&poses[k], &poses[(k + 1).min(poses.len() - 1)]);
    let f = x - k as f64;
    StampedPose {
        timestamp: a.timestamp + (b.timestamp - a.timestamp) * f,
        position: a.position + (b.position - a.position) * f,
        rotation: a.rotation.slerp(&b.rotation, f),
    }
}

/// A plane as one row of pixels meets it: with the row's ray slope `y'` fixed, each dot
/// product of a pixel's ray with the plane's axes is `a x' + b`, with `b` the same for
/// the whole row.
struct PlaneInRow<'p, 's> {
    view: &'p PlaneInView<'s>,
    /// The columns' pixel-centre range outside which the ray misses the plane.
    x0: f64,
    x1: f64,
    /// `n_c . d`, `u_c . d`, `v_c . d` as (coefficient of x', rest).
    normal: (f64, f64),
    along_u: (f64, f64),
    along_v: (f64, f64),
}

/// Adds one pose's radiance to every pixel of `band` (and its z-depth when `depth_too`):
/// each pixel's ray against the planes its row can meet, the nearest hit's texture and
/// pictures at the pixel's footprint, 0.5 where nothing is hit. Row by row: the row's part
/// of each ray-plane product is formed once, and a hit no nearer than the best so far is
/// not tested against the plane's edges.
fn trace_band(
    band: &mut Band,
    planes: &[(PlaneInView, Option<[f64; 4]>)],
    camera: &PinholeRadtan,
    ray_x: &[f64],
    depth_too: bool,
    cache: &mut SampleCache,
) {
    let w = ray_x.len();
    // The planes a row can meet, in scene order (ties resolve as without the boxes).
    let mut row_planes: Vec<PlaneInRow> = Vec::new();
    let rows = band.radiance.chunks_mut(w).zip(band.depth.chunks_mut(w));
    for (r, (values, depths)) in rows.enumerate() {
        let y = (band.first_row + r) as f64 + 0.5;
        let ray_y = (y - camera.cy) / camera.fy;
        row_planes.clear();
        row_planes.extend(planes.iter().filter_map(|(p, b)| {
            let (x0, x1) = match b {
                None => (f64::NEG_INFINITY, f64::INFINITY),
                Some([x0, x1, y0, y1]) => (y >= *y0 && y <= *y1).then_some((*x0, *x1))?,
            };
            let row_part = |a: &Vector3<f64>| (a.x, a.y * ray_y + a.z);
            Some(PlaneInRow {
                view: p,
                x0,
                x1,
                normal: row_part(&p.n_c),
                along_u: row_part(&p.u_c),
                along_v: row_part(&p.v_c),
            })
        }));
        let row_norm2 = ray_y * ray_y + 1.0;
        for (c, (value, z)) in values.iter_mut().zip(depths.iter_mut()).enumerate() {
            let (x, rx) = (c as f64 + 0.5, ray_x[c]);
            // (t, u, v, n . d, plane) of the nearest hit in front (> 1 cm) on the plane.
            let mut best: Option<(f64, f64, f64, f64, &PlaneInView)> = None;
            for rp in &row_planes {
                if x < rp.x0 || x > rp.x1 {
                    continue;
                }
                let n_d = rp.normal.0 * rx + rp.normal.1;
                if n_d.abs() < 1e-12 {
                    continue;
                }
                let t = rp.view.k / n_d;
                if t <= 0.01 || best.is_some_and(|b| t >= b.0) {
                    continue;
                }
                let u = rp.view.u0 + t * (rp.along_u.0 * rx + rp.along_u.1);
                if u < 0.0 || u > rp.view.plane.width {
                    continue;
                }
                let v = rp.view.v0 + t * (rp.along_v.0 * rx + rp.along_v.1);
                if v >= 0.0 && v <= rp.view.plane.height {
                    best = Some((t, u, v, n_d, rp.view));
                }
            }
            let Some((t, u, v, n_d, p)) = best else {
                *value += 0.5;
                continue;
            };
            // Metres per pixel on the plane: distance over focal, stretched by the slant
            // of the surface (|cos| = |n.d| / |d|, at least 0.15).
            let norm = (rx * rx + row_norm2).sqrt();
            let footprint = if n_d.abs() >= 0.15 * norm {
                t * norm * norm / (camera.fx * n_d.abs())
            } else {
                t * norm / (camera.fx * 0.15)
            };
            let mut here = p.plane.texture.sample_cached(u, v, footprint, cache);
            for picture in &p.plane.pictures {
                if let Some((coverage, bright)) = picture.sample(u, v, footprint) {
                    here = here * (1.0 - coverage) + bright * coverage;
                }
            }
            *value += here;
            if depth_too {
                *z = t as f32; // d has z = 1: t is the z-depth
            }
        }
    }
}

/// Renders `poses` (one, or the sub-frame poses of a blurred frame) averaged, for frame
/// number `index` (noise and exposure depend on it).
pub fn render_frame(
    scene: &Scene,
    camera: &PinholeRadtan,
    poses: &[StampedPose],
    index: u64,
    options: &RenderOptions,
) -> Frame {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut radiance = vec![0f64; w * h];
    let mut depth = vec![0f32; w * h];
    let mut grey = vec![0u8; w * h];
    let threads = options.threads.clamp(1, 16);
    let rolling = options.rolling_shutter && poses.len() > 1;
    // Each (sub-frame) pose's planes, as seen from it; with a rolling shutter each row
    // gets its own below, and the frame is one exposure.
    let views: Vec<Vec<(PlaneInView, Option<[f64; 4]>)>> = if rolling {
        Vec::new()
    } else {
        poses
            .iter()
            .map(|pose| planes_seen(scene, pose, camera))
            .collect()
    };
    // Poses averaged per row with a rolling shutter (1 without blur).
    let row_blur = if rolling && options.rolling_exposure > 0.0 {
        options.blur_samples.max(1)
    } else {
        1
    };
    // Poses averaged, and the one whose depth is kept.
    let (n, centre) = if rolling {
        (row_blur as f64, 0)
    } else {
        (poses.len().max(1) as f64, poses.len() / 2)
    };
    // Each column's ray slope, once per frame instead of per pixel (the same division).
    let ray_x: Vec<f64> = (0..w)
        .map(|c| (c as f64 + 0.5 - camera.cx) / camera.fx)
        .collect();
    let gain =
        options.exposure_scale * (1.0 + options.exposure_drift * (index as f64 * 0.02).sin());
    // Bands of rows taken by whichever thread is free: a room's ceiling, walls and floor
    // cost differently, and the PNG writer shares the cores, so fixed halves of the image
    // left a core idle a third of the time.
    let bands = std::sync::Mutex::new(
        radiance
            .chunks_mut(BAND_ROWS * w)
            .zip(depth.chunks_mut(BAND_ROWS * w))
            .zip(grey.chunks_mut(BAND_ROWS * w))
            .enumerate()
            .map(|(b, ((radiance, depth), grey))| Band {
                first_row: b * BAND_ROWS,
                row_width: w,
                radiance,
                depth,
                grey,
            }),
    );
    let next_band = || bands.lock().ok().and_then(|mut it| it.next());
    std::thread::scope(|s| {
        for _ in 0..threads {
            let (views, next_band, ray_x) = (&views, &next_band, &ray_x);
            s.spawn(move || {
                let mut cache = SampleCache::default();
                while let Some(mut band) = next_band() {
                    if rolling {
                        for mut row in band.rows() {
                            let at = (row.first_row as f64 + 0.5) / h as f64;
                            for k in 0..row_blur {
                                // The row's place in the readout, then its exposure's
                                // sample k (the middle one keeps the depth).
                                let at = if row_blur > 1 {
                                    let e = options.rolling_exposure;
                                    let offset = k as f64 / (row_blur - 1) as f64 - 0.5;
                                    e / 2.0 + at * (1.0 - e) + offset * e
                                } else {
                                    at
                                };
                                let pose = interpolate(poses, at);
                                let planes = planes_seen(scene, &pose, camera);
                                let depth_too = k == row_blur / 2;
                                trace_band(&mut row, &planes, camera, ray_x, depth_too, &mut cache);
                            }
                        }
                    }
                    for (k, planes) in views.iter().enumerate() {
                        let depth_too = k == centre;
                        trace_band(&mut band, planes, camera, ray_x, depth_too, &mut cache);
                    }
                    let first = band.first_row * w;
                    // Grey levels per unit of summed radiance: a product per pixel, not a
                    // quotient (the last place differs; no grey level in the bench did).
                    let grey_per_radiance = 255.0 * gain / n;
                    for (i, (g, r)) in band.grey.iter_mut().zip(band.radiance.iter()).enumerate() {
                        let v = grey_per_radiance * r
                            + options.noise_sigma * gaussian(index, (first + i) as u64);
                        // Rounded half away from zero as `f64::round`, without its library
                        // call; the same for every value the clamp keeps.
                        let floor = fast_floor(v);
                        let rounded = if v - floor >= 0.5 { floor + 1.0 } else { floor };
                        *g = rounded.clamp(0.0, 255.0) as u8;
                    }
                }
            });
        }
    });
    Frame {
        width: camera.width,
        height: camera.height,
        grey,
        depth,
    }
}

/// Grey levels (before noise) to the sensor's bytes: the frame's Gaussian noise added,
/// rounded and clamped as [`render_frame`] does.
pub(crate) fn add_noise(levels: &[f64], index: u64, sigma: f64) -> Vec<u8> {
    levels
        .iter()
        .enumerate()
        .map(|(i, level)| {
            let v = level + sigma * gaussian(index, i as u64);
            v.round().clamp(0.0, 255.0) as u8
        })
        .collect()
}

#[cfg(test)]
mod tests;
