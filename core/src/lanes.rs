//! Per-dimension state of a session and the per-dimension steps of the law (the hot loops).
//!
//! The state is the columns of one D x 10 nalgebra matrix: one allocation per session (instead of one per
//! vector) keeps an idle D = 6 session under its 1 KiB budget, and the column-major layout
//! keeps every per-dimension vector contiguous, so each step is one fused loop over plain slices that
//! the compiler vectorizes, without bounds checks.

use nalgebra::DMatrix;

use crate::config::{lane, SessionConfig};
use crate::sine::{sin_reduced, REDUCTION_LIMIT};

const AMPLITUDE: usize = 0;
const FREQUENCY: usize = 1;
const RATE: usize = 2;
const LOW: usize = 3;
const HIGH: usize = 4;
const LEARNING_RATE: usize = 5;
const SHIFT: usize = 6;
const SINE: usize = 7;
const ACTION: usize = 8;
const SCALE: usize = 9;
const COLUMNS: usize = 10;

// `split_mut` hands out the mutable columns as one contiguous tail in this order.
const _: () =
    assert!(SHIFT + 1 == SINE && SINE + 1 == ACTION && ACTION + 1 == SCALE && SCALE + 1 == COLUMNS);
// `set_rate` splits the matrix between the two rate columns.
const _: () = assert!(RATE < LEARNING_RATE);

/// Every column at once, borrowed from [`Lanes`].
struct Columns<'a> {
    /// K, broadcast.
    amplitude: &'a [f64],
    /// w, broadcast.
    frequency: &'a [f64],
    /// alpha_e = alpha * gamma_a^e for the current episode.
    rate: &'a [f64],
    /// Lower bound, saturated at `-f64::MAX` so clipping always yields a finite value.
    low: &'a [f64],
    /// Upper bound, saturated at `f64::MAX`.
    high: &'a [f64],
    /// v.
    shift: &'a mut [f64],
    /// `sin(w * tau)` of the last probe, reused by its report.
    sine: &'a mut [f64],
    /// The sampled action `a_t` of the last probe.
    action: &'a mut [f64],
    /// The action scale sigma of the last probe (1 when it sent none).
    scale: &'a mut [f64],
}

/// How a report turns its response into a step of v (section 1b; the defaults are section 1's law).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct StepRule {
    /// Scale the step by sigma (`normalize_response`): `alpha_e sigma s g` instead of `alpha_e s h`.
    pub scaled: bool,
    /// `1 - lambda`: the share of v that survives the leak.
    pub keep: f64,
    /// L, or +inf.
    pub limit: f64,
    /// kappa, or +inf: each element of v stays within `kappa * sigma`.
    pub trust: f64,
}

impl StepRule {
    /// `min(L, kappa sigma)`: L, kappa and sigma are > 0, so the bound is >= 0 and never NaN, and
    /// `clamp(-bound, bound)` cannot panic.
    #[inline(always)]
    fn bound(self, sigma: f64) -> f64 {
        self.limit.min(self.trust * sigma)
    }
}

/// A per-dimension field of [`SessionConfig`]; the lanes hold it broadcast to D values, so the session
/// need not keep the config's own vectors.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Field {
    Amplitude,
    Frequency,
    LearningRate,
    ActionLow,
    ActionHigh,
}

// Per-field tables (a session's `shapes`) are indexed by `field as usize` in the order of `ALL`.
const _: () = {
    let mut i = 0;
    while i < Field::ALL.len() {
        assert!(Field::ALL[i] as usize == i);
        i += 1;
    }
};

impl Field {
    pub const ALL: [Field; 5] = [
        Field::Amplitude,
        Field::Frequency,
        Field::LearningRate,
        Field::ActionLow,
        Field::ActionHigh,
    ];

    /// The field's values as given in `config` (empty, length 1 or length D).
    pub fn of(self, config: &SessionConfig) -> &[f64] {
        match self {
            Field::Amplitude => &config.amplitude,
            Field::Frequency => &config.frequency,
            Field::LearningRate => &config.learning_rate,
            Field::ActionLow => &config.action_low,
            Field::ActionHigh => &config.action_high,
        }
    }

    fn column(self) -> usize {
        match self {
            Field::Amplitude => AMPLITUDE,
            Field::Frequency => FREQUENCY,
            Field::LearningRate => LEARNING_RATE,
            Field::ActionLow => LOW,
            Field::ActionHigh => HIGH,
        }
    }

    /// The lane value of an unset (empty) field: unbounded sides saturate so clipping stays finite.
    fn unset(self) -> f64 {
        match self {
            Field::ActionLow => -f64::MAX,
            Field::ActionHigh => f64::MAX,
            Field::Amplitude | Field::Frequency | Field::LearningRate => 0.0,
        }
    }
}

/// The per-dimension values a probe holds for the report that answers it (see [`Lanes::held`]).
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Held {
    pub action: Vec<f64>,
    pub sine: Vec<f64>,
    pub scale: Vec<f64>,
}

#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Lanes {
    columns: DMatrix<f64>,
    /// Largest w: tells in O(1) whether every `w * tau` is inside the fast sine's range.
    max_frequency: f64,
}

impl Lanes {
    /// Resolves (broadcasts) the config's per-dimension fields; v, s and a start at 0. The config must be valid.
    pub fn new(config: &SessionConfig) -> Self {
        let dim = config.action_dim as usize;
        let mut columns = DMatrix::zeros(dim, COLUMNS);
        for field in Field::ALL {
            let values = field.of(config);
            for (i, x) in columns.column_mut(field.column()).iter_mut().enumerate() {
                // A valid config's values are finite, so the lanes hold them exactly.
                *x = lane(values, i, field.unset());
            }
        }
        let max_frequency = columns.column(FREQUENCY).max();
        columns.column_mut(SCALE).fill(1.0);
        let mut lanes = Self {
            columns,
            max_frequency,
        };
        lanes.set_rate(1.0);
        lanes
    }

    /// The D values of a config field (broadcast; unset bounds read as `-f64::MAX` / `f64::MAX`).
    pub fn field(&self, field: Field) -> &[f64] {
        self.column(field.column())
    }

    pub fn dim(&self) -> usize {
        self.columns.nrows()
    }

    /// Sets alpha_e = alpha * factor for every dimension (once per episode, not per step).
    pub fn set_rate(&mut self, factor: f64) {
        let dim = self.dim();
        let all = self.columns.as_mut_slice();
        let (head, tail) = all.split_at_mut(LEARNING_RATE * dim);
        let rate = head
            .get_mut(RATE * dim..(RATE + 1) * dim)
            .unwrap_or_default();
        for (x, &alpha) in rate.iter_mut().zip(tail.iter()) {
            *x = alpha * factor;
        }
    }

    pub fn reset_shift(&mut self) {
        self.columns.column_mut(SHIFT).fill(0.0);
    }

    /// Sets v to `shift` (D values).
    pub fn set_shift(&mut self, shift: &[f64]) {
        for (v, &x) in self.split_mut().shift.iter_mut().zip(shift) {
            *v = x;
        }
    }

    pub fn shift(&self) -> &[f64] {
        self.column(SHIFT)
    }

    /// What the last probe held for its report: the sampled action `a_t`, `sin(w tau)` and sigma.
    pub fn held(&self) -> Held {
        Held {
            action: self.column(ACTION).to_vec(),
            sine: self.column(SINE).to_vec(),
            scale: self.column(SCALE).to_vec(),
        }
    }

    /// Takes back what [`held`](Self::held) gave, and the shift v (D values each).
    pub fn set_held(&mut self, shift: &[f64], held: &Held) {
        let c = self.split_mut();
        let columns = [
            (c.shift, shift),
            (c.action, &held.action[..]),
            (c.sine, &held.sine[..]),
            (c.scale, &held.scale[..]),
        ];
        for (column, values) in columns {
            for (x, &value) in column.iter_mut().zip(values) {
                *x = value;
            }
        }
    }

    /// Holds the action scale sigma for the coming report: 1 for an empty `scale`, else broadcast.
    pub fn set_scale(&mut self, scale: &[f64]) {
        let held = self.split_mut().scale;
        match scale {
            [] => held.fill(1.0),
            [sigma] => held.fill(*sigma),
            _ => {
                for (x, &sigma) in held.iter_mut().zip(scale) {
                    *x = sigma;
                }
            }
        }
    }

    /// Holds `a`, caches `s = sin(w * tau)` and appends `clip(a + (v + K s), lo, hi)` per dimension.
    pub fn probe(&mut self, action: &[f64], tau: f64, out: &mut Vec<f64>) {
        // One range check per probe keeps the per-lane loop branch-free (and so vectorized).
        if tau * self.max_frequency <= REDUCTION_LIMIT {
            self.probe_with(action, tau, out, sin_reduced);
        } else {
            self.probe_with(action, tau, out, f64::sin);
        }
    }

    #[inline(always)]
    fn probe_with(
        &mut self,
        action: &[f64],
        tau: f64,
        out: &mut Vec<f64>,
        sin: impl Fn(f64) -> f64,
    ) {
        let fresh = append_zeros(out, action.len());
        let c = self.split_mut();
        let held = c.action.iter_mut().zip(c.sine.iter_mut());
        let params = c.frequency.iter().zip(c.amplitude).zip(c.shift.iter());
        let bounds = c.low.iter().zip(c.high);
        let dims = fresh
            .iter_mut()
            .zip(action)
            .zip(held)
            .zip(params)
            .zip(bounds);
        for ((((probe, &a), (held, sine)), ((&w, &k), &v)), (&lo, &hi)) in dims {
            // Exactly `w_i * (t * dt)`, the expression every client reproduces.
            let s = sin(w * tau);
            *held = a;
            *sine = s;
            *probe = clip(a + (v + k * s), lo, hi);
        }
    }

    /// Holds `a` and appends `clip(a, lo, hi)`: the pass-through probe.
    pub fn hold(&mut self, action: &[f64], out: &mut Vec<f64>) {
        let c = self.split_mut();
        for (held, &a) in c.action.iter_mut().zip(action) {
            *held = a;
        }
        push_clipped(out, action.iter().copied(), c.low, c.high);
    }

    /// `v <- clamp((1 - lambda) v + step, -bound, bound)` with `step = alpha_e s x` (or `alpha_e sigma s x`
    /// when `rule.scaled`) and `bound = min(L, kappa sigma)`, unless an element would be non-finite (then v
    /// is kept), and appends the improved action `clip(a + v, lo, hi)`. Returns whether v was updated.
    pub fn update(&mut self, x: f64, rule: StepRule, out: &mut Vec<f64>) -> bool {
        // Two instances, so the per-lane loop has no branch on the rule.
        if rule.scaled {
            self.update_with::<true>(x, rule, out)
        } else {
            self.update_with::<false>(x, rule, out)
        }
    }

    #[inline(always)]
    fn update_with<const SCALED: bool>(
        &mut self,
        x: f64,
        rule: StepRule,
        out: &mut Vec<f64>,
    ) -> bool {
        let fresh = append_zeros(out, self.dim());
        let c = self.split_mut();
        // The candidates go to `fresh` first: v must stay untouched unless all of them are finite.
        let mut finite = true;
        let steps = c
            .shift
            .iter()
            .zip(c.rate)
            .zip(c.sine.iter())
            .zip(c.scale.iter());
        for (candidate, (((&v, &rate), &s), &sigma)) in fresh.iter_mut().zip(steps) {
            let gain = if SCALED { rate * sigma } else { rate };
            // With section 1b unset (keep = 1, trust = +inf) this is `clamp(v + alpha_e s h, -L, L)`
            // exactly.
            let bound = rule.bound(sigma);
            *candidate = (rule.keep * v + gain * s * x).clamp(-bound, bound);
            finite &= candidate.is_finite();
        }
        let dims = c
            .shift
            .iter_mut()
            .zip(c.scale.iter())
            .zip(c.action.iter())
            .zip(c.low.iter().zip(c.high));
        for (slot, (((v, &sigma), &a), (&lo, &hi))) in fresh.iter_mut().zip(dims) {
            *v = if finite {
                *slot
            } else {
                // A skipped update keeps v, but inside this report's bound: |v| <= kappa sigma holds
                // after every report, even when sigma shrank. (A no-op for the section 1 law.)
                v.clamp(-rule.bound(sigma), rule.bound(sigma))
            };
            *slot = clip(a + *v, lo, hi);
        }
        finite
    }

    /// Keeps v inside this report's bound without a step, and appends the improved action: the report
    /// whose normalization failed (see `Session::report`).
    pub fn skip_update(&mut self, rule: StepRule, out: &mut Vec<f64>) {
        self.clamp_shift(rule);
        self.push_action(false, out);
    }

    /// Clamps v into `min(L, kappa sigma)` with the held sigma (a no-op for the section 1 law).
    pub fn clamp_shift(&mut self, rule: StepRule) {
        let c = self.split_mut();
        for (v, &sigma) in c.shift.iter_mut().zip(c.scale.iter()) {
            *v = v.clamp(-rule.bound(sigma), rule.bound(sigma));
        }
    }

    /// Appends `clip(a + clamp(shift, -bound, bound), lo, hi)` with `bound = min(L, kappa sigma)` of
    /// `scale` (empty = 1, one value = broadcast): what [`set_scale`](Self::set_scale),
    /// [`clamp_shift`](Self::clamp_shift) and [`push_action`](Self::push_action) give for a held
    /// shift, computed without holding anything.
    pub fn applied_with(
        &self,
        shift: &[f64],
        action: &[f64],
        scale: &[f64],
        rule: StepRule,
        out: &mut Vec<f64>,
    ) {
        let sigma = |i: usize| match scale {
            [] => 1.0,
            [sigma] => *sigma,
            _ => scale.get(i).copied().unwrap_or(1.0),
        };
        let values = action.iter().zip(shift).enumerate().map(|(i, (&a, &v))| {
            let bound = rule.bound(sigma(i));
            a + v.clamp(-bound, bound)
        });
        push_clipped(out, values, self.column(LOW), self.column(HIGH));
    }

    /// Appends the improved action for the held `a` and current v: `clip(a + v)`, or `clip(a)` when
    /// `pass_through`.
    pub fn push_action(&self, pass_through: bool, out: &mut Vec<f64>) {
        let (action, shift) = (self.column(ACTION), self.column(SHIFT));
        let values = action
            .iter()
            .zip(shift)
            .map(|(&a, &v)| if pass_through { a } else { a + v });
        push_clipped(out, values, self.column(LOW), self.column(HIGH));
    }

    fn column(&self, column: usize) -> &[f64] {
        let dim = self.dim();
        self.columns
            .as_slice()
            .get(column * dim..(column + 1) * dim)
            .unwrap_or_default()
    }

    #[inline(always)]
    fn split_mut(&mut self) -> Columns<'_> {
        let dim = self.dim();
        let all = self.columns.as_mut_slice();
        let (fixed, rest) = all.split_at_mut(SHIFT * dim);
        let (shift, rest) = rest.split_at_mut(dim);
        let (sine, rest) = rest.split_at_mut(dim);
        let (action, scale) = rest.split_at_mut(dim);
        let (amplitude, fixed) = fixed.split_at(dim);
        let (frequency, fixed) = fixed.split_at(dim);
        let (rate, fixed) = fixed.split_at(dim);
        let (low, fixed) = fixed.split_at(dim);
        let (high, _learning_rate) = fixed.split_at(dim);
        Columns {
            amplitude,
            frequency,
            rate,
            low,
            high,
            shift,
            sine,
            action,
            scale,
        }
    }
}

/// Grows `out` by `n` zeros and returns them to be overwritten: writing through a slice, unlike `push`,
/// has no per-element capacity check, so the loops that fill it vectorize.
fn append_zeros(out: &mut Vec<f64>, n: usize) -> &mut [f64] {
    let start = out.len();
    out.resize(start + n, 0.0);
    out.get_mut(start..).unwrap_or_default()
}

fn push_clipped(out: &mut Vec<f64>, values: impl Iterator<Item = f64>, low: &[f64], high: &[f64]) {
    out.extend(
        values
            .zip(low.iter().zip(high))
            .map(|(x, (&lo, &hi))| clip(x, lo, hi)),
    );
}

/// `x` clipped to `[lo, hi]`; the bounds are finite (unbounded sides saturate at `f64::MAX`), so an
/// overflowed `a + v` still yields a finite value.
#[inline(always)]
fn clip(x: f64, lo: f64, hi: f64) -> f64 {
    // Plain comparisons compile to maxsd/minsd; f64::max/min would add NaN handling that x never needs.
    let x = if x < lo { lo } else { x };
    if x > hi {
        hi
    } else {
        x
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config() -> SessionConfig {
        SessionConfig {
            action_low: vec![f64::MIN, -1.0, -2.0],
            ..SessionConfig::new(3, 0.01, vec![0.5], vec![10.0, 20.0, 30.0], vec![2.0])
        }
    }

    #[test]
    fn resolves_broadcasts_and_saturates_unbounded_sides() {
        let mut lanes = Lanes::new(&config());
        lanes.set_rate(0.5);
        assert_eq!(lanes.dim(), 3);
        assert_eq!(lanes.max_frequency, 30.0);
        assert_eq!(lanes.column(LOW), &[-f64::MAX, -1.0, -2.0]);
        assert_eq!(lanes.column(HIGH), &[f64::MAX; 3]);
        assert_eq!(lanes.field(Field::LearningRate), &[2.0; 3]);
        let c = lanes.split_mut();
        assert_eq!(c.amplitude, &[0.5; 3]);
        assert_eq!(c.frequency, &[10.0, 20.0, 30.0]);
        assert_eq!(c.rate, &[1.0; 3]);
        assert_eq!(c.shift, &[0.0; 3]);
        assert_eq!(c.scale, &[1.0; 3]);
        assert_eq!((c.sine.len(), c.action.len()), (3, 3));
    }

    #[test]
    fn set_scale_broadcasts_and_resets_to_one() {
        let mut lanes = Lanes::new(&config());
        lanes.set_scale(&[0.5]);
        assert_eq!(lanes.column(SCALE), &[0.5; 3]);
        lanes.set_scale(&[1.0, 2.0, 3.0]);
        assert_eq!(lanes.column(SCALE), &[1.0, 2.0, 3.0]);
        lanes.set_scale(&[]);
        assert_eq!(lanes.column(SCALE), &[1.0; 3]);
    }

    #[test]
    fn probe_falls_back_to_libm_far_beyond_the_reduction_range() {
        let mut lanes = Lanes::new(&config());
        for tau in [0.37, 3.3e4, 3.4e4, 1e9] {
            let mut out = Vec::new();
            lanes.probe(&[0.0; 3], tau, &mut out);
            let sine = lanes.split_mut().sine.to_vec();
            for (s, w) in sine.iter().zip([10.0, 20.0, 30.0]) {
                let exact = (w * tau).sin();
                assert!(
                    (s - exact).abs() <= f64::EPSILON,
                    "sin({w} * {tau}) = {exact}, got {s}"
                );
                if w * tau > REDUCTION_LIMIT {
                    assert_eq!(*s, exact, "libm itself beyond the limit");
                }
            }
        }
    }

    #[test]
    fn skipped_update_keeps_v_and_still_returns_the_action() {
        let mut lanes = Lanes::new(&config());
        lanes.probe(&[1.0, 0.5, 0.25], 0.1, &mut Vec::new());
        let mut out = vec![7.0];
        let rule = StepRule {
            scaled: false,
            keep: 1.0,
            limit: f64::INFINITY,
            trust: f64::INFINITY,
        };
        assert!(!lanes.update(f64::INFINITY, rule, &mut out));
        assert_eq!(lanes.shift(), &[0.0; 3]);
        assert_eq!(out, vec![7.0, 1.0, 0.5, 0.25]);
        assert!(lanes.update(1.0, rule, &mut out));
        assert_ne!(lanes.shift(), &[0.0; 3]);
    }

    #[test]
    fn trust_region_bounds_each_lane_by_its_scale() {
        let mut lanes = Lanes::new(&config());
        lanes.probe(&[0.0; 3], 0.1, &mut Vec::new());
        lanes.set_scale(&[0.1, 1.0, 10.0]);
        let rule = StepRule {
            scaled: true,
            keep: 1.0,
            limit: 5.0,
            trust: 2.0,
        };
        // A huge response pushes every lane to its bound min(L, kappa sigma).
        assert!(lanes.update(1e300, rule, &mut Vec::new()));
        let bounds = [0.2, 2.0, 5.0];
        for (v, bound) in lanes.shift().iter().zip(bounds) {
            assert_eq!(v.abs(), bound);
        }
    }
}
