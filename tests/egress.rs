//! Results over zenoh from a real replayed run, read by a zenoh client in this process.

mod common;

use common::*;
use egoslam_messages::v1 as pb;
use egoslam_sources::ground_truth::read_tum_file;
use prost::Message;
use std::time::{Duration, Instant};
use zenoh::Wait;

#[test]
fn a_zenoh_client_gets_poses_trajectory_status_and_a_snapshot() {
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let out = tempfile::tempdir().expect("tempdir");
    let mut run = egoslam()
        .args(["run", "--realtime", "--device", "it", "--input"])
        .arg(tum_fixture())
        .arg("--out")
        .arg(out.path())
        .env("EGOSLAM_ZENOH_LISTEN", &endpoint)
        .spawn()
        .expect("run");

    // Connect to the merger's loopback listener (it appears once the merger has started).
    let config =
        egoslam_egress::zenoh_config(&[], std::slice::from_ref(&endpoint)).expect("config");
    let start = Instant::now();
    let session = loop {
        if let Ok(s) = zenoh::open(config.clone()).wait() {
            if s.info().peers_zid().wait().count() > 0 {
                break s;
            }
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "merger never listened on {endpoint}"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    let trajectory = session
        .declare_subscriber("egoslam/it/trajectory")
        .wait()
        .expect("sub");
    let status = session
        .declare_subscriber("egoslam/it/status")
        .wait()
        .expect("sub");
    let poses = session
        .declare_subscriber("egoslam/it/pose")
        .wait()
        .expect("sub");

    let (mut trajectories, mut statuses, mut pose_messages, mut snapshot) =
        (Vec::new(), Vec::new(), Vec::new(), None);
    while run.try_wait().expect("poll").is_none() {
        while let Ok(Some(s)) = trajectory.try_recv() {
            trajectories
                .push(pb::Trajectory::decode(&*s.payload().to_bytes()).expect("trajectory"));
        }
        while let Ok(Some(s)) = status.try_recv() {
            statuses.push(pb::Status::decode(&*s.payload().to_bytes()).expect("status"));
        }
        while let Ok(Some(s)) = poses.try_recv() {
            pose_messages.push(pb::Pose::decode(&*s.payload().to_bytes()).expect("pose"));
        }
        if snapshot.is_none() && !trajectories.is_empty() {
            let replies = session.get("egoslam/it/snapshot").wait().expect("get");
            if let Ok(Some(reply)) = replies.recv_timeout(Duration::from_secs(5)) {
                let sample = reply.result().expect("snapshot reply");
                snapshot =
                    Some(pb::Snapshot::decode(&*sample.payload().to_bytes()).expect("snapshot"));
            }
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(run.wait().expect("exit").success());

    let file = read_tum_file(&out.path().join("keyframes.tum")).expect("keyframes.tum");
    let in_file = |p: &pb::Pose| {
        let x = p.position.unwrap_or_default();
        file.iter().any(|f| {
            (f.timestamp - p.timestamp_s).abs() < 1e-5
                && (f.position.x - x.x).abs() < 1e-5
                && (f.position.z - x.z).abs() < 1e-5
        })
    };
    let last = trajectories.last().expect("trajectory messages arrived");
    assert!(
        last.poses.len() >= 20,
        "{} keyframes in the last trajectory message",
        last.poses.len()
    );
    assert!(
        last.poses.iter().all(in_file),
        "published keyframes match keyframes.tum"
    );
    // On this clip the background refinement starts at window 3 (measured cross-window error
    // 2.6 px > 1.5) and moves keyframes already published: they come again, revised.
    assert!(
        last.poses.iter().any(|p| p.revision > 0),
        "no revised keyframe in the final trajectory"
    );
    let snapshot = snapshot.expect("snapshot answered");
    let snap_keyframes = snapshot.keyframes.expect("keyframes").poses;
    // A snapshot taken mid-run holds the poses of that moment: each is in the file, or was
    // revised later (background refinement) and published again with a higher revision.
    let latest_revision = |frame_id: u64| {
        trajectories
            .iter()
            .flat_map(|t| &t.poses)
            .filter(|p| p.frame_id == frame_id)
            .map(|p| p.revision)
            .max()
            .unwrap_or(0)
    };
    assert!(!snap_keyframes.is_empty());
    for p in &snap_keyframes {
        assert!(
            in_file(p) || latest_revision(p.frame_id) > p.revision,
            "snapshot keyframe {} (revision {}) neither in the file nor revised later",
            p.frame_id,
            p.revision
        );
        let in_file_by_time = file
            .iter()
            .any(|f| (f.timestamp - p.timestamp_s).abs() < 1e-5);
        assert!(
            in_file_by_time,
            "snapshot keyframe {} not in the file",
            p.frame_id
        );
    }
    // Every point goes out, each with how well it is known (map.ply keeps the known ones).
    let points = snapshot.map.expect("map").points;
    assert!(!points.is_empty());
    assert!(
        points.iter().all(|p| p.observations >= 2),
        "observation counts"
    );
    assert!(
        points.iter().filter(|p| p.relative_std.is_some()).count() * 10 > points.len() * 9,
        "relative_std missing"
    );
    // Sigma is from the median over every observation: most points agree within 5 of it.
    let sigmas: Vec<f64> = points
        .iter()
        .filter_map(|p| p.largest_reprojection_sigmas)
        .collect();
    assert!(sigmas.len() * 10 > points.len() * 9, "reprojection missing");
    assert!(
        sigmas.iter().filter(|&&s| s <= 5.0).count() * 2 > sigmas.len(),
        "most points agree with their observations within 5 sigma"
    );
    assert!(statuses.iter().any(|s| s.service == "merger"
        && s.state == pb::ServiceState::Running as i32
        && s.windows >= 1));
    // Every status names its run, the one report.json names: the clip's keyframes are held
    // for its readout rather than the run starting again (docs/config.md, "Calibration
    // from the stream"), which would be a new run to a client.
    let run_id = report(out.path())["run_id"]
        .as_str()
        .expect("run_id")
        .to_string();
    assert!(run_id.starts_with("run"), "{run_id}");
    assert_eq!(statuses.last().map(|s| &s.run_id), Some(&run_id));
    let mut runs: Vec<&str> = statuses.iter().map(|s| s.run_id.as_str()).collect();
    runs.dedup();
    assert_eq!(runs.len(), 1, "runs {runs:?}");
    for run in &runs {
        let windows: Vec<u64> = statuses
            .iter()
            .filter(|s| s.run_id == *run)
            .map(|s| s.windows)
            .collect();
        assert!(
            windows.windows(2).all(|w| w[0] <= w[1]),
            "windows only grow within a run: {windows:?}"
        );
    }
    assert!(
        pose_messages.len() >= 20,
        "{} pose messages",
        pose_messages.len()
    );
    assert!(pose_messages.iter().all(|p| p.timestamp_s > 0.0));
    // After this run, not beside it: two real-time runs at once on two cores drop frames
    // and starve both of CPU.
    every_frame_is_published_first_as_its_live_pose();
}

fn every_frame_is_published_first_as_its_live_pose() {
    // The client listens and the merger connects to it as it starts, so the client's
    // subscription is in place before the first frame (connecting to the merger's
    // listener instead races the replay's first frames).
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let config =
        egoslam_egress::zenoh_config(std::slice::from_ref(&endpoint), &[]).expect("config");
    let session = zenoh::open(config).wait().expect("listen");
    let received = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let sink = received.clone();
    let _poses = session
        .declare_subscriber("egoslam/live/pose")
        .callback(move |s| {
            let pose = pb::Pose::decode(&*s.payload().to_bytes()).expect("pose");
            sink.lock().expect("sink").push(pose);
        })
        .wait()
        .expect("sub");
    let out = tempfile::tempdir().expect("tempdir");
    let status = egoslam()
        .args(["run", "--realtime", "--device", "live", "--zenoh-connect"])
        .arg(&endpoint)
        .arg("--input")
        .arg(tum_fixture())
        .arg("--out")
        .arg(out.path())
        .env("EGOSLAM_ZENOH_LISTEN", "tcp/127.0.0.1:0")
        .status()
        .expect("run");
    assert!(status.success());
    let pose_messages = received.lock().expect("poses").clone();
    live_poses_come_first(&pose_messages, &report(out.path()));
}

/// Every frame's first pose is the live tracker's revision 0, published as the frame
/// arrived; the windows' poses follow as revisions marked refined.
fn live_poses_come_first(pose_messages: &[pb::Pose], report: &serde_json::Value) {
    let live = [
        pb::TrackingState::Tracking,
        pb::TrackingState::Rotation,
        pb::TrackingState::Predicted,
        pb::TrackingState::Lost,
    ]
    .map(|s| s as i32);
    let mut first: std::collections::BTreeMap<u64, &pb::Pose> = Default::default();
    for p in pose_messages {
        first.entry(p.frame_id).or_insert(p);
    }
    // The frames the pipeline took (a real-time replay drops those the frontend could not
    // take, on a loaded machine): every one reaches the client, also those the final
    // trajectory leaves out (keyframes before a gap that no window joins).
    let dropped = report["dropped_frames"].as_u64().expect("dropped frames");
    let frames = report["frames"].as_u64().expect("frames") - dropped;
    let missing: Vec<u64> = (0..report["frames"].as_u64().expect("frames"))
        .filter(|f| !first.contains_key(f))
        .collect();
    assert_eq!(
        first.len() as u64,
        frames,
        "frames with a pose at the client (missing {missing:?}, dropped by the replay: {dropped})"
    );
    for p in first.values() {
        assert!(
            p.revision == 0 && live.contains(&p.tracking),
            "frame {}: first pose revision {} state {}",
            p.frame_id,
            p.revision,
            p.tracking
        );
    }
    // A round started again (with an estimated calibration) numbers its poses from
    // round << 24: a frame's first pose in it is live too.
    let round_first = |p: &pb::Pose| egoslam_messages::first_of_round(p.revision);
    assert!(pose_messages
        .iter()
        .filter(|p| !round_first(p))
        .all(|p| p.tracking == pb::TrackingState::Refined as i32));
    assert!(pose_messages
        .iter()
        .filter(|p| round_first(p))
        .all(|p| live.contains(&p.tracking)));
    // This clip is a head turning in place with tracks living a fraction of a second, all
    // of it before the first map (below): the live tracker follows its frames from their
    // tracks, by rotation or by PnP on its own points (measured 118 of 120: 20 by PnP, 98
    // by rotation); more than a quarter predicted or lost would mean it lost the clip.
    let followed = first
        .values()
        .filter(|p| {
            p.tracking == pb::TrackingState::Tracking as i32
                || p.tracking == pb::TrackingState::Rotation as i32
        })
        .count();
    assert!(
        followed * 4 >= first.len() * 3,
        "{followed} of {} frames followed from their tracks",
        first.len()
    );
    let hops = &report["latency_ms"];
    assert_eq!(hops["live_published"]["frames"].as_u64(), Some(frames));
    // The orientation is what the live poses give on this clip: measured 1.8 deg (refined:
    // 1.3 deg; ignoring the rotation: 35 deg; with frames dropped by a loaded machine,
    // up to 5.1 deg). Their positions (2.9 cm) are barely better than a constant
    // position (3.9 cm): the clip's keyframes are held for its readout to its end, so its
    // live poses come before any map (docs/merger.md, "Live poses").
    let orientation = report["accuracy"]["live"]["orientation_rmse_deg"]
        .as_f64()
        .expect("orientation");
    assert!(
        orientation < 8.0,
        "live orientation error {orientation} deg"
    );
}
