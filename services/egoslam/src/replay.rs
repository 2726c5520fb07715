//! The replay service: reads a sequence and publishes its frames on the bus.

use crate::options::ReplayArgs;
use anyhow::{bail, Context};
use egoslam_bus::{Bus, BusOptions, Delivery, FrameMeta, FramePublisher};
use egoslam_runtime::ServiceStats;
use egoslam_sources::{calibration::read_calibration_file, open_source, FrameSource};
use opencv::prelude::*;
use std::time::{Duration, Instant};

/// Prefix of the replay's counters of skipped frames, one per reason
/// (`skipped_frames.decode`, ...), gathered under `skipped_frames` in report.json.
pub const SKIPPED_PREFIX: &str = "skipped_frames.";

pub fn run(args: ReplayArgs) -> anyhow::Result<()> {
    let mut stats = ServiceStats::new("replay");
    let Some(input) = args.sequence.input.clone() else {
        bail!("replay needs --input (or input.path in the config file)")
    };
    let mut source = open_source(&input, args.sequence.rate.fps)?;
    let total = source.len_hint();
    let camera = match &args.service.camera {
        Some(path) => Some(read_calibration_file(path)?),
        None => None,
    };
    let bus = Bus::open(
        "replay",
        BusOptions {
            namespace: args.service.namespace.clone(),
            ..BusOptions::default()
        },
    )?;
    let delivery = if args.sequence.realtime {
        Delivery::DropNewest
    } else {
        Delivery::Lossless
    };
    let mut publisher: Option<FramePublisher> = None;
    let (start, mut first_t) = (Instant::now(), None);
    let mut last_progress = Instant::now();
    let mut last_id = 0;
    let mut calibration_checked = false;
    // SIGINT/SIGTERM: stop reading, end the stream where it is, so that the services
    // behind finish what was sent and write their results.
    let mut interrupted = false;
    while let Some(frame) = stats.time("decode", || source.next_frame()) {
        if egoslam_bus::stop_requested() {
            interrupted = true;
            break;
        }
        // Bad frames (missing, undecodable, another size, out-of-order timestamps) never
        // reach here: the source skips, names and counts them (FrameStream).
        let frame = frame?;
        let (w, h) = (frame.image.cols() as u32, frame.image.rows() as u32);
        if !calibration_checked {
            if let Some(calib) = &camera {
                // Fails with the calibration file and both sizes named.
                calib.camera_for(w, h)?;
            }
            calibration_checked = true;
        }
        let image = if frame.image.is_continuous() {
            frame.image
        } else {
            frame.image.try_clone()?
        };
        let pixels = image
            .data_bytes()
            .with_context(|| format!("{}: pixel access", frame.source))?;
        if publisher.is_none() {
            publisher = Some(FramePublisher::create(&bus, pixels.len(), delivery)?);
            egoslam_runtime::systemd::ready("camera");
        }
        let Some(publisher) = publisher.as_mut() else {
            bail!("frame publisher missing")
        };
        if args.sequence.realtime {
            let t0 = *first_t.get_or_insert(frame.timestamp);
            // Timestamps are finite and increasing (FrameStream); a gap too long for a
            // Duration is not waited for.
            let due = Duration::try_from_secs_f64((frame.timestamp - t0).max(0.0))
                .unwrap_or(Duration::ZERO);
            if let Some(wait) = due.checked_sub(start.elapsed()) {
                if !bus.idle(wait) {
                    interrupted = true;
                    break;
                }
            }
        }
        let meta = FrameMeta {
            frame_id: frame.index,
            timestamp: frame.timestamp,
            width: w,
            height: h,
            // The replay's send stands in for the camera's capture.
            captured_unix_ns: egoslam_bus::unix_now_ns(),
            ..FrameMeta::default()
        };
        match stats.time("publish", || publisher.send(meta, pixels)) {
            Ok(()) => {}
            // A lossless send waiting for room gives up on the stop request.
            Err(_) if egoslam_bus::stop_requested() => {
                interrupted = true;
                break;
            }
            Err(e) => return Err(e.into()),
        }
        stats.frames += 1;
        last_id = frame.index;
        if last_progress.elapsed() > Duration::from_secs(2) {
            last_progress = Instant::now();
            let fps = stats.frames as f64 / start.elapsed().as_secs_f64();
            match total {
                Some(n) => tracing::info!("replay: {}/{n} frames ({fps:.1} fps)", stats.frames),
                None => tracing::info!("replay: {} frames ({fps:.1} fps)", stats.frames),
            }
        }
    }
    if interrupted {
        tracing::warn!(
            frames = stats.frames,
            "stop requested: the stream ends here"
        );
        stats.count("interrupted", 1);
    }
    let Some(mut publisher) = publisher else {
        if interrupted {
            return Ok(stats.write(&args.service.output.out)?);
        }
        bail!("{}: no frames", input.display())
    };
    publisher.finish(last_id)?;
    stats.count("dropped_frames", publisher.dropped());
    for (reason, n) in source.skipped().iter() {
        stats.count(&format!("{SKIPPED_PREFIX}{reason}"), n);
    }
    tracing::info!(
        frames = stats.frames,
        dropped = publisher.dropped(),
        "replay finished"
    );
    Ok(stats.write(&args.service.output.out)?)
}
