//! The viewer fed by the real zenoh publisher (egoslam_egress::Egress, as the merger uses
//! it), recording into an MCAP file read back with the `mcap` crate.

use egoslam_egress::{Egress, EgressOptions, NetworkOptions};
use egoslam_messages::v1 as pb;
use egoslam_viewer::feed::{free_loopback_endpoint, Feed};
use egoslam_viewer::{Viewer, ViewerOptions};
use foxglove::messages::{PointCloud, PoseInFrame};
use prost::Message;
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

fn pose(frame: u64, x: f64) -> pb::Pose {
    pb::Pose {
        frame_id: frame,
        timestamp_s: 100.0 + frame as f64 / 30.0,
        position: Some(pb::Vec3 { x, y: 0.0, z: 0.0 }),
        orientation: Some(pb::Quaternion {
            w: 1.0,
            ..Default::default()
        }),
        ..Default::default()
    }
}

#[test]
fn what_the_merger_publishes_is_recorded_on_foxglove_schemas() {
    let dir = tempfile::tempdir().expect("tempdir");
    let recording = dir.path().join("run.mcap");
    let viewer = Arc::new(
        Viewer::start(&ViewerOptions {
            foxglove: Some("127.0.0.1:0".into()),
            record: Some(recording.clone()),
            cloud_interval: Duration::ZERO,
            ..ViewerOptions::default()
        })
        .expect("viewer"),
    );
    assert!(viewer.port().is_some_and(|p| p > 0));
    let endpoint = free_loopback_endpoint().expect("free port");
    let feed = Feed::open(
        &NetworkOptions {
            listen: vec![endpoint.clone()],
            ..NetworkOptions::client(&[], None)
        },
        "rec",
        viewer.clone(),
    )
    .expect("feed");
    // The merger's side: its own session, connecting to the feed's.
    let egress = Egress::open(&EgressOptions {
        device: "rec".into(),
        network: NetworkOptions {
            listen: Vec::new(),
            connect: vec![endpoint],
            ..NetworkOptions::default()
        },
    })
    .expect("egress");
    // Puts go nowhere until the feed's subscriptions reach the publisher: a status until
    // one arrives, then the stream.
    let running = pb::Status {
        service: "merger".into(),
        state: pb::ServiceState::Running as i32,
        ..Default::default()
    };
    let started = std::time::Instant::now();
    while feed.received() == 0 {
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "the feed hears nothing"
        );
        egress.publish_status(&running).expect("status");
        std::thread::sleep(Duration::from_millis(100));
    }
    let poses: Vec<pb::Pose> = (0..150).map(|f| pose(f, f as f64 * 0.01)).collect();
    egress.publish_poses(&poses).expect("poses");
    let points: Vec<pb::MapPoint> = (0..500)
        .map(|i| pb::MapPoint {
            track_id: i,
            position: Some(pb::Vec3 {
                x: i as f64,
                y: 1.0,
                z: 2.0,
            }),
            ..Default::default()
        })
        .collect();
    egress.publish_map(&points).expect("map");
    egress
        .publish_trajectory(&pb::Trajectory {
            poses: poses.iter().step_by(10).cloned().collect(),
        })
        .expect("trajectory");
    egress
        .publish_status(&pb::Status {
            service: "merger".into(),
            state: pb::ServiceState::Finished as i32,
            frames: 150,
            ..Default::default()
        })
        .expect("status");
    assert!(
        feed.wait_finished(Duration::from_secs(10)),
        "no FINISHED status"
    );
    assert_eq!(feed.undecodable(), 0);
    drop(feed);
    drop(egress);
    viewer.finish().expect("finish");

    let bytes = std::fs::read(&recording).expect("recording");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("a summary section");
    let stats = summary.stats.expect("statistics");
    let mut by_topic = BTreeMap::new();
    for (id, channel) in &summary.channels {
        let schema = channel
            .schema
            .as_ref()
            .map(|s| s.name.clone())
            .unwrap_or_default();
        assert_eq!(channel.message_encoding, "protobuf");
        let count = stats.channel_message_counts.get(id).copied().unwrap_or(0);
        by_topic.insert(channel.topic.clone(), (schema, count));
    }
    assert_eq!(
        by_topic["/egoslam/pose"],
        ("foxglove.PoseInFrame".into(), 150)
    );
    assert_eq!(by_topic["/tf"], ("foxglove.FrameTransform".into(), 150));
    assert_eq!(by_topic["/egoslam/map"].0, "foxglove.PointCloud");
    assert_eq!(by_topic["/egoslam/keyframes"].1, 1);
    assert!(by_topic["/egoslam/status"].1 >= 2);
    let mut last_pose = None;
    let mut cloud = None;
    for message in mcap::MessageStream::new(&bytes).expect("messages") {
        let message = message.expect("message");
        match message.channel.topic.as_str() {
            "/egoslam/pose" => last_pose = Some(PoseInFrame::decode(&*message.data).expect("pose")),
            "/egoslam/map" => cloud = Some(PointCloud::decode(&*message.data).expect("cloud")),
            _ => {}
        }
    }
    let last = last_pose.expect("a pose");
    assert_eq!(last.frame_id, "map");
    let x = last.pose.and_then(|p| p.position).map(|v| v.x);
    assert!(x.is_some_and(|x| (x - 1.49).abs() < 1e-9), "{x:?}");
    assert_eq!(cloud.expect("a cloud").data.len(), 500 * 12);
}
