//! `StepAhead`: Algorithm 1's probes and applied actions of a step from the shifts known ahead of
//! the server's answer, with esa-core's own function (`esa_core::fused_step::probes_ahead`), so
//! that a client of the pipelined step applies, and evaluates its critic at,
//! the bits the server would have answered; a quadratic critic it evaluates as the in-process
//! engine does (`esa_core::fused_step::QuadraticCritic`).

use esa_core::fused_step::{self, QuadraticCritic, StepCritic};
use esa_core::Session;
use esa_store::Error;
use numpy::IntoPyArray;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use crate::arrays::{shaped, shaped_tuple, tiled, Values};
use crate::engine_class::decode_config;
use crate::errors::engine_error;

/// A `QuadraticCritic`'s fields: gain, curvature, offset, and the box's bounds or None.
type Quadratic<'py> = (
    Any<'py>,
    Any<'py>,
    Any<'py>,
    Option<Any<'py>>,
    Option<Any<'py>>,
);
type Any<'py> = Bound<'py, PyAny>;

/// The configs of N sessions of one action dimension; see the module stub for the API.
#[pyclass(frozen, module = "esa_client._native")]
pub(crate) struct StepAhead {
    /// Fresh sessions of the configs: only their configs are read.
    sessions: Vec<Session>,
    /// Each session's action dimension (all one), as esa-core's critics take them.
    dims: Vec<usize>,
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
        let dims = vec![dim; sessions.len()];
        Ok(Self { sessions, dims })
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
        let (probes, applied) = self.ahead(py, shifts, steps, actions, action_scales)?;
        shaped_tuple(py, [probes, applied], self.sessions.len(), self.dim())
    }

    /// `(probes, applied, q_values, q_references)` of the step `steps`, with the values of the
    /// `(gain, curvature, offset, low, high)` quadratic critic at the probes, `(N,)`, and at the
    /// applied actions when `paired` (else None), checked first as the in-process engine does.
    #[allow(clippy::too_many_arguments)] // `probes`' arrays, the critic and `paired`
    fn probes_quadratic<'py>(
        &self,
        py: Python<'py>,
        shifts: &Bound<'py, PyAny>,
        steps: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        action_scales: Option<&Bound<'py, PyAny>>,
        critic: Quadratic<'py>,
        paired: bool,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let (n, values) = (self.sessions.len(), self.dims.iter().sum());
        let (gain, curvature, offset, low, high) = critic;
        let gains = Values::<f64>::floats(&gain)?;
        let curvatures = Values::<f64>::floats(&curvature)?;
        let offsets = Values::<f64>::floats(&offset)?;
        let [lows, highs] = tiled([low.as_ref(), high.as_ref()], n, values)?;
        let critic = QuadraticCritic {
            gains: gains.as_slice(),
            curvatures: curvatures.as_slice(),
            offsets: offsets.as_slice(),
            lows: &lows,
            highs: &highs,
            paired,
        };
        critic
            .check(&self.dims)
            .map_err(|err| engine_error(py, err.into()))?;
        let (probes, applied) = self.ahead(py, shifts, steps, actions, action_scales)?;
        let (q_values, q_references) = critic.values(&self.dims, &probes, &applied);
        let references = paired.then(|| q_references.into_owned().into_pyarray(py));
        let [probes, applied] = [probes, applied].map(|values| shaped(py, values, n, self.dim()));
        let q_values = q_values.into_owned().into_pyarray(py);
        (probes?, applied?, q_values, references).into_pyobject(py)
    }

    fn __len__(&self) -> usize {
        self.sessions.len()
    }
}

impl StepAhead {
    /// The action dimension D of every session.
    fn dim(&self) -> Option<usize> {
        self.dims.first().copied()
    }

    /// esa-core's `probes_ahead` of the arrays as Python gives them.
    fn ahead(
        &self,
        py: Python<'_>,
        shifts: &Bound<'_, PyAny>,
        steps: &Bound<'_, PyAny>,
        actions: &Bound<'_, PyAny>,
        action_scales: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<(Vec<f64>, Vec<f64>)> {
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
        Ok((probes, applied))
    }
}
