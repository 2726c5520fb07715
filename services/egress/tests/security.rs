//! TLS and access control of the egress session, with real zenoh sessions over 127.0.0.1
//! and certificates made by `openssl` for each test (support/pki.rs).

mod support;

use egoslam_egress::{zenoh_config, Egress, EgressOptions, NetworkOptions};
use egoslam_messages::v1 as pb;
use prost::Message;
use std::time::{Duration, Instant};
use zenoh::Wait;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("free port")
}

fn server(endpoint: &str, tls: egoslam_egress::TlsOptions, remote_read_only: bool) -> Egress {
    Egress::open(&EgressOptions {
        device: "sec".into(),
        network: NetworkOptions {
            listen: vec![endpoint.into()],
            connect: Vec::new(),
            tls: Some(tls),
            remote_read_only,
        },
    })
    .expect("egress session")
}

/// A client session, or `None` when it cannot connect within 3 s.
fn client(endpoint: &str, tls: Option<egoslam_egress::TlsOptions>) -> Option<zenoh::Session> {
    let config = NetworkOptions::client(&[endpoint.to_string()], tls)
        .zenoh_config()
        .expect("client config");
    connect(config)
}

/// Opens `config`, giving up after 3 s; `None` unless a peer is connected.
fn connect(mut config: zenoh::Config) -> Option<zenoh::Session> {
    config
        .insert_json5("connect/exit_on_failure", "true")
        .expect("exit_on_failure");
    config
        .insert_json5("connect/timeout_ms", "3000")
        .expect("timeout");
    let session = zenoh::open(config).wait().ok()?;
    (session.info().peers_zid().wait().count() > 0).then_some(session)
}

fn pose(frame_id: u64) -> pb::Pose {
    pb::Pose {
        frame_id,
        ..Default::default()
    }
}

/// Publishes poses from `egress` until `subscriber` gets one or `wait` passes.
fn delivered(
    egress: &Egress,
    subscriber: &zenoh::pubsub::Subscriber<
        zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>,
    >,
    wait: Duration,
) -> Option<pb::Pose> {
    let start = Instant::now();
    let mut frame = 0;
    while start.elapsed() < wait {
        frame += 1;
        egress.publish_poses(&[pose(frame)]).expect("publish");
        if let Ok(Some(sample)) = subscriber.recv_timeout(Duration::from_millis(100)) {
            return Some(pb::Pose::decode(&*sample.payload().to_bytes()).expect("decode"));
        }
    }
    None
}

/// A subscriber on the egress's own session: what reaches the merger from outside.
type Observer =
    zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

/// A TLS egress on a free loopback port, an observer of `observed` on its session, and a
/// client that trusts the CA (without a certificate of its own).
fn tls_server_and_client(
    pki: &support::pki::Pki,
    remote_read_only: bool,
    observed: &str,
) -> (Egress, Observer, zenoh::Session) {
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let egress = server(&endpoint, pki.tls(Some("server"), "ca"), remote_read_only);
    let observer = egress
        .session()
        .declare_subscriber(observed)
        .wait()
        .expect("observer");
    let session = client(&endpoint, Some(pki.tls(None, "ca"))).expect("trusted client connects");
    (egress, observer, session)
}

/// Puts `payload` from `client` on `key` until the server-side `observer` sees a message
/// (its size is returned) or 3 s pass.
fn put_until_seen(
    client: &zenoh::Session,
    key: &str,
    payload: &[u8],
    observer: &Observer,
) -> Option<usize> {
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(3) {
        client
            .put(key, payload.to_vec())
            .wait()
            .expect("client put");
        if let Ok(Some(s)) = observer.recv_timeout(Duration::from_millis(100)) {
            return Some(s.payload().len());
        }
    }
    None
}

fn read_only_case(pki: &support::pki::Pki, remote_read_only: bool) -> (Option<pb::Pose>, bool) {
    let (egress, observer, session) = tls_server_and_client(pki, remote_read_only, "egoslam/**");
    let poses = session
        .declare_subscriber("egoslam/sec/pose")
        .wait()
        .expect("subscribe");
    let got = delivered(&egress, &poses, Duration::from_secs(10));
    // Drain what the egress itself published.
    while let Ok(Some(_)) = observer.try_recv() {}
    let forged = pose(999_999).encode_to_vec();
    let wrote = put_until_seen(&session, "egoslam/sec/pose", &forged, &observer).is_some();
    (got, wrote)
}

#[test]
fn a_tls_client_gets_results_but_cannot_publish_into_the_session() {
    let pki = support::pki::Pki::new();
    let (got, wrote) = read_only_case(&pki, true);
    assert!(got.is_some_and(|p| p.frame_id > 0), "no pose over TLS");
    assert!(!wrote, "a remote put reached the egress session");
    // The same put does arrive when remote writes are allowed: the check above can fail.
    let (got, wrote) = read_only_case(&pki, false);
    assert!(got.is_some());
    assert!(
        wrote,
        "control: a remote put should arrive without the read-only policy"
    );
}

#[test]
fn the_snapshot_can_still_be_queried_under_the_read_only_policy() {
    let pki = support::pki::Pki::new();
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let egress = server(&endpoint, pki.tls(Some("server"), "ca"), true);
    egress.set_snapshot(&pb::Snapshot {
        keyframes: Some(pb::Trajectory {
            poses: vec![pose(7)],
        }),
        ..Default::default()
    });
    let session = client(&endpoint, Some(pki.tls(None, "ca"))).expect("client");
    let replies = session.get("egoslam/sec/snapshot").wait().expect("get");
    let reply = replies
        .recv_timeout(Duration::from_secs(5))
        .expect("channel")
        .expect("a reply");
    let sample = reply.result().expect("snapshot");
    let snapshot = pb::Snapshot::decode(&*sample.payload().to_bytes()).expect("decode");
    let frames: Vec<u64> = snapshot
        .keyframes
        .map(|t| t.poses.iter().map(|p| p.frame_id).collect())
        .unwrap_or_default();
    assert_eq!(frames, vec![7]);
}

#[test]
fn a_server_certificate_from_an_untrusted_ca_is_refused() {
    let pki = support::pki::Pki::new();
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let _egress = server(&endpoint, pki.tls(Some("rogue-server"), "rogue-ca"), true);
    assert!(
        client(&endpoint, Some(pki.tls(None, "ca"))).is_none(),
        "connected to a server whose certificate our CA did not sign"
    );
    // Plain TCP to a TLS listener is refused as well.
    let plain = zenoh_config(&[], &[endpoint.replace("tls/", "tcp/")]).expect("config");
    assert!(
        connect(plain).is_none(),
        "plain TCP session on a TLS listener"
    );
}

#[test]
fn mutual_tls_admits_only_the_named_clients() {
    let pki = support::pki::Pki::new();
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let mut tls = pki.tls(Some("server"), "ca");
    tls.mutual = true;
    tls.allowed_common_names = vec!["viewer".into()];
    let egress = server(&endpoint, tls, true);

    assert!(
        client(&endpoint, Some(pki.tls(None, "ca"))).is_none(),
        "a client without a certificate connected to a mutual-TLS listener"
    );
    let received = |name: &str| {
        let session = client(&endpoint, Some(pki.tls(Some(name), "ca")))
            .unwrap_or_else(|| panic!("{name} has a certificate from the CA and connects"));
        let poses = session
            .declare_subscriber("egoslam/sec/pose")
            .wait()
            .expect("subscribe");
        delivered(&egress, &poses, Duration::from_secs(4)).is_some()
    };
    assert!(received("viewer"), "the allowed client got nothing");
    assert!(
        !received("intruder"),
        "a client not in the list got results"
    );
}

#[test]
fn oversized_messages_from_the_network_are_dropped() {
    // Remote writes allowed here, so that only the size bound can stop the put.
    let pki = support::pki::Pki::new();
    let (_egress, observer, session) = tls_server_and_client(&pki, false, "egoslam/sec/inbox");
    let arrives =
        |bytes: usize| put_until_seen(&session, "egoslam/sec/inbox", &vec![7u8; bytes], &observer);
    assert_eq!(arrives(1000), Some(1000), "a small message must arrive");
    let big = 4 * egoslam_egress::MAX_INCOMING_MESSAGE_BYTES;
    while let Ok(Some(_)) = observer.try_recv() {}
    assert_eq!(arrives(big), None, "a {big}-byte message was accepted");
}
