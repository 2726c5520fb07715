//! Opening a channel's service and its ports with the channel's QoS.

use crate::{Bus, BusOpenError, Channel, Delivery, SendError};
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::BackpressureAction;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use std::fmt::Debug;
use std::time::Duration;

pub(crate) type Service<H> = PubSubFactory<ipc::Service, [u8], H>;

/// The service of `channel`, created by whichever side comes first.
pub(crate) fn open_service<H: Debug + ZeroCopySend>(
    bus: &Bus,
    channel: &Channel,
) -> Result<Service<H>, BusOpenError> {
    let name = bus.service_name(channel);
    let service_name: ServiceName = name
        .as_str()
        .try_into()
        .map_err(|_| BusOpenError::BadName(name.clone()))?;
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

pub(crate) fn create_publisher<H: Debug + ZeroCopySend + Default>(
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
    builder.create().map_err(|e| BusOpenError::Port {
        service: bus.service_name(channel),
        reason: format!("{e:?}"),
    })
}

pub(crate) fn create_subscriber<H: Debug + ZeroCopySend>(
    bus: &Bus,
    channel: &Channel,
    service: &Service<H>,
) -> Result<Subscriber<ipc::Service, [u8], H>, BusOpenError> {
    service
        .subscriber_builder()
        .buffer_size(channel.buffer)
        .create()
        .map_err(|e| BusOpenError::Port {
            service: bus.service_name(channel),
            reason: format!("{e:?}"),
        })
}

/// Blocks until at least one subscriber is connected (so nothing is sent into the void).
pub(crate) fn wait_for_subscriber<H: Debug + ZeroCopySend>(
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

/// Loans, fills and sends one sample; returns the number of consumers reached.
///
/// With [`Delivery::Lossless`] a sample that reached no consumer is sent again until it
/// does: iceoryx2 only blocks on a full buffer once the subscriber has connected its side,
/// which it does on its first `receive`; samples sent before that would otherwise vanish.
/// Fails after the delivery timeout (consumer hung or gone).
pub(crate) fn send_bytes<H: Debug + ZeroCopySend + Default + Copy>(
    bus: &Bus,
    channel: &Channel,
    publisher: &Publisher<ipc::Service, [u8], H>,
    header: H,
    bytes: &[u8],
    delivery: Delivery,
) -> Result<usize, SendError> {
    let start = std::time::Instant::now();
    loop {
        let mut sample = publisher
            .loan_slice_uninit(bytes.len())
            .map_err(|e| SendError::Loan {
                service: bus.service_name(channel),
                reason: format!("{e:?}"),
            })?;
        *sample.user_header_mut() = header;
        let sample = sample.write_from_slice(bytes);
        let delivered = sample.send().map_err(|_| SendError::NotDelivered {
            service: bus.service_name(channel),
        })?;
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

/// Whether the producers of a service have all gone; cleans up dead nodes first, so a
/// producer killed with SIGKILL is noticed.
pub(crate) fn producers_gone<H: Debug + ZeroCopySend>(bus: &Bus, service: &Service<H>) -> bool {
    let _ = bus.node().try_cleanup_dead_nodes();
    service.dynamic_config().number_of_publishers() == 0
}
