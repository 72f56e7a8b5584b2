//! `AppliedAhead`: Algorithm 1's applied actions from shifts known ahead of the server's answer,
//! with esa-core's own function (`esa_core::linear_step::applied_ahead`), so that a client of the
//! pipelined step applies the bits the server would have answered.

use esa_core::linear_step;
use esa_core::Session;
use esa_store::Error;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::arrays::{shaped, Values};
use crate::engine_class::decode_config;
use crate::errors::engine_error;

/// The configs of N sessions of one action dimension; see the module stub for the API.
#[pyclass(frozen, module = "esa_client._native")]
pub(crate) struct AppliedAhead {
    /// Fresh sessions of the configs: only their configs are read.
    sessions: Vec<Session>,
    dim: usize,
}

#[pymethods]
impl AppliedAhead {
    /// The sessions of the encoded `esa.v1.SessionConfig`s `configs`, one per session, all of
    /// one action dimension.
    #[new]
    fn new(py: Python<'_>, configs: Vec<Vec<u8>>) -> PyResult<Self> {
        let sessions = configs
            .iter()
            .map(|config| Ok(Session::new(decode_config(config)?)?))
            .collect::<Result<Vec<_>, Error>>()
            .map_err(|err| engine_error(py, err))?;
        let dim = sessions.first().map_or(0, Session::action_dim);
        if sessions.is_empty() || sessions.iter().any(|s| s.action_dim() != dim) {
            return Err(PyValueError::new_err(format!(
                "configs: expected one or more configs of one action_dim, got {} configs",
                sessions.len()
            )));
        }
        Ok(Self { sessions, dim })
    }

    /// `clip(a + clamp(shift, -bound, bound), lo, hi)` per session and dimension, `(N, D)`.
    #[pyo3(signature = (shifts, actions, action_scales = None))]
    fn __call__<'py>(
        &self,
        py: Python<'py>,
        shifts: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        action_scales: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let shifts = Values::<f64>::floats(shifts)?;
        let actions = Values::<f64>::floats(actions)?;
        let scales = match action_scales {
            Some(scales) => Values::<f64>::floats(scales)?,
            None => Values::empty(),
        };
        let mut applied = Vec::with_capacity(actions.as_slice().len());
        linear_step::applied_ahead(
            &self.sessions,
            shifts.as_slice(),
            actions.as_slice(),
            scales.as_slice(),
            &mut applied,
        )
        .map_err(|err| engine_error(py, err.into()))?;
        shaped(py, applied, self.sessions.len(), Some(self.dim))
    }

    fn __len__(&self) -> usize {
        self.sessions.len()
    }
}
