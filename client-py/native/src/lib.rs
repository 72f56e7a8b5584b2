//! `esa_client._native`: esa-core in-process for Python.
//!
//! An [`Engine`] holds sessions by id, like an `esa-server` does, and runs the same
//! all-or-nothing batches (`esa_core::batch`) over numpy arrays, without a process or a socket
//! in between. Validation and error codes are the server's (CONTRACT.md section 2): a refused
//! call raises `EngineError(code, message, index)` with the gRPC status code the server answers
//! the same case with, and changes nothing. The stub `esa_client/_native.pyi` documents the API.
//!
//! A [`client::GrpcClient`] reaches an esa-server instead: the same calls over gRPC (tonic), the
//! GIL released while they wait; a failed call raises `StatusError(code, message, index)`.

use numpy::ndarray::Array2;
use numpy::{Element, IntoPyArray, PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods};
use parking_lot::{Mutex, MutexGuard};
use prost::Message;
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyBytes, PyDict, PyTuple};

mod client;
mod engine;

use esa_proto::v1 as pb;

/// By default, batches of more action values than this run with the GIL released (measured:
/// `native/bench_engine.py --gil`); below it, releasing the GIL and taking it back (and copying the
/// inputs, which Python threads could write to meanwhile) costs a larger part of the call.
const DETACH_VALUES: usize = 4096;

create_exception!(
    esa_client._native,
    EngineError,
    PyException,
    "A refused call; nothing changed. Attributes: code (the gRPC status code number the server \
     answers the same case with), message (str) and index (the failing batch item, or None)."
);

fn engine_error(py: Python<'_>, err: engine::EngineError) -> PyErr {
    let exc = EngineError::new_err(err.message.clone());
    status_error(py, exc, err.code as i32, err.message, err.index)
}

/// `exc` with the attributes of a failed call: its gRPC `code` number, `message` and `index`.
fn status_error(
    py: Python<'_>,
    exc: PyErr,
    code: i32,
    message: String,
    index: Option<usize>,
) -> PyErr {
    let value = exc.value(py);
    let attributes = (|| -> PyResult<()> {
        value.setattr("code", code)?;
        value.setattr("message", message)?;
        value.setattr("index", index)?;
        Ok(())
    })();
    match attributes {
        Ok(()) => exc,
        Err(failed) => failed,
    }
}

/// Sessions by id, each stepped by esa-core; see the module stub for the API.
#[pyclass(frozen, module = "esa_client._native")]
struct Engine {
    inner: Mutex<engine::Engine>,
    /// Batches of more action values than this release the GIL.
    detach_values: usize,
}

/// A list of session ids resolved once (`Engine.resolve`), for batch calls without hashing.
#[pyclass(frozen, module = "esa_client._native")]
struct BatchHandle {
    inner: engine::Handle,
}

impl Engine {
    /// The engine's state. A thread that holds the GIL never blocks on the lock: a batch that
    /// released the GIL may hold it, and it needs no GIL to finish.
    fn lock<'a>(&'a self, py: Python<'_>) -> MutexGuard<'a, engine::Engine> {
        loop {
            if let Some(guard) = self.inner.try_lock() {
                return guard;
            }
            py.detach(|| drop(self.inner.lock()));
        }
    }
}

#[pymethods]
impl Engine {
    #[new]
    #[pyo3(signature = (max_sessions = engine::DEFAULT_MAX_SESSIONS, detach_values = DETACH_VALUES))]
    fn new(max_sessions: usize, detach_values: usize) -> Self {
        Self {
            inner: Mutex::new(engine::Engine::new(max_sessions)),
            detach_values,
        }
    }

    /// Batches of more action values than this release the GIL while they run.
    #[getter]
    fn detach_values(&self) -> usize {
        self.detach_values
    }

    /// The live-session limit.
    #[getter]
    fn max_sessions(&self, py: Python<'_>) -> usize {
        self.lock(py).max_sessions()
    }

    fn __len__(&self, py: Python<'_>) -> usize {
        self.lock(py).live()
    }

    fn __contains__(&self, py: Python<'_>, session_id: &str) -> bool {
        self.lock(py).contains(session_id)
    }

    /// Creates a session from an encoded `esa.v1.SessionConfig`; returns its id.
    #[pyo3(signature = (session_id, config))]
    fn create_session(
        &self,
        py: Python<'_>,
        session_id: Option<&str>,
        config: &[u8],
    ) -> PyResult<String> {
        let config = pb::SessionConfig::decode(config).map_err(|err| {
            engine_error(
                py,
                engine::EngineError {
                    code: engine::Code::InvalidArgument,
                    message: format!(
                        "config: expected an encoded esa.v1.SessionConfig message: {err}"
                    ),
                    index: None,
                },
            )
        })?;
        self.lock(py)
            .create_session(session_id, esa_proto::convert::config_from_proto(config))
            .map_err(|err| engine_error(py, err))
    }

    /// An encoded `esa.v1.GetSessionResponse` for the session.
    fn get_session<'py>(&self, py: Python<'py>, session_id: &str) -> PyResult<Bound<'py, PyBytes>> {
        let response = self
            .lock(py)
            .get_session(session_id)
            .map_err(|err| engine_error(py, err))?;
        Ok(PyBytes::new(py, &response.encode_to_vec()))
    }

    /// Closes the session.
    fn close_session(&self, py: Python<'_>, session_id: &str) -> PyResult<()> {
        self.lock(py)
            .close_session(session_id)
            .map_err(|err| engine_error(py, err))
    }

    /// Ends the session's episode; returns its completed episodes.
    fn end_episode(&self, py: Python<'_>, session_id: &str) -> PyResult<u64> {
        self.lock(py)
            .end_episode(session_id)
            .map_err(|err| engine_error(py, err))
    }

    /// Probe of one session: returns (probe, applied), each of the session's dimension.
    #[pyo3(signature = (session_id, step, action, episode_start = false, action_scale = None))]
    fn probe_one<'py>(
        &self,
        py: Python<'py>,
        session_id: &str,
        step: u64,
        action: &Bound<'py, PyAny>,
        episode_start: bool,
        action_scale: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let action = Values::<f64>::floats(action)?;
        let scale = match action_scale {
            Some(scale) => Values::<f64>::floats(scale)?,
            None => Values::empty(),
        };
        let (probe, applied) = self
            .lock(py)
            .probe_one(
                session_id,
                step,
                action.as_slice(),
                scale.as_slice(),
                episode_start,
            )
            .map_err(|err| engine_error(py, err))?;
        PyTuple::new(py, [probe.into_pyarray(py), applied.into_pyarray(py)])
    }

    /// Report of one session: returns the improved action.
    #[pyo3(signature = (session_id, step, q_value, q_reference = None))]
    fn report_one<'py>(
        &self,
        py: Python<'py>,
        session_id: &str,
        step: u64,
        q_value: f64,
        q_reference: Option<f64>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let action = self
            .lock(py)
            .report_one(session_id, step, q_value, q_reference)
            .map_err(|err| engine_error(py, err))?;
        Ok(action.into_pyarray(py).into_any())
    }

    /// Resolves session ids into a handle for `probe` and `report`.
    fn resolve(&self, py: Python<'_>, session_ids: Vec<String>) -> PyResult<BatchHandle> {
        let inner = self
            .lock(py)
            .resolve(&session_ids)
            .map_err(|err| engine_error(py, err))?;
        Ok(BatchHandle { inner })
    }

    /// ProbeBatch: returns (probes, applied).
    #[pyo3(signature = (handle, steps, actions, episode_starts = None, action_scales = None))]
    fn probe<'py>(
        &self,
        py: Python<'py>,
        handle: &Bound<'py, BatchHandle>,
        steps: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        episode_starts: Option<&Bound<'py, PyAny>>,
        action_scales: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let handle = &handle.get().inner;
        let steps = Values::<u64>::steps(steps)?;
        let actions = Values::<f64>::floats(actions)?;
        let starts = match episode_starts {
            Some(starts) => Values::<bool>::bools(starts)?,
            None => Values::empty(),
        };
        let scales = match action_scales {
            Some(scales) => Values::<f64>::floats(scales)?,
            None => Values::empty(),
        };
        let output = if handle.values() > self.detach_values {
            let (steps, actions, starts, scales) = (
                steps.owned(),
                actions.owned(),
                starts.owned(),
                scales.owned(),
            );
            py.detach(|| {
                self.inner
                    .lock()
                    .probe(handle, &steps, &actions, &starts, &scales)
            })
        } else {
            self.lock(py).probe(
                handle,
                steps.as_slice(),
                actions.as_slice(),
                starts.as_slice(),
                scales.as_slice(),
            )
        }
        .map_err(|err| engine_error(py, err))?;
        let n = handle.len();
        let probes = shaped(py, output.probes, n, output.dim)?;
        let applied = shaped(py, output.applied, n, output.dim)?;
        PyTuple::new(py, [probes, applied])
    }

    /// ReportBatch: returns the improved actions.
    #[pyo3(signature = (handle, steps, q_values, q_references = None))]
    fn report<'py>(
        &self,
        py: Python<'py>,
        handle: &Bound<'py, BatchHandle>,
        steps: &Bound<'py, PyAny>,
        q_values: &Bound<'py, PyAny>,
        q_references: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let handle = &handle.get().inner;
        let steps = Values::<u64>::steps(steps)?;
        let q_values = Values::<f64>::floats(q_values)?;
        let references = match q_references {
            Some(references) => Values::<f64>::floats(references)?,
            None => Values::empty(),
        };
        let output = if handle.values() > self.detach_values {
            let (steps, q_values, references) =
                (steps.owned(), q_values.owned(), references.owned());
            py.detach(|| {
                self.inner
                    .lock()
                    .report(handle, &steps, &q_values, &references)
            })
        } else {
            self.lock(py).report(
                handle,
                steps.as_slice(),
                q_values.as_slice(),
                references.as_slice(),
            )
        }
        .map_err(|err| engine_error(py, err))?;
        shaped(py, output.actions, handle.len(), output.dim)
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        let engine = self.lock(py);
        format!(
            "Engine(live={}, max_sessions={})",
            engine.live(),
            engine.max_sessions()
        )
    }
}

#[pymethods]
impl BatchHandle {
    /// The session ids, in item order.
    #[getter]
    fn ids(&self) -> Vec<String> {
        self.inner.ids().map(str::to_owned).collect()
    }

    fn __len__(&self) -> usize {
        self.inner.len()
    }

    fn __repr__(&self) -> String {
        format!("BatchHandle(n={})", self.inner.len())
    }
}

/// The values of an array argument: borrowed from a C-contiguous numpy array of the right dtype,
/// else converted by numpy (which raises for what it cannot convert).
enum Values<'py, T: Element> {
    Array(numpy::PyReadonlyArrayDyn<'py, T>),
    Owned(Vec<T>),
}

impl<'py, T: Element + Copy> Values<'py, T> {
    fn empty() -> Self {
        Values::Owned(Vec::new())
    }

    /// Borrows `object` when it is a C-contiguous array of `T`.
    fn borrow(object: &Bound<'py, PyAny>) -> Option<Self> {
        let array = object.cast::<PyArrayDyn<T>>().ok()?;
        if !array.is_c_contiguous() {
            return None;
        }
        array.try_readonly().ok().map(Values::Array)
    }

    /// Converts `object` with `numpy.ascontiguousarray(object, dtype)`.
    fn convert(object: &Bound<'py, PyAny>, dtype: &str) -> PyResult<Self> {
        let py = object.py();
        let kwargs = PyDict::new(py);
        kwargs.set_item("dtype", dtype)?;
        let converted = numpy_function(py, "ascontiguousarray")?.call((object,), Some(&kwargs))?;
        let array = converted.cast_into::<PyArrayDyn<T>>()?;
        let values = array.readonly().as_slice().map(<[T]>::to_vec);
        values
            .map(Values::Owned)
            .map_err(|err| PyValueError::new_err(err.to_string()))
    }

    fn as_slice(&self) -> &[T] {
        match self {
            // A C-contiguous array (checked when borrowed) is a slice.
            Values::Array(array) => array.as_slice().unwrap_or(&[]),
            Values::Owned(values) => values,
        }
    }

    /// The values, owned: what a call that releases the GIL reads, since Python code could
    /// write to a numpy array meanwhile.
    fn owned(&self) -> Vec<T> {
        self.as_slice().to_vec()
    }
}

impl<'py> Values<'py, f64> {
    /// Float values (`actions`, `action_scales`, `q_values`, `q_references`), any shape, C order.
    fn floats(object: &Bound<'py, PyAny>) -> PyResult<Self> {
        match Self::borrow(object) {
            Some(values) => Ok(values),
            None => Self::convert(object, "float64"),
        }
    }
}

impl<'py> Values<'py, bool> {
    /// Episode-start flags.
    fn bools(object: &Bound<'py, PyAny>) -> PyResult<Self> {
        match Self::borrow(object) {
            Some(values) => Ok(values),
            None => Self::convert(object, "bool"),
        }
    }
}

impl<'py> Values<'py, u64> {
    /// Signed steps as unsigned ones; a negative step is a ValueError (numpy would wrap it).
    fn unsigned(signed: &[i64]) -> PyResult<Self> {
        signed
            .iter()
            .map(|&step| {
                u64::try_from(step).map_err(|_| {
                    PyValueError::new_err(format!("steps: expected integers >= 0, got {step}"))
                })
            })
            .collect::<PyResult<Vec<u64>>>()
            .map(Values::Owned)
    }

    /// Steps: unsigned integers; signed ones must not be negative (numpy would wrap them).
    fn steps(object: &Bound<'py, PyAny>) -> PyResult<Self> {
        if let Some(values) = Self::borrow(object) {
            return Ok(values);
        }
        // int64 is numpy's default integer: read it without numpy's conversion.
        if let Some(signed) = Values::<i64>::borrow(object) {
            return Self::unsigned(signed.as_slice());
        }
        let py = object.py();
        let array = numpy_function(py, "asarray")?.call1((object,))?;
        let kind: String = array.getattr("dtype")?.getattr("kind")?.extract()?;
        match kind.as_str() {
            "u" => Self::convert(&array, "uint64"),
            "i" => Self::unsigned(Values::<i64>::convert(&array, "int64")?.as_slice()),
            _ => Err(PyTypeError::new_err(format!(
                "steps: expected an array of unsigned integers, got dtype kind {kind:?}"
            ))),
        }
    }
}

fn numpy_function<'py>(py: Python<'py>, name: &str) -> PyResult<Bound<'py, PyAny>> {
    static NUMPY: PyOnceLock<Py<PyModule>> = PyOnceLock::new();
    let numpy = NUMPY.get_or_try_init(py, || py.import("numpy").map(Bound::unbind))?;
    numpy.bind(py).getattr(name)
}

/// `values` as an (n, dim) array when every item has the same dimension, else flat.
fn shaped<'py>(
    py: Python<'py>,
    values: Vec<f64>,
    n: usize,
    dim: Option<usize>,
) -> PyResult<Bound<'py, PyAny>> {
    match dim {
        Some(dim) => Array2::from_shape_vec((n, dim), values)
            .map(|array| array.into_pyarray(py).into_any())
            .map_err(|err| PyValueError::new_err(err.to_string())),
        None => Ok(values.into_pyarray(py).into_any()),
    }
}

/// esa-core in-process (`Engine`, `BatchHandle`, `EngineError`), a gRPC client (`GrpcClient`,
/// `GrpcBatch`, `StatusError`) and the gRPC code numbers.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add_class::<Engine>()?;
    m.add_class::<BatchHandle>()?;
    m.add("EngineError", py.get_type::<EngineError>())?;
    m.add_class::<client::GrpcClient>()?;
    m.add_class::<client::GrpcBatch>()?;
    m.add("StatusError", py.get_type::<client::StatusError>())?;
    m.add("INVALID_ARGUMENT", engine::Code::InvalidArgument as i32)?;
    m.add("NOT_FOUND", engine::Code::NotFound as i32)?;
    m.add("ALREADY_EXISTS", engine::Code::AlreadyExists as i32)?;
    m.add("RESOURCE_EXHAUSTED", engine::Code::ResourceExhausted as i32)?;
    m.add(
        "FAILED_PRECONDITION",
        engine::Code::FailedPrecondition as i32,
    )?;
    m.add("MAX_BATCH_ITEMS", esa_core::batch::MAX_BATCH_ITEMS)?;
    m.add("MAX_BATCH_VALUES", esa_core::batch::MAX_BATCH_VALUES)?;
    m.add("MAX_ID_BYTES", engine::MAX_ID_BYTES)?;
    m.add("DETACH_VALUES", DETACH_VALUES)?;
    Ok(())
}
