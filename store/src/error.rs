//! The one error of a request, whatever carries it: its [`Code`], its message (the `Display`)
//! and the batch item it is about ([`Error::item_index`]). Wrappers only translate it: the
//! server into a gRPC `Status` or an in-band `StreamError`, the Python module into an exception
//! with the same code, message and index.

use esa_core::batch::BatchError;
use esa_core::CoreError;

/// The status codes a request can fail with, numbered as gRPC numbers them (`code as i32` is
/// the number a client sees).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(i32)]
pub enum Code {
    /// A malformed request: bad config, wrong length, NaN/inf, bad id, batch size.
    InvalidArgument = 3,
    /// A request message was begun but not completed in time.
    DeadlineExceeded = 4,
    /// Unknown, closed or expired session.
    NotFound = 5,
    /// Same id, different config.
    AlreadyExists = 6,
    /// A limit (sessions, session memory, request size or request memory) is reached.
    ResourceExhausted = 8,
    /// Step mismatch, report without probe.
    FailedPrecondition = 9,
    /// The server is shutting down: nothing changed, and the server that comes back (with its
    /// state file) answers the same request.
    Unavailable = 14,
    /// A required auth token is missing or wrong.
    Unauthenticated = 16,
}

/// Everything a request can fail with; nothing changed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum Error {
    /// The core rejected the request (bad config, wrong length, non-finite value, step
    /// mismatch, report without probe).
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
    /// A limit (sessions, session memory, request size or request memory) is reached.
    #[error("{0}")]
    ResourceExhausted(String),
    /// The server requires a token and the request carried none, or another one.
    #[error("{0}")]
    Unauthenticated(String),
    /// A request message was begun but not completed in time.
    #[error("{0}")]
    DeadlineExceeded(String),
    /// The server is shutting down and takes no more requests; nothing changed.
    #[error("{0}")]
    Unavailable(String),
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

    /// No room for another session: `live` sessions are held, `max_sessions` at most.
    pub fn session_limit(live: usize, max_sessions: usize) -> Self {
        Error::ResourceExhausted(format!(
            "session limit reached: {live} live sessions, at most {max_sessions} \
             (esa-server --max-sessions, Engine max_sessions); close finished sessions or \
             raise the limit"
        ))
    }

    /// The session of `id` appears in a batch again, first at item `first`.
    pub fn repeated(id: &str, first: usize) -> Self {
        Error::InvalidArgument(format!(
            "session id {id:?} also appears at item {first}; a session may appear at most once \
             per batch"
        ))
    }

    /// The status code of this error.
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
            Error::Unavailable(_) => Code::Unavailable,
            Error::AlreadyExists(_) => Code::AlreadyExists,
            Error::Item { source, .. } => source.code(),
        }
    }

    /// The batch item this error is about, if it is about one.
    pub fn item_index(&self) -> Option<usize> {
        match self {
            Error::Item { index, .. } => Some(*index),
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
