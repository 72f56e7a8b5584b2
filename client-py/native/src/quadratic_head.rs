//! `QuadraticHead`: ESAPPO's head at a step's states, esa-core's forward pass and closed form.

use esa_core::quadratic_head::{self as head, Dense};
use numpy::IntoPyArray;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use crate::arrays::{shaped, Values};

/// ESAPPO's quadratic head, from the weights and biases of its three torch layers.
#[pyclass(module = "esa_client._native", frozen)]
pub(crate) struct QuadraticHead(head::QuadraticHead);

fn floats32(object: &Bound<'_, PyAny>) -> PyResult<Vec<f32>> {
    Values::read(object, "float32").map(Values::owned)
}

fn refused(err: esa_core::CoreError) -> PyErr {
    PyValueError::new_err(err.to_string())
}

#[pymethods]
impl QuadraticHead {
    #[new]
    fn new(layers: Vec<(Bound<'_, PyAny>, Bound<'_, PyAny>)>) -> PyResult<Self> {
        let dense = layers
            .iter()
            .map(|(weight, bias)| Ok(Dense::new(floats32(weight)?, floats32(bias)?)))
            .collect::<PyResult<Vec<_>>>()?;
        let layers: [Dense; 3] = dense.try_into().map_err(|all: Vec<Dense>| {
            PyValueError::new_err(format!("expected 3 layers, got {}", all.len()))
        })?;
        head::QuadraticHead::new(layers).map(Self).map_err(refused)
    }

    fn closed_form<'py>(
        &self,
        py: Python<'py>,
        features: &Bound<'py, PyAny>,
        mean: &Bound<'py, PyAny>,
        std: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let (mean, std) = (Values::floats(mean)?, Values::floats(std)?);
        let form = (self.0)
            .closed_form(&floats32(features)?, mean.as_slice(), std.as_slice())
            .map_err(refused)?;
        let (n, d) = (form.offset.len(), Some(self.0.action_dim()));
        let gain = shaped(py, form.gain, n, d)?;
        let curvature = shaped(py, form.curvature, n, d)?;
        PyTuple::new(
            py,
            [gain, curvature, form.offset.into_pyarray(py).into_any()],
        )
    }
}
