use super::*;

fn camera() -> PinholeRadtan {
    PinholeRadtan::new(640, 480, [500.0, 500.0, 320.0, 240.0], [0.0; 5]).expect("camera")
}

/// Uniform numbers in [0, 1) from a seed (a 64-bit LCG: the tests need repeatable numbers,
/// not good ones).
fn uniform_from(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed;
    move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// 400 points on a wall 4-6 m ahead; track id = index.
fn scene() -> Vec<Vector3<f64>> {
    let mut uniform = uniform_from(5);
    (0..400)
        .map(|_| {
            Vector3::new(
                8.0 * uniform() - 4.0,
                4.0 * uniform() - 2.0,
                4.0 + 2.0 * uniform(),
            )
        })
        .collect()
}

/// A camera facing down the z axis, at `z` on it, at time `t`.
pub(super) fn on_axis(t: f64, z: f64) -> StampedPose {
    StampedPose {
        timestamp: t,
        position: Vector3::new(0.0, 0.0, z),
        rotation: UnitQuaternion::identity(),
    }
}

/// The camera walking sideways along x at 1 m/s, turning slowly, at 30 fps.
fn pose_at(frame: u32) -> StampedPose {
    let t = f64::from(frame) / 30.0;
    StampedPose {
        timestamp: t,
        position: Vector3::new(t, 0.05 * t, 0.0),
        rotation: UnitQuaternion::from_euler_angles(0.0, 0.1 * t, 0.0),
    }
}

/// The camera turning in place at 0.3 rad/s, at 30 fps.
fn turning_in_place(frame: u32) -> StampedPose {
    StampedPose {
        timestamp: f64::from(frame) / 30.0,
        position: Vector3::zeros(),
        rotation: UnitQuaternion::from_euler_angles(0.0, 0.01 * f64::from(frame), 0.0),
    }
}

fn observe(points: &[Vector3<f64>], pose: &StampedPose) -> Vec<(u64, Point2<f64>)> {
    let cam = camera();
    let r_cw = pose.rotation.inverse();
    points
        .iter()
        .enumerate()
        .filter_map(|(i, x)| {
            let px = cam.project_undistorted(&(r_cw * (x - pose.position)))?;
            cam.contains(px).then_some((i as u64, px))
        })
        .collect()
}

fn error(a: &StampedPose, b: &StampedPose) -> (f64, f64) {
    (
        (a.position - b.position).norm(),
        a.rotation.angle_to(&b.rotation).to_degrees(),
    )
}

fn map_of(points: &[Vector3<f64>], ids: std::ops::Range<usize>, newest: StampedPose) -> MapView {
    MapView {
        camera: Some(camera()),
        segment: 3,
        points: ids.map(|i| (i as u64, points[i])).collect(),
        newest_keyframe: Some(newest),
        pace: None,
    }
}

/// A tracker on the whole map that tracked frames 0-2.
fn tracking_three_frames(points: &[Vector3<f64>], options: LiveTrackerOptions) -> LiveTracker {
    let mut tracker = LiveTracker::new(options);
    tracker.set_map(map_of(points, 0..400, pose_at(0)));
    for frame in 0..3 {
        let truth = pose_at(frame);
        tracker.track(truth.timestamp, &observe(points, &truth));
    }
    tracker
}

#[test]
fn a_frame_is_tracked_on_the_map_from_the_newest_keyframe() {
    let points = scene();
    let mut tracker = LiveTracker::new(LiveTrackerOptions::default());
    assert!(
        tracker.track(0.0, &observe(&points, &pose_at(0))).is_none(),
        "no map yet"
    );
    tracker.set_map(map_of(&points, 0..400, pose_at(0)));
    for frame in 1..10 {
        let truth = pose_at(frame);
        let live = tracker
            .track(truth.timestamp, &observe(&points, &truth))
            .expect("a map");
        assert_eq!((live.state, live.segment), (TrackingState::Tracking, 3));
        let (dx, da) = error(&live.pose, &truth);
        assert!(dx < 1e-3 && da < 0.01, "frame {frame}: {dx} m, {da} deg");
        assert!(live.inliers > 100);
    }
}

#[test]
fn a_late_map_is_carried_to_the_present_through_the_frames_since_its_keyframe() {
    let points = scene();
    let mut tracker = LiveTracker::new(LiveTrackerOptions::default());
    // One second of frames before any map: nothing to pose them on.
    for frame in 0..30 {
        let truth = pose_at(frame);
        assert!(tracker
            .track(truth.timestamp, &observe(&points, &truth))
            .is_none());
    }
    // The first map arrives: keyframe 10 and the first 100 points only.
    tracker.set_map(map_of(&points, 0..100, pose_at(10)));
    let (_, local) = tracker.points();
    assert!(local > 150, "{local} points triangulated on the way");
    // Those 100 tracks have ended: the frame is posed on the points triangulated since.
    let in_view: Vec<(u64, Point2<f64>)> = observe(&points, &pose_at(30))
        .into_iter()
        .filter(|(t, _)| *t >= 100)
        .collect();
    let live = tracker.track(pose_at(30).timestamp, &in_view).expect("map");
    assert_eq!(live.state, TrackingState::Tracking);
    let (dx, da) = error(&live.pose, &pose_at(30));
    assert!(dx < 0.01 && da < 0.1, "{dx} m, {da} deg");
}

#[test]
fn a_map_older_than_the_frames_kept_does_not_take_the_tracker_back_to_its_keyframe() {
    let points = scene();
    let mut tracker = LiveTracker::new(LiveTrackerOptions::default());
    tracker.set_map(map_of(&points, 0..400, pose_at(0)));
    // Four seconds tracked: the camera 4 m and 23 deg from where the map began.
    for frame in 1..=120 {
        let truth = pose_at(frame);
        tracker.track(truth.timestamp, &observe(&points, &truth));
    }
    // A solver far behind hands over a map whose newest keyframe is 3.8 s old, older than
    // the frames the tracker keeps to re-track from.
    tracker.set_map(map_of(&points, 0..400, pose_at(5)));
    for frame in 121..125 {
        let truth = pose_at(frame);
        let live = tracker
            .track(truth.timestamp, &observe(&points, &truth))
            .expect("a map");
        assert_eq!(live.state, TrackingState::Tracking, "frame {frame}");
        let (dx, da) = error(&live.pose, &truth);
        assert!(dx < 1e-3 && da < 0.01, "frame {frame}: {dx} m, {da} deg");
    }
}

#[test]
fn without_points_in_view_the_pose_is_predicted_then_lost() {
    let points = scene();
    let mut tracker = tracking_three_frames(&points, LiveTrackerOptions::default());
    // Nothing tracked from frame 3 on: constant velocity for 0.5 s, then the last pose.
    let predicted = tracker.track(pose_at(4).timestamp, &[]).expect("map");
    assert_eq!(predicted.state, TrackingState::Predicted);
    let (dx, da) = error(&predicted.pose, &pose_at(4));
    assert!(
        dx < 1e-6 && da < 1e-4,
        "constant velocity is exact here: {dx} m, {da} deg"
    );
    let lost = tracker.track(pose_at(30).timestamp, &[]).expect("map");
    assert_eq!(lost.state, TrackingState::Lost);
    assert!(
        error(&lost.pose, &pose_at(2)).0 < 1e-6,
        "the last tracked pose"
    );
    // A new segment forgets the old one's motion.
    tracker.set_map(MapView {
        segment: 4,
        ..map_of(&points, 0..400, pose_at(29))
    });
    let live = tracker
        .track(pose_at(30).timestamp, &observe(&points, &pose_at(30)))
        .expect("map");
    assert_eq!((live.state, live.segment), (TrackingState::Tracking, 4));
}

#[test]
fn after_frames_not_posed_a_turn_found_by_pnp_is_taken() {
    let points = scene();
    let mut tracker = tracking_three_frames(&points, LiveTrackerOptions::default());
    // A quick glance: 0.2 s the tracker could not pose, the head 35 deg further round.
    for frame in 3..9 {
        tracker.track(pose_at(frame).timestamp, &[]);
    }
    let glance = UnitQuaternion::from_euler_angles(0.0, 35f64.to_radians(), 0.0);
    let truth = StampedPose {
        rotation: pose_at(9).rotation * glance,
        ..pose_at(9)
    };
    let in_view = observe(&points, &truth);
    assert!(in_view.len() > 50, "{} points in view", in_view.len());
    let live = tracker.track(truth.timestamp, &in_view).expect("map");
    assert_eq!(live.state, TrackingState::Tracking);
    let (dx, da) = error(&live.pose, &truth);
    assert!(dx < 1e-3 && da < 0.01, "{dx} m, {da} deg");
    // Without the allowance for the gap, the prior's 20 deg refuse it.
    let strict = LiveTrackerOptions {
        max_turn_rate_deg_s: 0.0,
        ..LiveTrackerOptions::default()
    };
    let mut strict = tracking_three_frames(&points, strict);
    let refused = strict.track(truth.timestamp, &in_view).expect("map");
    assert_ne!(refused.state, TrackingState::Tracking);
}

#[test]
fn before_the_first_window_a_turn_is_followed_from_the_first_frame() {
    let points = scene();
    let mut tracker = LiveTracker::new(LiveTrackerOptions::default());
    let first = tracker.begin_at_origin(camera(), 0, 0.0, &observe(&points, &turning_in_place(0)));
    assert_eq!(first.state, TrackingState::Rotation);
    for frame in 1..20 {
        let truth = turning_in_place(frame);
        let live = tracker
            .track(truth.timestamp, &observe(&points, &truth))
            .expect("the origin");
        assert_eq!(live.state, TrackingState::Rotation);
        let (dx, da) = error(&live.pose, &truth);
        assert!(dx < 1e-12 && da < 0.01, "frame {frame}: {dx} m, {da} deg");
    }
    // A walk is not a turn: near points disagree with any rotation.
    let mut tracker = LiveTracker::new(LiveTrackerOptions::default());
    let near: Vec<Vector3<f64>> = points.iter().map(|x| x * 0.3).collect();
    tracker.begin_at_origin(camera(), 0, 0.0, &observe(&near, &pose_at(0)));
    let walked = tracker
        .track(pose_at(6).timestamp, &observe(&near, &pose_at(6)))
        .expect("the origin");
    assert_ne!(walked.state, TrackingState::Rotation);
}

#[test]
fn after_a_gap_that_ended_every_track_the_turn_is_followed_again() {
    let points = scene();
    // After frames 5-16 were dropped, the frontend tracks afresh: new ids.
    let retracked = |frame: u32| -> Vec<(u64, Point2<f64>)> {
        observe(&points, &turning_in_place(frame))
            .into_iter()
            .map(|(t, px)| (t + 1000, px))
            .collect()
    };
    let mut tracker = LiveTracker::new(LiveTrackerOptions::default());
    tracker.begin_at_origin(camera(), 0, 0.0, &observe(&points, &turning_in_place(0)));
    for frame in 1..5 {
        tracker.track(
            turning_in_place(frame).timestamp,
            &observe(&points, &turning_in_place(frame)),
        );
    }
    let resumed = tracker
        .track(turning_in_place(17).timestamp, &retracked(17))
        .expect("the origin");
    assert_ne!(resumed.state, TrackingState::Rotation, "nothing shared");
    for frame in 18..40 {
        let truth = turning_in_place(frame);
        let live = tracker
            .track(truth.timestamp, &retracked(frame))
            .expect("the origin");
        assert_eq!(live.state, TrackingState::Rotation, "frame {frame}");
        // Turned from the first frame after the gap: off by what that frame missed of the
        // turn during the gap, no more.
        let turned = resumed.pose.rotation.inverse() * live.pose.rotation;
        let truly_turned = turning_in_place(17).rotation.inverse() * truth.rotation;
        let da = turned.angle_to(&truly_turned).to_degrees();
        assert!(da < 0.01, "frame {frame}: {da} deg");
    }
}

#[test]
fn the_rotation_from_rays_ignores_tracks_that_moved_on_their_own() {
    let points = scene();
    let turn = UnitQuaternion::from_euler_angles(0.02, -0.05, 0.01);
    let before: FxHashMap<u64, Vector3<f64>> = points
        .iter()
        .enumerate()
        .map(|(i, x)| (i as u64, x.normalize()))
        .collect();
    // Camera now = camera before turned by `turn`; a third of the tracks slid elsewhere.
    let now: FxHashMap<u64, Vector3<f64>> = before
        .iter()
        .map(|(t, b)| {
            let r = turn.inverse() * b;
            let r = if t % 3 == 0 {
                (r + Vector3::new(0.05, -0.03, 0.0)).normalize()
            } else {
                r
            };
            (*t, r)
        })
        .collect();
    let (rotation, inliers) = rotation_between(&before, &now, 3.0 / 500.0).expect("fit");
    assert!(rotation.angle_to(&turn).to_degrees() < 1e-6);
    assert_eq!(inliers, points.len() - points.len().div_ceil(3));
}

#[test]
fn walking_on_with_no_map_point_in_view_moves_at_the_maps_pace() {
    let points = scene();
    // The map's newest keyframe is frame 0, with none of its points in view (as after a
    // turn in place, whose windows bring none); the wearer walks on at the map's 1 m/s.
    let walk = |pace: Option<f64>| {
        let mut tracker = LiveTracker::new(LiveTrackerOptions::default());
        tracker.track(0.0, &observe(&points, &pose_at(0)));
        tracker.set_map(MapView {
            pace,
            ..map_of(&points, 0..0, pose_at(0))
        });
        (1..=30)
            .map(|frame| {
                let truth = pose_at(frame);
                let live = tracker
                    .track(truth.timestamp, &observe(&points, &truth))
                    .expect("map");
                (live.state, error(&live.pose, &truth).0)
            })
            .collect::<Vec<_>>()
    };
    let walked = walk(Some(1.0));
    // By rotation until the rays show the walk (3 px of parallax; sideways before a wall
    // is nearly a turn, so 8 frames here), then on.
    let first_moved = walked
        .iter()
        .position(|(s, _)| *s == TrackingState::Predicted)
        .expect("moved on");
    assert!(first_moved <= 10, "{walked:?}");
    assert!(
        walked[first_moved + 1..]
            .iter()
            .all(|(s, _)| *s == TrackingState::Tracking),
        "{walked:?}"
    );
    let (_, last) = walked[29];
    assert!(last < 0.05, "1 m walked, {last} m off: {walked:?}");
    // Without a pace the position is held: a metre behind after the second.
    let held = walk(None);
    assert!(
        held.iter().all(|(s, _)| *s == TrackingState::Rotation),
        "{held:?}"
    );
    assert!(held[29].1 > 0.9, "{held:?}");
}

#[test]
fn before_the_first_window_a_walk_ahead_is_followed_at_the_new_maps_pace() {
    // Points 1.2-1.8 m ahead (a road before a car, a desk before a wearer), straight
    // ahead at 1 m/s (the new segment's pace is one unit per second): within frames the
    // rays fit no rotation, and no map point exists yet.
    let points: Vec<Vector3<f64>> = scene().iter().map(|x| x * 0.3).collect();
    let ahead = |frame: u32| StampedPose {
        timestamp: f64::from(frame) / 30.0,
        position: Vector3::new(0.0, 0.0, f64::from(frame) / 30.0),
        rotation: UnitQuaternion::identity(),
    };
    let mut tracker = LiveTracker::new(LiveTrackerOptions::default());
    tracker.begin_at_origin(camera(), 0, 0.0, &observe(&points, &ahead(0)));
    let walked: Vec<(TrackingState, f64)> = (1..=30)
        .map(|frame| {
            let truth = ahead(frame);
            let live = tracker
                .track(truth.timestamp, &observe(&points, &truth))
                .expect("the origin");
            (live.state, error(&live.pose, &truth).0)
        })
        .collect();
    assert!(
        walked
            .iter()
            .all(|(s, _)| matches!(s, TrackingState::Predicted | TrackingState::Tracking)),
        "{walked:?}"
    );
    let (_, last) = walked[29];
    // Moved on from the first frame itself (which anchors the first walk), not from a
    // frame held there by a rotation fit: nothing is lost but noise.
    assert!(last < 1e-3, "1 m walked, {last} m off: {walked:?}");
}

/// A walk ahead (0.8 m/s, swaying and turning a little) tracked with tracks of 1 px
/// uniform noise, the map holding only the first 50 points: the RMS position error and the
/// worst of frames 1-89.
fn walk_ahead_on_own_points(options: LiveTrackerOptions) -> (f64, f64) {
    let points = scene();
    let ahead = |frame: u32| {
        let t = f64::from(frame) / 30.0;
        StampedPose {
            timestamp: t,
            position: Vector3::new(0.1 * (3.0 * t).sin(), 0.02 * (9.0 * t).sin(), 0.8 * t),
            rotation: UnitQuaternion::from_euler_angles(0.0, 0.1 * (2.0 * t).sin(), 0.0),
        }
    };
    let mut uniform = uniform_from(11);
    let mut noise = move || uniform() - 0.5;
    let mut tracker = LiveTracker::new(options);
    tracker.set_map(map_of(&points, 0..50, ahead(0)));
    let (mut squares, mut worst) = (0.0, 0.0f64);
    for frame in 1..90 {
        let truth = ahead(frame);
        let seen: Vec<(u64, Point2<f64>)> = observe(&points, &truth)
            .into_iter()
            .map(|(t, p)| (t, Point2::new(p.x + noise(), p.y + noise())))
            .collect();
        let live = tracker.track(truth.timestamp, &seen).expect("map");
        assert_eq!(live.state, TrackingState::Tracking, "frame {frame}");
        let (dx, _) = error(&live.pose, &truth);
        squares += dx * dx;
        worst = worst.max(dx);
    }
    ((squares / 89.0).sqrt(), worst)
}

#[test]
fn the_local_adjustment_holds_a_walk_on_the_trackers_own_points() {
    let (adjusted_rms, adjusted_worst) = walk_ahead_on_own_points(LiveTrackerOptions::default());
    let (plain_rms, plain_worst) = walk_ahead_on_own_points(LiveTrackerOptions {
        local_adjustment: None,
        ..LiveTrackerOptions::default()
    });
    // Measured: 0.0046 / 0.0072 m adjusted (every second frame), 0.032 / 0.081 m without.
    assert!(
        adjusted_rms < 0.02 && adjusted_worst < 0.04,
        "adjusted: RMS {adjusted_rms} m, worst {adjusted_worst} m"
    );
    assert!(
        adjusted_rms < 0.7 * plain_rms && adjusted_worst < 0.7 * plain_worst,
        "adjusted {adjusted_rms} / {adjusted_worst} m against {plain_rms} / {plain_worst} m"
    );
}

/// Turning in place with the map's pace known and no map point in view, while most tracks
/// end and start again every 5 frames; the 80 that live through the turn are observed from
/// a camera drifting sideways at 1.5 m/s, as drifting tracks look like parallax. Returns
/// each frame's state and position error.
fn turn_with_surviving_tracks_drifting(options: LiveTrackerOptions) -> Vec<(TrackingState, f64)> {
    let points = scene();
    let observe_turn = |frame: u32| {
        let truth = turning_in_place(frame);
        let ghost = StampedPose {
            position: Vector3::new(0.05 * f64::from(frame), 0.0, 0.0),
            ..truth
        };
        let generation = u64::from(frame / 5);
        let survivors = observe(&points, &ghost)
            .into_iter()
            .filter(|(id, _)| id % 5 == 0);
        let renewed = observe(&points, &truth)
            .into_iter()
            .filter(|(id, _)| id % 5 != 0)
            .map(|(id, px)| (id + 1000 * (generation + 1), px));
        (truth, survivors.chain(renewed).collect::<Vec<_>>())
    };
    let mut tracker = LiveTracker::new(options);
    let (first, tracks) = observe_turn(0);
    tracker.track(first.timestamp, &tracks);
    tracker.set_map(MapView {
        pace: Some(1.0),
        ..map_of(&points, 0..0, first)
    });
    (1..=30)
        .map(|frame| {
            let (truth, tracks) = observe_turn(frame);
            let live = tracker.track(truth.timestamp, &tracks).expect("map");
            (live.state, error(&live.pose, &truth).0)
        })
        .collect()
}

#[test]
fn a_turn_in_place_is_not_walked_on_by_the_drift_of_the_tracks_that_lived_through_it() {
    let held = turn_with_surviving_tracks_drifting(LiveTrackerOptions::default());
    assert!(
        held.iter()
            .all(|(s, e)| *s == TrackingState::Rotation && *e < 1e-6),
        "{held:?}"
    );
    // Walking on from any frame sharing 20 tracks, the drift moves the position on.
    let walked = turn_with_surviving_tracks_drifting(LiveTrackerOptions {
        walk_min_track_share: 0.0,
        ..LiveTrackerOptions::default()
    });
    assert!(walked.iter().any(|(_, e)| *e > 0.1), "{walked:?}");
}
