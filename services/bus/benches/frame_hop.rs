//! One-way latency of a 640x480 grey frame between two processes over the `frames` channel,
//! publish (loan + copy into shared memory + send + wake-up) to receive (woken consumer
//! holding the sample). Method in docs/benchmarks.md.
//!
//! `cargo bench -p egoslam-bus --bench frame_hop`

use egoslam_bus::{Bus, BusOptions, Delivery, FrameMeta, FramePublisher, FrameSubscriber};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

const FRAMES: u64 = 2000;
const WIDTH: u32 = 640;
const HEIGHT: u32 = 480;

fn now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

fn options(ns: &str) -> BusOptions {
    BusOptions {
        namespace: ns.into(),
        ..BusOptions::default()
    }
}

fn consumer(ns: &str, mode: &str) {
    let bus = Bus::open("bench_consumer", options(ns)).expect("bus");
    let sub = FrameSubscriber::create(&bus).expect("subscriber");
    let mut latencies = Vec::with_capacity(FRAMES as usize);
    loop {
        let frame = sub.receive().expect("receive").expect("not terminated");
        let received = now();
        if frame.meta().is_end_of_stream() {
            break;
        }
        assert_eq!(frame.pixels().len(), (WIDTH * HEIGHT) as usize);
        latencies.push((received - frame.meta().timestamp) * 1e6);
    }
    // Skip warm-up (page faults of the first loans).
    let mut l: Vec<f64> = latencies[100..].to_vec();
    l.sort_by(f64::total_cmp);
    let p = |q: f64| l[((l.len() - 1) as f64 * q) as usize];
    println!(
        "frame hop 640x480 grey ({mode}: stamped {}), {} frames, one way: median {:.1} us, p90 {:.1} us, p99 {:.1} us",
        if mode == "copy" { "before the copy into shared memory" } else { "after writing in shared memory, at send" },
        l.len(),
        p(0.5),
        p(0.9),
        p(0.99)
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(pos) = args.iter().position(|a| a == "--consumer") {
        consumer(&args[pos + 1], &args[pos + 2]);
        return;
    }
    for mode in ["in-place", "copy"] {
        hop(mode == "copy", mode);
    }
}

fn hop(copy_mode: bool, mode: &str) {
    let ns = format!(
        "bench_hop_{}_{}",
        std::process::id(),
        mode.replace('-', "_")
    );
    let exe = std::env::current_exe().expect("exe");
    let mut child = std::process::Command::new(exe)
        .args(["--consumer", &ns, mode])
        .spawn()
        .expect("consumer");
    let bus = Bus::open("bench_producer", options(&ns)).expect("bus");
    let mut publisher = FramePublisher::create(&bus, (WIDTH * HEIGHT) as usize, Delivery::Lossless)
        .expect("publisher");
    let pixels = vec![128u8; (WIDTH * HEIGHT) as usize];
    for id in 0..FRAMES {
        if copy_mode {
            let meta = FrameMeta {
                frame_id: id,
                timestamp: now(),
                width: WIDTH,
                height: HEIGHT,
                ..FrameMeta::default()
            };
            publisher.send(meta, &pixels).expect("send");
        } else {
            // The producer writes the frame into shared memory, then stamps and sends it.
            let fill = |dst: &mut [std::mem::MaybeUninit<u8>]| {
                for (d, s) in dst.iter_mut().zip(&pixels) {
                    d.write(*s);
                }
                FrameMeta {
                    frame_id: id,
                    timestamp: now(),
                    width: WIDTH,
                    height: HEIGHT,
                    ..FrameMeta::default()
                }
            };
            publisher.send_in_place(pixels.len(), fill).expect("send");
        }
        // 500 frames/s: the consumer is idle (asleep) when each frame arrives, as in service.
        std::thread::sleep(Duration::from_millis(2));
    }
    publisher.finish(FRAMES - 1).expect("eos");
    assert!(child.wait().expect("consumer").success());
}
