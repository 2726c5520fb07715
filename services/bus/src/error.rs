//! One error enum per fallible bus operation.

/// Opening the node or a port failed.
#[derive(Debug, thiserror::Error)]
pub enum BusOpenError {
    /// The process or service name is not a valid iceoryx2 name.
    #[error("invalid bus name {0:?}")]
    BadName(String),
    /// The iceoryx2 node could not be created (e.g. /dev/shm not writable).
    #[error("cannot create iceoryx2 node: {0}")]
    Node(String),
    /// The service exists with other settings (another egoslam version?) or cannot be created.
    #[error("cannot open service {service}: {reason}")]
    Service { service: String, reason: String },
    /// The publisher or subscriber port could not be created (too many ports?).
    #[error("cannot create port on {service}: {reason}")]
    Port { service: String, reason: String },
    /// No consumer connected within the connect timeout.
    #[error("no subscriber connected to {service} within {seconds} s")]
    NoSubscriber { service: String, seconds: u64 },
}

/// Publishing a sample failed.
#[derive(Debug, thiserror::Error)]
pub enum SendError {
    /// No shared memory could be loaned (all samples in flight).
    #[error("cannot loan a sample on {service}: {reason}")]
    Loan { service: String, reason: String },
    /// A lossless consumer did not read within the delivery timeout (hung or dead).
    #[error("consumer of {service} did not take the sample within the delivery timeout")]
    NotDelivered { service: String },
    /// The frame does not fit the channel (not 8-bit grey, not contiguous, too large).
    #[error("bad frame for {service}: {reason}")]
    BadFrame { service: String, reason: String },
}

/// Receiving a sample failed.
#[derive(Debug, thiserror::Error)]
pub enum ReceiveError {
    /// iceoryx2 failed to receive (corrupt connection).
    #[error("cannot receive on {service}: {reason}")]
    Port { service: String, reason: String },
    /// The payload is not a valid protobuf message of the channel's type.
    #[error("undecodable message on {service}: {reason}")]
    Decode { service: String, reason: String },
    /// The producer vanished (died) before sending end of stream.
    #[error("producer of {service} disappeared before end of stream")]
    ProducerGone { service: String },
}
