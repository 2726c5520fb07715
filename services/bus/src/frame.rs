//! The zero-copy frames channel: grey pixels in shared memory, metadata in a C header.

use crate::port::{Inbox, Outbox};
use crate::{Bus, BusOpenError, Delivery, ReceiveError, SendError, FRAMES};
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;

/// Header of a frame sample. `#[repr(C)]` so a C++ iceoryx2 subscriber can read it.
#[derive(Debug, Default, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct FrameMeta {
    /// Index in the input stream (gaps mean frames were dropped in real-time mode).
    pub frame_id: u64,
    /// Capture time, seconds.
    pub timestamp: f64,
    pub width: u32,
    pub height: u32,
    /// Bit 0: end of stream (the payload is empty).
    pub flags: u32,
    pub reserved: u32,
    /// When the frame entered the pipeline (the replay's or camera's send time), Unix
    /// nanoseconds; 0 when unknown. Where the latency figures start.
    pub captured_unix_ns: u64,
}

/// Now as Unix nanoseconds (0 if the clock is before 1970).
pub fn unix_now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

impl FrameMeta {
    /// Flag bit of the last, empty, sample of a stream.
    pub const END_OF_STREAM: u32 = 1;

    /// True for the end-of-stream marker.
    pub fn is_end_of_stream(&self) -> bool {
        self.flags & Self::END_OF_STREAM != 0
    }
}

/// Publishes frames; the pixels are copied once, into shared memory, and read in place.
pub struct FramePublisher<'a> {
    bus: &'a Bus,
    outbox: Outbox<FrameMeta>,
    dropped: u64,
}

impl<'a> FramePublisher<'a> {
    /// Opens the frames channel as producer and waits for the consumer to connect.
    /// `max_bytes` is the largest frame (width x height) expected: it sizes the first loan.
    pub fn create(
        bus: &'a Bus,
        max_bytes: usize,
        delivery: Delivery,
    ) -> Result<Self, BusOpenError> {
        Ok(Self {
            bus,
            outbox: Outbox::open(bus, &FRAMES, max_bytes, delivery)?,
            dropped: 0,
        })
    }

    /// Sends one frame of `width` x `height` 8-bit grey pixels (row-major, no padding).
    pub fn send(&mut self, meta: FrameMeta, pixels: &[u8]) -> Result<(), SendError> {
        if pixels.len() != meta.width as usize * meta.height as usize {
            return Err(SendError::BadFrame {
                service: self.bus.service_name(&FRAMES),
                reason: format!("{} bytes for {}x{}", pixels.len(), meta.width, meta.height),
            });
        }
        if self.outbox.send(self.bus, &FRAMES, meta, pixels)? == 0 {
            tracing::debug!(
                frame_id = meta.frame_id,
                "frame not delivered (consumer full)"
            );
            self.dropped += 1;
        }
        Ok(())
    }

    /// Sends a frame whose pixels `fill` writes straight into shared memory (every byte of
    /// the `width * height` slice), returning the header; no intermediate buffer. `fill` may
    /// run more than once if the first sample reached no consumer (lossless start-up).
    pub fn send_in_place(
        &mut self,
        len: usize,
        fill: impl FnMut(&mut [std::mem::MaybeUninit<u8>]) -> FrameMeta,
    ) -> Result<(), SendError> {
        if self.outbox.send_in_place(self.bus, &FRAMES, len, fill)? == 0 {
            self.dropped += 1;
        }
        Ok(())
    }

    /// Sends the end-of-stream marker, losslessly whatever the frame mode: a dropped marker
    /// would leave the consumer waiting.
    pub fn finish(&mut self, last_frame_id: u64) -> Result<(), SendError> {
        let meta = FrameMeta {
            frame_id: last_frame_id,
            flags: FrameMeta::END_OF_STREAM,
            ..FrameMeta::default()
        };
        self.outbox
            .send_with(self.bus, &FRAMES, meta, &[], Delivery::Lossless)
            .map(|_| ())
    }

    /// Frames dropped because the consumer was full (real-time mode only).
    pub fn dropped(&self) -> u64 {
        self.dropped
    }
}

/// A received frame, still in shared memory; released when dropped.
pub struct ReceivedFrame {
    sample: Sample<ipc::Service, [u8], FrameMeta>,
}

impl ReceivedFrame {
    /// The frame's header.
    pub fn meta(&self) -> &FrameMeta {
        self.sample.user_header()
    }

    /// The pixels, read in place from shared memory.
    pub fn pixels(&self) -> &[u8] {
        self.sample.payload()
    }

    /// Why the header does not describe the payload, if it does not: a size that is not the
    /// payload's, or a non-finite timestamp. An end-of-stream marker carries no pixels.
    fn problem(&self) -> Option<String> {
        let meta = self.meta();
        if meta.is_end_of_stream() {
            return None;
        }
        let pixels = self.pixels().len();
        let expected = u64::from(meta.width) * u64::from(meta.height);
        if meta.width == 0 || meta.height == 0 || expected != pixels as u64 {
            return Some(format!("{pixels} bytes for {}x{}", meta.width, meta.height));
        }
        if !meta.timestamp.is_finite() {
            return Some(format!("timestamp {}", meta.timestamp));
        }
        None
    }
}

/// Receives frames.
pub struct FrameSubscriber<'a> {
    bus: &'a Bus,
    inbox: Inbox<FrameMeta>,
    dropped: std::cell::Cell<u64>,
}

impl<'a> FrameSubscriber<'a> {
    /// Opens the frames channel as consumer.
    pub fn create(bus: &'a Bus) -> Result<Self, BusOpenError> {
        Ok(Self {
            bus,
            inbox: Inbox::open(bus, &FRAMES)?,
            dropped: Default::default(),
        })
    }

    /// Waits for the next frame. `Ok(None)` means the process was asked to stop.
    /// Fails with [`ReceiveError::ProducerGone`] if the producer dies mid-stream.
    /// A frame whose header does not describe its pixels is dropped and counted
    /// ([`Self::dropped`]).
    pub fn receive(&self) -> Result<Option<ReceivedFrame>, ReceiveError> {
        loop {
            let Some(sample) = self.inbox.next_sample(self.bus, &FRAMES)? else {
                return Ok(None);
            };
            let frame = ReceivedFrame { sample };
            match frame.problem() {
                None => return Ok(Some(frame)),
                Some(problem) => {
                    self.dropped.set(self.dropped.get() + 1);
                    tracing::warn!(
                        frame_id = frame.meta().frame_id,
                        "frame message dropped: {problem}"
                    );
                }
            }
        }
    }

    /// Frame messages dropped so far because their header did not match their pixels.
    pub fn dropped(&self) -> u64 {
        self.dropped.get()
    }
}
