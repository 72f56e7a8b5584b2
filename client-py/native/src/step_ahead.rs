//! `StepAhead`: Algorithm 1's applied actions (and probes) of a step from the shifts known ahead
//! of the server's answer, with esa-core's own functions (`esa_core::fused_step::applied_ahead`,
//! `probes_ahead`), so that a client of the pipelined step applies, and evaluates its critic at,
//! the bits the server would have answered.

use esa_core::fused_step;
use esa_core::Session;
use esa_store::Error;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use crate::arrays::{shaped, shaped_tuple, Values};
use crate::engine_class::decode_config;
use crate::errors::engine_error;

/// The configs of N sessions of one action dimension; see the module stub for the API.
#[pyclass(frozen, module = "esa_client._native")]
pub(crate) struct StepAhead {
    /// Fresh sessions of the configs: only their configs are read.
    sessions: Vec<Session>,
    dim: usize,
}

#[pymethods]
impl StepAhead {
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
        let scales = Values::<f64>::floats_or_empty(action_scales)?;
        let mut applied = Vec::with_capacity(actions.as_slice().len());
        fused_step::applied_ahead(
            &self.sessions,
            shifts.as_slice(),
            actions.as_slice(),
            scales.as_slice(),
            &mut applied,
        )
        .map_err(|err| engine_error(py, err.into()))?;
        shaped(py, applied, self.sessions.len(), Some(self.dim))
    }

    /// `(probes, applied)` of the step `steps` (one per session), each `(N, D)`.
    #[pyo3(signature = (shifts, steps, actions, action_scales = None))]
    fn probes<'py>(
        &self,
        py: Python<'py>,
        shifts: &Bound<'py, PyAny>,
        steps: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        action_scales: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let shifts = Values::<f64>::floats(shifts)?;
        let steps = Values::<u64>::steps(steps)?;
        let actions = Values::<f64>::floats(actions)?;
        let scales = Values::<f64>::floats_or_empty(action_scales)?;
        let capacity = actions.as_slice().len();
        let (mut probes, mut applied) =
            (Vec::with_capacity(capacity), Vec::with_capacity(capacity));
        fused_step::probes_ahead(
            &self.sessions,
            shifts.as_slice(),
            steps.as_slice(),
            actions.as_slice(),
            scales.as_slice(),
            &mut probes,
            &mut applied,
        )
        .map_err(|err| engine_error(py, err.into()))?;
        shaped_tuple(py, [probes, applied], self.sessions.len(), Some(self.dim))
    }

    fn __len__(&self) -> usize {
        self.sessions.len()
    }
}
