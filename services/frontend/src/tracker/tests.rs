//! Tests of the tracker (kept beside it to keep tracker.rs short).

use super::*;
use crate::keyframe_policy::KeyframePolicy;
use opencv::core::{Mat, Rect};

/// A blurred random texture, big enough to crop shifted views from.
fn texture(w: i32, h: i32) -> Mat {
    let mut noise = Mat::new_rows_cols_with_default(h, w, CV_8UC1, Scalar::all(0.0)).expect("mat");
    opencv::core::set_rng_seed(7).expect("seed");
    opencv::core::randu(&mut noise, &Scalar::all(0.0), &Scalar::all(255.0)).expect("randu");
    let mut blurred = Mat::default();
    imgproc::gaussian_blur_def(&noise, &mut blurred, Size::new(7, 7), 1.5).expect("blur");
    blurred
}

fn crop(img: &Mat, x: i32, y: i32, w: i32, h: i32) -> Mat {
    Mat::roi(img, Rect::new(x, y, w, h))
        .expect("roi")
        .try_clone()
        .expect("clone")
}

fn camera(w: u32, h: u32) -> PinholeRadtan {
    PinholeRadtan::new(
        w,
        h,
        [300.0, 300.0, w as f64 / 2.0, h as f64 / 2.0],
        [0.0; 5],
    )
    .expect("camera")
}

#[test]
fn tracks_follow_a_known_shift_and_flow_triggers_keyframes() {
    let big = texture(600, 300);
    let (w, h) = (320, 240);
    let mut tracker = Tracker::new(camera(w as u32, h as u32), TrackerOptions::default());
    let mut keyframes = Vec::new();
    let mut first_positions = std::collections::HashMap::new();
    for i in 0..20 {
        // The camera pans right by 3 px per frame: content moves left by 3 px.
        let out = tracker
            .process(i, &crop(&big, 3 * i as i32, 30, w, h))
            .expect("tracks");
        if let Some(k) = out.keyframe {
            if k.keyframe_id == 0 {
                for t in &k.tracks {
                    first_positions.insert(t.track_id, t.raw);
                }
            } else if k.keyframe_id == 1 {
                // Every track of the first keyframe still alive moved by exactly -3 px/frame.
                let shift = -3.0 * k.frame_id as f32;
                let mut checked = 0;
                for t in &k.tracks {
                    if let Some(p0) = first_positions.get(&t.track_id) {
                        assert!(
                            (t.raw.x - p0.x - shift).abs() < 0.2,
                            "x {} -> {}",
                            p0.x,
                            t.raw.x
                        );
                        assert!((t.raw.y - p0.y).abs() < 0.2);
                        checked += 1;
                    }
                }
                assert!(checked > 200, "only {checked} tracks survived");
            }
            keyframes.push((k.frame_id, k.reason));
        }
        assert!(
            out.live_tracks > 300,
            "frame {i}: {} tracks",
            out.live_tracks
        );
    }
    // 3 px/frame: mean flow passes m = 20 px on the 7th frame after a keyframe.
    assert_eq!(keyframes[0], (0, KeyframeReason::First));
    assert_eq!(keyframes[1], (7, KeyframeReason::Flow));
    assert_eq!(keyframes[2], (14, KeyframeReason::Flow));
}

#[test]
fn forward_backward_check_drops_tracks_on_a_scrambled_frame() {
    let big = texture(400, 300);
    let mut tracker = Tracker::new(camera(320, 240), TrackerOptions::default());
    tracker
        .process(0, &crop(&big, 0, 0, 320, 240))
        .expect("first");
    let before = tracker.live_tracks();
    // An unrelated image: LK converges somewhere for many points, but not consistently
    // in both directions.
    let other = texture(400, 300);
    let mut flipped = Mat::default();
    opencv::core::flip(&crop(&other, 50, 40, 320, 240), &mut flipped, -1).expect("flip");
    let out = tracker.process(1, &flipped).expect("tracks");
    assert!(
        out.rejected_forward_backward > before / 4,
        "rejected {} of {before}",
        out.rejected_forward_backward
    );
}

#[test]
fn keyframe_every_p_frames_without_motion_and_finish_closes_the_stream() {
    let img = texture(320, 240);
    let mut tracker = Tracker::new(camera(320, 240), TrackerOptions::default());
    let mut kf_frames = Vec::new();
    for i in 0..65 {
        if let Some(k) = tracker.process(i, &img).expect("tracks").keyframe {
            kf_frames.push(k.frame_id);
        }
    }
    assert_eq!(kf_frames, vec![0, 30, 60]);
    let last = tracker
        .finish()
        .expect("trailing frames make a last keyframe");
    assert_eq!(
        (last.frame_id, last.reason, last.keyframe_id),
        (64, KeyframeReason::Last, 3)
    );
    assert!(tracker.finish().is_none());
}

#[test]
fn rejects_wrong_size_and_colour() {
    let mut tracker = Tracker::new(camera(320, 240), TrackerOptions::default());
    let small = Mat::new_rows_cols_with_default(10, 10, CV_8UC1, Scalar::all(0.0)).expect("mat");
    assert!(matches!(
        tracker.process(0, &small),
        Err(TrackerError::SizeMismatch { .. })
    ));
    let colour = Mat::new_rows_cols_with_default(240, 320, opencv::core::CV_8UC3, Scalar::all(0.0))
        .expect("mat");
    assert!(matches!(
        tracker.process(0, &colour),
        Err(TrackerError::NotGrey { .. })
    ));
}

mod pyramid_tests {
    use super::super::*;

    /// Corners are detected on pyramid entry 2 and doubled: it must be level 1, unpadded.
    #[test]
    fn level_one_is_half_size_and_aligned() {
        let mut img =
            Mat::new_rows_cols_with_default(240, 320, CV_8UC1, Scalar::all(0.0)).expect("mat");
        imgproc::circle(
            &mut img,
            Point::new(100, 60),
            6,
            Scalar::all(255.0),
            -1,
            imgproc::LINE_8,
            0,
        )
        .expect("draw");
        let mut pyramid = Vector::<Mat>::new();
        video::build_optical_flow_pyramid_def(&img, &mut pyramid, Size::new(9, 9), 3)
            .expect("pyramid");
        let half = pyramid.get(2).expect("level 1");
        let mut max_loc = Point::default();
        opencv::core::min_max_loc(
            &half,
            None,
            None,
            None,
            Some(&mut max_loc),
            &opencv::core::no_array(),
        )
        .expect("minmax");
        assert_eq!((half.cols(), half.rows()), (160, 120));
        assert!(
            (max_loc.x - 50).abs() <= 2 && (max_loc.y - 30).abs() <= 2,
            "{max_loc:?}"
        );
    }
}

#[test]
fn a_blind_frame_ends_every_track_and_the_view_restarts_with_new_ones() {
    let big = texture(600, 300);
    let (w, h) = (320, 240);
    let mut tracker = Tracker::new(camera(w as u32, h as u32), TrackerOptions::default());
    let first = tracker.process(0, &crop(&big, 0, 30, w, h)).expect("frame");
    let before: Vec<u64> = first
        .keyframe
        .expect("first keyframe")
        .tracks
        .iter()
        .map(|t| t.track_id)
        .collect();
    // Lens covered: a dark frame with sensor noise (sigma 2 grey levels).
    let mut dark = Mat::new_rows_cols_with_default(h, w, CV_8UC1, Scalar::all(0.0)).expect("mat");
    opencv::core::randn(&mut dark, &Scalar::all(8.0), &Scalar::all(2.0)).expect("noise");
    for i in 1..5 {
        let out = tracker.process(i, &dark).expect("dark frame");
        assert!(
            out.blind && out.live_tracks == 0 && out.keyframe.is_none(),
            "{out:?}"
        );
    }
    // The view returns: a keyframe with only new tracks.
    let back = tracker.process(5, &crop(&big, 0, 30, w, h)).expect("frame");
    assert!(!back.blind);
    let k = back.keyframe.expect("a keyframe once the view returns");
    assert!(k.tracks.len() > 100, "{}", k.tracks.len());
    assert!(k.tracks.iter().all(|t| !before.contains(&t.track_id)));
}

/// A pan that speeds up by 20 px per frame (steps of 20, 40, 60, 80 px): the share of the
/// tracks alive before the last step (80 px, further than LK reaches from a standing
/// start) that survive it, and the tracker's image velocity after it.
fn survival_of_a_whip_pan(predict_motion: bool) -> (f64, f32) {
    let big = texture(600, 300);
    let (w, h) = (320, 240);
    let options = TrackerOptions {
        predict_motion,
        ..TrackerOptions::default()
    };
    let mut tracker = Tracker::new(camera(w as u32, h as u32), options);
    tracker
        .process(0, &crop(&big, 0, 30, w, h))
        .expect("frame 0");
    let mut x = 0;
    let mut before = std::collections::HashSet::new();
    for (i, step) in [20, 40, 60, 80].into_iter().enumerate() {
        x += step;
        before = tracker.tracks.iter().map(|t| t.id).collect();
        tracker
            .process(i as u64 + 1, &crop(&big, x, 30, w, h))
            .expect("frame");
    }
    // Tracks that could have stayed in view (content moved 80 px left).
    let survived = tracker
        .tracks
        .iter()
        .filter(|t| before.contains(&t.id))
        .count();
    (
        survived as f64 / before.len().max(1) as f64,
        tracker.image_velocity.x,
    )
}

#[test]
fn predicted_motion_keeps_tracks_through_a_whip_pan() {
    let (without, _) = survival_of_a_whip_pan(false);
    let (with, speed) = survival_of_a_whip_pan(true);
    eprintln!(
        "tracks surviving the 80 px step: {without:.2} without the prediction, {with:.2} with it"
    );
    // 80 px of the 320 px view leave the image: at most 3/4 can survive.
    assert!(with > 0.45, "with the prediction only {with:.2} survived");
    assert!(
        without < 0.2,
        "{without:.2} survived without the prediction"
    );
    assert!((speed + 80.0).abs() < 1.0, "image velocity {speed}");
}

#[test]
fn a_rolling_shutter_readout_moves_observations_to_the_middle_row_time() {
    // The same pan (content 3 px left per frame, frames 1/30 s apart) through two trackers,
    // one told of a 20 ms readout. A track on row y was read (y - h/2) / h x 20 ms after
    // the middle row; by the middle row's time it was 3 px x 30 x that further right.
    let big = texture(600, 300);
    let (w, h) = (320, 240);
    let rolling = TrackerOptions {
        rolling_shutter_s: 0.020,
        ..TrackerOptions::default()
    };
    let mut global = Tracker::new(camera(w as u32, h as u32), TrackerOptions::default());
    let mut shutter = Tracker::new(camera(w as u32, h as u32), rolling);
    let (mut a, mut b) = (Vec::new(), Vec::new());
    for i in 0..20u64 {
        let frame = crop(&big, 3 * i as i32, 30, w, h);
        let t = i as f64 / 30.0;
        a.extend(global.process_timed(i, t, &frame).expect("global").keyframe);
        b.extend(
            shutter
                .process_timed(i, t, &frame)
                .expect("rolling")
                .keyframe,
        );
    }
    assert!(a.len() >= 2 && a.len() == b.len());
    let (ka, kb) = (&a[1], &b[1]);
    let mut checked = 0;
    for (ta, tb) in ka.tracks.iter().zip(&kb.tracks) {
        assert_eq!(ta.track_id, tb.track_id);
        // The image position is unchanged (descriptors are taken there); the geometry's
        // (undistorted: no lens distortion here, so the same pixel) moved.
        assert_eq!(ta.raw, tb.raw);
        let dt_row = (f64::from(ta.raw.y) - h as f64 / 2.0) / h as f64 * 0.020;
        let expected = -(-3.0 * 30.0) * dt_row; // velocity -90 px/s, moved back by dt_row
        let moved = f64::from(tb.undistorted.x - ta.undistorted.x);
        assert!(
            (moved - expected).abs() < 0.05,
            "row {}: moved {moved} instead of {expected}",
            ta.raw.y
        );
        assert!((tb.undistorted.y - ta.undistorted.y).abs() < 0.05);
        checked += 1;
    }
    assert!(checked > 100, "{checked}");
    // Without timestamps nothing is corrected.
    let mut untimed = Tracker::new(camera(w as u32, h as u32), rolling);
    let mut c = Vec::new();
    for i in 0..20u64 {
        c.extend(
            untimed
                .process(i, &crop(&big, 3 * i as i32, 30, w, h))
                .expect("untimed")
                .keyframe,
        );
    }
    let positions = |k: &KeyframeTracks| -> Vec<_> {
        k.tracks
            .iter()
            .map(|t| (t.track_id, t.raw, t.undistorted))
            .collect()
    };
    assert_eq!(positions(&c[1]), positions(ka));
}

#[test]
fn keyframes_tracked_uncorrected_are_recorrected_as_a_tracker_told_the_readout_makes_them() {
    // An accelerating pan through two trackers, one told of a 20 ms readout, each keyframe
    // centred on the frame after it; the other's keyframes, recorrected once the readout is
    // known, must land where the told tracker put them.
    let big = texture(1200, 300);
    let (w, h) = (320, 240);
    let readout = 0.020;
    let told = TrackerOptions {
        rolling_shutter_s: readout,
        ..TrackerOptions::default()
    };
    let mut untold = Tracker::new(camera(w as u32, h as u32), TrackerOptions::default());
    let mut shutter = Tracker::new(camera(w as u32, h as u32), told);
    let (mut a, mut b) = (Vec::new(), Vec::new());
    let (mut pending_a, mut pending_b): (Option<KeyframeTracks>, Option<KeyframeTracks>) =
        (None, None);
    for i in 0..24u64 {
        let frame = crop(&big, (i * i) as i32 / 2 + 2 * i as i32, 30, w, h);
        let t = i as f64 / 30.0;
        let oa = untold.process_timed(i, t, &frame).expect("untold");
        let ob = shutter.process_timed(i, t, &frame).expect("told");
        if let (Some(mut ka), Some(mut kb)) = (pending_a.take(), pending_b.take()) {
            assert_eq!(untold.centre_keyframe(&mut ka), 0);
            shutter.centre_keyframe(&mut kb);
            a.push(ka);
            b.push(kb);
        }
        pending_a = oa.keyframe;
        pending_b = ob.keyframe;
    }
    assert!(
        a.len() >= 2 && a.len() == b.len(),
        "{} {}",
        a.len(),
        b.len()
    );
    let mut checked = 0;
    let mut largest_correction = 0.0f32;
    for (ka, kb) in a.iter_mut().zip(&b) {
        for (ta, tb) in ka.tracks.iter_mut().zip(&kb.tracks) {
            assert_eq!((ta.track_id, ta.raw), (tb.track_id, tb.raw));
            let before = ta.undistorted;
            assert!(untold.recorrect(ta, readout));
            largest_correction = largest_correction.max((ta.undistorted - before).norm());
            assert!(
                (ta.undistorted - tb.undistorted).norm() < 1e-3,
                "track {}: {:?} recorrected, {:?} told",
                ta.track_id,
                ta.undistorted,
                tb.undistorted
            );
            checked += 1;
        }
    }
    assert!(checked > 200, "{checked}");
    assert!(largest_correction > 0.5, "{largest_correction}");
}

#[test]
fn a_rolling_shutter_correction_uses_the_velocity_at_the_frame_time() {
    // An accelerating pan: the content is i^2 px left at frame i, so its velocity at frame
    // i is 2i px per frame, while the motion over the last frame is 2i - 1 (the velocity
    // half a frame earlier). The correction must follow the former: on rows read over 10 ms
    // from the middle one the two differ by >= 0.3 px.
    let big = texture(1000, 300);
    let (w, h) = (320, 240);
    let rolling = TrackerOptions {
        rolling_shutter_s: 0.030,
        ..TrackerOptions::default()
    };
    let offset = |i: u64| (i * i) as f64;
    let mut global = Tracker::new(camera(w as u32, h as u32), TrackerOptions::default());
    let mut shutter = Tracker::new(camera(w as u32, h as u32), rolling);
    let mut pairs = Vec::new();
    for i in 0..24u64 {
        let frame = crop(&big, offset(i) as i32, 30, w, h);
        let t = i as f64 / 30.0;
        let a = global.process_timed(i, t, &frame).expect("global").keyframe;
        let b = shutter
            .process_timed(i, t, &frame)
            .expect("rolling")
            .keyframe;
        if let (Some(a), Some(b)) = (a, b) {
            pairs.push((i, a, b));
        }
    }
    let (i, ka, kb) = pairs
        .iter()
        .find(|(i, _, _)| *i >= 10)
        .expect("a keyframe after frame 10");
    let velocity = 2.0 * *i as f64 * 30.0; // px/s, leftwards
    let (mut far_rows, mut right) = (0, 0);
    for (ta, tb) in ka.tracks.iter().zip(&kb.tracks) {
        let dt_row = (f64::from(ta.raw.y) - h as f64 / 2.0) / h as f64 * 0.030;
        if dt_row.abs() < 0.010 {
            continue;
        }
        far_rows += 1;
        let moved = f64::from(tb.undistorted.x - ta.undistorted.x);
        if (moved - velocity * dt_row).abs() < 0.1 {
            right += 1;
        }
    }
    // Tracks born lately use the median motion instead; most are old enough.
    assert!(
        far_rows > 30,
        "{far_rows} tracks on far rows (keyframe at frame {i})"
    );
    assert!(
        right * 10 > far_rows * 8,
        "{right} of {far_rows} tracks moved by the velocity at the frame time"
    );
}

#[test]
fn a_keyframe_centred_on_the_next_frame_follows_a_turn_onset() {
    // A pan that starts at frame 6 and accelerates ever faster (content 0.2 (i - 6)^3 px
    // left at frame i): the velocity at frame 10 is 0.6 x 16 = 9.6 px per frame. The
    // extrapolation from the frames before reads 9.2, the centred difference with the
    // next frame 9.8; every frame is a keyframe here, so frame 10's can be compared.
    let big = texture(700, 300);
    let (w, h) = (320, 240);
    let offset = |i: u64| 0.2 * (i.saturating_sub(6) as f64).powi(3);
    let frame_at = |x: f64| {
        let shift =
            Mat::from_slice_2d(&[[1.0f64, 0.0, -x - 20.0], [0.0, 1.0, -30.0]]).expect("matrix");
        let mut out = Mat::default();
        imgproc::warp_affine(
            &big,
            &mut out,
            &shift,
            Size::new(w, h),
            imgproc::INTER_LINEAR,
            opencv::core::BORDER_REPLICATE,
            Scalar::all(0.0),
        )
        .expect("warp");
        out
    };
    let options = TrackerOptions {
        rolling_shutter_s: 0.030,
        keyframes: KeyframePolicy {
            max_frames_between: 1,
            ..KeyframePolicy::default()
        },
        ..TrackerOptions::default()
    };
    let mut tracker = Tracker::new(camera(w as u32, h as u32), options);
    let mut keyframe_10 = None;
    for i in 0..=11u64 {
        let out = tracker
            .process_timed(i, i as f64 / 30.0, &frame_at(offset(i)))
            .expect("tracks");
        if i == 10 {
            keyframe_10 = out.keyframe;
        }
    }
    let extrapolated = keyframe_10.expect("frame 10 is a keyframe");
    let mut centred = extrapolated.clone();
    assert!(tracker.centre_keyframe(&mut centred) > 100);
    let velocity = 0.6 * 16.0 * 30.0; // px/s, leftwards
    let error = |k: &KeyframeTracks| {
        let (mut sum, mut n) = (0.0, 0);
        for t in &k.tracks {
            let dt_row = (f64::from(t.raw.y) - h as f64 / 2.0) / h as f64 * 0.030;
            if dt_row.abs() < 0.010 {
                continue;
            }
            // Read dt_row after the middle row: by the middle row's time the content was
            // velocity x dt_row further right.
            let expected = f64::from(t.raw.x) + velocity * dt_row;
            sum += (f64::from(t.undistorted.x) - expected).abs();
            n += 1;
        }
        assert!(n > 30, "{n} tracks on far rows");
        sum / n as f64
    };
    let (before, after) = (error(&extrapolated), error(&centred));
    assert!(
        after < 0.6 * before,
        "mean error {before:.3} px extrapolated, {after:.3} px centred"
    );
    // Centring needs the very next frame: after another one it refuses.
    let frame = frame_at(offset(12));
    tracker
        .process_timed(12, 12.0 / 30.0, &frame)
        .expect("tracks");
    let mut late = extrapolated.clone();
    assert_eq!(tracker.centre_keyframe(&mut late), 0);
    assert_eq!(late, extrapolated);
}

#[test]
fn a_new_tracker_resumed_from_a_saved_frame_keeps_the_track_ids() {
    let big = texture(600, 300);
    let (w, h) = (320, 240);
    let mut before = Tracker::new(camera(w as u32, h as u32), TrackerOptions::default());
    let mut saved = None;
    for i in 0..5 {
        let frame = crop(&big, 3 * i as i32, 30, w, h);
        before.process(i, &frame).expect("tracks");
        saved = Some(frame);
    }
    let saved = saved.expect("a frame");
    let tracks: Vec<(u64, Point2f)> = before.resumable_tracks().collect();
    assert!(tracks.len() > 300, "{} tracks", tracks.len());
    // The restarted process: a new tracker, its ids continued, starting from frame 4 and
    // given frame 9 next (the frames between were lost with the old process): 15 px on.
    let mut after = Tracker::new(camera(w as u32, h as u32), TrackerOptions::default());
    let (next_keyframe, next_track) = before.next_ids();
    after.resume_ids(next_keyframe, next_track);
    after
        .resume_from(&ResumePoint {
            frame_id: 4,
            timestamp_s: f64::NAN,
            image: &saved,
            tracks: &tracks,
        })
        .expect("resumes");
    let out = after.process(9, &crop(&big, 27, 30, w, h)).expect("tracks");
    let moved: std::collections::HashMap<u64, Point2f> = tracks.iter().copied().collect();
    let continued: Vec<_> = after
        .sample_tracks(usize::MAX)
        .into_iter()
        .filter(|t| moved.contains_key(&t.track_id))
        .collect();
    assert!(
        continued.len() * 10 > tracks.len() * 9,
        "{} of {}",
        continued.len(),
        tracks.len()
    );
    for t in &continued {
        let p0 = moved[&t.track_id];
        assert!(
            (t.raw.x - (p0.x - 15.0)).abs() < 0.3,
            "x {} -> {}",
            p0.x,
            t.raw.x
        );
        assert!((t.raw.y - p0.y).abs() < 0.3);
    }
    // Not a first keyframe of a new stream: the keyframe rule counts from the saved frame.
    assert!(out
        .keyframe
        .is_none_or(|k| k.reason != KeyframeReason::First));
    // New tracks take ids after every id given before the restart.
    let (_, next) = after.next_ids();
    assert!(next >= next_track);
}
