//! The module's exceptions, and how a refused call becomes one: `EngineError` (the in-process
//! engine) and `StatusError` (a server's answer to `GrpcClient`), both carrying the gRPC status
//! `code` number, the `message` and the failing batch item's `index`.

use pyo3::create_exception;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use pyo3::PyTypeInfo;

create_exception!(
    esa_client._native,
    EngineError,
    PyException,
    "A refused call; nothing changed. Attributes: code (the gRPC status code number the server \
     answers the same case with), message (str) and index (the failing batch item, or None)."
);

create_exception!(
    esa_client._native,
    StatusError,
    PyException,
    "A failed call to a server. Attributes: code (the gRPC status code number), message (str) \
     and index (the failing batch item, or None)."
);

/// The `EngineError` of a refused engine call: esa-store's code, message and item.
pub(crate) fn engine_error(py: Python<'_>, err: esa_store::Error) -> PyErr {
    status_error::<EngineError>(py, err.code() as i32, err.to_string(), err.item_index())
}

/// An exception `E` of `message` with the attributes of a failed call: its gRPC `code` number,
/// `message` and `index`.
pub(crate) fn status_error<E: PyTypeInfo>(
    py: Python<'_>,
    code: i32,
    message: String,
    index: Option<usize>,
) -> PyErr {
    let exc = PyErr::new::<E, _>(message.clone());
    let value = exc.value(py);
    let attributes = value
        .setattr("code", code)
        .and_then(|()| value.setattr("message", message))
        .and_then(|()| value.setattr("index", index));
    attributes.err().unwrap_or(exc)
}
