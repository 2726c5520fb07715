//! Lossless channels of protobuf messages (keyframes, windows).

use crate::port::{self, Service};
use crate::{Bus, BusOpenError, Channel, Delivery, ReceiveError, SendError};
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use std::marker::PhantomData;
use std::time::{Duration, Instant};

/// Publishes protobuf messages of type `M` on a lossless channel.
pub struct MessagePublisher<'a, M> {
    bus: &'a Bus,
    channel: Channel,
    publisher: Publisher<ipc::Service, [u8], u64>,
    _service: Service<u64>,
    buffer: Vec<u8>,
    sequence: u64,
    _message: PhantomData<M>,
}

impl<'a, M: prost::Message> MessagePublisher<'a, M> {
    /// Opens `channel` as producer and waits for its consumer to connect.
    pub fn create(bus: &'a Bus, channel: Channel) -> Result<Self, BusOpenError> {
        let service = port::open_service::<u64>(bus, &channel)?;
        let publisher = port::create_publisher(bus, &channel, &service, Delivery::Lossless)?;
        port::wait_for_subscriber(bus, &channel, &service)?;
        Ok(Self {
            bus,
            channel,
            publisher,
            _service: service,
            buffer: Vec::with_capacity(channel.initial_bytes),
            sequence: 0,
            _message: PhantomData,
        })
    }

    /// Encodes and sends; blocks while the consumer is full, fails if it stays full past the
    /// delivery timeout.
    pub fn send(&mut self, message: &M) -> Result<(), SendError> {
        self.buffer.clear();
        message
            .encode(&mut self.buffer)
            .map_err(|e| SendError::Loan {
                service: self.bus.service_name(&self.channel),
                reason: e.to_string(),
            })?;
        port::send_bytes(
            self.bus,
            &self.channel,
            &self.publisher,
            self.sequence,
            &self.buffer,
            Delivery::Lossless,
        )?;
        self.sequence += 1;
        Ok(())
    }
}

/// Receives protobuf messages of type `M`. The header carries a sequence number, so a gap
/// (which the lossless QoS forbids) would be reported rather than passed on silently.
pub struct MessageSubscriber<'a, M> {
    bus: &'a Bus,
    channel: Channel,
    service: Service<u64>,
    subscriber: Subscriber<ipc::Service, [u8], u64>,
    expected: u64,
    _message: PhantomData<M>,
}

impl<'a, M: prost::Message + Default> MessageSubscriber<'a, M> {
    /// Opens `channel` as consumer.
    pub fn create(bus: &'a Bus, channel: Channel) -> Result<Self, BusOpenError> {
        let service = port::open_service::<u64>(bus, &channel)?;
        let subscriber = port::create_subscriber(bus, &channel, &service)?;
        Ok(Self {
            bus,
            channel,
            service,
            subscriber,
            expected: 0,
            _message: PhantomData,
        })
    }

    /// Waits for and decodes the next message. `Ok(None)`: the process was asked to stop.
    pub fn receive(&mut self) -> Result<Option<M>, ReceiveError> {
        let name = self.bus.service_name(&self.channel);
        let mut last_liveness_check = Instant::now();
        let sample = crate::poll_until(
            self.bus,
            None,
            || {
                let got = self.subscriber.receive().map_err(|e| ReceiveError::Port {
                    service: name.clone(),
                    reason: format!("{e:?}"),
                })?;
                if got.is_none() && last_liveness_check.elapsed() > Duration::from_secs(1) {
                    last_liveness_check = Instant::now();
                    if port::producers_gone(self.bus, &self.service)
                        && !self.subscriber.has_samples().unwrap_or(false)
                    {
                        return Err(ReceiveError::ProducerGone {
                            service: name.clone(),
                        });
                    }
                }
                Ok(got)
            },
            || unreachable!("no timeout"),
        )?;
        let Some(sample) = sample else {
            return Ok(None);
        };
        let sequence = *sample.user_header();
        if sequence != self.expected {
            return Err(ReceiveError::Decode {
                service: name,
                reason: format!("sequence gap: expected {}, got {sequence}", self.expected),
            });
        }
        self.expected += 1;
        M::decode(sample.payload())
            .map(Some)
            .map_err(|e| ReceiveError::Decode {
                service: name,
                reason: e.to_string(),
            })
    }
}
