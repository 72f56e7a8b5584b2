//! `AdvantageMlp`: ESAPPO's advantage head, forward, for one rollout step.
//!
//! ESAPPO scores a step's probes with `A = w(s) . (a - mu) / sigma`, `w` a tanh MLP of the
//! observation (`esa_client.common.advantage_head`). A step has one observation per env: numpy or
//! torch would spend more time dispatching their dozen small operations than computing them. This
//! class holds a copy of the head's layers (taken again after each fit) and returns, in one call,
//! the step's critic linear in the action in ESA units, `Q(a) = gain . a + offset` with
//! `gain = w h / sigma` and `offset = w . (c - mu) / sigma` (`c`, `h`: the Box's center and
//! half-width), which `Engine.step_closed_form` evaluates.

use std::borrow::Cow;

use numpy::ndarray::{Array1, Array2, ArrayView2};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;

/// What `critic` returns: `gain` (N, D) and `offset` (N,).
type Critic<'py> = (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<f64>>);

/// What `step_inputs` returns: `scaled` and `gain` (N, D), `offset` (N,) and `units` (N, D).
type StepInputs<'py> = (
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray2<f64>>,
);

/// The head's input, float32 or float64 `(N, F)`: float64 observations (MuJoCo's) are rounded
/// to float32 here, as torch's `float()` rounds them (to nearest, ties to even), without the
/// separate numpy cast per step.
enum Features<'py> {
    Single(PyReadonlyArray2<'py, f32>),
    Double(PyReadonlyArray2<'py, f64>),
}

impl<'py> Features<'py> {
    /// Reads `object` by casts, not by a derived `FromPyObject`: that would build a Python
    /// exception for each variant it tries first, which costs more than the head's forward.
    fn read(object: &Bound<'py, PyAny>) -> PyResult<Self> {
        if let Ok(array) = object.cast::<PyArray2<f32>>() {
            return Ok(Self::Single(array.try_readonly()?));
        }
        if let Ok(array) = object.cast::<PyArray2<f64>>() {
            return Ok(Self::Double(array.try_readonly()?));
        }
        Err(PyTypeError::new_err(format!(
            "features: expected a float32 or float64 array of 2 dimensions, got {}",
            object.repr()?
        )))
    }
}

/// One linear layer, `weight` row-major (outputs x inputs) as torch stores it.
struct Layer {
    weight: Vec<f32>,
    bias: Vec<f32>,
    inputs: usize,
}

impl Layer {
    fn outputs(&self) -> usize {
        self.bias.len()
    }

    /// `weight x + bias`, written over `out`.
    fn forward(&self, input: &[f32], out: &mut Vec<f32>) {
        out.clear();
        out.extend(
            self.weight
                .chunks_exact(self.inputs)
                .zip(&self.bias)
                .map(|(row, bias)| row.iter().zip(input).map(|(w, x)| w * x).sum::<f32>() + bias),
        );
    }
}

/// The head's layers and the action space's scaling; see the module stub for the API.
#[pyclass(frozen, module = "esa_client._native")]
pub(crate) struct AdvantageMlp {
    layers: Vec<Layer>,
    center: Vec<f64>,
    half_width: Vec<f64>,
    /// The std in ESA units divides in float32, as numpy divides a float32 std by the
    /// half-width of a float32 (or float16) Box; else in float64.
    single_units: bool,
}

/// ESAPPO's step inputs, each flat in row order: the sample in ESA units, the critic's gain
/// (N D values) and offset (N values), and the policy's std in ESA units (N D values).
struct HeadInputs {
    scaled: Vec<f64>,
    gain: Vec<f64>,
    offset: Vec<f64>,
    units: Vec<f64>,
}

fn invalid(message: String) -> PyErr {
    PyValueError::new_err(message)
}

/// The rows of a `(n, width)` array (borrowed where contiguous), checking the width.
fn rows<'a, T: Clone>(
    array: &'a ArrayView2<'_, T>,
    width: usize,
    name: &str,
) -> PyResult<Vec<Cow<'a, [T]>>> {
    if array.ncols() != width {
        return Err(invalid(format!(
            "{name}: expected {width} columns, got shape {:?}",
            array.shape()
        )));
    }
    Ok(array
        .rows()
        .into_iter()
        .map(|row| match row.to_slice() {
            Some(slice) => Cow::Borrowed(slice),
            None => Cow::Owned(row.to_vec()),
        })
        .collect())
}

impl AdvantageMlp {
    fn features_dim(&self) -> usize {
        self.layers[0].inputs
    }

    pub(crate) fn action_dim(&self) -> usize {
        self.center.len()
    }

    /// A step's inputs from the policy's float32 `(N, D)` sample, mean and std (see
    /// `step_inputs` and `units`), checking every shape.
    fn inputs(
        &self,
        features: &Bound<'_, PyAny>,
        actions: &PyReadonlyArray2<'_, f32>,
        mean: &PyReadonlyArray2<'_, f32>,
        std: &PyReadonlyArray2<'_, f32>,
    ) -> PyResult<HeadInputs> {
        let each = self.each_w(&Features::read(features)?)?;
        let (n, dim) = (each.len(), self.action_dim());
        let actions = actions.as_array();
        let samples = rows(&actions, dim, "actions")?;
        if samples.len() != n {
            return Err(invalid(format!(
                "expected actions with {n} rows (one per features row), got {}",
                samples.len()
            )));
        }
        let std = std.as_array();
        let (gain, offset) = self.linear_critic(&each, &mean.as_array(), &std)?;
        let scaled = samples
            .iter()
            .flat_map(|sample| {
                (0..dim).map(|d| (f64::from(sample[d]) - self.center[d]) / self.half_width[d])
            })
            .collect();
        Ok(HeadInputs {
            scaled,
            gain,
            offset,
            units: self.units_of(&std)?,
        })
    }

    /// `max(std / h, tiny)` of each row of `std`, float64: the std in ESA units, floored at
    /// float32's smallest normal number (the contract needs sigma > 0); numpy's bits for the
    /// Box's dtype (`single_units`), NaN kept as `np.maximum` keeps it.
    fn units_of(&self, std: &ArrayView2<'_, f32>) -> PyResult<Vec<f64>> {
        let tiny = f32::MIN_POSITIVE;
        let dim = self.action_dim();
        Ok(rows(std, dim, "std")?
            .iter()
            .flat_map(|row| {
                (0..dim).map(|d| {
                    if self.single_units {
                        // Exact: the half-width is a float32 widened.
                        let unit = row[d] / self.half_width[d] as f32;
                        f64::from(if unit < tiny { tiny } else { unit })
                    } else {
                        let unit = f64::from(row[d]) / self.half_width[d];
                        if unit < f64::from(tiny) {
                            f64::from(tiny)
                        } else {
                            unit
                        }
                    }
                })
            })
            .collect())
    }

    /// A step's shift in the Box's units from its sample and answer in ESA units.
    fn shift_value(&self, scaled: f64, applied: f64, d: usize) -> f64 {
        (applied - scaled) * self.half_width[d]
    }

    /// The env's action: the float32 sample plus the float64 shift, cast back to float32.
    fn executed_value(sample: f32, shift: f64) -> f32 {
        // f64 to f32 with `as` rounds to nearest, ties to even: numpy's astype.
        (f64::from(sample) + shift) as f32
    }

    /// `f(x, y, d)` of the `(N, D)` arrays `first` and `second` (named in the errors), value by
    /// value, as an `(N, D)` array.
    fn elementwise<'py, T, U, V>(
        &self,
        py: Python<'py>,
        first: (&PyReadonlyArray2<'py, T>, &str),
        second: (&PyReadonlyArray2<'py, U>, &str),
        f: impl Fn(T, U, usize) -> V,
    ) -> PyResult<Bound<'py, PyArray2<V>>>
    where
        T: numpy::Element + Copy,
        U: numpy::Element + Copy,
        V: numpy::Element,
    {
        let dim = self.action_dim();
        let (x, y) = (first.0.as_array(), second.0.as_array());
        let (x, y) = (rows(&x, dim, first.1)?, rows(&y, dim, second.1)?);
        if x.len() != y.len() {
            return Err(invalid(format!(
                "expected {} and {} with as many rows, got {} and {}",
                first.1,
                second.1,
                x.len(),
                y.len()
            )));
        }
        let mut values = Vec::with_capacity(x.len() * dim);
        for (row_x, row_y) in x.iter().zip(&y) {
            values.extend((0..dim).map(|d| f(row_x[d], row_y[d], d)));
        }
        matrix(py, values, x.len(), dim)
    }

    /// The step's critic of each row of `each` (`w`), as `critic` returns it, checking that
    /// `mean` and `std` have one row of D values per row.
    fn linear_critic(
        &self,
        each: &[Vec<f32>],
        mean: &ArrayView2<'_, f32>,
        std: &ArrayView2<'_, f32>,
    ) -> PyResult<(Vec<f64>, Vec<f64>)> {
        let (n, dim) = (each.len(), self.action_dim());
        let means = rows(mean, dim, "mean")?;
        let stds = rows(std, dim, "std")?;
        if means.len() != n || stds.len() != n {
            return Err(invalid(format!(
                "expected mean and std with {n} rows (one per features row), got {} and {}",
                means.len(),
                stds.len()
            )));
        }
        let mut gain = Vec::with_capacity(n * dim);
        let mut offset = Vec::with_capacity(n);
        for ((w, mean), std) in each.iter().zip(means).zip(stds) {
            let mut total = 0.0;
            for d in 0..dim {
                let (w, sigma) = (f64::from(w[d]), f64::from(std[d]));
                gain.push(w * self.half_width[d] / sigma);
                total += w * (self.center[d] - f64::from(mean[d])) / sigma;
            }
            offset.push(total);
        }
        Ok((gain, offset))
    }

    /// `w(features)` for each row of `features`, in float32.
    fn each_w(&self, features: &Features<'_>) -> PyResult<Vec<Vec<f32>>> {
        let width = self.features_dim();
        let (mut hidden, mut next) = (Vec::new(), Vec::new());
        let mut w = |input: &mut dyn Iterator<Item = f32>| {
            hidden.clear();
            hidden.extend(input);
            let last = self.layers.len() - 1;
            for (index, layer) in self.layers.iter().enumerate() {
                layer.forward(&hidden, &mut next);
                if index < last {
                    next.iter_mut().for_each(|v| *v = v.tanh());
                }
                std::mem::swap(&mut hidden, &mut next);
            }
            hidden.clone()
        };
        Ok(match features {
            Features::Single(array) => rows(&array.as_array(), width, "features")?
                .iter()
                .map(|row| w(&mut row.iter().copied()))
                .collect(),
            // f64 to f32 with `as` rounds to nearest, ties to even: torch's float().
            Features::Double(array) => rows(&array.as_array(), width, "features")?
                .iter()
                .map(|row| w(&mut row.iter().map(|&v| v as f32)))
                .collect(),
        })
    }
}

#[pymethods]
impl AdvantageMlp {
    #[new]
    #[pyo3(signature = (weights, biases, center, half_width, single_units = false))]
    fn new(
        weights: Vec<PyReadonlyArray2<'_, f32>>,
        biases: Vec<PyReadonlyArray1<'_, f32>>,
        center: Vec<f64>,
        half_width: Vec<f64>,
        single_units: bool,
    ) -> PyResult<Self> {
        if weights.is_empty() || weights.len() != biases.len() {
            return Err(invalid(format!(
                "expected as many biases as weights (at least one layer), got {} and {}",
                weights.len(),
                biases.len()
            )));
        }
        let mut layers: Vec<Layer> = Vec::with_capacity(weights.len());
        for (index, (weight, bias)) in weights.iter().zip(&biases).enumerate() {
            let (weight, bias) = (weight.as_array(), bias.as_array());
            let (outputs, inputs) = weight.dim();
            let expected_inputs = layers.last().map_or(inputs, Layer::outputs);
            if inputs != expected_inputs || bias.len() != outputs || outputs == 0 || inputs == 0 {
                return Err(invalid(format!(
                    "layer {index}: expected a weight of shape (outputs, {expected_inputs}) and \
                     a bias of length outputs, got {:?} and {}",
                    weight.shape(),
                    bias.len()
                )));
            }
            layers.push(Layer {
                weight: weight.iter().copied().collect(),
                bias: bias.iter().copied().collect(),
                inputs,
            });
        }
        let action_dim = layers.last().map_or(0, Layer::outputs);
        if center.len() != action_dim || half_width.len() != action_dim {
            return Err(invalid(format!(
                "expected center and half_width of length {action_dim} (the last layer's \
                 outputs), got {} and {}",
                center.len(),
                half_width.len()
            )));
        }
        if !center.iter().chain(&half_width).all(|v| v.is_finite())
            || half_width.iter().any(|&h| h <= 0.0)
        {
            return Err(invalid(format!(
                "expected finite center and half_width > 0, got {center:?} and {half_width:?}"
            )));
        }
        Ok(Self {
            layers,
            center,
            half_width,
            single_units,
        })
    }

    /// F, the features each row of `features` has.
    #[getter(features_dim)]
    fn py_features_dim(&self) -> usize {
        self.features_dim()
    }

    /// D, the action dimension.
    #[getter(action_dim)]
    fn py_action_dim(&self) -> usize {
        self.action_dim()
    }

    /// `w(features)`: float64 (N, D).
    fn weights<'py>(
        &self,
        py: Python<'py>,
        features: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let each = self.each_w(&Features::read(features)?)?;
        let (n, dim) = (each.len(), self.action_dim());
        let values = each.into_iter().flatten().map(f64::from).collect();
        matrix(py, values, n, dim)
    }

    /// The step's critic in ESA units: `(gain, offset)`, float64 (N, D) and (N,).
    fn critic<'py>(
        &self,
        py: Python<'py>,
        features: &Bound<'py, PyAny>,
        mean: PyReadonlyArray2<'py, f32>,
        std: PyReadonlyArray2<'py, f32>,
    ) -> PyResult<Critic<'py>> {
        let each = self.each_w(&Features::read(features)?)?;
        let (gain, offset) = self.linear_critic(&each, &mean.as_array(), &std.as_array())?;
        Ok((
            matrix(py, gain, each.len(), self.action_dim())?,
            Array1::from(offset).into_pyarray(py),
        ))
    }

    /// ESAPPO's step inputs in one call: the sample and std in ESA units, and the step's critic.
    ///
    /// `actions`, `mean` and `std` are the policy's float32 `(N, D)`. Returns `(scaled, gain,
    /// offset, units)`: the sample in ESA units `(a - c) / h`, float64 `(N, D)` (numpy's float64
    /// operations on the widened values, so the same bits), the critic as `critic` gives it, and
    /// the std in ESA units floored at float32's smallest normal number, float64 `(N, D)`.
    fn step_inputs<'py>(
        &self,
        py: Python<'py>,
        features: &Bound<'py, PyAny>,
        actions: PyReadonlyArray2<'py, f32>,
        mean: PyReadonlyArray2<'py, f32>,
        std: PyReadonlyArray2<'py, f32>,
    ) -> PyResult<StepInputs<'py>> {
        let inputs = self.inputs(features, &actions, &mean, &std)?;
        let (n, dim) = (inputs.offset.len(), self.action_dim());
        Ok((
            matrix(py, inputs.scaled, n, dim)?,
            matrix(py, inputs.gain, n, dim)?,
            Array1::from(inputs.offset).into_pyarray(py),
            matrix(py, inputs.units, n, dim)?,
        ))
    }

    /// The shift of a step's answer in the Box's units: `(applied - scaled) h`, float64 (N, D).
    fn shift<'py>(
        &self,
        py: Python<'py>,
        scaled: PyReadonlyArray2<'py, f64>,
        applied: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        self.elementwise(py, (&scaled, "scaled"), (&applied, "applied"), |x, y, d| {
            self.shift_value(x, y, d)
        })
    }

    /// The env's actions: the float32 sample plus the float64 shift, cast back to float32.
    fn executed<'py>(
        &self,
        py: Python<'py>,
        actions: PyReadonlyArray2<'py, f32>,
        shift: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        self.elementwise(py, (&actions, "actions"), (&shift, "shift"), |a, s, _| {
            Self::executed_value(a, s)
        })
    }
}

/// `values` as an `(n, dim)` array.
fn matrix<T: numpy::Element>(
    py: Python<'_>,
    values: Vec<T>,
    n: usize,
    dim: usize,
) -> PyResult<Bound<'_, PyArray2<T>>> {
    Array2::from_shape_vec((n, dim), values)
        .map(|array| array.into_pyarray(py))
        .map_err(|err| invalid(err.to_string()))
}
