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
}

/// Decoded grey frames, replay -> frontend. Buffer of 4 frames: enough to absorb decode
/// jitter, small enough that a live camera is never more than 4 frames behind.
pub const FRAMES: Channel = Channel {
    name: "frames",
    buffer: 4,
    initial_bytes: 640 * 480,
};

/// Keyframes with their tracks, frontend -> solver (about 1000 tracks x 24 bytes).
pub const KEYFRAMES: Channel = Channel {
    name: "keyframes",
    buffer: 64,
    initial_bytes: 64 * 1024,
};

/// Window solutions, solver -> merger.
pub const WINDOWS: Channel = Channel {
    name: "windows",
    buffer: 16,
    initial_bytes: 256 * 1024,
};
