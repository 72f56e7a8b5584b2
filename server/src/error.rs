//! The server's errors: what a request fails with, translated for its transport, and why the
//! server could not start.
//!
//! A request fails with [`Error`], esa-store's transport-neutral error (its code, message and
//! failing batch item). This module only maps it: to a gRPC [`Status`] ([`status`]), to the
//! in-band `StreamError` of StepStream and of Zenoh replies ([`stream_error`]), and its code to
//! gRPC's ([`grpc_code`]), so a case has the same code and words on every transport, and an
//! error about one batch item carries the item's index as data ([`esa_proto::details`]).
//! [`StartError`] is why the server could not start or keep serving: never a request's fault,
//! never sent to a client; [`io_context`] words the I/O errors it carries.

use std::io;

use tonic::Status;

use crate::pb;

pub use esa_store::{Code, Error};

/// The gRPC status code of `err` (`as i32`, the number carried by `StreamError.code`).
pub fn grpc_code(err: &Error) -> tonic::Code {
    match err.code() {
        Code::InvalidArgument => tonic::Code::InvalidArgument,
        Code::DeadlineExceeded => tonic::Code::DeadlineExceeded,
        Code::NotFound => tonic::Code::NotFound,
        Code::AlreadyExists => tonic::Code::AlreadyExists,
        Code::ResourceExhausted => tonic::Code::ResourceExhausted,
        Code::FailedPrecondition => tonic::Code::FailedPrecondition,
        Code::Unauthenticated => tonic::Code::Unauthenticated,
        Code::Unavailable => tonic::Code::Unavailable,
    }
}

/// The batch item `err` is about, as the wire carries it.
fn item_index(err: &Error) -> Option<u32> {
    // A batch holds at most `codec::MAX_BATCH_ITEMS` items, so the index fits.
    err.item_index().and_then(|index| u32::try_from(index).ok())
}

/// The status answering a failed unary call; an error about one batch item carries the item in
/// the status details (`grpc-status-details-bin`).
pub fn status(err: Error) -> Status {
    let (code, message) = (grpc_code(&err), err.to_string());
    match item_index(&err) {
        Some(index) => {
            let details = esa_proto::details::status_details(code as i32, &message, index);
            Status::with_details(code, message, details)
        }
        None => Status::new(code, message),
    }
}

/// The in-band error of StepStream and the reply error of Zenoh.
pub fn stream_error(err: Error) -> pb::StreamError {
    pb::StreamError {
        code: grpc_code(&err) as i32,
        item: item_index(&err).map(|index| pb::BatchItem { index }),
        message: err.to_string(),
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
    Io(#[from] io::Error),
    /// The reflection service could not be built from the descriptors.
    #[error("reflection: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    /// The Zenoh session could not be opened, declared on or closed.
    #[cfg(feature = "zenoh")]
    #[error("zenoh: {0}")]
    Zenoh(String),
}

/// `err` with `context` in front of its message (the kind is kept).
pub fn io_context(err: io::Error, context: String) -> io::Error {
    io::Error::new(err.kind(), format!("{context}: {err}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_code_keeps_its_grpc_number() {
        let cases = [
            Error::InvalidArgument(String::new()),
            Error::DeadlineExceeded(String::new()),
            Error::NotFound(String::new()),
            Error::AlreadyExists(String::new()),
            Error::ResourceExhausted(String::new()),
            Error::Core(esa_core::CoreError::NoPendingProbe { step: 0 }),
            Error::Unauthenticated(String::new()),
            Error::Unavailable(String::new()),
        ];
        for err in cases {
            assert_eq!(grpc_code(&err) as i32, err.code() as i32, "{err:?}");
        }
    }

    #[test]
    fn an_item_error_carries_its_index_on_every_transport() {
        let err = Error::item(3, Error::NotFound("x".into()));
        let message = err.to_string();
        let in_band = stream_error(err.clone());
        assert_eq!(in_band.item.map(|item| item.index), Some(3));
        assert_eq!((in_band.code, in_band.message), (5, message.clone()));
        let unary = status(err);
        assert_eq!(
            (unary.code(), unary.message()),
            (tonic::Code::NotFound, &*message)
        );
        assert!(!unary.details().is_empty());
    }
}
