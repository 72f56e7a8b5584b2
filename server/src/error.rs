//! The server's two error types.
//!
//! [`Error`] is what a request fails with, and its single mapping to a gRPC
//! status: every transport (gRPC unary, the in-band `StreamError` of
//! StepStream, and other adapters over [`crate::handler::EsaHandler`]) reports
//! failures through [`Error::code`], so a case has the same code everywhere,
//! and an error about one batch item carries the item's index as data
//! ([`esa_proto::details`]). [`StartError`] is why the server could not start
//! or keep serving: never a request's fault, never sent to a client.

use esa_core::batch::BatchError;
use esa_core::CoreError;
use tonic::{Code, Status};

use crate::pb;

/// Everything a request can fail with.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The core rejected the request (bad config, wrong length, non-finite
    /// value, step mismatch, report without probe).
    #[error(transparent)]
    Core(#[from] CoreError),
    /// The session id is unknown, was closed, or expired after being idle.
    #[error(
        "session {0:?} not found: it is unknown, was closed or expired after being idle; \
         create it with CreateSession"
    )]
    NotFound(String),
    /// A request field is malformed; the message names the field.
    #[error("{0}")]
    InvalidArgument(String),
    /// A server limit (sessions, session memory, request size or request memory) is reached.
    #[error("{0}")]
    ResourceExhausted(String),
    /// The server requires a token and the request carried none, or another one.
    #[error("{0}")]
    Unauthenticated(String),
    /// A request message was begun but not completed in time.
    #[error("{0}")]
    DeadlineExceeded(String),
    /// A session with this id exists with a different config.
    #[error(
        "session {0:?} already exists with a different config; \
         close it first, or create it with another id"
    )]
    AlreadyExists(String),
    /// One item of a batch failed; nothing in the batch was applied.
    #[error("item {index}: {source}")]
    Item {
        /// Position of the failing item in the request.
        index: usize,
        /// What was wrong with it.
        source: Box<Error>,
    },
}

impl Error {
    /// Attributes `err` to batch item `index`.
    pub fn item(index: usize, err: impl Into<Error>) -> Self {
        Error::Item {
            index,
            source: Box::new(err.into()),
        }
    }

    /// The gRPC status code of this error (`code() as i32` is the number
    /// carried by `StreamError.code`).
    pub fn code(&self) -> Code {
        match self {
            Error::Core(CoreError::InvalidConfig(_) | CoreError::InvalidArgument(_)) => {
                Code::InvalidArgument
            }
            Error::Core(CoreError::StepMismatch { .. } | CoreError::NoPendingProbe { .. }) => {
                Code::FailedPrecondition
            }
            Error::NotFound(_) => Code::NotFound,
            Error::InvalidArgument(_) => Code::InvalidArgument,
            Error::ResourceExhausted(_) => Code::ResourceExhausted,
            Error::Unauthenticated(_) => Code::Unauthenticated,
            Error::DeadlineExceeded(_) => Code::DeadlineExceeded,
            Error::AlreadyExists(_) => Code::AlreadyExists,
            Error::Item { source, .. } => source.code(),
        }
    }

    /// The batch item this error is about, if it is about one.
    pub fn item_index(&self) -> Option<u32> {
        match self {
            // A batch holds at most `codec::MAX_BATCH_ITEMS` items, so the index fits.
            Error::Item { index, .. } => u32::try_from(*index).ok(),
            _ => None,
        }
    }
}

/// A refused batch: the whole request's error is INVALID_ARGUMENT with the core's message, an
/// item's error is that item's, worded `item {index}: ...` either way.
impl From<BatchError> for Error {
    fn from(err: BatchError) -> Self {
        match err {
            BatchError::Request(message) => Error::InvalidArgument(message),
            BatchError::Item { index, error } => Error::item(index, error),
        }
    }
}

/// The status answering a failed unary call; an error about one batch item
/// carries the item in the status details (`grpc-status-details-bin`).
impl From<Error> for Status {
    fn from(err: Error) -> Self {
        let (code, message) = (err.code(), err.to_string());
        match err.item_index() {
            Some(index) => {
                let details = esa_proto::details::status_details(code as i32, &message, index);
                Status::with_details(code, message, details)
            }
            None => Status::new(code, message),
        }
    }
}

/// The in-band error of StepStream and the reply error of Zenoh.
impl From<Error> for pb::StreamError {
    fn from(err: Error) -> Self {
        pb::StreamError {
            code: err.code() as i32,
            item: err.item_index().map(|index| pb::BatchItem { index }),
            message: err.to_string(),
        }
    }
}

/// Why the server could not start or keep serving.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// A flag or setting is unusable; the message names it.
    #[error("{0}")]
    Config(String),
    /// The gRPC server failed.
    #[error("transport: {0}")]
    Transport(#[from] tonic::transport::Error),
    /// Binding or using a listener (or reading a file) failed.
    #[error("{0}")]
    Io(#[from] std::io::Error),
    /// The reflection service could not be built from the descriptors.
    #[error("reflection: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    /// The Zenoh session could not be opened, declared on or closed.
    #[error("zenoh: {0}")]
    Zenoh(String),
}
