//! The one error type of the server and its single mapping to gRPC status.
//!
//! Every transport (gRPC unary, the in-band `StreamError` of StepStream, and
//! other adapters over [`crate::handler::EsaHandler`]) reports failures through
//! [`Error::code`], so a case has the same code everywhere.

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
    /// The server could not start or keep serving (never a request's fault).
    #[error("transport: {0}")]
    Transport(#[from] tonic::transport::Error),
    /// Binding or using a listener failed.
    #[error("{0}")]
    Io(#[from] std::io::Error),
    /// The reflection service could not be built from the descriptors.
    #[error("reflection: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    /// The Zenoh session could not be opened, declared on or closed.
    #[error("zenoh: {0}")]
    Zenoh(String),
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
            Error::Transport(_) | Error::Io(_) | Error::Zenoh(_) => Code::Unavailable,
            Error::Reflection(_) => Code::Internal,
            Error::Item { source, .. } => source.code(),
        }
    }
}

impl From<Error> for Status {
    fn from(err: Error) -> Self {
        Status::new(err.code(), err.to_string())
    }
}

impl From<Error> for pb::StreamError {
    fn from(err: Error) -> Self {
        pb::StreamError {
            code: err.code() as i32,
            message: err.to_string(),
        }
    }
}
