//! The bus between threads of one process (the pipeline tests cover separate processes).

use egoslam_bus::*;
use egoslam_messages::internal::v1::Keyframe;
use std::time::Duration;

fn options(test: &str) -> BusOptions {
    BusOptions {
        namespace: format!("test_{test}_{}", std::process::id()),
        delivery_timeout: Duration::from_millis(500),
        connect_timeout: Duration::from_secs(10),
    }
}

/// A consumer thread that reads frames until end of stream, calls `each` on every frame
/// and returns the frame ids it saw.
fn consume_frames(
    opts: BusOptions,
    each: impl Fn(&ReceivedFrame) + Send + 'static,
) -> std::thread::JoinHandle<Vec<u64>> {
    std::thread::spawn(move || {
        let bus = Bus::open("consumer", opts).expect("bus");
        let sub = FrameSubscriber::create(&bus).expect("subscriber");
        let mut ids = Vec::new();
        loop {
            let f = sub.receive().expect("receive").expect("not terminated");
            if f.meta().is_end_of_stream() {
                break;
            }
            ids.push(f.meta().frame_id);
            each(&f);
        }
        ids
    })
}

#[test]
fn frames_arrive_intact_in_order_with_end_of_stream() {
    let opts = options("frames");
    let consumer = consume_frames(opts.clone(), |f| {
        let expected = (f.meta().frame_id % 251) as u8;
        assert!(f.pixels().iter().all(|&p| p == expected));
        assert_eq!(f.pixels().len(), 64 * 48);
    });
    let bus = Bus::open("producer", opts).expect("bus");
    let mut publisher =
        FramePublisher::create(&bus, 64 * 48, Delivery::Lossless).expect("publisher");
    for id in 0..100u64 {
        let meta = FrameMeta {
            frame_id: id,
            timestamp: id as f64 / 30.0,
            width: 64,
            height: 48,
            ..Default::default()
        };
        publisher
            .send(meta, &vec![(id % 251) as u8; 64 * 48])
            .expect("send");
    }
    let bad = FrameMeta {
        width: 10,
        height: 10,
        ..Default::default()
    };
    assert!(matches!(
        publisher.send(bad, &[0; 5]),
        Err(SendError::BadFrame { .. })
    ));
    publisher.finish(99).expect("eos");
    let ids = consumer.join().expect("consumer thread");
    assert_eq!(ids, (0..100).collect::<Vec<_>>());
    assert_eq!(publisher.dropped(), 0);
}

#[test]
fn lossless_messages_survive_a_slow_consumer() {
    let opts = options("slow");
    let consumer_opts = opts.clone();
    let consumer = std::thread::spawn(move || {
        let bus = Bus::open("consumer", consumer_opts).expect("bus");
        let mut sub = MessageSubscriber::<Keyframe>::create(&bus, KEYFRAMES).expect("subscriber");
        let mut ids = Vec::new();
        while ids.len() < 300 {
            let k = sub.receive().expect("receive").expect("not terminated");
            if ids.len() % 50 == 0 {
                std::thread::sleep(Duration::from_millis(20));
            }
            ids.push(k.keyframe_id);
        }
        ids
    });
    let bus = Bus::open("producer", opts).expect("bus");
    let mut publisher = MessagePublisher::<Keyframe>::create(&bus, KEYFRAMES).expect("publisher");
    for id in 0..300u64 {
        // Messages bigger than the initial slice make the publisher reallocate.
        let tracks =
            (0..(id as usize * 20)).map(|t| egoslam_messages::internal::v1::TrackObservation {
                track_id: t as u64,
                ..Default::default()
            });
        let kf = Keyframe {
            keyframe_id: id,
            tracks: tracks.collect(),
            ..Default::default()
        };
        publisher.send(&kf).expect("lossless send");
    }
    let ids = consumer.join().expect("consumer thread");
    assert_eq!(ids, (0..300).collect::<Vec<_>>());
}

#[test]
fn a_consumer_that_stops_reading_fails_the_producer_instead_of_hanging_it() {
    let opts = options("hung");
    let bus_c = Bus::open("consumer", opts.clone()).expect("bus");
    let _sub = MessageSubscriber::<Keyframe>::create(&bus_c, KEYFRAMES).expect("subscriber");
    let bus = Bus::open("producer", opts).expect("bus");
    let mut publisher = MessagePublisher::<Keyframe>::create(&bus, KEYFRAMES).expect("publisher");
    let mut result = Ok(());
    for id in 0..(KEYFRAMES.buffer as u64 + 2) {
        result = publisher.send(&Keyframe {
            keyframe_id: id,
            ..Default::default()
        });
        if result.is_err() {
            break;
        }
    }
    assert!(
        matches!(result, Err(SendError::NotDelivered { .. })),
        "{result:?}"
    );
}

#[test]
fn live_frames_for_a_slow_consumer_are_dropped_and_counted_never_lost_silently() {
    let opts = options("live");
    // A consumer ten times slower than the camera.
    let consumer = consume_frames(opts.clone(), |_| {
        std::thread::sleep(Duration::from_millis(5))
    });
    let bus = Bus::open("producer", opts).expect("bus");
    let mut publisher =
        FramePublisher::create(&bus, 64 * 48, Delivery::DropNewest).expect("publisher");
    for id in 0..200u64 {
        let meta = FrameMeta {
            frame_id: id,
            timestamp: id as f64 / 30.0,
            width: 64,
            height: 48,
            ..Default::default()
        };
        publisher.send(meta, &[0u8; 64 * 48]).expect("send");
        std::thread::sleep(Duration::from_micros(500));
    }
    publisher.finish(199).expect("end of stream is lossless");
    let ids = consumer.join().expect("consumer thread");
    let dropped = publisher.dropped();
    assert!(
        dropped > 50,
        "a slow consumer must cost frames: {dropped} dropped"
    );
    // Every frame is either received or counted as dropped, and order is kept.
    assert_eq!(
        ids.len() as u64 + dropped,
        200,
        "{} received, {dropped} dropped",
        ids.len()
    );
    assert!(ids.windows(2).all(|w| w[0] < w[1]));
}

#[test]
fn invalid_messages_are_dropped_and_counted_and_the_stream_goes_on() {
    let opts = options("garbage");
    let consumer_opts = opts.clone();
    let consumer = std::thread::spawn(move || {
        let bus = Bus::open("consumer", consumer_opts).expect("bus");
        let mut sub = MessageSubscriber::<Keyframe>::create(&bus, KEYFRAMES).expect("subscriber");
        let mut got = Vec::new();
        while got.len() < 3 {
            let (sequence, k) = sub.receive_numbered().expect("receive").expect("message");
            got.push((sequence, k.keyframe_id));
        }
        (got, sub.dropped())
    });
    let bus = Bus::open("producer", opts.clone()).expect("bus");
    let mut publisher = MessagePublisher::<Keyframe>::create(&bus, KEYFRAMES).expect("publisher");
    let keyframe = |id| Keyframe {
        keyframe_id: id,
        ..Default::default()
    };
    publisher.send(&keyframe(7)).expect("send");
    // Not protobuf: a truncated length-delimited field.
    publisher
        .send_encoded(&[0x0a, 0xff, 0xff, 0x01])
        .expect("send");
    publisher.send(&keyframe(8)).expect("send");
    publisher.send(&keyframe(9)).expect("send");
    let (got, dropped) = consumer.join().expect("consumer thread");
    assert_eq!(got, vec![(0, 7), (2, 8), (3, 9)]);
    assert_eq!(dropped, 1);
}

#[test]
fn a_frame_whose_header_does_not_match_its_pixels_is_dropped() {
    let opts = options("badframe");
    let consumer = consume_frames(opts.clone(), |f| assert_eq!(f.pixels().len(), 64 * 48));
    let bus = Bus::open("producer", opts).expect("bus");
    let mut publisher =
        FramePublisher::create(&bus, 64 * 48, Delivery::Lossless).expect("publisher");
    let meta = |id, width| FrameMeta {
        frame_id: id,
        timestamp: id as f64 / 30.0,
        width,
        height: 48,
        ..Default::default()
    };
    publisher.send(meta(0, 64), &[1; 64 * 48]).expect("send");
    // The header claims 80x48 over a 64x48 payload.
    publisher
        .send_in_place(64 * 48, |pixels| {
            pixels.iter_mut().for_each(|p| {
                p.write(0);
            });
            meta(1, 80)
        })
        .expect("send");
    publisher.send(meta(2, 64), &[1; 64 * 48]).expect("send");
    publisher.finish(2).expect("eos");
    assert_eq!(consumer.join().expect("consumer thread"), vec![0, 2]);
}

#[test]
fn a_lossy_producer_can_wait_for_its_consumer_before_it_sends() {
    let opts = options("lossy_wait");
    let bus = Bus::open("producer", opts.clone()).expect("bus");
    let mut publisher =
        MessagePublisher::<Keyframe>::create_lossy(&bus, LIVE_FRAMES).expect("publisher");
    assert!(
        !publisher.wait_for_consumer(Duration::from_millis(100)),
        "no consumer yet"
    );
    // The consumer starts late; the producer waits for it, then its first message arrives.
    let consumer = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(300));
        let bus = Bus::open("consumer", opts).expect("bus");
        let mut sub = MessageSubscriber::<Keyframe>::create(&bus, LIVE_FRAMES).expect("sub");
        sub.receive_lossy_within(Duration::from_secs(5))
            .expect("receive")
            .map(|k| k.keyframe_id)
    });
    let waited = std::time::Instant::now();
    assert!(publisher.wait_for_consumer(Duration::from_secs(5)));
    assert!(waited.elapsed() >= Duration::from_millis(200));
    let first = Keyframe {
        keyframe_id: 7,
        ..Keyframe::default()
    };
    publisher.send(&first).expect("send");
    assert_eq!(consumer.join().expect("consumer"), Some(7));
}
