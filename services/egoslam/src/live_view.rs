//! `egoslam run --foxglove/--record`: the run's live view (egoslam_viewer), started before
//! anything else so that a viewer sees the run from its first second. Its zenoh session
//! listens on a free loopback port and the merger connects to it, beside whatever the
//! merger itself listens on.

use crate::cli::{EgressArgs, ViewArgs};
use anyhow::Context;
use egoslam_egress::NetworkOptions;
use egoslam_viewer::feed::{free_loopback_endpoint, Feed};
use egoslam_viewer::{Viewer, ViewerOptions};
use std::sync::Arc;
use std::time::Duration;

pub struct LiveView {
    viewer: Arc<Viewer>,
    feed: Feed,
    endpoint: String,
}

impl LiveView {
    /// The view, if one was asked for.
    pub fn start(view: &ViewArgs, egress: &EgressArgs) -> anyhow::Result<Option<Self>> {
        if !view.wanted() {
            return Ok(None);
        }
        if egress.zenoh_listen.iter().any(|e| e == "none") {
            anyhow::bail!(
                "--foxglove and --record show what the merger publishes over zenoh: drop --zenoh-listen none"
            );
        }
        let viewer = Arc::new(Viewer::start(&ViewerOptions {
            foxglove: view.foxglove.clone(),
            record: view.record.clone(),
            ..ViewerOptions::default()
        })?);
        if let Some(port) = viewer.port() {
            eprintln!("Foxglove: ws://127.0.0.1:{port} (open connection in the Foxglove app)");
        }
        let endpoint = free_loopback_endpoint().context("finding a free loopback port")?;
        let network = NetworkOptions {
            listen: vec![endpoint.clone()],
            ..NetworkOptions::client(&[], None)
        };
        let feed = Feed::open(&network, &egress.device, viewer.clone())?;
        Ok(Some(Self {
            viewer,
            feed,
            endpoint,
        }))
    }

    /// The merger's flag that connects it to this view.
    pub fn merger_flag(&self) -> String {
        format!("--zenoh-connect={}", self.endpoint)
    }

    /// After the services ended: the last results in, the recording closed.
    pub fn finish(self, interrupted: bool) -> anyhow::Result<()> {
        let wait = if interrupted {
            Duration::ZERO
        } else {
            Duration::from_secs(5)
        };
        if !self.feed.wait_finished(wait) && !interrupted {
            tracing::warn!("the live view did not see the merger finish; the recording ends here");
        }
        drop(self.feed);
        self.viewer.finish()?;
        Ok(())
    }
}
