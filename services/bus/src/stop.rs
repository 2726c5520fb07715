//! Stopping on request within a bounded time.
//!
//! iceoryx2 catches SIGINT and SIGTERM (`SignalHandlingMode::HandleTerminationRequests`) and
//! reports them to whoever waits on the node next; a service then finishes cleanly. A
//! service busy elsewhere (a long solve, a send to a consumer that is gone) would not look
//! for a while, and a service still running when systemd's TimeoutStopSec or the launcher's
//! stop deadline runs out is killed without a word. So every process that opens the bus
//! also watches for the signal itself (signal-hook chains iceoryx2's handler, which still
//! runs) and exits [`STOP_GRACE`] after it if it has not ended by then.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::Duration;

/// How long a service may take to finish after SIGINT or SIGTERM before it exits anyway:
/// well inside the launcher's 5 s stop and systemd's TimeoutStopSec=10.
pub const STOP_GRACE: Duration = Duration::from_secs(2);

/// Exit status of a process that did not finish within [`STOP_GRACE`] (128 + SIGTERM, as a
/// shell reports a process killed by it).
pub const STOP_DEADLINE_EXIT: i32 = 143;

static REQUESTED: OnceLock<Arc<AtomicBool>> = OnceLock::new();

/// Whether SIGINT or SIGTERM has been received (once [`watch_stop_requests`] has run). Unlike
/// iceoryx2's own check, asking does not reset it.
pub fn stop_requested() -> bool {
    REQUESTED.get().is_some_and(|f| f.load(Ordering::Relaxed))
}

/// Starts watching for SIGINT/SIGTERM (once per process; later calls do nothing). Call it
/// after the iceoryx2 node is created, so that its handler is the one chained.
pub fn watch_stop_requests() {
    let mut first = false;
    let flag = REQUESTED.get_or_init(|| {
        first = true;
        Arc::new(AtomicBool::new(false))
    });
    if !first {
        return;
    }
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        if let Err(e) = signal_hook::flag::register(signal, Arc::clone(flag)) {
            tracing::warn!(signal, "cannot watch for stop requests: {e}");
            return;
        }
    }
    let flag = Arc::clone(flag);
    let spawned = std::thread::Builder::new()
        .name("stop-deadline".into())
        .spawn(move || {
            while !flag.load(Ordering::Relaxed) {
                std::thread::sleep(Duration::from_millis(50));
            }
            std::thread::sleep(STOP_GRACE);
            tracing::error!(
                "still running {:.1} s after the stop request: exiting",
                STOP_GRACE.as_secs_f64()
            );
            std::process::exit(STOP_DEADLINE_EXIT);
        });
    if let Err(e) = spawned {
        tracing::warn!("cannot start the stop deadline: {e}");
    }
}

/// A service's loop ended because SIGINT or SIGTERM asked it to stop: the way a service is
/// stopped (systemd, the launcher ending or starting a run again), reported as such rather
/// than as a failure. `during` says what was cut short ("" when nothing was).
#[derive(Debug, thiserror::Error)]
#[error("stopped by a signal{during}")]
pub struct StoppedBySignal {
    pub during: &'static str,
}
