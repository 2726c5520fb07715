//! Camera paths (world_from_camera poses at the frame times): the paper's three profiles,
//! a procedural head-mounted walker, and replays of recorded head trajectories.

use egoslam_geometry::StampedPose;
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use std::f64::consts::{PI, TAU};

/// Why a recorded trajectory could not be replayed.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PathError {
    /// A line could not be parsed.
    #[error("line {line}: {problem}")]
    Parse { line: usize, problem: String },
    /// Fewer than two poses.
    #[error("the trajectory has fewer than two poses")]
    TooShort,
}

/// Parameters of the procedural walker; defaults are a brisk indoor walk with the head
/// scanning as people do (the ranges: yaw scans +-30-60 deg at 0.3-1 Hz).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WalkerOptions {
    /// Walking speed, m/s (default 1.2).
    pub speed: f64,
    /// Step frequency, Hz, and vertical head bob amplitude, m (default 1.8 Hz, 3 cm).
    pub step_hz: f64,
    pub bob_m: f64,
    /// Head yaw scan: amplitude (deg) and frequency (Hz); default 45 deg at 0.4 Hz.
    pub scan_deg: f64,
    pub scan_hz: f64,
    /// A downward glance of this many degrees every `glance_every_s` (default 20, 7 s).
    pub glance_deg: f64,
    pub glance_every_s: f64,
    /// A stop of `stop_s` every `stop_every_s` (default 2 s every 25 s).
    pub stop_every_s: f64,
    pub stop_s: f64,
    /// A full 360 deg turn on the spot every `turn_every_s` (default 60 s), lasting 4 s.
    pub turn_every_s: f64,
    /// Half side of the square loop walked around the room's central block, m (default 5).
    pub loop_half_side: f64,
    /// Largest body turn rate, deg/s: corners become sharp 90 deg turns (default 180).
    pub max_turn_rate_deg: f64,
}

impl Default for WalkerOptions {
    fn default() -> Self {
        Self {
            speed: 1.2,
            step_hz: 1.8,
            bob_m: 0.03,
            scan_deg: 45.0,
            scan_hz: 0.4,
            glance_deg: 20.0,
            glance_every_s: 7.0,
            stop_every_s: 25.0,
            stop_s: 2.0,
            turn_every_s: 60.0,
            loop_half_side: 5.0,
            max_turn_rate_deg: 180.0,
        }
    }
}

/// A camera path.
#[derive(Debug, Clone, PartialEq)]
pub enum CameraPath {
    /// Paper: straight towards the planes, 2.0 m.
    Frontal,
    /// Paper: sideways past the planes, 4.0 m.
    LeftRight,
    /// Paper: a 3.7 m walk towards the planes with head yaw, pitch and bob.
    Egomotion,
    /// A walk around the room's central block.
    Walker(WalkerOptions),
    /// A recorded trajectory, re-expressed relative to its first pose and started where
    /// the walker starts.
    Replay(Vec<StampedPose>),
    /// The walker with one hard event 3 s in (the robustness cases); the walk
    /// resumes after it.
    Event(RobustnessEvent),
}

/// A hard moment for a SLAM system, inserted into a walk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RobustnessEvent {
    /// Standing still, the head turns 60 deg to one side and back (4 s): no translation.
    PureRotation,
    /// A full 360 deg turn on the spot (4 s).
    Spin,
    /// The camera does not move at all for 5 s.
    Static,
    /// A fast head shake: +-20 deg yaw at 3 Hz for 2 s while walking.
    Shake,
    /// The image goes dark for 1 s (lens covered, lights off): the renderer's job, the
    /// path is the plain walk.
    Dark,
    /// The wearer stops and the image goes dark for 2 s (lights off, lens covered), then
    /// the walk goes on from where it stopped: tracking is lost for certain, and the view
    /// after it is the view before it (issue 7's forced blackout, for relocalization and
    /// segment linking).
    Blackout,
}

impl RobustnessEvent {
    /// When the event starts and how long it lasts, seconds.
    pub fn window(self) -> (f64, f64) {
        let duration = match self {
            RobustnessEvent::PureRotation | RobustnessEvent::Spin => 4.0,
            RobustnessEvent::Static => 5.0,
            RobustnessEvent::Shake => 2.0,
            RobustnessEvent::Dark => 1.0,
            RobustnessEvent::Blackout => 2.0,
        };
        (3.0, duration)
    }
}

/// Camera orientation from head yaw (about the world's vertical), pitch (about the
/// camera's x, positive looks down) and roll.
fn orientation(yaw: f64, pitch: f64, roll: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw)
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), -pitch)
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll)
}

fn pose(t: f64, position: Vector3<f64>, rotation: UnitQuaternion<f64>) -> StampedPose {
    StampedPose {
        timestamp: t,
        position,
        rotation,
    }
}

/// Where and how the walker starts: a loop corner, facing along the first side.
fn walker_start(half: f64) -> StampedPose {
    pose(
        0.0,
        Vector3::new(-half, 0.0, -half),
        orientation(PI / 2.0, 0.0, 0.0),
    )
}

impl CameraPath {
    /// Poses at `frames` instants `1/fps` apart, starting at t = 0.
    pub fn poses(&self, frames: usize, fps: f64) -> Vec<StampedPose> {
        let duration = (frames.max(2) - 1) as f64 / fps;
        let times = (0..frames).map(|i| i as f64 / fps);
        match self {
            CameraPath::Frontal => times
                .map(|t| {
                    pose(
                        t,
                        Vector3::new(0.0, 0.0, 2.0 * t / duration),
                        orientation(0.0, 0.0, 0.0),
                    )
                })
                .collect(),
            CameraPath::LeftRight => times
                .map(|t| {
                    pose(
                        t,
                        Vector3::new(-2.0 + 4.0 * t / duration, 0.0, 0.0),
                        orientation(0.0, 0.0, 0.0),
                    )
                })
                .collect(),
            CameraPath::Egomotion => times
                .map(|t| {
                    let s = t / duration;
                    let position = Vector3::new(
                        0.03 * (TAU * 0.9 * t).sin(),
                        0.03 * (TAU * 1.8 * t).sin(),
                        3.7 * s,
                    );
                    let yaw = 20f64.to_radians() * (TAU * 0.4 * t).sin();
                    let pitch = 6f64.to_radians() * (TAU * 0.7 * t).sin();
                    pose(
                        t,
                        position,
                        orientation(yaw, pitch, 0.02 * (TAU * 0.9 * t).sin()),
                    )
                })
                .collect(),
            CameraPath::Walker(o) => walk(o, frames, fps),
            CameraPath::Replay(recorded) => replay(recorded, frames, fps),
            CameraPath::Event(event) => with_event(*event, frames, fps),
        }
    }
}

/// Smooth bump in [0, 1] over a window of `width` seconds starting at each multiple of
/// `period` (raised cosine).
fn bump(t: f64, period: f64, width: f64) -> f64 {
    let phase = t.rem_euclid(period);
    if phase < width {
        0.5 - 0.5 * (TAU * phase / width).cos()
    } else {
        0.0
    }
}

fn walk(o: &WalkerOptions, frames: usize, fps: f64) -> Vec<StampedPose> {
    let half = o.loop_half_side;
    let corners = [
        Vector3::new(-half, 0.0, -half),
        Vector3::new(half, 0.0, -half),
        Vector3::new(half, 0.0, half),
        Vector3::new(-half, 0.0, half),
    ];
    let side = 2.0 * half;
    let dt = 1.0 / fps;
    let mut distance: f64 = 0.0;
    let mut body_yaw = PI / 2.0; // facing +x, along the first side
    let mut spin: f64 = 0.0;
    let mut step_phase: f64 = 0.0;
    let mut out = Vec::with_capacity(frames);
    for i in 0..frames {
        let t = i as f64 * dt;
        let turning = o.turn_every_s > 0.0 && t > 5.0 && (t - 5.0).rem_euclid(o.turn_every_s) < 4.0;
        let stopped = turning || (t > 3.0 && (t - 3.0).rem_euclid(o.stop_every_s) < o.stop_s);
        // Position on the square loop by walked distance.
        let along = distance.rem_euclid(4.0 * side);
        let k = (along / side).floor() as usize % 4;
        let (a, b) = (corners[k], corners[(k + 1) % 4]);
        let dir = (b - a) / side;
        let base = a + dir * (along - k as f64 * side);
        // The body turns towards the walking direction, rate-limited: sharp corners.
        let target = dir.x.atan2(dir.z);
        let error = (target - body_yaw + PI).rem_euclid(TAU) - PI;
        let max_step = o.max_turn_rate_deg.to_radians() * dt;
        body_yaw += error.clamp(-max_step, max_step);
        if turning {
            spin += TAU / 4.0 * dt;
        } else {
            // Finish a started spin at the next full turn, then hold.
            spin = (spin / TAU).round() * TAU;
        }
        if !stopped {
            distance += o.speed * dt;
            step_phase += TAU * o.step_hz * dt;
        }
        let moving = if stopped { 0.0 } else { 1.0 };
        let scan_amplitude = o.scan_deg.to_radians() * (0.75 + 0.25 * (TAU * 0.05 * t).sin());
        let yaw = body_yaw + spin + scan_amplitude * (TAU * o.scan_hz * t).sin();
        let pitch = o.glance_deg.to_radians() * bump(t, o.glance_every_s, 1.2);
        let bob = Vector3::new(0.0, -o.bob_m * moving * step_phase.sin(), 0.0);
        let sway = Vector3::new(dir.z, 0.0, -dir.x) * 0.015 * moving * (0.5 * step_phase).sin();
        out.push(pose(
            t,
            base + bob + sway,
            orientation(yaw, pitch, 0.01 * moving * (0.5 * step_phase).sin()),
        ));
    }
    out
}

/// A walk (no periodic stops or turns of its own) with `event` inserted at its start time.
fn with_event(event: RobustnessEvent, frames: usize, fps: f64) -> Vec<StampedPose> {
    let calm = WalkerOptions {
        stop_s: 0.0,
        turn_every_s: 0.0,
        ..WalkerOptions::default()
    };
    let walk = walk(&calm, frames, fps);
    let (start, duration) = event.window();
    let begin = ((start * fps) as usize).min(frames.saturating_sub(1));
    let event_frames = ((duration * fps) as usize).min(frames - begin);
    let at = walk[begin];
    let mut out: Vec<StampedPose> = walk[..begin].to_vec();
    for k in 0..event_frames {
        let t = (begin + k) as f64 / fps;
        let s = k as f64 / event_frames.max(1) as f64;
        let yaw = |angle: f64| UnitQuaternion::from_axis_angle(&Vector3::y_axis(), angle);
        let p = match event {
            RobustnessEvent::PureRotation => pose(
                t,
                at.position,
                yaw(60f64.to_radians() * (PI * s).sin()) * at.rotation,
            ),
            RobustnessEvent::Spin => pose(t, at.position, yaw(TAU * s) * at.rotation),
            RobustnessEvent::Static | RobustnessEvent::Blackout => {
                pose(t, at.position, at.rotation)
            }
            RobustnessEvent::Shake => {
                let w = walk[begin + k];
                pose(
                    t,
                    w.position,
                    yaw(20f64.to_radians() * (TAU * 3.0 * (t - start)).sin()) * w.rotation,
                )
            }
            RobustnessEvent::Dark => walk[begin + k],
        };
        out.push(p);
    }
    // The walk resumes where it was (moving events continue it in place).
    let resumed = if matches!(event, RobustnessEvent::Shake | RobustnessEvent::Dark) {
        begin + event_frames
    } else {
        begin
    };
    for w in &walk[resumed..] {
        if out.len() >= frames {
            break;
        }
        out.push(StampedPose {
            timestamp: out.len() as f64 / fps,
            ..*w
        });
    }
    out
}

fn replay(recorded: &[StampedPose], frames: usize, fps: f64) -> Vec<StampedPose> {
    let start = walker_start(WalkerOptions::default().loop_half_side);
    let Some(first) = recorded.first() else {
        return Vec::new();
    };
    let to_first = |p: &StampedPose| {
        (
            first.rotation.inverse() * (p.position - first.position),
            first.rotation.inverse() * p.rotation,
        )
    };
    let t0 = first.timestamp;
    let mut out = Vec::with_capacity(frames);
    let mut j = 0;
    for i in 0..frames {
        let t = t0 + i as f64 / fps;
        while j + 2 < recorded.len() && recorded[j + 1].timestamp < t {
            j += 1;
        }
        let (a, b) = (&recorded[j], &recorded[(j + 1).min(recorded.len() - 1)]);
        if t > b.timestamp {
            break;
        }
        let span = (b.timestamp - a.timestamp).max(1e-12);
        let w = ((t - a.timestamp) / span).clamp(0.0, 1.0);
        let (pa, ra) = to_first(a);
        let (pb, rb) = to_first(b);
        let (p, r) = (pa.lerp(&pb, w), ra.slerp(&rb, w));
        out.push(pose(
            t - t0,
            start.position + start.rotation * p,
            start.rotation * r,
        ));
    }
    out
}

/// A head trajectory from a Project Aria MPS `closed_loop_trajectory.csv` (or HOT3D
/// `headset_trajectory.csv`), as camera poses (x right, y down, z forward) in a world with
/// gravity along +y. Aria's device axes are not the camera's, so the forward axis is taken
/// as the device axis that best follows the horizontal walking direction, and up as the one
/// most opposed to gravity (MPS world: z up).
pub fn aria_head_trajectory(csv: &str) -> Result<Vec<StampedPose>, PathError> {
    let mut lines = csv.lines().enumerate();
    let (_, header) = lines.next().ok_or(PathError::TooShort)?;
    let columns: Vec<&str> = header.split(',').map(str::trim).collect();
    let find = |names: &[&str]| columns.iter().position(|c| names.contains(c));
    let parse_err = |line: usize, problem: &str| PathError::Parse {
        line,
        problem: problem.into(),
    };
    let time = find(&["tracking_timestamp_us", "timestamp[ns]"])
        .ok_or_else(|| parse_err(1, "no timestamp column"))?;
    let scale = if columns[time].ends_with("[ns]") {
        1e-9
    } else {
        1e-6
    };
    let cols = [
        find(&["tx_world_device", "t_wo_x[m]"]),
        find(&["ty_world_device", "t_wo_y[m]"]),
        find(&["tz_world_device", "t_wo_z[m]"]),
        find(&["qw_world_device", "q_wo_w"]),
        find(&["qx_world_device", "q_wo_x"]),
        find(&["qy_world_device", "q_wo_y"]),
        find(&["qz_world_device", "q_wo_z"]),
    ];
    let mut raw: Vec<(f64, Vector3<f64>, UnitQuaternion<f64>)> = Vec::new();
    for (n, line) in lines {
        let fields: Vec<&str> = line.split(',').collect();
        let value = |c: Option<usize>| -> Result<f64, PathError> {
            let c = c.ok_or_else(|| parse_err(1, "missing pose column"))?;
            fields
                .get(c)
                .and_then(|f| f.trim().parse().ok())
                .ok_or_else(|| parse_err(n + 1, "not a number"))
        };
        let t = value(Some(time))? * scale;
        let p = Vector3::new(value(cols[0])?, value(cols[1])?, value(cols[2])?);
        let q = nalgebra::Quaternion::new(
            value(cols[3])?,
            value(cols[4])?,
            value(cols[5])?,
            value(cols[6])?,
        );
        if raw.last().is_some_and(|(last, _, _)| t <= *last) {
            continue;
        }
        raw.push((t, p, UnitQuaternion::from_quaternion(q)));
    }
    if raw.len() < 2 {
        return Err(PathError::TooShort);
    }
    // MPS world (z up) -> ours (y down).
    let world = Rotation3::from_matrix_unchecked(Matrix3::new(
        1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0,
    ));
    let axes = [
        Vector3::x(),
        -Vector3::x(),
        Vector3::y(),
        -Vector3::y(),
        Vector3::z(),
        -Vector3::z(),
    ];
    let mut forward_score = [0.0; 6];
    let mut up_score = [0.0; 6];
    for w in raw.windows(2) {
        let velocity = (w[1].1 - w[0].1) / (w[1].0 - w[0].0);
        let horizontal = Vector3::new(velocity.x, velocity.y, 0.0);
        for (i, a) in axes.iter().enumerate() {
            let d = w[0].2 * a;
            up_score[i] += d.z;
            if horizontal.norm() > 0.3 {
                forward_score[i] += d.dot(&horizontal.normalize());
            }
        }
    }
    let best = |s: &[f64; 6], skip: Option<usize>| {
        (0..6)
            .filter(|i| skip.is_none_or(|k| i / 2 != k / 2))
            .max_by(|a, b| s[*a].total_cmp(&s[*b]))
            .unwrap_or(0)
    };
    let up = best(&up_score, None);
    let forward = best(&forward_score, Some(up));
    let (z_c, y_c) = (axes[forward], -axes[up]);
    let device_from_camera =
        Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[y_c.cross(&z_c), y_c, z_c]));
    let device_from_camera = UnitQuaternion::from_rotation_matrix(&device_from_camera);
    let world = UnitQuaternion::from_rotation_matrix(&world);
    Ok(raw
        .into_iter()
        .map(|(t, p, q)| pose(t, world * p, world * q * device_from_camera))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_profiles_have_the_paper_lengths() {
        let length = |p: &[StampedPose]| -> f64 {
            p.windows(2)
                .map(|w| (w[1].position - w[0].position).norm())
                .sum()
        };
        let f = CameraPath::Frontal.poses(300, 30.0);
        assert!((length(&f) - 2.0).abs() < 1e-9);
        let lr = CameraPath::LeftRight.poses(300, 30.0);
        assert!((length(&lr) - 4.0).abs() < 1e-9);
        let e = CameraPath::Egomotion.poses(300, 30.0);
        let end = e.last().expect("poses").position.z;
        assert!((end - 3.7).abs() < 1e-9, "{end}");
    }

    #[test]
    fn the_walker_walks_turns_stops_and_scans() {
        let fps = 30.0;
        let p = CameraPath::Walker(WalkerOptions::default()).poses(30 * 120, fps);
        assert_eq!(p.len(), 3600);
        // Stays inside the room and outside the central block (with a margin).
        for q in &p {
            let (x, z) = (q.position.x.abs(), q.position.z.abs());
            assert!(x.max(z) < 7.0 && x.max(z) > 2.5, "{:?}", q.position);
        }
        // Head turn rates reach a sharp-turn level, and somewhere it stands still.
        let rates: Vec<f64> = p
            .windows(2)
            .map(|w| w[0].rotation.angle_to(&w[1].rotation).to_degrees() * fps)
            .collect();
        let fastest = rates.iter().cloned().fold(0.0, f64::max);
        assert!(fastest > 90.0, "{fastest} deg/s");
        let still = p
            .windows(2)
            .filter(|w| (w[1].position - w[0].position).norm() < 1e-3)
            .count();
        assert!(still > 60, "{still} frames without moving");
        let walked: f64 = p
            .windows(2)
            .map(|w| (w[1].position - w[0].position).norm())
            .sum();
        assert!(walked > 100.0 && walked < 160.0, "{walked} m in 2 min");
    }

    #[test]
    fn events_happen_when_said_and_the_walk_resumes() {
        let fps = 30.0;
        for event in [
            RobustnessEvent::PureRotation,
            RobustnessEvent::Spin,
            RobustnessEvent::Static,
            RobustnessEvent::Shake,
            RobustnessEvent::Dark,
            RobustnessEvent::Blackout,
        ] {
            let p = CameraPath::Event(event).poses(450, fps);
            assert_eq!(p.len(), 450, "{event:?}");
            let (start, duration) = event.window();
            let inside = &p[(start * fps) as usize + 1..((start + duration) * fps) as usize];
            let moved: f64 = inside
                .windows(2)
                .map(|w| (w[1].position - w[0].position).norm())
                .sum();
            let turned: f64 = inside
                .windows(2)
                .map(|w| w[0].rotation.angle_to(&w[1].rotation))
                .sum::<f64>()
                .to_degrees();
            match event {
                RobustnessEvent::PureRotation => {
                    assert!(moved < 1e-9 && turned > 110.0, "{turned}")
                }
                RobustnessEvent::Spin => {
                    assert!(moved < 1e-9 && (turned - 360.0).abs() < 15.0, "{turned}")
                }
                RobustnessEvent::Static => assert!(moved < 1e-9 && turned < 1e-9),
                RobustnessEvent::Shake => assert!(moved > 1.0 && turned > 400.0, "{turned}"),
                RobustnessEvent::Dark => assert!(moved > 0.5),
                RobustnessEvent::Blackout => assert!(moved < 1e-9 && turned < 1e-9),
            }
            let after: f64 = p[300..]
                .windows(2)
                .map(|w| (w[1].position - w[0].position).norm())
                .sum();
            assert!(after > 3.0, "{event:?}: walks again ({after} m)");
        }
    }

    #[test]
    fn an_aria_trajectory_becomes_camera_poses() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../../shared/data/trajectories/aria_head_mounted/projectaria_tools_mps_sample_closed_loop_trajectory.csv");
        let Ok(text) = std::fs::read_to_string(&path) else {
            // CI (`CI` set, as .ci/run does) always has it: absent there is a failure.
            assert!(
                std::env::var_os("CI").is_none_or(|v| v.is_empty() || v == "false"),
                "{} is absent, and CI always has the shared test data",
                path.display()
            );
            eprintln!("skipping: {} absent", path.display());
            return;
        };
        let poses = aria_head_trajectory(&text).expect("parsed");
        assert!(poses.len() > 100);
        // The camera looks roughly horizontally (|forward.y| small) most of the time.
        let level = poses
            .iter()
            .filter(|p| (p.rotation * Vector3::z()).y.abs() < 0.6)
            .count();
        assert!(level * 10 > poses.len() * 8, "{level} of {}", poses.len());
        let replayed = CameraPath::Replay(poses).poses(300, 30.0);
        assert_eq!(replayed.len(), 300);
        assert!(aria_head_trajectory("a,b\n1,2\n").is_err());
    }
}
