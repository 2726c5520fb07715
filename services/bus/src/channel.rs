//! The channels and their quality of service.

/// How a channel delivers when its consumer is slower than its producer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Delivery {
    /// Producer waits for space (no sample is ever overwritten or dropped).
    Lossless,
    /// Producer drops the new sample for a full consumer and counts it (live cameras).
    DropNewest,
}

/// A named iceoryx2 publish-subscribe service.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Channel {
    /// Last component of the service name.
    pub name: &'static str,
    /// Samples a subscriber can hold before the producer must wait or drop.
    pub buffer: usize,
    /// Initial slice size in bytes; messages grow it (power-of-two reallocation).
    pub initial_bytes: usize,
    /// How long a consumer waits for a vanished producer to be restarted before it gives
    /// up, seconds (0: the producer cannot be restarted; fail at once).
    pub restart_grace_s: u64,
}

/// Decoded grey frames, replay -> frontend. Buffer of 16 frames (0.53 s at 30 fps): the
/// frontend stalls for a moment when it decides the rolling-shutter readout and releases
/// the keyframes it held for it (report.json `frontend.readout_estimate` and
/// `frontend.release_held`: ~190 ms together on a loaded machine; with both cores busy
/// elsewhere a 4-frame buffer dropped 13 frames in a row there); frames a live camera
/// drops leave a gap in the tracks, and a gap in a turn in place splits the map
/// (docs/solver.md). The frontend runs at several times real time,
/// so the buffer is empty outside such a stall, and the frames a stall queued are worked
/// off within a few frame intervals.
pub const FRAMES: Channel = Channel {
    name: "frames",
    buffer: 16,
    initial_bytes: 640 * 480,
    // The replay (or camera) is not restartable: a consumer fails as soon as it is gone.
    restart_grace_s: 0,
};

/// Keyframes with their tracks, frontend -> solver (about 1000 tracks x 24 bytes). Buffer
/// of 256: the rolling-shutter hold releases the keyframes of its first 150 frames at once
/// (`--readout-frames`, at most a keyframe per frame), and a frontend that had to wait for
/// the solver to take them missed frames of a live camera meanwhile (64: 7-9 frames dropped
/// in the rendered walk's turn in place, the map split there).
pub const KEYFRAMES: Channel = Channel {
    name: "keyframes",
    buffer: 256,
    initial_bytes: 64 * 1024,
    // A restarted frontend (launcher or systemd, RestartSec=1) comes back within seconds.
    restart_grace_s: 10,
};

/// Window solutions, solver -> merger.
pub const WINDOWS: Channel = Channel {
    name: "windows",
    buffer: 16,
    initial_bytes: 256 * 1024,
    restart_grace_s: 10,
};

/// Every tracked frame's live tracks, frontend -> the merger's live tracker
/// (`egoslam.internal.v1.LiveFrame`, ~1000 tracks x ~24 bytes). Lossy: the producer never waits (a
/// pose is worth something only while the frame is new), and a consumer that is not there
/// (not started yet, restarting) misses frames rather than holding the frontend back.
pub const LIVE_FRAMES: Channel = Channel {
    name: "live_frames",
    buffer: 8,
    initial_bytes: 32 * 1024,
    restart_grace_s: 10,
};
