//! Typed errors: every failed call is one [`Error`], with the gRPC status [`Code`], the
//! message, the failing batch item and a [`Kind`] to match on (the Python client's exception
//! classes, one for one).

use std::fmt;

use tonic::{Code, Status, TimeoutExpired};

use esa_proto::v1 as pb;

/// What went wrong, by the status code the contract gives each case (CONTRACT.md section 2).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum Kind {
    /// NOT_FOUND: no such session (closed, expired, or the server restarted).
    SessionNotFound,
    /// INVALID_ARGUMENT: a bad config, id, length or value; nothing changed.
    InvalidArgument,
    /// FAILED_PRECONDITION: a step out of turn (a report without its probe, a wrong step).
    StepMismatch,
    /// RESOURCE_EXHAUSTED: a server limit (sessions, memory, message size).
    ResourceExhausted,
    /// ALREADY_EXISTS: CreateSession with an id in use.
    SessionAlreadyExists,
    /// UNAUTHENTICATED: a missing or wrong token.
    Unauthenticated,
    /// UNAVAILABLE: no server, or the connection was lost; repeating the call is safe.
    ServerUnavailable,
    /// DEADLINE_EXCEEDED: no answer within the client's timeout; repeating the call is safe.
    DeadlineExceeded,
    /// Any other status.
    Other,
}

impl Kind {
    /// The kind of a status code.
    pub fn of(code: Code) -> Self {
        match code {
            Code::NotFound => Self::SessionNotFound,
            Code::InvalidArgument => Self::InvalidArgument,
            Code::FailedPrecondition => Self::StepMismatch,
            Code::ResourceExhausted => Self::ResourceExhausted,
            Code::AlreadyExists => Self::SessionAlreadyExists,
            Code::Unauthenticated => Self::Unauthenticated,
            Code::Unavailable => Self::ServerUnavailable,
            Code::DeadlineExceeded => Self::DeadlineExceeded,
            _ => Self::Other,
        }
    }
}

/// A failed call: nothing changed on the server (CONTRACT.md section 2).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Error {
    code: Code,
    message: String,
    index: Option<usize>,
}

impl Error {
    /// An error with this code and message, about no batch item.
    pub fn new(code: Code, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
            index: None,
        }
    }

    /// The gRPC status code.
    pub fn code(&self) -> Code {
        self.code
    }

    /// What to match on.
    pub fn kind(&self) -> Kind {
        Kind::of(self.code)
    }

    /// The server's message.
    pub fn message(&self) -> &str {
        &self.message
    }

    /// The batch item (its position in the request) that the whole batch was refused for.
    pub fn index(&self) -> Option<usize> {
        self.index
    }

    /// Whether repeating the same call is safe and may succeed (UNAVAILABLE, DEADLINE_EXCEEDED).
    pub fn is_retryable(&self) -> bool {
        matches!(
            self.kind(),
            Kind::ServerUnavailable | Kind::DeadlineExceeded
        )
    }

    /// The error of a failed call, with the batch item its details name.
    ///
    /// Tonic's own statuses get the contract's code (and grpcio's): a passed deadline is
    /// CANCELLED in tonic; a connection lost mid-call is UNKNOWN, a connection that closes
    /// before the call is sent (a failed mutual-TLS handshake) is CANCELLED, and bytes that are
    /// not HTTP/2 (a plaintext client at a TLS port, whose alert it reads) are INTERNAL, each
    /// with the transport error as its source (a status the server sent has none): all three
    /// are UNAVAILABLE.
    pub fn from_status(status: &Status) -> Self {
        let index = esa_proto::details::batch_item(status.details()).map(|index| index as usize);
        let (code, message) = match std::error::Error::source(status) {
            _ if status.code() == Code::Cancelled
                && status.message() == TimeoutExpired(()).to_string() =>
            {
                (Code::DeadlineExceeded, status.message().to_string())
            }
            Some(source)
                if matches!(
                    status.code(),
                    Code::Unknown | Code::Internal | Code::Cancelled
                ) =>
            {
                (
                    Code::Unavailable,
                    format!("{}: {}", status.message(), chain(source)),
                )
            }
            _ => (status.code(), status.message().to_string()),
        };
        Self {
            code,
            message,
            index,
        }
    }

    /// The error a StepStream answered one request with.
    pub fn from_stream(error: pb::StreamError) -> Self {
        Self {
            code: Code::from_i32(error.code),
            message: error.message,
            index: error.item.map(|item| item.index as usize),
        }
    }

    pub(crate) fn deadline(timeout: std::time::Duration) -> Self {
        Self::new(
            Code::DeadlineExceeded,
            format!("no answer within {} s", timeout.as_secs_f64()),
        )
    }

    pub(crate) fn invalid(what: &str, err: &dyn fmt::Display) -> Self {
        Self::new(Code::InvalidArgument, format!("{what}: {err}"))
    }
}

impl From<Status> for Error {
    fn from(status: Status) -> Self {
        Self::from_status(&status)
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:?}: {}", self.code, self.message)?;
        if let Some(index) = self.index {
            write!(f, " (batch item {index})")?;
        }
        Ok(())
    }
}

impl std::error::Error for Error {}

/// An error and its sources, `outer: inner: ...`.
fn chain(error: &(dyn std::error::Error + 'static)) -> String {
    let mut text = error.to_string();
    let mut next = error.source();
    while let Some(source) = next {
        text = format!("{text}: {source}");
        next = source.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;

    fn with_transport_source(code: Code) -> Status {
        let mut status = Status::new(code, "h2 protocol error: http2 error");
        status.set_source(Arc::new(std::io::Error::other("not HTTP/2")));
        status
    }

    #[test]
    fn a_transport_failure_is_unavailable_whatever_code_tonic_gave_it() {
        for code in [Code::Unknown, Code::Internal, Code::Cancelled] {
            let err = Error::from_status(&with_transport_source(code));
            assert_eq!(err.kind(), Kind::ServerUnavailable, "{code:?}");
            assert!(err.message().ends_with(": not HTTP/2"), "{err}");
        }
    }

    #[test]
    fn a_status_the_server_sent_keeps_its_code() {
        for code in [
            Code::Unknown,
            Code::Internal,
            Code::Cancelled,
            Code::NotFound,
        ] {
            assert_eq!(Error::from_status(&Status::new(code, "x")).code(), code);
        }
    }
}
