//! The replay service: reads a sequence and publishes its frames on the bus.

use crate::cli::ReplayArgs;
use crate::stats::ServiceStats;
use anyhow::{bail, Context};
use egoslam_bus::{Bus, BusOptions, Delivery, FrameMeta, FramePublisher};
use egoslam_sources::{calibration::read_calibration_file, open_source, SourceError};
use opencv::prelude::*;
use std::time::{Duration, Instant};

pub fn run(args: ReplayArgs) -> anyhow::Result<()> {
    let mut stats = ServiceStats::new("replay");
    let Some(input) = args.input.clone() else {
        bail!("replay needs --input (or input.path in the config file)")
    };
    let mut source = open_source(&input, args.fps)?;
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
    let delivery = if args.realtime {
        Delivery::DropNewest
    } else {
        Delivery::Lossless
    };
    let mut publisher: Option<FramePublisher> = None;
    let (start, mut first_t) = (Instant::now(), None);
    let mut last_progress = Instant::now();
    let mut last_id = 0;
    let mut size: Option<(u32, u32)> = None;
    while let Some(frame) = stats.time("decode", || source.next_frame()) {
        // A corrupt or truncated frame after the first is skipped, named and counted: one
        // bad file must not end a long recording (the first frame is checked by `run`).
        let frame = match frame {
            Ok(f) => f,
            Err(e @ SourceError::BadImage { .. }) if size.is_some() => {
                tracing::warn!(error = %e, "corrupt frame skipped");
                stats.count("corrupt_frames", 1);
                continue;
            }
            Err(e) => return Err(e.into()),
        };
        let (w, h) = (frame.image.cols() as u32, frame.image.rows() as u32);
        match size {
            None => {
                if let Some(calib) = &camera {
                    // Fails with the calibration file and both sizes named.
                    calib.camera_for(w, h)?;
                }
                size = Some((w, h));
            }
            Some((w0, h0)) if (w0, h0) != (w, h) => {
                tracing::warn!(source = %frame.source, "frame is {w}x{h}, the stream {w0}x{h0}: skipped");
                stats.count("wrong_size_frames", 1);
                continue;
            }
            Some(_) => {}
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
            crate::systemd::ready("camera");
        }
        let Some(publisher) = publisher.as_mut() else {
            bail!("frame publisher missing")
        };
        if args.realtime {
            let t0 = *first_t.get_or_insert(frame.timestamp);
            let due = Duration::from_secs_f64((frame.timestamp - t0).max(0.0));
            if let Some(wait) = due.checked_sub(start.elapsed()) {
                if !bus.idle(wait) {
                    bail!("terminated by signal");
                }
            }
        }
        let meta = FrameMeta {
            frame_id: frame.index,
            timestamp: frame.timestamp,
            width: w,
            height: h,
            ..FrameMeta::default()
        };
        stats.time("publish", || publisher.send(meta, pixels))?;
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
    let Some(mut publisher) = publisher else {
        bail!("{}: no frames", input.display())
    };
    publisher.finish(last_id)?;
    stats.count("dropped_frames", publisher.dropped());
    tracing::info!(
        frames = stats.frames,
        dropped = publisher.dropped(),
        "replay finished"
    );
    stats.write(&args.service.out)
}
