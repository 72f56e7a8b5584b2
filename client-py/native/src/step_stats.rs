//! `StepStats`: what ESA did to a learner's actions, summed step by step for its log.
//!
//! A learner logs, per step and averaged over its envs, how far ESA moved the actions and how
//! often they left the env's bounds. Computed in numpy, a dozen small calls per step cost about
//! as much as the ESA step itself; here a step's sums cost one call.

use numpy::{PyUntypedArray, PyUntypedArrayMethods};
use parking_lot::Mutex;
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::arrays::Values;

/// The per-step statistics, in the order `means` lists them.
const PER_STEP: [&str; 5] = [
    "mean_abs_shift",
    "clipped_fraction",
    "shift_over_std",
    "kl_per_dim",
    "improvement",
];
const SHIFT: usize = 0;
const CLIPPED: usize = 1;
const OVER_STD: usize = 2;
const KL: usize = 3;
const IMPROVEMENT: usize = 4;

/// Running sums of per-step values and counts since the last reset.
#[derive(Default)]
struct Sums {
    /// `(sum, steps)` of each of `PER_STEP`.
    per_step: [(f64, u64); PER_STEP.len()],
    /// Counts since the last record (`sessions_restored`, ...), in the order first added.
    counts: Vec<(String, f64)>,
}

/// The env's action bounds (in the units of the actions ESA sees) and the running sums.
#[pyclass(frozen, module = "esa_client._native")]
pub(crate) struct StepStats {
    clip_low: Vec<f64>,
    clip_high: Vec<f64>,
    sums: Mutex<Sums>,
}

impl Sums {
    /// Adds one step's `value` to the statistic `index` of `PER_STEP`.
    fn add(&mut self, index: usize, value: f64) {
        let (sum, steps) = &mut self.per_step[index];
        *sum += value;
        *steps += 1;
    }
}

impl StepStats {
    /// Adds one step of N envs: `sampled` and `applied` (N D values), `scales` the policy's
    /// std in the same units (N D values) or empty. Cannot fail: `add_step` checks first.
    fn add(&self, sampled: &[f64], applied: &[f64], scales: &[f64]) {
        let dim = self.clip_low.len();
        if sampled.is_empty() {
            return;
        }
        let values = sampled.len() as f64;
        let (mut shift, mut over_std, mut kl) = (0.0, 0.0, 0.0);
        let mut clipped_rows = 0usize;
        for (row, (sampled, applied)) in sampled
            .chunks_exact(dim)
            .zip(applied.chunks_exact(dim))
            .enumerate()
        {
            let mut clipped = false;
            for d in 0..dim {
                let v = applied[d] - sampled[d];
                shift += v.abs();
                clipped |= applied[d] < self.clip_low[d] || applied[d] > self.clip_high[d];
                if let Some(&sigma) = scales.get(row * dim + d) {
                    let z = v / sigma;
                    over_std += z.abs();
                    kl += 0.5 * z * z;
                }
            }
            clipped_rows += usize::from(clipped);
        }
        let rows = (sampled.len() / dim) as f64;
        let mut sums = self.sums.lock();
        sums.add(SHIFT, shift / values);
        sums.add(CLIPPED, clipped_rows as f64 / rows);
        if !scales.is_empty() {
            // KL(behaviour || pi) of N(mu + v, s^2) against N(mu, s^2), per dimension.
            sums.add(OVER_STD, over_std / values);
            sums.add(KL, kl / values);
        }
    }
}

/// The N rows of `array`, a numpy array of shape `(N, dim)`, N = `rows` when given.
fn rows_of(
    array: &Bound<'_, PyAny>,
    rows: Option<usize>,
    dim: usize,
    name: &str,
) -> PyResult<usize> {
    let array = array.cast::<PyUntypedArray>().map_err(|_| {
        PyTypeError::new_err(format!(
            "{name}: expected a numpy array of shape (N, {dim})"
        ))
    })?;
    match array.shape() {
        [n, width] if *width == dim && rows.is_none_or(|rows| rows == *n) => Ok(*n),
        shape => {
            let rows = rows.map_or("N".to_owned(), |rows| rows.to_string());
            let message = format!("expected {name} of shape ({rows}, {dim}), got {shape:?}");
            Err(PyValueError::new_err(message))
        }
    }
}

#[pymethods]
impl StepStats {
    /// Sums steps whose actions the env clips to `[clip_low, clip_high]` (D values each).
    #[new]
    fn new(clip_low: Vec<f64>, clip_high: Vec<f64>) -> PyResult<Self> {
        if clip_low.len() != clip_high.len() || clip_low.is_empty() {
            return Err(PyValueError::new_err(format!(
                "expected clip_low and clip_high of one length D >= 1, got {} and {}",
                clip_low.len(),
                clip_high.len()
            )));
        }
        Ok(Self {
            clip_low,
            clip_high,
            sums: Mutex::new(Sums::default()),
        })
    }

    /// Adds one step: the sampled and applied actions `(N, D)`, and the policy's std `(N, D)` in
    /// the same units or None.
    #[pyo3(signature = (sampled, applied, scales = None))]
    fn add_step(
        &self,
        sampled: &Bound<'_, PyAny>,
        applied: &Bound<'_, PyAny>,
        scales: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<()> {
        let dim = self.clip_low.len();
        let rows = Some(rows_of(sampled, None, dim, "sampled")?);
        rows_of(applied, rows, dim, "applied")?;
        if let Some(scales) = scales {
            rows_of(scales, rows, dim, "scales")?;
        }
        let (sampled, applied) = (Values::floats(sampled)?, Values::floats(applied)?);
        let scales = Values::floats_or_empty(scales)?;
        self.add(sampled.as_slice(), applied.as_slice(), scales.as_slice());
        Ok(())
    }

    /// Adds one step's `esa/improvement`.
    fn add_improvement(&self, value: f64) {
        self.sums.lock().add(IMPROVEMENT, value);
    }

    /// Adds `count` to the count `key` (reported as a total, not a mean).
    fn add_count(&self, key: &str, count: f64) {
        let counts = &mut self.sums.lock().counts;
        match counts.iter_mut().find(|(name, _)| name == key) {
            Some((_, total)) => *total += count,
            None => counts.push((key.to_owned(), count)),
        }
    }

    /// The mean of each per-step statistic over its steps, and the counts: `{name: value}`,
    /// only what was added since the last reset.
    fn means<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let sums = self.sums.lock();
        let means = PyDict::new(py);
        for (name, &(sum, steps)) in PER_STEP.iter().zip(&sums.per_step) {
            if steps > 0 {
                means.set_item(*name, sum / steps as f64)?;
            }
        }
        for (name, count) in &sums.counts {
            means.set_item(name, *count)?;
        }
        Ok(means)
    }

    /// Forgets everything added (after a log record).
    fn reset(&self) {
        *self.sums.lock() = Sums::default();
    }
}
