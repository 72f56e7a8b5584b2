//! numpy at the module's edge: the values of an array argument ([`Values`], copied, or
//! converted by numpy) and the arrays a call returns ([`shaped`]).

use numpy::ndarray::Array2;
use numpy::{Element, IntoPyArray, PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyDict, PyTuple};

/// The values of an array argument, copied (under the GIL) from a C-contiguous numpy array of
/// the right dtype, else converted by numpy (which raises for what it cannot convert). Owned,
/// so that a call can release the GIL while Python threads write to the arrays.
pub(crate) struct Values<T>(Vec<T>);

impl<T: Element + Copy> Values<T> {
    pub(crate) fn empty() -> Self {
        Values(Vec::new())
    }

    /// Copies `object` when it is a C-contiguous array of `T`.
    pub(crate) fn copied(object: &Bound<'_, PyAny>) -> Option<Self> {
        let array = object.cast::<PyArrayDyn<T>>().ok()?;
        if !array.is_c_contiguous() {
            return None; // numpy's as_slice also takes Fortran order
        }
        // SAFETY: the GIL is held for the copy, so no Python code writes to the array meanwhile
        // (numpy's own C functions read arrays the same way; its borrow flags cost more than
        // the copy of a batch).
        unsafe { array.as_slice() }
            .ok()
            .map(|values| Values(values.to_vec()))
    }

    /// Converts `object` with `numpy.ascontiguousarray(object, dtype)`.
    pub(crate) fn convert(object: &Bound<'_, PyAny>, dtype: &str) -> PyResult<Self> {
        let py = object.py();
        let kwargs = PyDict::new(py);
        kwargs.set_item("dtype", dtype)?;
        let converted = numpy_function(py, "ascontiguousarray")?.call((object,), Some(&kwargs))?;
        let array = converted.cast_into::<PyArrayDyn<T>>()?;
        let values = array.readonly().as_slice().map(<[T]>::to_vec);
        values
            .map(Values)
            .map_err(|err| PyValueError::new_err(err.to_string()))
    }

    /// [`Self::copied`], else [`Self::convert`] to `dtype`.
    pub(crate) fn read(object: &Bound<'_, PyAny>, dtype: &str) -> PyResult<Self> {
        match Self::copied(object) {
            Some(values) => Ok(values),
            None => Self::convert(object, dtype),
        }
    }

    pub(crate) fn as_slice(&self) -> &[T] {
        &self.0
    }

    /// The values.
    pub(crate) fn owned(self) -> Vec<T> {
        self.0
    }
}

impl Values<f64> {
    /// Float values (`actions`, `action_scales`, `q_values`, `q_references`), any shape, C order.
    /// float32 is widened here: numpy's conversion costs more than the copy of a batch.
    pub(crate) fn floats(object: &Bound<'_, PyAny>) -> PyResult<Self> {
        if let Some(values) = Self::copied(object) {
            return Ok(values);
        }
        match Values::<f32>::copied(object) {
            Some(narrow) => Ok(Values(narrow.0.into_iter().map(f64::from).collect())),
            None => Self::convert(object, "float64"),
        }
    }

    /// Optional float values: None reads as none (action scales of all 1, no references).
    pub(crate) fn floats_or_empty(object: Option<&Bound<'_, PyAny>>) -> PyResult<Self> {
        object.map_or_else(|| Ok(Self::empty()), Self::floats)
    }
}

impl Values<bool> {
    /// Episode-start flags.
    pub(crate) fn bools(object: &Bound<'_, PyAny>) -> PyResult<Self> {
        Self::read(object, "bool")
    }
}

impl Values<u64> {
    /// Signed steps as unsigned ones; a negative step is a ValueError (numpy would wrap it).
    pub(crate) fn unsigned(signed: &[i64]) -> PyResult<Self> {
        signed
            .iter()
            .map(|&step| {
                u64::try_from(step).map_err(|_| {
                    PyValueError::new_err(format!("steps: expected integers >= 0, got {step}"))
                })
            })
            .collect::<PyResult<Vec<u64>>>()
            .map(Values)
    }

    /// Steps: unsigned integers; signed ones must not be negative (numpy would wrap them).
    pub(crate) fn steps(object: &Bound<'_, PyAny>) -> PyResult<Self> {
        if let Some(values) = Self::copied(object) {
            return Ok(values);
        }
        // int64 is numpy's default integer: read it without numpy's conversion.
        if let Some(signed) = Values::<i64>::copied(object) {
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
pub(crate) fn shaped<'py>(
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

/// Several answers of n items as a tuple of [`shaped`] arrays, e.g. `(probes, applied)`.
pub(crate) fn shaped_tuple<'py, const K: usize>(
    py: Python<'py>,
    answers: [Vec<f64>; K],
    n: usize,
    dim: Option<usize>,
) -> PyResult<Bound<'py, PyTuple>> {
    let arrays = answers
        .into_iter()
        .map(|values| shaped(py, values, n, dim))
        .collect::<PyResult<Vec<_>>>()?;
    PyTuple::new(py, arrays)
}

/// A box's `[low, high]` bounds (D values each, or None: empty) repeated for the `n` items of a
/// batch of `values` action values: as many as the actions, or as given (esa-core then names a
/// bad length).
pub(crate) fn tiled(
    bounds: [Option<&Bound<'_, PyAny>>; 2],
    n: usize,
    values: usize,
) -> PyResult<[Vec<f64>; 2]> {
    let tile = |bound| -> PyResult<Vec<f64>> {
        let bound = Values::<f64>::floats_or_empty(bound)?.owned();
        let short = !bound.is_empty() && bound.len() != values && bound.len() * n == values;
        Ok(if short { bound.repeat(n) } else { bound })
    };
    Ok([tile(bounds[0])?, tile(bounds[1])?])
}
