//! The window solver service: keyframes from the bus -> windows -> solutions on the bus.

use crate::cli::ServiceArgs;
use crate::stats::ServiceStats;
use anyhow::bail;
use egoslam_bus::{Bus, BusOptions, MessagePublisher, MessageSubscriber, KEYFRAMES, WINDOWS};
use egoslam_messages::v1 as pb;
use egoslam_solver::windowing::Window;
use egoslam_solver::{WindowBuilder, WindowOptions};

/// Timing facts of a keyframe, for the merger's per-frame trajectory.
fn stamp(k: &pb::Keyframe) -> pb::KeyframeStamp {
    pb::KeyframeStamp {
        keyframe_id: k.keyframe_id,
        frame_id: k.frame_id,
        timestamp_s: k.timestamp_s,
        frames_since_previous_ids: k.frames_since_previous.iter().map(|f| f.frame_id).collect(),
        frames_since_previous_timestamps_s: k
            .frames_since_previous
            .iter()
            .map(|f| f.timestamp_s)
            .collect(),
    }
}

/// Solves one window. Until the estimators land this forwards the keyframes only.
fn solve(
    window_id: u64,
    window: &Window<pb::Keyframe>,
    stats: &mut ServiceStats,
) -> pb::WindowSolution {
    stats.time("window", || pb::WindowSolution {
        window_id,
        keyframe_ids: window.keyframes.iter().map(|k| k.keyframe_id).collect(),
        overlap: window.overlap as u32,
        keyframes: window.keyframes.iter().map(stamp).collect(),
        quality: Some(pb::SolutionQuality {
            status: pb::SolveStatus::PassThrough as i32,
            reason: "pass-through: no window estimator in this build".into(),
            ..Default::default()
        }),
        ..Default::default()
    })
}

pub fn run(args: ServiceArgs) -> anyhow::Result<()> {
    let mut stats = ServiceStats::new("solver");
    let mut builder = WindowBuilder::new(WindowOptions {
        size: args.pipeline.window,
        overlap: args.pipeline.overlap,
    })?;
    let bus = Bus::open(
        "solver",
        BusOptions {
            namespace: args.namespace.clone(),
            ..BusOptions::default()
        },
    )?;
    let mut keyframes = MessageSubscriber::<pb::Keyframe>::create(&bus, KEYFRAMES)?;
    let mut windows = MessagePublisher::<pb::WindowSolution>::create(&bus, WINDOWS)?;
    let mut trailing = Vec::new();
    loop {
        let Some(k) = keyframes.receive()? else {
            bail!("terminated by signal")
        };
        let end_of_stream = k.end_of_stream;
        let window = if end_of_stream {
            trailing = k.trailing_frames;
            builder.finish()
        } else {
            stats.keyframes += 1;
            builder.push(k)
        };
        if let Some(window) = window {
            let solution = solve(stats.windows, &window, &mut stats);
            windows.send(&solution)?;
            stats.windows += 1;
        }
        if end_of_stream {
            break;
        }
    }
    // The end-of-stream message carries the frames after the last keyframe (normally none).
    windows.send(&pb::WindowSolution {
        end_of_stream: true,
        trailing_frames: trailing,
        ..Default::default()
    })?;
    tracing::info!(
        keyframes = stats.keyframes,
        windows = stats.windows,
        "solver finished"
    );
    stats.write(&args.out)
}
