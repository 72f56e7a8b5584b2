//! The washout (first-order high-pass) filter H applied to the scalar Q value.

/// Backward-Euler first-order washout: `y_k = beta * (y_{k-1} + x_k - x_{k-1})`, `beta = 1 / (1 + w_h dt)`.
///
/// It removes the slowly varying level of Q so that only the part correlated with the sinusoidal probe
/// drives the shift update. It starts at rest: the first sample after [`reset`](Self::reset) sets
/// `x_{-1} := x_0, y_{-1} := 0`, so its output is exactly 0.
#[derive(Clone, Debug, PartialEq)]
pub struct Washout {
    beta: f64,
    previous_input: f64,
    previous_output: f64,
    at_rest: bool,
}

/// What a [`Washout`] remembers between samples (its pole comes from the config).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WashoutMemory {
    /// `x_{k-1}`, the last input.
    pub previous_input: f64,
    /// `y_{k-1}`, the last output (0 after an output that overflowed).
    pub previous_output: f64,
    /// True until the first sample after a reset: that sample's output is exactly 0.
    pub at_rest: bool,
}

impl Washout {
    /// A filter at rest with cutoff `cutoff` rad/s sampled every `dt` seconds.
    pub fn new(cutoff: f64, dt: f64) -> Self {
        Self {
            beta: 1.0 / (1.0 + cutoff * dt),
            previous_input: 0.0,
            previous_output: 0.0,
            at_rest: true,
        }
    }

    /// The discrete pole `beta = 1 / (1 + w_h dt)`.
    pub fn beta(&self) -> f64 {
        self.beta
    }

    /// The filter's memory: the last input and output, and whether it is at rest.
    pub fn memory(&self) -> WashoutMemory {
        WashoutMemory {
            previous_input: self.previous_input,
            previous_output: self.previous_output,
            at_rest: self.at_rest,
        }
    }

    /// Takes back a memory that [`memory`](Self::memory) gave (of a filter with the same cutoff and
    /// step), so the next sample is filtered as it would have been.
    pub fn set_memory(&mut self, memory: WashoutMemory) {
        self.previous_input = memory.previous_input;
        self.previous_output = memory.previous_output;
        self.at_rest = memory.at_rest;
    }

    /// Puts the filter back at rest; the next sample yields exactly 0.
    pub fn reset(&mut self) {
        self.at_rest = true;
    }

    /// Filters one sample.
    ///
    /// The output can overflow to infinity when consecutive samples differ by more than `f64::MAX`; the
    /// caller then skips its update, and the filter restarts at rest from this sample so that one extreme
    /// pair of samples does not poison (NaN) every later output of the episode.
    pub fn apply(&mut self, x: f64) -> f64 {
        let y = if self.at_rest {
            0.0
        } else {
            self.beta * (self.previous_output + x - self.previous_input)
        };
        self.previous_input = x;
        self.previous_output = if y.is_finite() { y } else { 0.0 };
        self.at_rest = false;
        y
    }
}

#[cfg(test)]
mod tests {
    use approx::assert_relative_eq;

    use super::*;

    #[test]
    fn first_output_is_exactly_zero() {
        let mut f = Washout::new(6.0, 0.01);
        assert_eq!(f.apply(-123.456), 0.0);
    }

    #[test]
    fn follows_the_washout_recurrence() {
        let mut f = Washout::new(6.0, 0.01);
        let beta = 1.0 / 1.06;
        assert_eq!(f.beta(), beta);
        let xs = [3.0, 5.0, 4.0, 4.0, -2.0];
        let mut expected = vec![0.0];
        for k in 1..xs.len() {
            let y = beta * (expected[k - 1] + xs[k] - xs[k - 1]);
            expected.push(y);
        }
        let got: Vec<f64> = xs.iter().map(|&x| f.apply(x)).collect();
        for (g, e) in got.iter().zip(&expected) {
            assert_relative_eq!(*g, *e, epsilon = 1e-15);
        }
        assert_relative_eq!(got[1], beta * 2.0, epsilon = 1e-15);
    }

    #[test]
    fn washes_out_a_constant() {
        let mut f = Washout::new(6.0, 0.01);
        f.apply(0.0);
        let mut y = f.apply(1.0);
        assert_relative_eq!(y, 1.0 / 1.06, epsilon = 1e-15);
        for _ in 0..2000 {
            y = f.apply(1.0);
        }
        assert!(y.abs() < 1e-12, "a step input must decay, got {y}");
    }

    #[test]
    fn reset_restarts_at_rest() {
        let mut f = Washout::new(6.0, 0.01);
        f.apply(1.0);
        f.apply(9.0);
        f.reset();
        assert_eq!(f.apply(100.0), 0.0);
        assert_relative_eq!(f.apply(101.0), 1.0 / 1.06, epsilon = 1e-13);
    }

    #[test]
    fn overflow_does_not_poison_later_outputs() {
        let mut f = Washout::new(6.0, 0.01);
        f.apply(-f64::MAX);
        assert_eq!(f.apply(f64::MAX), f64::INFINITY);
        let y = f.apply(f64::MAX);
        assert!(y.is_finite(), "filter must recover, got {y}");
        assert!(f.apply(0.0).is_finite());
    }
}
