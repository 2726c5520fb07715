//! The zero-copy frames channel: grey pixels in shared memory, metadata in a C header.

use crate::port::{self, Service};
use crate::{Bus, BusOpenError, Delivery, ReceiveError, SendError, FRAMES};
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use std::time::{Duration, Instant};

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
    _service: Service<FrameMeta>,
    publisher: Publisher<ipc::Service, [u8], FrameMeta>,
    delivery: Delivery,
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
        let service = port::open_service::<FrameMeta>(bus, &FRAMES)?;
        let channel = crate::Channel {
            initial_bytes: max_bytes.max(1),
            ..FRAMES
        };
        let publisher = port::create_publisher(bus, &channel, &service, delivery)?;
        port::wait_for_subscriber(bus, &FRAMES, &service)?;
        Ok(Self {
            bus,
            _service: service,
            publisher,
            delivery,
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
        let delivered = port::send_bytes(
            self.bus,
            &FRAMES,
            &self.publisher,
            meta,
            pixels,
            self.delivery,
        )?;
        if delivered == 0 {
            tracing::debug!(
                frame_id = meta.frame_id,
                "frame not delivered (consumer full)"
            );
            self.dropped += 1;
        }
        Ok(())
    }

    /// Sends the end-of-stream marker (lossless whatever the frame delivery mode).
    pub fn finish(&mut self, last_frame_id: u64) -> Result<(), SendError> {
        let meta = FrameMeta {
            frame_id: last_frame_id,
            flags: FrameMeta::END_OF_STREAM,
            ..FrameMeta::default()
        };
        // Lossless whatever the frame mode: a dropped marker would hang the consumer.
        port::send_bytes(
            self.bus,
            &FRAMES,
            &self.publisher,
            meta,
            &[],
            Delivery::Lossless,
        )
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
    service: Service<FrameMeta>,
    subscriber: Subscriber<ipc::Service, [u8], FrameMeta>,
}

impl<'a> FrameSubscriber<'a> {
    /// Opens the frames channel as consumer.
    pub fn create(bus: &'a Bus) -> Result<Self, BusOpenError> {
        let service = port::open_service::<FrameMeta>(bus, &FRAMES)?;
        let subscriber = port::create_subscriber(bus, &FRAMES, &service)?;
        Ok(Self {
            bus,
            service,
            subscriber,
        })
    }

    /// Waits for the next frame. `Ok(None)` means the process was asked to stop.
    /// Fails with [`ReceiveError::ProducerGone`] if the producer dies mid-stream.
    pub fn receive(&self) -> Result<Option<ReceivedFrame>, ReceiveError> {
        let mut last_liveness_check = Instant::now();
        crate::poll_until(
            self.bus,
            None,
            || {
                let got = self.subscriber.receive().map_err(|e| ReceiveError::Port {
                    service: self.bus.service_name(&FRAMES),
                    reason: format!("{e:?}"),
                })?;
                if got.is_none() && last_liveness_check.elapsed() > Duration::from_secs(1) {
                    last_liveness_check = Instant::now();
                    if port::producers_gone(self.bus, &self.service)
                        && !self.subscriber.has_samples().unwrap_or(false)
                    {
                        return Err(ReceiveError::ProducerGone {
                            service: self.bus.service_name(&FRAMES),
                        });
                    }
                }
                Ok(got.map(|sample| ReceivedFrame { sample }))
            },
            || unreachable!("no timeout"),
        )
    }
}
