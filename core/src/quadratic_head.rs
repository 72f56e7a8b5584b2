//! ESAPPO's quadratic head at one step's states, as the closed-form critic [`fused_step`] probes.
//!
//! The head is a multilayer perceptron of the state, two tanh layers and a linear output
//! `(w, r)`, with `A(s, a) = w . z + sum_j u_j (z_j^2 - 1)`, `u = -softplus(r)` and
//! `z = (a - mu) / sigma`. A learner trains it (in torch) and runs its forward pass here at each
//! step: torch's per-operation cost on a batch of one state is many times the arithmetic.
//! The forward pass is in `f32`, as the learner's; the closed form in `f64`.
//!
//! [`fused_step`]: crate::fused_step

use crate::CoreError;

/// One dense layer: `y = W x + b`, `W` row-major `(outputs, inputs)`.
#[derive(Clone, Debug)]
pub struct Dense {
    weight: Vec<f32>,
    bias: Vec<f32>,
}

impl Dense {
    /// A layer from its row-major weight and its bias (one value per output).
    pub fn new(weight: Vec<f32>, bias: Vec<f32>) -> Self {
        Dense { weight, bias }
    }

    fn inputs(&self) -> usize {
        self.weight.len() / self.bias.len().max(1)
    }

    fn apply(&self, x: &[f32], out: &mut Vec<f32>) {
        out.clear();
        out.extend(
            self.weight
                .chunks_exact(x.len())
                .zip(&self.bias)
                .map(|(row, b)| row.iter().zip(x).map(|(w, v)| w * v).sum::<f32>() + b),
        );
    }
}

/// The quadratic head's coefficients in a step's action units: `A = sum_j c_j x_j^2 + g_j x_j`
/// plus `offset` per state, `x` the action in the units `mu` and `sigma` are given in.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ClosedForm {
    /// `g = w / sigma - 2 c mu`, `(N, D)` row-major.
    pub gain: Vec<f64>,
    /// `c = u / sigma^2 <= 0`, `(N, D)` row-major.
    pub curvature: Vec<f64>,
    /// `sum_j c_j mu_j^2 - w_j mu_j / sigma_j - u_j`, one per state.
    pub offset: Vec<f64>,
}

/// The head's three layers, `features -> hidden -> hidden -> 2 D`.
#[derive(Clone, Debug)]
pub struct QuadraticHead {
    layers: [Dense; 3],
}

impl QuadraticHead {
    /// The head from its layers, input first.
    ///
    /// # Errors
    /// [`CoreError::InvalidArgument`] if a layer's weight is not `outputs x inputs` for the
    /// previous layer's outputs, or the last layer's outputs are not an even `2 D >= 2`.
    pub fn new(layers: [Dense; 3]) -> Result<Self, CoreError> {
        for (i, layer) in layers.iter().enumerate() {
            let (outputs, inputs) = (layer.bias.len(), layer.inputs());
            let expected = i.checked_sub(1).map(|p| layers[p].bias.len());
            if outputs == 0
                || inputs == 0
                || layer.weight.len() != outputs * inputs
                || expected.is_some_and(|e| e != inputs)
            {
                return Err(CoreError::InvalidArgument(format!(
                    "layer {i}: expected a weight of {outputs} x {} values, got {}",
                    expected.unwrap_or(inputs),
                    layer.weight.len()
                )));
            }
        }
        if layers[2].bias.len() % 2 != 0 {
            return Err(CoreError::InvalidArgument(format!(
                "expected 2 D outputs (w and u), got {}",
                layers[2].bias.len()
            )));
        }
        Ok(QuadraticHead { layers })
    }

    /// The action dimension D.
    pub fn action_dim(&self) -> usize {
        self.layers[2].bias.len() / 2
    }

    /// The closed form at N states: `features` `(N, F)`, the policy's `mean` and `std` `(N, D)`
    /// in action units, all row-major.
    ///
    /// # Errors
    /// [`CoreError::InvalidArgument`] if the lengths disagree with the head, or a value is not
    /// finite, or a `std` is not positive.
    pub fn closed_form(
        &self,
        features: &[f32],
        mean: &[f64],
        std: &[f64],
    ) -> Result<ClosedForm, CoreError> {
        let (f, d) = (self.layers[0].inputs(), self.action_dim());
        let n = features.len() / f;
        if features.len() != n * f || mean.len() != n * d || std.len() != n * d {
            return Err(CoreError::InvalidArgument(format!(
                "expected features of N x {f} values and mean, std of N x {d}, got {}, {} and {}",
                features.len(),
                mean.len(),
                std.len()
            )));
        }
        if !features.iter().all(|v| v.is_finite())
            || !mean.iter().all(|v| v.is_finite())
            || !std.iter().all(|&v| v.is_finite() && v > 0.0)
        {
            return Err(CoreError::InvalidArgument(
                "expected finite features and mean, and a finite std > 0".into(),
            ));
        }
        let mut form = ClosedForm::default();
        let (mut hidden, mut raw) = (Vec::new(), Vec::new());
        for ((x, mu), sigma) in features
            .chunks_exact(f)
            .zip(mean.chunks_exact(d))
            .zip(std.chunks_exact(d))
        {
            self.layers[0].apply(x, &mut raw);
            hidden.clear();
            hidden.extend(raw.iter().map(|v| v.tanh()));
            self.layers[1].apply(&hidden, &mut raw);
            raw.iter_mut().for_each(|v| *v = v.tanh());
            std::mem::swap(&mut hidden, &mut raw);
            self.layers[2].apply(&hidden, &mut raw);
            let mut offset = 0.0;
            for j in 0..d {
                let (w, u) = (f64::from(raw[j]), -f64::from(softplus(raw[d + j])));
                let (m, s) = (mu[j], sigma[j]);
                let c = u / (s * s);
                form.curvature.push(c);
                form.gain.push(w / s - 2.0 * c * m);
                offset += c * m * m - w * m / s - u;
            }
            form.offset.push(offset);
        }
        Ok(form)
    }
}

/// torch's `softplus` (beta 1, threshold 20): `log(1 + e^x)`, `x` itself above 20.
fn softplus(x: f32) -> f32 {
    if x > 20.0 {
        x
    } else {
        x.exp().ln_1p()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A head with one hidden unit per layer, F = 1, D = 1, whose forward pass is easy by hand.
    fn tiny(w_out: f32, r_out: f32) -> QuadraticHead {
        let layer = || Dense::new(vec![0.0], vec![0.0]);
        // Hidden units are tanh(0) = 0, so the output is the last bias.
        QuadraticHead::new([
            layer(),
            layer(),
            Dense::new(vec![0.0, 0.0], vec![w_out, r_out]),
        ])
        .unwrap()
    }

    #[test]
    fn closed_form_matches_the_head_at_any_action() {
        let head = tiny(0.5, -0.3);
        let (mu, sigma) = (0.2, 0.4);
        let form = head.closed_form(&[1.0], &[mu], &[sigma]).unwrap();
        let u = -f64::from(softplus(-0.3));
        for x in [-1.0, 0.0, 0.7] {
            let z = (x - mu) / sigma;
            let head_value = 0.5 * z + u * (z * z - 1.0);
            let closed = form.curvature[0] * x * x + form.gain[0] * x + form.offset[0];
            assert!(
                (head_value - closed).abs() < 1e-6,
                "{head_value} vs {closed}"
            );
        }
        assert!(form.curvature[0] < 0.0);
    }

    #[test]
    fn rejects_mismatched_layers_and_inputs() {
        let bad = QuadraticHead::new([
            Dense::new(vec![0.0; 6], vec![0.0; 3]),
            Dense::new(vec![0.0; 4], vec![0.0; 2]),
            Dense::new(vec![0.0; 4], vec![0.0; 2]),
        ]);
        assert!(matches!(bad, Err(CoreError::InvalidArgument(m)) if m.starts_with("layer 1")));
        let odd = QuadraticHead::new([
            Dense::new(vec![0.0], vec![0.0]),
            Dense::new(vec![0.0], vec![0.0]),
            Dense::new(vec![0.0; 3], vec![0.0; 3]),
        ]);
        assert!(odd.is_err());
        let head = tiny(0.0, 0.0);
        assert!(head.closed_form(&[1.0, 2.0], &[0.0], &[1.0]).is_err());
        assert!(head.closed_form(&[1.0], &[0.0], &[0.0]).is_err());
        assert!(head.closed_form(&[f32::NAN], &[0.0], &[1.0]).is_err());
    }
}
