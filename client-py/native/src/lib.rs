//! `esa_client._native`: esa-core for Python, in-process or through a server.
//!
//! Each file holds one concern; this one only declares them and registers what Python sees:
//!
//! - [`engine_class`]: `Engine` and `BatchHandle`, esa-core in-process over numpy arrays, on the
//!   handle cache of [`engine`] over esa-store's sessions by id, and `check_config`, the one
//!   validation of a session config. Validation, error codes and
//!   messages are the server's (CONTRACT.md section 2).
//! - [`client`]: `GrpcClient` and `GrpcBatch`, the same calls to an esa-server over gRPC (tonic),
//!   the GIL released while they wait.
//! - [`errors`]: the exceptions a refused call raises, `EngineError` and `StatusError`, each with
//!   the gRPC status `code`, `message` and failing batch item `index`.
//! - [`arrays`]: numpy arguments in, numpy arrays out.
//! - [`quadratic_head`]: `QuadraticHead`, ESAPPO's head at a step's states (esa-core's).
//! - [`step_ahead`]: `StepAhead`, the applied actions and probes of a pipelined step from the
//!   shifts the previous step's answer carried.
//! - [`step_stats`]: `StepStats`, the sums behind a learner's per-step ESA statistics.
//!
//! The stub `esa_client/_native.pyi` documents the API.

use pyo3::prelude::*;

mod arrays;
mod client;
mod engine;
mod engine_class;
mod errors;
mod quadratic_head;
mod step_ahead;
mod step_stats;

use esa_store::Code;

/// esa-core in-process (`Engine`, `BatchHandle`, `EngineError`), a gRPC client (`GrpcClient`,
/// `GrpcBatch`, `StatusError`) and the gRPC code numbers.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add_class::<engine_class::Engine>()?;
    m.add_class::<engine_class::BatchHandle>()?;
    m.add_function(wrap_pyfunction!(engine_class::check_config, m)?)?;
    m.add_class::<quadratic_head::QuadraticHead>()?;
    m.add_class::<step_ahead::StepAhead>()?;
    m.add_class::<step_stats::StepStats>()?;
    m.add("EngineError", py.get_type::<errors::EngineError>())?;
    m.add_class::<client::GrpcClient>()?;
    m.add_class::<client::GrpcBatch>()?;
    m.add("StatusError", py.get_type::<errors::StatusError>())?;
    m.add("INVALID_ARGUMENT", Code::InvalidArgument as i32)?;
    m.add("NOT_FOUND", Code::NotFound as i32)?;
    m.add("ALREADY_EXISTS", Code::AlreadyExists as i32)?;
    m.add("RESOURCE_EXHAUSTED", Code::ResourceExhausted as i32)?;
    m.add("FAILED_PRECONDITION", Code::FailedPrecondition as i32)?;
    m.add("MAX_BATCH_ITEMS", esa_core::batch::MAX_BATCH_ITEMS)?;
    m.add("MAX_BATCH_VALUES", esa_core::batch::MAX_BATCH_VALUES)?;
    m.add("MAX_ID_BYTES", esa_store::MAX_ID_BYTES)?;
    m.add("DETACH_VALUES", engine_class::DETACH_VALUES)?;
    Ok(())
}
