//! Channels of protobuf messages: lossless (keyframes, windows) and lossy (live frames).

use crate::port::{Inbox, Outbox};
use crate::{Bus, BusOpenError, Channel, Delivery, ReceiveError, SendError};
use std::marker::PhantomData;

/// Publishes protobuf messages of type `M` on a lossless channel.
pub struct MessagePublisher<'a, M> {
    bus: &'a Bus,
    channel: Channel,
    outbox: Outbox<u64>,
    buffer: Vec<u8>,
    sequence: u64,
    _message: PhantomData<M>,
}

impl<'a, M: prost::Message> MessagePublisher<'a, M> {
    /// Opens `channel` as producer and waits for its consumer to connect.
    pub fn create(bus: &'a Bus, channel: Channel) -> Result<Self, BusOpenError> {
        Ok(Self {
            bus,
            channel,
            outbox: Outbox::open(bus, &channel, channel.initial_bytes, Delivery::Lossless)?,
            buffer: Vec::with_capacity(channel.initial_bytes),
            sequence: 0,
            _message: PhantomData,
        })
    }

    /// Opens a lossy channel (the live frames) as producer: a send never waits, and
    /// reaches whichever consumer is there, if any (see [`Delivery::DropNewest`]).
    pub fn create_lossy(bus: &'a Bus, channel: Channel) -> Result<Self, BusOpenError> {
        Ok(Self {
            bus,
            channel,
            outbox: Outbox::open_without_waiting(
                bus,
                &channel,
                channel.initial_bytes,
                Delivery::DropNewest,
            )?,
            buffer: Vec::with_capacity(channel.initial_bytes),
            sequence: 0,
            _message: PhantomData,
        })
    }

    /// Numbers the next message `sequence` instead of continuing from 0: a restarted
    /// producer that resumes its stream (the solver, from its journal) goes on where its
    /// predecessor stopped, so that the consumer sees no new stream and no gap.
    pub fn continue_at(mut self, sequence: u64) -> Self {
        self.sequence = sequence;
        self
    }

    /// Encodes `message` into the reused buffer.
    fn encode(&mut self, message: &M) -> Result<(), SendError> {
        self.buffer.clear();
        message
            .encode(&mut self.buffer)
            .map_err(|e| SendError::Loan {
                service: self.bus.service_name(&self.channel),
                reason: e.to_string(),
            })
    }

    /// Encodes and sends; blocks while the consumer is full, fails if it stays full past the
    /// delivery timeout.
    pub fn send(&mut self, message: &M) -> Result<(), SendError> {
        self.encode(message)?;
        self.outbox
            .send(self.bus, &self.channel, self.sequence, &self.buffer)?;
        self.sequence += 1;
        Ok(())
    }

    /// On a lossy channel: waits up to `patience` for a consumer to connect; whether one
    /// did. A producer that must not lose a lossy consumer's first messages waits for it
    /// before it takes its own input.
    pub fn wait_for_consumer(&self, patience: std::time::Duration) -> bool {
        self.outbox.wait_for_consumer(self.bus, patience)
    }

    /// On a lossy channel: sends, and sends again until a consumer took it or `patience`
    /// has passed; whether one did. For the one message a consumer must not miss while it
    /// may still be connecting (iceoryx2 connects a subscriber at its first receive).
    pub fn send_patiently(
        &mut self,
        message: &M,
        patience: std::time::Duration,
    ) -> Result<bool, SendError> {
        self.encode(message)?;
        let start = std::time::Instant::now();
        loop {
            let delivered =
                self.outbox
                    .send(self.bus, &self.channel, self.sequence, &self.buffer)?;
            if delivered > 0 || start.elapsed() >= patience {
                self.sequence += 1;
                return Ok(delivered > 0);
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
    }

    /// Sends a payload that is already encoded (a recorded stream replayed by a tool) with
    /// the next sequence number. The bytes are not checked here: the consumer drops what it
    /// cannot decode.
    pub fn send_encoded(&mut self, payload: &[u8]) -> Result<(), SendError> {
        self.outbox
            .send(self.bus, &self.channel, self.sequence, payload)?;
        self.sequence += 1;
        Ok(())
    }
}

impl<M> MessagePublisher<'_, M> {
    /// Ends the stream: waits until the consumer has disconnected, so that nothing sent is
    /// lost with this process (see docs/bus.md). Call after the end-of-stream message.
    /// Returns `false` when the process was asked to terminate meanwhile.
    pub fn finish(self) -> bool {
        self.outbox.wait_until_consumers_leave(self.bus)
    }
}

/// Receives protobuf messages of type `M`. The header carries the producer's sequence number,
/// handed to the consumer with each message. The lossless QoS allows a forward gap only when
/// a producer died after journaling a message and before sending it, and its successor
/// continued the numbering: the gap is logged and passed on, and the consumer fills it from
/// the producer's journal (the merger does; docs/durability.md). A number going backwards
/// (other than a restart from 0) is an error. The first number need not be 0: a consumer
/// restarted mid-stream joins where the producer is.
pub struct MessageSubscriber<'a, M> {
    bus: &'a Bus,
    channel: Channel,
    inbox: Inbox<u64>,
    expected: Option<u64>,
    dropped: u64,
    missed: u64,
    _message: PhantomData<M>,
}

impl<'a, M: prost::Message + Default> MessageSubscriber<'a, M> {
    /// Opens `channel` as consumer.
    pub fn create(bus: &'a Bus, channel: Channel) -> Result<Self, BusOpenError> {
        Ok(Self {
            bus,
            channel,
            inbox: Inbox::open(bus, &channel)?,
            expected: None,
            dropped: 0,
            missed: 0,
            _message: PhantomData,
        })
    }

    /// Waits for and decodes the next message. `Ok(None)`: the process was asked to stop.
    pub fn receive(&mut self) -> Result<Option<M>, ReceiveError> {
        Ok(self.receive_numbered()?.map(|(_, m)| m))
    }

    /// As [`Self::receive`], with the producer's sequence number of the message. A message
    /// that is not valid (see [`Self::dropped`]) is skipped.
    pub fn receive_numbered(&mut self) -> Result<Option<(u64, M)>, ReceiveError> {
        loop {
            let Some(sample) = self.inbox.next_sample(self.bus, &self.channel)? else {
                return Ok(None);
            };
            if let Some(message) = self.validated(sample) {
                return Ok(Some(message));
            }
        }
    }

    /// The next valid message with its sequence number if one has arrived; `Ok(None)` when
    /// none has. Never waits: a consumer busy with something else (the merger waiting for
    /// its background refinement) keeps taking messages, so the producer's lossless `send`
    /// does not run into its delivery timeout.
    pub fn try_receive_numbered(&mut self) -> Result<Option<(u64, M)>, ReceiveError> {
        loop {
            let Some(sample) = self.inbox.try_next_sample(self.bus, &self.channel)? else {
                return Ok(None);
            };
            if let Some(message) = self.validated(sample) {
                return Ok(Some(message));
            }
        }
    }

    /// For a lossy channel: the next valid message if one arrives within `timeout`. Gaps
    /// in the numbering are messages the producer dropped: counted in [`Self::missed`],
    /// not reported.
    pub fn receive_lossy_within(
        &mut self,
        timeout: std::time::Duration,
    ) -> Result<Option<M>, ReceiveError> {
        let Some(sample) = self
            .inbox
            .next_sample_within(self.bus, &self.channel, timeout)?
        else {
            return Ok(None);
        };
        let sequence = *sample.user_header();
        if let Some(expected) = self.expected {
            self.missed += sequence.saturating_sub(expected);
        }
        self.expected = Some(sequence + 1);
        match M::decode(sample.payload()) {
            Ok(message) => Ok(Some(message)),
            Err(e) => {
                self.dropped += 1;
                tracing::warn!(error = %e, dropped = self.dropped, "bus message dropped");
                Ok(None)
            }
        }
    }

    /// Messages of a lossy channel that the producer dropped before they reached this
    /// consumer (it was full or not there).
    pub fn missed(&self) -> u64 {
        self.missed
    }

    /// Messages dropped so far: undecodable payloads and sequence numbers going back. One
    /// bad message (a foreign or broken producer, a torn write) must not stop the pipeline;
    /// the lossless stream's own messages are always valid, and a real loss shows as a
    /// forward gap, which the consumer fills from the producer's journal.
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    fn validated(
        &mut self,
        sample: iceoryx2::sample::Sample<iceoryx2::service::ipc::Service, [u8], u64>,
    ) -> Option<(u64, M)> {
        match self.decode(sample) {
            Ok(message) => Some(message),
            Err(e) => {
                self.dropped += 1;
                tracing::warn!(error = %e, dropped = self.dropped, "bus message dropped");
                None
            }
        }
    }

    fn decode(
        &mut self,
        sample: iceoryx2::sample::Sample<iceoryx2::service::ipc::Service, [u8], u64>,
    ) -> Result<(u64, M), ReceiveError> {
        let name = self.bus.service_name(&self.channel);
        let sequence = *sample.user_header();
        if let Some(expected) = self.expected {
            if sequence == 0 && expected > 0 {
                // A restarted producer numbers from 0 again: a new stream, not a gap.
                tracing::warn!(service = %name, after = expected, "producer restarted: a new stream begins");
            } else if sequence > expected {
                tracing::warn!(service = %name, expected, got = sequence, "sequence gap: the consumer fills it from the producer's journal");
            } else if sequence < expected {
                return Err(ReceiveError::Decode {
                    service: name,
                    reason: format!("sequence went back: expected {expected}, got {sequence}"),
                });
            }
        }
        let message = M::decode(sample.payload()).map_err(|e| ReceiveError::Decode {
            service: name,
            reason: e.to_string(),
        })?;
        self.expected = Some(sequence + 1);
        Ok((sequence, message))
    }
}
