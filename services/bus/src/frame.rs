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
}

/// Receives frames.
pub struct FrameSubscriber<'a> {
    bus: &'a Bus,
    inbox: Inbox<FrameMeta>,
}

impl<'a> FrameSubscriber<'a> {
    /// Opens the frames channel as consumer.
    pub fn create(bus: &'a Bus) -> Result<Self, BusOpenError> {
        Ok(Self {
            bus,
            inbox: Inbox::open(bus, &FRAMES)?,
        })
    }

    /// Waits for the next frame. `Ok(None)` means the process was asked to stop.
    /// Fails with [`ReceiveError::ProducerGone`] if the producer dies mid-stream.
    pub fn receive(&self) -> Result<Option<ReceivedFrame>, ReceiveError> {
        Ok(self
            .inbox
            .next_sample(self.bus, &FRAMES)?
            .map(|sample| ReceivedFrame { sample }))
    }
}
