//! The rolling-shutter readout time, estimated from tracks alone.
//!
//! A rolling shutter exposes row `y` of an `h`-row image `(y - h/2) / h` of the readout
//! after the middle row, so a tracked point moving at image velocity `v` is seen `v` times
//! that offset away from where it was at the frame's (middle-row) time. Between two frames
//! of a turning head, the points' bearings at the middle-row times are related by one
//! rotation (the parallax of a head's few centimetres per frame is small against it); at
//! the wrong readout they are not. So the readout is the value whose correction
//! ([`crate::tracker_options::TrackerOptions::rolling_shutter_s`], the same first-order
//! model) lets one rotation per consecutive frame pair explain the tracks best: a search
//! over a grid of readouts of the mean, trimmed, rotation-only residual (the rotation-only
//! model and its trimming as in the solver's relative poses; the principle of
//! self-calibrating the line delay from image motion as in Oth et al., "Rolling Shutter
//! Camera Calibration", CVPR 2013, there with a calibration target).
//!
//! A global-shutter camera has its minimum at 0 or nowhere in particular: an estimate is
//! only reported when it lowers the residual by a clear margin
//! ([`ReadoutEstimationOptions::min_relative_gain`]). Measured (`egoslam
//! calibrate-readout`): rendered walks with a 30 ms readout 30 ms (150 and 300 frames), a
//! head shake rendered at 15 ms 16 ms, tum_fr1_rpy 22 ms (its pipeline ATE is lowest told
//! 20-30 ms), and 0 on every global-shutter sequence here (rendered walks, turns, shake,
//! dark, Aria replay, KITTI, EuRoC), whose best gains were 0.0-0.9 % against 7-33 % with a
//! rolling shutter.

use crate::tracker::TrackPoint;
use egoslam_geometry::{median, rotation_aligning_trimmed, PinholeRadtan};
use nalgebra::{Point2, Vector2, Vector3};
use std::collections::HashMap;

/// Options; defaults with their reason.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReadoutEstimationOptions {
    /// Longest readout searched, seconds (default 0.05: a 30 fps rolling-shutter sensor
    /// reads out in 10-33 ms; the search stays below the frame interval's 1.5x).
    pub max_readout_s: f64,
    /// Grid step, seconds (default 0.001: the pipeline's error moves little within +-5 ms
    /// of the right readout, e.g. tum_fr1_rpy 1.69 / 1.75 cm told 20 / 30 ms).
    pub step_s: f64,
    /// The best readout's residual must be this fraction below the residual at 0, else 0
    /// is returned (default 0.02: pinhole rolling-shutter sequences gained 7-33 %,
    /// global-shutter ones at most 0.9 %), for a lens of [`Self::gain_focal_px`] or longer.
    pub min_relative_gain: f64,
    /// Focal length (pixels per radian at the centre) at and above which
    /// [`Self::min_relative_gain`] applies as it is; a shorter one scales it down in
    /// proportion (default 500, the rendered pinhole walks it was measured on). The
    /// readout's misfit is an angle times the focal, in pixels, while the tracking noise
    /// that makes up the rest of the residual is pixels whatever the lens: through a
    /// 260 px/rad fisheye the same 20 ms readout gained 1.5 % against 6 % through a
    /// 500 px pinhole, and the fisheye's global-shutter renders 0-0.2 %.
    pub gain_focal_px: f64,
    /// Fewest usable frame pairs (default 20: about a second of video at 30 fps with turns).
    pub min_pairs: usize,
    /// Fewest tracks a frame pair must share with known velocities (default 30: the
    /// rotation fit and its trimming need a margin over 3).
    pub min_tracks: usize,
    /// Tracks of a frame pair used, evenly spread by track id (default 1000, the
    /// frontend's default track count: the fit then took 76 ms on tum_fr1_rpy's 120 frames
    /// and 270 ms on 300 rendered ones, little next to tracking them; 200 moved
    /// tum_fr1_rpy's estimate from 22 to 20 ms).
    pub max_tracks: usize,
    /// Frame pairs whose median track moved less than this, pixels, are left out
    /// (default 1.0): a still camera says nothing about the readout, and its pairs would
    /// dilute the relative gain of the others.
    pub min_motion_px: f64,
    /// The grid is searched coarse to fine: first every this many steps, then every step
    /// around the best coarse point (default 5: 11 + 9 residuals instead of 51).
    pub coarse_steps: usize,
}

impl Default for ReadoutEstimationOptions {
    fn default() -> Self {
        Self {
            max_readout_s: 0.05,
            step_s: 0.001,
            min_relative_gain: 0.02,
            gain_focal_px: 500.0,
            min_pairs: 20,
            min_tracks: 30,
            max_tracks: 1000,
            min_motion_px: 1.0,
            coarse_steps: 5,
        }
    }
}

impl ReadoutEstimationOptions {
    /// [`Self::min_relative_gain`] for a lens of `focal_px` pixels per radian (scaled down
    /// below [`Self::gain_focal_px`]).
    pub fn significant_gain(&self, focal_px: f64) -> f64 {
        self.min_relative_gain * (focal_px / self.gain_focal_px).min(1.0)
    }
}

/// The tracks of one frame, as the tracker reports them with no readout correction.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameTracks {
    pub timestamp_s: f64,
    pub tracks: Vec<TrackPoint>,
}

/// What [`estimate_readout`] found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReadoutEstimate {
    /// The readout to correct with, seconds: `best_s` when significant, else 0.
    pub readout_s: f64,
    /// The grid point with the lowest residual, seconds.
    pub best_s: f64,
    /// Mean trimmed rotation-only residual at `best_s`, pixels.
    pub residual_px: f64,
    /// The same at a global shutter (readout 0), pixels.
    pub residual_at_zero_px: f64,
    /// Frame pairs the residual is averaged over.
    pub pairs: usize,
    /// Whether `best_s` cleared [`ReadoutEstimationOptions::min_relative_gain`] (scaled to
    /// the lens) and lies inside the searched range.
    pub significant: bool,
}

/// Why no estimate could be made.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReadoutEstimationError {
    /// Too few consecutive frame pairs shared enough moving tracks (a short, blind or
    /// still input).
    #[error("only {pairs} frame pairs share {min_tracks} moving tracks; {needed} needed")]
    TooFewPairs {
        pairs: usize,
        min_tracks: usize,
        needed: usize,
    },
    /// The options make no grid (a step or a range that is not positive and finite).
    #[error("bad search grid: step {step_s} s up to {max_readout_s} s")]
    BadGrid { step_s: f64, max_readout_s: f64 },
}

/// One track seen in a frame, ready for any readout: its undistorted pixel, its image
/// velocity (pixels per second) and its row's offset from the middle row (fraction of
/// the readout).
#[derive(Debug, Clone, Copy)]
struct Sample {
    pixel: Vector2<f64>,
    velocity: Vector2<f64>,
    row_offset: f64,
}

impl Sample {
    /// The bearing at the middle row's time for `readout_s`.
    fn bearing(&self, camera: &PinholeRadtan, readout_s: f64) -> Vector3<f64> {
        let p = self.pixel - self.velocity * (self.row_offset * readout_s);
        camera.bearing_from_undistorted(Point2::new(p.x, p.y))
    }
}

/// A frame's undistorted track positions by track id.
type Positions = HashMap<u64, Vector2<f64>>;

fn positions(frame: &FrameTracks) -> Positions {
    frame
        .tracks
        .iter()
        .map(|t| {
            let u = t.undistorted;
            (t.track_id, Vector2::new(f64::from(u.x), f64::from(u.y)))
        })
        .collect()
}

/// The frame's tracks with velocities from the frames either side (central difference;
/// `before` and `after` are those frames' [`positions`] and times), keyed by track id;
/// tracks not seen in both neighbours are left out.
fn samples(
    camera: &PinholeRadtan,
    (before, before_s): (&Positions, f64),
    frame: &FrameTracks,
    (after, after_s): (&Positions, f64),
) -> HashMap<u64, Sample> {
    let dt = after_s - before_s;
    if dt.is_nan() || dt <= 0.0 {
        return HashMap::new();
    }
    frame
        .tracks
        .iter()
        .filter_map(|t| {
            let (pb, pa) = (before.get(&t.track_id)?, after.get(&t.track_id)?);
            let u = t.undistorted;
            Some((
                t.track_id,
                Sample {
                    pixel: Vector2::new(f64::from(u.x), f64::from(u.y)),
                    velocity: (pa - pb) / dt,
                    row_offset: camera.row_offset(f64::from(t.raw.y)),
                },
            ))
        })
        .collect()
}

/// Root-mean-square residual (pixels) of the best rotation between the pairs' bearings,
/// after trimming twice to 3x the median residual; NaN when trimming leaves under 3 pairs.
fn rotation_only_rms(pairs: &[(Vector3<f64>, Vector3<f64>)], focal_px: f64) -> f64 {
    let (r, kept, complete) =
        rotation_aligning_trimmed(pairs, |r, (a, b)| (r * a - b).norm(), 1e-12);
    if !complete {
        return f64::NAN;
    }
    let sq: f64 = kept.iter().map(|(a, b)| (r * a - b).norm_squared()).sum();
    (sq / kept.len() as f64).sqrt() * focal_px
}

/// Estimates the readout from consecutive frames' tracks (at least `min_pairs + 3`
/// frames, timestamps increasing).
pub fn estimate_readout(
    frames: &[FrameTracks],
    camera: &PinholeRadtan,
    options: &ReadoutEstimationOptions,
) -> Result<ReadoutEstimate, ReadoutEstimationError> {
    let _span = tracing::info_span!("estimate_readout", frames = frames.len()).entered();
    let (step, max) = (options.step_s, options.max_readout_s);
    if !(step > 0.0 && max >= 0.0 && step.is_finite() && max.is_finite()) {
        return Err(ReadoutEstimationError::BadGrid {
            step_s: step,
            max_readout_s: max,
        });
    }
    let indexed: Vec<Positions> = frames.iter().map(positions).collect();
    let neighbour = |k: usize| (&indexed[k], frames[k].timestamp_s);
    // A frame next to a gap (a frame skipped or dropped) is left out: its velocity, a
    // central difference over the longer interval, is off where the head accelerates.
    let interval = median(
        frames
            .windows(2)
            .map(|w| w[1].timestamp_s - w[0].timestamp_s)
            .collect(),
    );
    let evenly_spaced = |k: usize| {
        let (before, after) = (
            frames[k].timestamp_s - frames[k - 1].timestamp_s,
            frames[k + 1].timestamp_s - frames[k].timestamp_s,
        );
        before.max(after) <= 1.5 * interval
    };
    let per_frame: Vec<HashMap<u64, Sample>> = (1..frames.len().saturating_sub(1))
        .map(|k| {
            if evenly_spaced(k) {
                samples(camera, neighbour(k - 1), &frames[k], neighbour(k + 1))
            } else {
                HashMap::new()
            }
        })
        .collect();
    let pairs: Vec<Vec<(Sample, Sample)>> = per_frame
        .windows(2)
        .map(|w| {
            // In track-id order, so that the sums and the estimate do not depend on the
            // maps' iteration order.
            let mut shared: Vec<(u64, Sample, Sample)> = w[0]
                .iter()
                .filter_map(|(id, a)| Some((*id, *a, *w[1].get(id)?)))
                .collect();
            shared.sort_unstable_by_key(|(id, _, _)| *id);
            let stride = shared.len().div_ceil(options.max_tracks.max(1)).max(1);
            shared
                .iter()
                .step_by(stride)
                .map(|(_, a, b)| (*a, *b))
                .collect::<Vec<_>>()
        })
        .filter(|p| {
            p.len() >= options.min_tracks.min(options.max_tracks)
                && median(p.iter().map(|(a, b)| (b.pixel - a.pixel).norm()).collect())
                    >= options.min_motion_px
        })
        .collect();
    if pairs.len() < options.min_pairs {
        return Err(ReadoutEstimationError::TooFewPairs {
            pairs: pairs.len(),
            min_tracks: options.min_tracks,
            needed: options.min_pairs,
        });
    }
    let focal = camera.fx;
    let residual = |readout: f64| -> f64 {
        let (sum, n) = pairs
            .iter()
            .map(|p| {
                let bearings: Vec<_> = p
                    .iter()
                    .map(|(a, b)| (a.bearing(camera, readout), b.bearing(camera, readout)))
                    .collect();
                rotation_only_rms(&bearings, focal)
            })
            .filter(|r| r.is_finite())
            .fold((0.0, 0usize), |(s, n), r| (s + r, n + 1));
        if n == 0 {
            f64::INFINITY
        } else {
            sum / n as f64
        }
    };
    let steps = (max / step).round() as usize;
    let coarse = options.coarse_steps.max(1);
    let at_zero = residual(0.0);
    let (mut best_k, mut best) = (0, at_zero);
    let consider = |k: usize, best_k: &mut usize, best: &mut f64| {
        let r = residual(k as f64 * step);
        if r < *best {
            (*best_k, *best) = (k, r);
        }
    };
    for k in (coarse..=steps).step_by(coarse) {
        consider(k, &mut best_k, &mut best);
    }
    let centre = best_k;
    for k in centre.saturating_sub(coarse - 1)..=(centre + coarse - 1).min(steps) {
        if k % coarse != 0 {
            consider(k, &mut best_k, &mut best);
        }
    }
    let best_s = best_k as f64 * step;
    let min_gain = options.significant_gain(focal);
    // A residual still falling at the longest readout searched (1.5 frame intervals) has
    // no minimum there: something else than a readout is being fitted (the rendered
    // egomotion profile through a global-shutter fisheye: its parallax gained 1.2 % at
    // the 50 ms limit).
    let inside = best_k < steps;
    let significant = inside && best < at_zero * (1.0 - min_gain);
    Ok(ReadoutEstimate {
        readout_s: if significant { best_s } else { 0.0 },
        best_s,
        residual_px: best,
        residual_at_zero_px: at_zero,
        pairs: pairs.len(),
        significant,
    })
}

/// The estimation on a live stream, where nothing can be read ahead: frames are collected
/// as they are tracked (with no correction) and the readout is estimated once `frames`
/// are in; an input that gives no estimate (still, blind) is retried on the next `frames`,
/// `attempts` times in all, and then taken as a global shutter.
#[derive(Debug, Clone)]
pub struct OnlineReadoutEstimator {
    options: ReadoutEstimationOptions,
    frames: usize,
    attempts_left: u32,
    attempts: u32,
    collected: Vec<FrameTracks>,
    early: Option<EarlyGlobalShutter>,
}

/// A global shutter decided before the attempt's frames are in: the frames held for the
/// estimate (a live stream's keyframes, readout_hold.rs) wait on it, and a global-shutter
/// camera, which most are, has nothing to wait for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EarlyGlobalShutter {
    /// Frames of the first attempt after which it is tried (at least `min_pairs + 3`).
    pub frames: usize,
    /// Largest relative gain of the best readout over a global shutter that decides it,
    /// as a fraction of [`ReadoutEstimationOptions::min_relative_gain`] (scaled to the
    /// lens as it is).
    pub max_gain_share: f64,
}

impl Default for EarlyGlobalShutter {
    /// 75 frames (2.5 s at 30 fps) and half the significant gain (1 % through a 500 px
    /// lens): over their first 60-90 frames the rendered global-shutter walks gained
    /// 0.6-0.9 % (pinhole) and 0.1 % (fisheye), rolling-shutter inputs (a 30 ms render,
    /// TUM fr1) 3.9-5.6 %; over 45 frames a global shutter still gained 1.9 %. Anything
    /// not clearly a global shutter waits for the whole attempt, whose longer estimate
    /// the readout's value needs (35 ms from 120 frames of the 30 ms render, 46-50 ms
    /// from 60-90).
    fn default() -> Self {
        Self {
            frames: 75,
            max_gain_share: 0.5,
        }
    }
}

/// What [`OnlineReadoutEstimator::push`] decided.
#[derive(Debug, Clone, PartialEq)]
pub enum OnlineReadout {
    /// Still collecting frames.
    Collecting,
    /// Estimated: correct with `readout_s` from now on.
    Estimated(ReadoutEstimate),
    /// No estimate after every attempt (the last error): a global shutter is assumed.
    GaveUp(ReadoutEstimationError),
}

impl OnlineReadoutEstimator {
    /// Collects `frames` frames per attempt, `attempts` times at most.
    pub fn new(options: ReadoutEstimationOptions, frames: usize, attempts: u32) -> Self {
        Self {
            options,
            frames: frames.max(options.min_pairs + 3),
            attempts_left: attempts.max(1),
            attempts: attempts.max(1),
            collected: Vec::new(),
            early: None,
        }
    }

    /// Also decides a global shutter early (see [`EarlyGlobalShutter`]).
    pub fn deciding_global_shutter_early(self, early: EarlyGlobalShutter) -> Self {
        Self {
            early: Some(early),
            ..self
        }
    }

    /// The early decision, when it is time for it and the frames so far clearly show a
    /// global shutter.
    fn global_shutter_early(&self, camera: &PinholeRadtan) -> Option<ReadoutEstimate> {
        let early = self.early?;
        let at = early.frames.max(self.options.min_pairs + 3);
        if !self.in_first_attempt() || self.collected.len() != at || at >= self.frames {
            return None;
        }
        let estimate = estimate_readout(&self.collected, camera, &self.options).ok()?;
        let min_gain = self.options.significant_gain(camera.fx);
        let gain = 1.0 - estimate.residual_px / estimate.residual_at_zero_px;
        tracing::info!(
            frames = at,
            gain,
            best_ms = estimate.best_s * 1e3,
            "rolling-shutter readout: early check for a global shutter"
        );
        (gain < early.max_gain_share * min_gain).then_some(ReadoutEstimate {
            readout_s: 0.0,
            significant: false,
            ..estimate
        })
    }

    /// Adds the next frame's tracks (as the tracker reports them without correction).
    pub fn push(&mut self, frame: FrameTracks, camera: &PinholeRadtan) -> OnlineReadout {
        self.collected.push(frame);
        if let Some(global) = self.global_shutter_early(camera) {
            self.collected.clear();
            self.attempts_left = 0;
            return OnlineReadout::Estimated(global);
        }
        if self.collected.len() < self.frames {
            return OnlineReadout::Collecting;
        }
        let result = estimate_readout(&self.collected, camera, &self.options);
        self.collected.clear();
        self.attempts_left = self.attempts_left.saturating_sub(1);
        match result {
            Ok(estimate) => OnlineReadout::Estimated(estimate),
            Err(e) if self.attempts_left == 0 => OnlineReadout::GaveUp(e),
            Err(_) => OnlineReadout::Collecting,
        }
    }

    /// Whether the first attempt is still collecting.
    pub fn in_first_attempt(&self) -> bool {
        self.attempts_left == self.attempts
    }

    /// The estimate from the frames collected so far, when the stream ends before an
    /// attempt is complete (a short recording: as reading it ahead would).
    pub fn finish(
        &mut self,
        camera: &PinholeRadtan,
    ) -> Result<ReadoutEstimate, ReadoutEstimationError> {
        let collected = std::mem::take(&mut self.collected);
        // Too few frames make too few pairs: `estimate_readout` says so.
        estimate_readout(&collected, camera, &self.options)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3 as V3};
    const JIT: f64 = 0.3;

    /// A camera turning at a changing rate among far points, imaged by a rolling shutter of
    /// `readout_s` (each point's row time found by fixed-point iteration), 0.3 px noise.
    fn turning_camera(readout_s: f64) -> (PinholeRadtan, Vec<FrameTracks>) {
        turning_lens(500.0, readout_s, JIT)
    }

    /// [`turning_camera`] through a lens of `focal` pixels per radian, with `jitter` px of
    /// noise (uniform, peak to peak).
    fn turning_lens(
        focal: f64,
        readout_s: f64,
        jitter_px: f64,
    ) -> (PinholeRadtan, Vec<FrameTracks>) {
        let camera =
            PinholeRadtan::new(640, 480, [focal, focal, 320.0, 240.0], [0.0; 5]).expect("camera");
        let points: Vec<V3<f64>> = (0..400)
            .map(|k| {
                let a = k as f64;
                V3::new((a * 0.37).sin() * 4.0, (a * 0.11).cos() * 3.0, 8.0)
            })
            .collect();
        let attitude = |t: f64| {
            Rotation3::from_euler_angles(0.5 * (3.0 * t).sin(), 0.8 * (2.0 * t).sin(), 0.1 * t)
        };
        let mut noise = 0x2545_F491_4F6C_DD1Du64;
        let mut jitter = || {
            noise ^= noise << 13;
            noise ^= noise >> 7;
            noise ^= noise << 17;
            ((noise >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * jitter_px
        };
        let frames = (0..40)
            .map(|f| {
                let t0 = f as f64 / 30.0;
                let tracks = points
                    .iter()
                    .enumerate()
                    .filter_map(|(id, p)| {
                        let mut row = 240.0;
                        let mut pixel = None;
                        for _ in 0..5 {
                            let t = t0 + (row / 480.0 - 0.5) * readout_s;
                            let q = attitude(t).inverse() * p;
                            let px = camera.project_undistorted(&q)?;
                            row = px.y;
                            pixel = Some(px);
                        }
                        let px = pixel?;
                        let (x, y) = ((px.x + jitter()) as f32, (px.y + jitter()) as f32);
                        camera.contains(px).then(|| TrackPoint {
                            track_id: id as u64,
                            raw: Point2::new(x, y),
                            undistorted: Point2::new(x, y),
                            image_velocity: None,
                        })
                    })
                    .collect();
                FrameTracks {
                    timestamp_s: t0,
                    tracks,
                }
            })
            .collect();
        (camera, frames)
    }

    #[test]
    fn finds_the_readout_of_a_rolling_shutter() {
        let (camera, frames) = turning_camera(0.025);
        let e = estimate_readout(&frames, &camera, &ReadoutEstimationOptions::default())
            .expect("estimate");
        assert!(e.significant, "{e:?}");
        assert!((e.readout_s - 0.025).abs() <= 0.002, "{e:?}");
    }

    #[test]
    fn a_short_focal_needs_a_smaller_gain() {
        // Through 260 px/rad with 0.7 px of noise a 20 ms readout lowers the residual by
        // ~1.7 % (the same noise through 500 px: ~4.6 %), below the pinhole's 2 %.
        let (camera, frames) = turning_lens(260.0, 0.02, 0.7);
        let options = ReadoutEstimationOptions::default();
        let e = estimate_readout(&frames, &camera, &options).expect("estimate");
        assert!(e.significant, "{e:?}");
        assert!((e.readout_s - 0.02).abs() <= 0.005, "{e:?}");
        let gain = 1.0 - e.residual_px / e.residual_at_zero_px;
        assert!((0.0104..0.02).contains(&gain), "gain {gain}");
        let unscaled = ReadoutEstimationOptions {
            gain_focal_px: 260.0,
            ..options
        };
        let e = estimate_readout(&frames, &camera, &unscaled).expect("estimate");
        assert!(!e.significant, "{e:?}");
        let (camera, frames) = turning_lens(260.0, 0.0, 0.7);
        let e = estimate_readout(&frames, &camera, &options).expect("estimate");
        assert_eq!(e.readout_s, 0.0, "{e:?}");
    }

    #[test]
    fn a_minimum_beyond_the_searched_range_is_not_a_readout() {
        // 80 ms: the residual still falls at the 50 ms limit, by half.
        let (camera, frames) = turning_camera(0.08);
        let e = estimate_readout(&frames, &camera, &ReadoutEstimationOptions::default())
            .expect("estimate");
        assert_eq!(e.best_s, 0.05, "{e:?}");
        assert!(e.residual_px < 0.6 * e.residual_at_zero_px, "{e:?}");
        assert!(!e.significant && e.readout_s == 0.0, "{e:?}");
    }

    #[test]
    fn a_global_shutter_gives_zero() {
        let (camera, frames) = turning_camera(0.0);
        let e = estimate_readout(&frames, &camera, &ReadoutEstimationOptions::default())
            .expect("estimate");
        assert_eq!(e.readout_s, 0.0, "{e:?}");
        assert!(!e.significant || e.best_s <= 0.002, "{e:?}");
    }

    /// A global shutter is decided at the early check; a rolling shutter waits for the
    /// attempt's frames and gets its readout from all of them.
    #[test]
    fn a_global_shutter_is_decided_early_and_a_rolling_one_waits() {
        let early = EarlyGlobalShutter {
            frames: 30,
            max_gain_share: 0.5,
        };
        let decide = |readout_s: f64| {
            let (camera, frames) = turning_camera(readout_s);
            let mut online =
                OnlineReadoutEstimator::new(ReadoutEstimationOptions::default(), 40, 2)
                    .deciding_global_shutter_early(early);
            frames
                .iter()
                .enumerate()
                .find_map(|(k, f)| match online.push(f.clone(), &camera) {
                    OnlineReadout::Collecting => None,
                    other => Some((k, other)),
                })
        };
        match decide(0.0) {
            Some((29, OnlineReadout::Estimated(e))) => assert_eq!(e.readout_s, 0.0, "{e:?}"),
            other => panic!("{other:?}"),
        }
        match decide(0.025) {
            Some((39, OnlineReadout::Estimated(e))) => {
                assert!((e.readout_s - 0.025).abs() <= 0.002, "{e:?}")
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn online_estimation_decides_after_its_frames_and_gives_up_on_a_still_camera() {
        let (camera, frames) = turning_camera(0.025);
        let mut online = OnlineReadoutEstimator::new(ReadoutEstimationOptions::default(), 40, 2);
        let mut decided = None;
        for (k, f) in frames.iter().enumerate() {
            match online.push(f.clone(), &camera) {
                OnlineReadout::Collecting => assert!(k < 39, "frame {k}"),
                other => decided = Some((k, other)),
            }
        }
        match decided {
            Some((39, OnlineReadout::Estimated(e))) => {
                assert!((e.readout_s - 0.025).abs() <= 0.002, "{e:?}")
            }
            other => panic!("{other:?}"),
        }
        // A camera that does not move: two attempts, then a global shutter.
        let still = FrameTracks {
            timestamp_s: 0.0,
            tracks: frames[0].tracks.clone(),
        };
        let mut online = OnlineReadoutEstimator::new(ReadoutEstimationOptions::default(), 30, 2);
        let outcomes: Vec<OnlineReadout> = (0..60)
            .map(|k| {
                let mut f = still.clone();
                f.timestamp_s = k as f64 / 30.0;
                online.push(f, &camera)
            })
            .collect();
        assert!(outcomes[..59]
            .iter()
            .all(|o| *o == OnlineReadout::Collecting));
        assert!(
            matches!(
                outcomes[59],
                OnlineReadout::GaveUp(ReadoutEstimationError::TooFewPairs { .. })
            ),
            "{:?}",
            outcomes[59]
        );
        // A stream that ends first: the estimate of what came, an error for none or one.
        let mut short = OnlineReadoutEstimator::new(ReadoutEstimationOptions::default(), 60, 2);
        frames
            .iter()
            .for_each(|f| assert_eq!(short.push(f.clone(), &camera), OnlineReadout::Collecting));
        let e = short.finish(&camera).expect("40 frames estimate");
        assert!((e.readout_s - 0.025).abs() <= 0.002, "{e:?}");
        for n in 0..2 {
            let mut empty = OnlineReadoutEstimator::new(ReadoutEstimationOptions::default(), 60, 2);
            frames[..n].iter().for_each(|f| {
                empty.push(f.clone(), &camera);
            });
            assert!(matches!(
                empty.finish(&camera),
                Err(ReadoutEstimationError::TooFewPairs { .. })
            ));
        }
    }

    #[test]
    fn too_few_frames_or_a_bad_grid_are_errors() {
        let (camera, frames) = turning_camera(0.0);
        assert!(matches!(
            estimate_readout(&frames[..10], &camera, &ReadoutEstimationOptions::default()),
            Err(ReadoutEstimationError::TooFewPairs { .. })
        ));
        let bad = ReadoutEstimationOptions {
            step_s: 0.0,
            ..Default::default()
        };
        assert!(matches!(
            estimate_readout(&frames, &camera, &bad),
            Err(ReadoutEstimationError::BadGrid { .. })
        ));
    }
}
