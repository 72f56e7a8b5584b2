//! Per-dimension state of a session, stored as the columns of one D x 8 nalgebra matrix.
//!
//! One allocation per session (instead of one per vector) keeps an idle D = 6 session well under the
//! 1 KiB budget of issue 7, and the column-major layout keeps every per-dimension vector contiguous, so the
//! hot loops run over plain slices without bounds checks.

use nalgebra::DMatrix;

use crate::config::{lane, SessionConfig};

const AMPLITUDE: usize = 0;
const FREQUENCY: usize = 1;
const RATE: usize = 2;
const LOW: usize = 3;
const HIGH: usize = 4;
const SHIFT: usize = 5;
const SINE: usize = 6;
const ACTION: usize = 7;
const COLUMNS: usize = 8;

// `split_mut` hands out the mutable columns as one contiguous tail in this order.
const _: () = assert!(SHIFT + 1 == SINE && SINE + 1 == ACTION && ACTION + 1 == COLUMNS);

/// Mutable views of every column at once, borrowed from [`Lanes`].
pub(crate) struct LanesMut<'a> {
    /// K, broadcast.
    pub amplitude: &'a [f64],
    /// w, broadcast.
    pub frequency: &'a [f64],
    /// alpha_e = alpha * gamma_a^e for the current episode.
    pub rate: &'a [f64],
    /// Lower bound, saturated at `-f64::MAX` so clipping always yields a finite value.
    pub low: &'a [f64],
    /// Upper bound, saturated at `f64::MAX`.
    pub high: &'a [f64],
    /// v.
    pub shift: &'a mut [f64],
    /// `sin(w * tau)` of the last probe, reused by the report.
    pub sine: &'a mut [f64],
    /// The sampled action `a_t` of the last probe.
    pub action: &'a mut [f64],
}

#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Lanes {
    columns: DMatrix<f64>,
}

impl Lanes {
    /// Resolves (broadcasts) the config's per-dimension fields; v, s and a start at 0. The config must be valid.
    pub fn new(config: &SessionConfig) -> Self {
        let dim = config.action_dim as usize;
        let mut columns = DMatrix::zeros(dim, COLUMNS);
        let fills: [(usize, &[f64], f64); 4] = [
            (AMPLITUDE, &config.amplitude, 0.0),
            (FREQUENCY, &config.frequency, 0.0),
            (LOW, &config.action_low, -f64::MAX),
            (HIGH, &config.action_high, f64::MAX),
        ];
        for (column, values, default) in fills {
            for (i, x) in columns.column_mut(column).iter_mut().enumerate() {
                *x = lane(values, i, default).clamp(-f64::MAX, f64::MAX);
            }
        }
        let mut lanes = Self { columns };
        lanes.set_rate(&config.learning_rate, 1.0);
        lanes
    }

    pub fn dim(&self) -> usize {
        self.columns.nrows()
    }

    /// Sets alpha_e = alpha * factor for every dimension (once per episode, not per step).
    pub fn set_rate(&mut self, learning_rate: &[f64], factor: f64) {
        for (i, x) in self.columns.column_mut(RATE).iter_mut().enumerate() {
            *x = lane(learning_rate, i, 0.0) * factor;
        }
    }

    pub fn reset_shift(&mut self) {
        self.columns.column_mut(SHIFT).fill(0.0);
    }

    pub fn shift(&self) -> &[f64] {
        self.column_slice(SHIFT)
    }

    pub fn low(&self) -> &[f64] {
        self.column_slice(LOW)
    }

    pub fn high(&self) -> &[f64] {
        self.column_slice(HIGH)
    }

    pub fn action(&self) -> &[f64] {
        self.column_slice(ACTION)
    }

    fn column_slice(&self, column: usize) -> &[f64] {
        let dim = self.dim();
        self.columns
            .as_slice()
            .get(column * dim..(column + 1) * dim)
            .unwrap_or_default()
    }

    #[inline]
    pub fn split_mut(&mut self) -> LanesMut<'_> {
        let dim = self.dim();
        let all = self.columns.as_mut_slice();
        let (fixed, rest) = all.split_at_mut(SHIFT * dim);
        let (shift, rest) = rest.split_at_mut(dim);
        let (sine, action) = rest.split_at_mut(dim);
        let (amplitude, fixed) = fixed.split_at(dim);
        let (frequency, fixed) = fixed.split_at(dim);
        let (rate, fixed) = fixed.split_at(dim);
        let (low, high) = fixed.split_at(dim);
        LanesMut {
            amplitude,
            frequency,
            rate,
            low,
            high,
            shift,
            sine,
            action,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resolves_broadcasts_and_saturates_unbounded_sides() {
        let config = SessionConfig {
            action_low: vec![f64::NEG_INFINITY, -1.0, -2.0],
            ..SessionConfig::new(3, 0.01, vec![0.5], vec![10.0, 20.0, 30.0], vec![2.0])
        };
        let mut lanes = Lanes::new(&config);
        lanes.set_rate(&config.learning_rate, 0.5);
        assert_eq!(lanes.dim(), 3);
        assert_eq!(lanes.low(), &[-f64::MAX, -1.0, -2.0]);
        assert_eq!(lanes.high(), &[f64::MAX; 3]);
        let split = lanes.split_mut();
        assert_eq!(split.amplitude, &[0.5; 3]);
        assert_eq!(split.frequency, &[10.0, 20.0, 30.0]);
        assert_eq!(split.rate, &[1.0; 3]);
        assert_eq!(split.low.len() + split.high.len() + split.shift.len(), 9);
        assert_eq!((split.sine.len(), split.action.len()), (3, 3));
    }
}
