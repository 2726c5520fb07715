//! What `egoslam run` shows while it runs: the live view (`--foxglove`, `--record`,
//! egoslam_viewer) and, on a terminal, the pipeline's progress bar (progress.rs). Both
//! follow the merger's results over zenoh like any client: a session of the launcher's
//! listens on a free loopback port and the merger connects to it, beside whatever the
//! merger itself listens on. The view starts before anything else in the run, so that a
//! viewer sees it from its first second.

use crate::options::{EgressArgs, ViewArgs};
use anyhow::Context;
use egoslam_egress::NetworkOptions;
use egoslam_messages::v1 as pb;
use egoslam_viewer::feed::{free_loopback_endpoint, Feed, ResultSink};
use egoslam_viewer::{Viewer, ViewerOptions};
use indicatif::ProgressBar;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// The results go to the viewer, and the merger's frame count to the progress bar.
#[derive(Default)]
struct Watchers {
    viewer: Option<Viewer>,
    bar: Mutex<Option<ProgressBar>>,
}

impl ResultSink for Watchers {
    fn pose(&self, pose: &pb::Pose) {
        if let Some(v) = &self.viewer {
            v.pose(pose);
        }
    }
    fn trajectory(&self, trajectory: &pb::Trajectory) {
        if let Some(v) = &self.viewer {
            v.trajectory(trajectory);
        }
    }
    fn map_points(&self, points: &pb::MapPoints) {
        if let Some(v) = &self.viewer {
            v.map_points(points);
        }
    }
    fn status(&self, status: &pb::Status) {
        if let Some(v) = &self.viewer {
            v.status(status);
        }
        if status.service == "merger" {
            if let Some(bar) = self.bar.lock().unwrap_or_else(|e| e.into_inner()).as_ref() {
                bar.set_position(status.frames);
                bar.set_message(format!("{} keyframes", status.keyframes));
            }
        }
    }
}

pub struct LiveView {
    watchers: Arc<Watchers>,
    feed: Feed,
    endpoint: String,
}

impl LiveView {
    /// The view and progress, if a view was asked for or stderr is a terminal; an error
    /// when a view was asked for and cannot be given.
    pub fn start(view: &ViewArgs, egress: &EgressArgs) -> anyhow::Result<Option<Self>> {
        let no_zenoh = egress.zenoh_listen.iter().any(|e| e == "none");
        if view.wanted() && no_zenoh {
            anyhow::bail!(
                "--foxglove and --record show what the merger publishes over zenoh: drop --zenoh-listen none"
            );
        }
        if no_zenoh || !(view.wanted() || crate::supervision::progress::on_terminal()) {
            return Ok(None);
        }
        let viewer = if view.wanted() {
            let viewer = Viewer::start(&ViewerOptions {
                foxglove: view.foxglove.clone(),
                record: view.record.clone(),
                ..ViewerOptions::default()
            })?;
            if let Some(port) = viewer.port() {
                eprintln!("Foxglove: ws://127.0.0.1:{port} (open connection in the Foxglove app)");
            }
            Some(viewer)
        } else {
            None
        };
        let watchers = Arc::new(Watchers {
            viewer,
            bar: Mutex::new(None),
        });
        let endpoint = free_loopback_endpoint().context("finding a free loopback port")?;
        let network = NetworkOptions {
            listen: vec![endpoint.clone()],
            ..NetworkOptions::client(&[], None)
        };
        let feed = Feed::open(&network, &egress.device, watchers.clone())?;
        Ok(Some(Self {
            watchers,
            feed,
            endpoint,
        }))
    }

    /// The merger's flag that connects it to this view.
    pub fn merger_flag(&self) -> String {
        format!("--zenoh-connect={}", self.endpoint)
    }

    /// From here on the merger's posed frames move `bar`.
    pub fn follow_with(&self, bar: ProgressBar) {
        *self.watchers.bar.lock().unwrap_or_else(|e| e.into_inner()) = Some(bar);
    }

    /// After the services ended: the last results in, the recording closed.
    pub fn finish(self, interrupted: bool) -> anyhow::Result<()> {
        let wait = if interrupted {
            Duration::ZERO
        } else {
            Duration::from_secs(5)
        };
        let finished = self.feed.wait_finished(wait);
        if let Some(bar) = self
            .watchers
            .bar
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take()
        {
            bar.finish_and_clear();
        }
        let Some(viewer) = &self.watchers.viewer else {
            return Ok(());
        };
        if !finished && !interrupted {
            tracing::warn!("the live view did not see the merger finish; the recording ends here");
        }
        drop(self.feed);
        viewer.finish()?;
        Ok(())
    }
}

/// `egoslam view`: the live view of a running egoslam, as a client of its zenoh output.
#[derive(clap::Args, Debug)]
pub struct ViewCommandArgs {
    /// The merger's zenoh endpoint (repeatable).
    #[arg(long, default_value = "tcp/127.0.0.1:7447")]
    pub connect: Vec<String>,
    /// Also listen here (repeatable), for a merger started with `--zenoh-connect` to it:
    /// it then reaches the view before it publishes anything. A view that connects to a
    /// running merger sees what is published from then on.
    #[arg(long)]
    pub listen: Vec<String>,
    /// Device name (egoslam/<device>/...).
    #[arg(long, default_value = "default")]
    pub device: String,
    #[command(flatten)]
    pub view: ViewArgs,
    /// Stop when the merger reports the stream finished (default: at Ctrl-C or SIGTERM).
    #[arg(long)]
    pub until_finished: bool,
}

pub fn view(args: ViewCommandArgs) -> anyhow::Result<()> {
    if !args.view.wanted() {
        anyhow::bail!("nothing to do: give --foxglove HOST:PORT and/or --record FILE.mcap");
    }
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, Arc::clone(&stop))
            .with_context(|| format!("catching signal {signal}"))?;
    }
    let viewer = Arc::new(Viewer::start(&ViewerOptions {
        foxglove: args.view.foxglove.clone(),
        record: args.view.record.clone(),
        ..ViewerOptions::default()
    })?);
    if let Some(port) = viewer.port() {
        eprintln!("Foxglove: ws://127.0.0.1:{port} (open connection in the Foxglove app)");
    }
    let network = NetworkOptions {
        listen: args.listen.clone(),
        ..NetworkOptions::client(&args.connect, None)
    };
    let feed = Feed::open(&network, &args.device, viewer.clone())?;
    tracing::info!(connect = ?args.connect, device = %args.device, "following egoslam");
    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
        if feed.wait_finished(Duration::from_millis(200)) && args.until_finished {
            break;
        }
    }
    drop(feed);
    viewer.finish()?;
    Ok(())
}
