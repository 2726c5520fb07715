//! Opening a channel's service and its ports with the channel's QoS.

use crate::{Bus, BusOpenError, Channel, Delivery, ReceiveError, SendError};
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::BackpressureAction;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use std::fmt::Debug;
use std::mem::MaybeUninit;
use std::time::Duration;

pub(crate) type Service<H> = PubSubFactory<ipc::Service, [u8], H>;

/// An iceoryx2 service name, or the error naming the invalid string.
fn iceoryx2_name(name: &str) -> Result<ServiceName, BusOpenError> {
    name.try_into()
        .map_err(|_| BusOpenError::BadName(name.to_string()))
}

/// The service of `channel`, created by whichever side comes first.
pub(crate) fn open_service<H: Debug + ZeroCopySend>(
    bus: &Bus,
    channel: &Channel,
) -> Result<Service<H>, BusOpenError> {
    let name = bus.service_name(channel);
    let service_name = iceoryx2_name(&name)?;
    bus.node()
        .service_builder(&service_name)
        .publish_subscribe::<[u8]>()
        .user_header::<H>()
        // Never overwrite an unread sample: losing a keyframe would corrupt the map silently.
        .enable_safe_overflow(false)
        .subscriber_max_buffer_size(channel.buffer)
        .history_size(0)
        .max_publishers(2)
        .max_subscribers(4)
        .open_or_create()
        .map_err(|e| BusOpenError::Service {
            service: name,
            reason: format!("{e:?}"),
        })
}

fn create_publisher<H: Debug + ZeroCopySend + Default>(
    bus: &Bus,
    channel: &Channel,
    service: &Service<H>,
    delivery: Delivery,
) -> Result<Publisher<ipc::Service, [u8], H>, BusOpenError> {
    let timeout = bus.options().delivery_timeout;
    let builder = service
        .publisher_builder()
        .initial_max_slice_len(channel.initial_bytes)
        .allocation_strategy(AllocationStrategy::PowerOfTwo);
    let builder = match delivery {
        Delivery::Lossless => builder
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
            .set_backpressure_handler(move |info: &iceoryx2::port::BackpressureInfo| {
                if info.elapsed_time > timeout {
                    BackpressureAction::DiscardDataAndFail
                } else {
                    if info.retries > 1000 {
                        std::thread::sleep(Duration::from_micros(100));
                    }
                    BackpressureAction::Retry
                }
            }),
        Delivery::DropNewest => builder.backpressure_strategy(BackpressureStrategy::DiscardData),
    };
    builder.create().map_err(port_error(bus, channel))
}

/// Maps an iceoryx2 port-creation error of `channel`.
fn port_error<E: Debug>(bus: &Bus, channel: &Channel) -> impl Fn(E) -> BusOpenError {
    let service = bus.service_name(channel);
    move |e| BusOpenError::Port {
        service: service.clone(),
        reason: format!("{e:?}"),
    }
}

fn create_subscriber<H: Debug + ZeroCopySend>(
    bus: &Bus,
    channel: &Channel,
    service: &Service<H>,
) -> Result<Subscriber<ipc::Service, [u8], H>, BusOpenError> {
    service
        .subscriber_builder()
        .buffer_size(channel.buffer)
        .create()
        .map_err(port_error(bus, channel))
}

/// Blocks until at least one subscriber is connected (so nothing is sent into the void).
fn wait_for_subscriber<H: Debug + ZeroCopySend>(
    bus: &Bus,
    channel: &Channel,
    service: &Service<H>,
) -> Result<bool, BusOpenError> {
    let seconds = bus.options().connect_timeout.as_secs();
    let connected = crate::poll_until(
        bus,
        Some(bus.options().connect_timeout),
        || {
            Ok::<_, BusOpenError>(
                (service.dynamic_config().number_of_subscribers() > 0).then_some(()),
            )
        },
        || BusOpenError::NoSubscriber {
            service: bus.service_name(channel),
            seconds,
        },
    )?;
    Ok(connected.is_some())
}

/// Loans `len` bytes, lets `fill` write the payload in place and return the header, sends;
/// returns the number of consumers reached.
///
/// With [`Delivery::Lossless`] a sample that reached no consumer is filled and sent again
/// until it does: iceoryx2 only blocks on a full buffer once the subscriber has connected its
/// side, which it does on its first `receive`; samples sent before that would otherwise
/// vanish. Fails after the delivery timeout (consumer hung or gone).
fn send_filled<H: Debug + ZeroCopySend + Default + Copy>(
    bus: &Bus,
    channel: &Channel,
    publisher: &Publisher<ipc::Service, [u8], H>,
    notifier: &Notifier,
    len: usize,
    mut fill: impl FnMut(&mut [MaybeUninit<u8>]) -> H,
    delivery: Delivery,
) -> Result<usize, SendError> {
    let start = std::time::Instant::now();
    loop {
        crate::record_activity();
        let mut sample = publisher
            .loan_slice_uninit(len)
            .map_err(|e| SendError::Loan {
                service: bus.service_name(channel),
                reason: format!("{e:?}"),
            })?;
        let header = fill(sample.payload_mut());
        *sample.user_header_mut() = header;
        // SAFETY: `fill` initialised every byte of the payload (its contract).
        let sample = unsafe { sample.assume_init() };
        let delivered = sample.send().map_err(|_| SendError::NotDelivered {
            service: bus.service_name(channel),
        })?;
        let _ = notifier.notify();
        if delivered > 0 || delivery == Delivery::DropNewest {
            return Ok(delivered);
        }
        if start.elapsed() > bus.options().delivery_timeout {
            return Err(SendError::NotDelivered {
                service: bus.service_name(channel),
            });
        }
        std::thread::sleep(Duration::from_micros(100));
    }
}

/// Copies `src` into a loaned payload.
fn copy_into(dst: &mut [MaybeUninit<u8>], src: &[u8]) {
    for (d, s) in dst.iter_mut().zip(src) {
        d.write(*s);
    }
}

/// Whether the producers of a service have all gone; cleans up dead nodes first, so a
/// producer killed with SIGKILL is noticed.
fn producers_gone<H: Debug + ZeroCopySend>(bus: &Bus, service: &Service<H>) -> bool {
    let _ = bus.node().try_cleanup_dead_nodes();
    service.dynamic_config().number_of_publishers() == 0
}

/// The wake-up event of a channel: producers notify after each send so that consumers can
/// sleep in the kernel instead of polling (one-way frame latency stays in microseconds).
fn open_wakeup(bus: &Bus, channel: &Channel) -> Result<EventService, BusOpenError> {
    let name = format!("{}/wakeup", bus.service_name(channel));
    let service_name = iceoryx2_name(&name)?;
    bus.node()
        .service_builder(&service_name)
        .event()
        .max_notifiers(2)
        .max_listeners(4)
        .open_or_create()
        .map_err(|e| BusOpenError::Service {
            service: name,
            reason: format!("{e:?}"),
        })
}

pub(crate) type EventService = iceoryx2::service::port_factory::event::PortFactory<ipc::Service>;
pub(crate) type Notifier = iceoryx2::port::notifier::Notifier<ipc::Service>;
pub(crate) type Listener = iceoryx2::port::listener::Listener<ipc::Service>;

fn create_notifier(
    bus: &Bus,
    channel: &Channel,
    events: &EventService,
) -> Result<Notifier, BusOpenError> {
    events
        .notifier_builder()
        .create()
        .map_err(port_error(bus, channel))
}

fn create_listener(
    bus: &Bus,
    channel: &Channel,
    events: &EventService,
) -> Result<Listener, BusOpenError> {
    events
        .listener_builder()
        .create()
        .map_err(port_error(bus, channel))
}

/// The consumer side of a channel: subscriber, wake-up listener and liveness check.
pub(crate) struct Inbox<H: Debug + ZeroCopySend> {
    pub(crate) service: Service<H>,
    pub(crate) subscriber: Subscriber<ipc::Service, [u8], H>,
    _events: EventService,
    listener: Listener,
}

impl<H: Debug + ZeroCopySend> Inbox<H> {
    pub(crate) fn open(bus: &Bus, channel: &Channel) -> Result<Self, BusOpenError> {
        let service = open_service::<H>(bus, channel)?;
        let subscriber = create_subscriber(bus, channel, &service)?;
        let events = open_wakeup(bus, channel)?;
        let listener = create_listener(bus, channel, &events)?;
        Ok(Self {
            service,
            subscriber,
            _events: events,
            listener,
        })
    }

    /// Waits for the next sample. `Ok(None)`: the process was asked to terminate.
    /// Fails with [`ReceiveError::ProducerGone`] if the producer dies mid-stream.
    /// The next sample if one is waiting; never waits.
    pub(crate) fn try_next_sample(
        &self,
        bus: &Bus,
        channel: &Channel,
    ) -> Result<Option<iceoryx2::sample::Sample<ipc::Service, [u8], H>>, ReceiveError> {
        crate::record_activity();
        self.subscriber.receive().map_err(|e| ReceiveError::Port {
            service: bus.service_name(channel),
            reason: format!("{e:?}"),
        })
    }

    /// The next sample, waiting at most `timeout` for one (woken by the producer's
    /// notification); `Ok(None)` when none came. No liveness check: for a lossy channel
    /// whose producer may be absent.
    pub(crate) fn next_sample_within(
        &self,
        bus: &Bus,
        channel: &Channel,
        timeout: Duration,
    ) -> Result<Option<iceoryx2::sample::Sample<ipc::Service, [u8], H>>, ReceiveError> {
        if let Some(sample) = self.try_next_sample(bus, channel)? {
            return Ok(Some(sample));
        }
        let _ = self.listener.timed_wait(|_| {}, timeout);
        self.try_next_sample(bus, channel)
    }

    pub(crate) fn next_sample(
        &self,
        bus: &Bus,
        channel: &Channel,
    ) -> Result<Option<iceoryx2::sample::Sample<ipc::Service, [u8], H>>, ReceiveError> {
        let name = || bus.service_name(channel);
        let mut last_liveness_check = std::time::Instant::now();
        let mut gone_since: Option<std::time::Instant> = None;
        loop {
            crate::record_activity();
            let got = self.subscriber.receive().map_err(|e| ReceiveError::Port {
                service: name(),
                reason: format!("{e:?}"),
            })?;
            if got.is_some() {
                return Ok(got);
            }
            if last_liveness_check.elapsed() > Duration::from_secs(1) {
                last_liveness_check = std::time::Instant::now();
                if producers_gone(bus, &self.service)
                    && !self.subscriber.has_samples().unwrap_or(false)
                {
                    // A restartable producer gets `restart_grace_s` to come back.
                    let since = *gone_since.get_or_insert_with(std::time::Instant::now);
                    if since.elapsed() >= Duration::from_secs(channel.restart_grace_s) {
                        return Err(ReceiveError::ProducerGone { service: name() });
                    }
                    if since.elapsed() < Duration::from_millis(1100) {
                        tracing::warn!(service = %name(), grace_s = channel.restart_grace_s, "producer gone; waiting for it to be restarted");
                    }
                } else {
                    gone_since = None;
                }
            }
            if !bus.idle(Duration::ZERO) {
                return Ok(None);
            }
            // Sleeps until a producer's notification (or 50 ms, for the checks above).
            let _ = self.listener.timed_wait(|_| {}, Duration::from_millis(50));
        }
    }
}

/// The producer side of a channel: publisher with the channel's QoS and wake-up notifier.
pub(crate) struct Outbox<H: Debug + ZeroCopySend> {
    _service: Service<H>,
    publisher: Publisher<ipc::Service, [u8], H>,
    _events: EventService,
    notifier: Notifier,
    delivery: Delivery,
}

impl<H: Debug + ZeroCopySend + Default + Copy> Outbox<H> {
    /// Opens the channel as producer (first loan sized `initial_bytes`) and waits for a
    /// consumer to connect.
    pub(crate) fn open(
        bus: &Bus,
        channel: &Channel,
        initial_bytes: usize,
        delivery: Delivery,
    ) -> Result<Self, BusOpenError> {
        let outbox = Self::open_without_waiting(bus, channel, initial_bytes, delivery)?;
        wait_for_subscriber(bus, channel, &outbox._service)?;
        Ok(outbox)
    }

    /// As [`Self::open`], without waiting for a consumer (a lossy channel whose consumer
    /// may come and go).
    pub(crate) fn open_without_waiting(
        bus: &Bus,
        channel: &Channel,
        initial_bytes: usize,
        delivery: Delivery,
    ) -> Result<Self, BusOpenError> {
        let service = open_service::<H>(bus, channel)?;
        let sized = Channel {
            initial_bytes: initial_bytes.max(1),
            ..*channel
        };
        let publisher = create_publisher(bus, &sized, &service, delivery)?;
        let events = open_wakeup(bus, channel)?;
        let notifier = create_notifier(bus, channel, &events)?;
        Ok(Self {
            _service: service,
            publisher,
            _events: events,
            notifier,
            delivery,
        })
    }

    /// Waits up to `patience` for a consumer to connect; whether one did (`false` too when
    /// the process is asked to terminate meanwhile).
    pub(crate) fn wait_for_consumer(&self, bus: &Bus, patience: std::time::Duration) -> bool {
        let connected = crate::poll_until(
            bus,
            Some(patience),
            || {
                Ok::<_, ()>(
                    (self._service.dynamic_config().number_of_subscribers() > 0).then_some(()),
                )
            },
            || (),
        );
        matches!(connected, Ok(Some(())))
    }

    /// Waits until every consumer has disconnected (finished, or died and was cleaned up).
    /// A producer must not exit while a consumer may still read: samples that grew the
    /// publisher's data segment live in memory the consumer maps lazily, and vanish with
    /// the producer (iceoryx2 then reports a "lost chunk"). `false`: asked to terminate.
    pub(crate) fn wait_until_consumers_leave(&self, bus: &Bus) -> bool {
        let mut last_cleanup = std::time::Instant::now();
        loop {
            crate::record_activity();
            if self._service.dynamic_config().number_of_subscribers() == 0 {
                return true;
            }
            if last_cleanup.elapsed() > Duration::from_millis(500) {
                last_cleanup = std::time::Instant::now();
                let _ = bus.node().try_cleanup_dead_nodes();
            }
            if !bus.idle(Duration::from_millis(10)) {
                return false;
            }
        }
    }

    /// Sends with the outbox's delivery mode (see [`send_filled`]).
    pub(crate) fn send(
        &self,
        bus: &Bus,
        channel: &Channel,
        header: H,
        bytes: &[u8],
    ) -> Result<usize, SendError> {
        self.send_with(bus, channel, header, bytes, self.delivery)
    }

    /// Sends with an explicit delivery mode (end-of-stream markers are always lossless).
    pub(crate) fn send_with(
        &self,
        bus: &Bus,
        channel: &Channel,
        header: H,
        bytes: &[u8],
        delivery: Delivery,
    ) -> Result<usize, SendError> {
        let fill = |dst: &mut [MaybeUninit<u8>]| {
            copy_into(dst, bytes);
            header
        };
        send_filled(
            bus,
            channel,
            &self.publisher,
            &self.notifier,
            bytes.len(),
            fill,
            delivery,
        )
    }

    /// Sends `len` bytes written in place by `fill` (which must write all of them and returns
    /// the header); see [`send_filled`].
    pub(crate) fn send_in_place(
        &self,
        bus: &Bus,
        channel: &Channel,
        len: usize,
        fill: impl FnMut(&mut [MaybeUninit<u8>]) -> H,
    ) -> Result<usize, SendError> {
        send_filled(
            bus,
            channel,
            &self.publisher,
            &self.notifier,
            len,
            fill,
            self.delivery,
        )
    }
}
