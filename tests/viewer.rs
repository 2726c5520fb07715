//! `egoslam run --foxglove --record` on the embedded TUM clip, replayed in real time: a
//! WebSocket client sees the channels advertised within 3 s of the launch, and the MCAP
//! recording has a pose for every frame and the map's points.

mod common;

use common::*;
use foxglove::messages::{PointCloud, PoseInFrame};
use prost::Message;
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// The JSON ops a `foxglove.sdk.v1` client receives first: serverInfo, then advertise.
fn first_ops(port: u16, deadline: Instant) -> Vec<serde_json::Value> {
    use tungstenite::client::IntoClientRequest;
    let mut request = format!("ws://127.0.0.1:{port}")
        .into_client_request()
        .expect("request");
    request.headers_mut().insert(
        "Sec-WebSocket-Protocol",
        "foxglove.sdk.v1".parse().expect("header"),
    );
    let stream = loop {
        match std::net::TcpStream::connect(("127.0.0.1", port)) {
            Ok(s) => break s,
            Err(e) => {
                assert!(Instant::now() < deadline, "no server on {port}: {e}");
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    };
    stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .expect("timeout");
    let (mut socket, _) = tungstenite::client(request, stream).expect("handshake");
    let mut ops = Vec::new();
    while ops.len() < 2 {
        match socket.read().expect("a message") {
            tungstenite::Message::Text(t) => {
                ops.push(serde_json::from_str(t.as_str()).expect("json"))
            }
            _ => continue,
        }
    }
    ops
}

#[test]
fn a_run_is_served_to_foxglove_and_recorded_into_mcap() {
    let out = tempfile::tempdir().expect("tempdir");
    let recording = out.path().join("run.mcap");
    let port = free_port();
    let launched = Instant::now();
    let run = egoslam()
        .args(["run", "--realtime", "--input"])
        .arg(tum_fixture())
        .arg("--out")
        .arg(out.path().join("out"))
        .arg("--foxglove")
        .arg(format!("127.0.0.1:{port}"))
        .arg("--record")
        .arg(&recording)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("run");
    let ops = first_ops(port, launched + Duration::from_secs(3));
    assert!(
        launched.elapsed() < Duration::from_secs(3),
        "{:?}",
        launched.elapsed()
    );
    assert_eq!(ops[0]["op"], "serverInfo", "{ops:?}");
    assert_eq!(ops[1]["op"], "advertise", "{ops:?}");
    let topics: Vec<&str> = ops[1]["channels"]
        .as_array()
        .expect("channels")
        .iter()
        .filter_map(|c| c["topic"].as_str())
        .collect();
    for topic in ["/egoslam/pose", "/tf", "/egoslam/map", "/egoslam/keyframes"] {
        assert!(topics.contains(&topic), "{topic} not in {topics:?}");
    }
    let status = run.wait_with_output().expect("run").status;
    assert!(status.success(), "{status}");

    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.path().join("out/report.json")).expect("report"))
            .expect("json");
    let posed = report["posed_frames"].as_u64().expect("posed_frames");
    let bytes = std::fs::read(&recording).expect("recording");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("a summary section: the recording was closed");
    let stats = summary.stats.expect("statistics");
    let counts: BTreeMap<String, u64> = summary
        .channels
        .iter()
        .map(|(id, c)| {
            let n = stats.channel_message_counts.get(id).copied().unwrap_or(0);
            (c.topic.clone(), n)
        })
        .collect();
    assert!(counts["/egoslam/pose"] >= posed, "{counts:?}");
    let mut last_cloud = None;
    for message in mcap::MessageStream::new(&bytes).expect("messages") {
        let message = message.expect("message");
        if message.channel.topic == "/egoslam/map" {
            last_cloud = Some(PointCloud::decode(&*message.data).expect("cloud"));
        }
    }
    // Every frame once as revision 0 (the camera transform), more poses with the
    // revisions. A frame's revision 0 is its live pose, or its window's when the lossy
    // live channel dropped it; a real-time run can leave tracked frames out of
    // trajectory.tum, so there are at least as many as posed frames.
    let frames = pose_frames(&bytes);
    assert_one_transform_per_first_pose(counts["/tf"], frames, &report);
    assert!(frames >= posed, "{frames} frames, {posed} posed");
    let points = report["map_points"].as_u64().expect("map_points");
    let cloud = last_cloud.expect("a point cloud");
    eprintln!(
        "PROBE {} cloud points, {points} map points",
        cloud.data.len() / 12
    );
    // The cloud holds every point published: each of the map's (new and moved points go
    // out after every window), and those culled since.
    assert!(
        cloud.data.len() as u64 >= 12 * points,
        "{} bytes, {points} points",
        cloud.data.len()
    );
}

/// `egoslam view` follows a run as a zenoh client (as it would a deployed merger whose
/// `--zenoh-connect` names it) and records every frame's first pose.
#[test]
fn egoslam_view_records_a_run_it_follows() {
    let dir = tempfile::tempdir().expect("tempdir");
    let recording = dir.path().join("view.mcap");
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let mut view = egoslam()
        .args([
            "view",
            "--device",
            "vt",
            "--until-finished",
            "--listen",
            &endpoint,
        ])
        .arg("--record")
        .arg(&recording)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("view");
    wait_until_following(&mut view);
    let out = dir.path().join("out");
    let report = run_report_with(
        &tum_fixture(),
        &out,
        &["--device", "vt", "--zenoh-connect", &endpoint],
    );
    let status = view.wait_with_output().expect("view").status;
    assert!(status.success(), "{status}");
    let posed = report["posed_frames"].as_u64().expect("posed");
    let bytes = std::fs::read(&recording).expect("recording");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("a summary section: the recording was closed");
    let stats = summary.stats.expect("statistics");
    let tf = summary
        .channels
        .iter()
        .find(|(_, c)| c.topic == "/tf")
        .map(|(id, _)| stats.channel_message_counts.get(id).copied().unwrap_or(0));
    // One camera transform per frame's revision 0 (see the test above).
    let frames = pose_frames(&bytes);
    assert_one_transform_per_first_pose(tf.expect("a /tf channel"), frames, &report);
    assert!(frames >= posed, "{frames} frames, {posed} posed");
}

/// Blocks until `egoslam view` says it follows (its subscribers and listener are up, so
/// a run started now reaches it before publishing), then drains its log on a thread.
fn wait_until_following(view: &mut std::process::Child) {
    use std::io::BufRead;
    let log = view.stderr.take().expect("piped stderr");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(log).lines().map_while(Result::ok) {
            if line.contains("following egoslam") {
                let _ = tx.send(());
            }
        }
    });
    rx.recv_timeout(Duration::from_secs(30))
        .expect("egoslam view never said it follows");
}

/// One camera transform per frame's first pose, and never two: the clip runs once (its
/// keyframes are held for the readout instead of the run starting again: docs/config.md,
/// "Calibration from the stream"). A live pose the lossy live channel dropped leaves its
/// frame without one (its window's pose comes as a later revision, which moves no
/// camera): at most 1 in 20.
fn assert_one_transform_per_first_pose(tf: u64, frames: u64, report: &serde_json::Value) {
    let rounds = 1 + report["calibration_restarts"].as_u64().expect("restarts");
    assert_eq!(rounds, 1, "the clip's readout is held, not a second run");
    assert!(
        tf <= frames && tf * 20 >= frames * 19,
        "{tf} camera transforms for {frames} frames"
    );
}

/// The frames (distinct capture times) of a recording's `/egoslam/pose` messages.
fn pose_frames(bytes: &[u8]) -> u64 {
    let mut frames = std::collections::BTreeSet::new();
    for message in mcap::MessageStream::new(bytes).expect("messages") {
        let message = message.expect("message");
        if message.channel.topic == "/egoslam/pose" {
            let p = PoseInFrame::decode(&*message.data).expect("pose");
            let t = p.timestamp.expect("stamped");
            frames.insert((t.sec(), t.nsec()));
        }
    }
    frames.len() as u64
}
