//! [`SessionConfig`]: the per-session parameters of the update law and the rules they must obey.

use std::f64::consts::PI;

use crate::CoreError;

/// Largest accepted action dimension.
pub const MAX_ACTION_DIM: u32 = 4096;

/// Parameters of one ESA session; mirrors proto `esa.v1.SessionConfig` field for field.
///
/// Per-dimension fields are kept as sent: length 1 broadcasts to every dimension, length D gives one
/// value per dimension. [`validate`](Self::validate) enforces CONTRACT.md section 1.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SessionConfig {
    /// D, the action dimension (1 ..= 4096).
    pub action_dim: u32,
    /// Seconds per environment step; finite, > 0.
    pub dt: f64,
    /// Perturbation amplitude K; finite, >= 0.
    pub amplitude: Vec<f64>,
    /// Perturbation frequency w in rad/s; finite, > 0, and `w * dt < pi`.
    pub frequency: Vec<f64>,
    /// Learning rate alpha; finite, >= 0. The session maximizes Q.
    pub learning_rate: Vec<f64>,
    /// Washout cutoff w_h in rad/s; finite, > 0; `None` means `min(w) / 10`.
    pub highpass_cutoff: Option<f64>,
    /// When true the washout is the identity.
    pub disable_highpass: bool,
    /// Lower action bound; finite; empty = unbounded. The contract rejects infinities
    /// anywhere in a request, so a client with a partly unbounded space sends `f64::MIN`.
    pub action_low: Vec<f64>,
    /// Upper action bound; finite; empty = unbounded (`f64::MAX` per dimension).
    pub action_high: Vec<f64>,
    /// Shift limit L: every element of v stays in `[-L, L]`; finite, > 0; `None` = no clamp.
    pub shift_limit: Option<f64>,
    /// Per-episode learning-rate decay gamma_a in (0, 1]; `None` = 1.
    pub lr_decay: Option<f64>,
    /// E: once `episodes_completed >= E > 0` the session passes actions through; 0 = unlimited.
    pub max_episodes: u64,
    /// Section 1b: divide the filtered response by its running RMS, clip it to `response_clip` and scale
    /// the step by the probe's action scale sigma, so the law does not depend on Q's scale or offset.
    pub normalize_response: bool,
    /// EMA rate rho of the response's running mean square, in (0, 1]; `None` = 0.05.
    pub response_rms_rate: Option<f64>,
    /// Clip c of the normalized response; finite, > 0; `None` = 3.
    pub response_clip: Option<f64>,
    /// Leak lambda in [0, 1): `v <- (1 - lambda) v + step`; `None` = 0.
    pub shift_leak: Option<f64>,
    /// Trust region kappa: `|v| <= kappa * sigma` per dimension; finite, > 0; `None` = no bound.
    pub trust_region: Option<f64>,
}

/// Default EMA rate of the response's running mean square (`response_rms_rate` unset).
pub const DEFAULT_RESPONSE_RMS_RATE: f64 = 0.05;
/// Default clip of the normalized response (`response_clip` unset).
pub const DEFAULT_RESPONSE_CLIP: f64 = 3.0;

impl SessionConfig {
    /// A config with the required fields set and every optional one at its default.
    pub fn new(
        action_dim: u32,
        dt: f64,
        amplitude: Vec<f64>,
        frequency: Vec<f64>,
        learning_rate: Vec<f64>,
    ) -> Self {
        Self {
            action_dim,
            dt,
            amplitude,
            frequency,
            learning_rate,
            highpass_cutoff: None,
            disable_highpass: false,
            action_low: Vec::new(),
            action_high: Vec::new(),
            shift_limit: None,
            lr_decay: None,
            max_episodes: 0,
            normalize_response: false,
            response_rms_rate: None,
            response_clip: None,
            shift_leak: None,
            trust_region: None,
        }
    }

    /// Checks every rule of CONTRACT.md sections 1 and 1b.
    ///
    /// The error message starts with the offending field (and index), then says what was expected and
    /// what was got, e.g. `frequency[1]: expected w * dt < pi (Nyquist), got 400 * 0.01 = 4`.
    pub fn validate(&self) -> Result<(), CoreError> {
        if !(1..=MAX_ACTION_DIM).contains(&self.action_dim) {
            return Err(invalid(format!(
                "action_dim: expected 1 <= action_dim <= {MAX_ACTION_DIM}, got {}",
                self.action_dim
            )));
        }
        let dim = self.action_dim as usize;
        if !(self.dt.is_finite() && self.dt > 0.0) {
            return Err(invalid(format!(
                "dt: expected a finite number > 0, got {}",
                self.dt
            )));
        }
        check_each("amplitude", &self.amplitude, dim, |k| {
            expect(k.is_finite() && k >= 0.0, "a finite number >= 0", k)
        })?;
        check_each("frequency", &self.frequency, dim, |w| {
            expect(w.is_finite() && w > 0.0, "a finite number > 0", w)?;
            if w * self.dt >= PI {
                return Err(format!(
                    "expected w * dt < pi (Nyquist), got {w} * {} = {}",
                    self.dt,
                    w * self.dt
                ));
            }
            Ok(())
        })?;
        check_each("learning_rate", &self.learning_rate, dim, |a| {
            expect(a.is_finite() && a >= 0.0, "a finite number >= 0", a)
        })?;
        check_positive("highpass_cutoff", self.highpass_cutoff)?;
        self.check_bounds(dim)?;
        check_positive("shift_limit", self.shift_limit)?;
        check_range("lr_decay", self.lr_decay, "(0, 1]", |g| g > 0.0 && g <= 1.0)?;
        // Section 1b. Like `highpass_cutoff`, each is validated even where it has no effect (the
        // normalization fields without `normalize_response`): a bad value is a client bug either way.
        check_range("response_rms_rate", self.response_rms_rate, "(0, 1]", |r| {
            r > 0.0 && r <= 1.0
        })?;
        check_positive("response_clip", self.response_clip)?;
        check_range("shift_leak", self.shift_leak, "[0, 1)", |l| {
            (0.0..1.0).contains(&l)
        })?;
        check_positive("trust_region", self.trust_region)?;
        Ok(())
    }

    fn check_bounds(&self, dim: usize) -> Result<(), CoreError> {
        if !self.action_low.is_empty() {
            check_each("action_low", &self.action_low, dim, |lo| {
                expect(lo.is_finite(), "a finite number", lo)
            })?;
        }
        if !self.action_high.is_empty() {
            check_each("action_high", &self.action_high, dim, |hi| {
                expect(hi.is_finite(), "a finite number", hi)
            })?;
        }
        if self.action_low.is_empty() || self.action_high.is_empty() {
            return Ok(());
        }
        for i in 0..dim {
            let (lo, hi) = (
                lane(&self.action_low, i, 0.0),
                lane(&self.action_high, i, 0.0),
            );
            if lo >= hi {
                return Err(invalid(format!(
                    "action_low[{i}]: expected action_low < action_high, got {lo} >= {hi}"
                )));
            }
        }
        Ok(())
    }

    /// The washout cutoff in force: the configured one, else `min(w) / 10`.
    pub fn effective_highpass_cutoff(&self) -> f64 {
        self.highpass_cutoff
            .unwrap_or_else(|| self.frequency.iter().copied().fold(f64::INFINITY, f64::min) / 10.0)
    }
}

/// Value of a per-dimension field at dimension `i`: the broadcast value for length 1, else element `i`;
/// `default` for an empty (unset) field.
pub(crate) fn lane(values: &[f64], i: usize, default: f64) -> f64 {
    match values {
        [] => default,
        [only] => *only,
        _ => values.get(i).copied().unwrap_or(default),
    }
}

/// `Ok` when `ok`, else the "expected ..., got ..." half of a message (the caller adds the field).
fn expect(ok: bool, expected: &str, got: f64) -> Result<(), String> {
    if ok {
        Ok(())
    } else {
        Err(format!("expected {expected}, got {got}"))
    }
}

fn invalid(message: String) -> CoreError {
    CoreError::InvalidConfig(message)
}

/// Checks a per-dimension field's length (1 or D, never empty) and each of its elements.
fn check_each(
    field: &str,
    values: &[f64],
    dim: usize,
    rule: impl Fn(f64) -> Result<(), String>,
) -> Result<(), CoreError> {
    if values.len() != 1 && values.len() != dim {
        return Err(invalid(format!(
            "{field}: expected length 1 (broadcast) or action_dim = {dim}, got {}",
            values.len()
        )));
    }
    for (i, &x) in values.iter().enumerate() {
        rule(x).map_err(|why| invalid(format!("{field}[{i}]: {why}")))?;
    }
    Ok(())
}

/// Checks an optional scalar against an interval (`rule` must be false for NaN).
fn check_range(
    field: &str,
    value: Option<f64>,
    interval: &str,
    rule: impl Fn(f64) -> bool,
) -> Result<(), CoreError> {
    match value {
        Some(x) if !rule(x) => Err(invalid(format!(
            "{field}: expected a number in {interval} (or unset), got {x}"
        ))),
        _ => Ok(()),
    }
}

fn check_positive(field: &str, value: Option<f64>) -> Result<(), CoreError> {
    match value {
        Some(x) if !(x.is_finite() && x > 0.0) => Err(invalid(format!(
            "{field}: expected a finite number > 0 (or unset), got {x}"
        ))),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn valid() -> SessionConfig {
        SessionConfig::new(2, 0.01, vec![0.2], vec![60.0, 75.0], vec![0.25])
    }

    /// Asserts the config is rejected with a message that starts with `field`.
    fn rejects(config: SessionConfig, field: &str) {
        match config.validate() {
            Err(CoreError::InvalidConfig(msg)) => {
                assert!(
                    msg.starts_with(field),
                    "message {msg:?} should start with {field:?}"
                )
            }
            other => panic!("expected InvalidConfig naming {field}, got {other:?}"),
        }
    }

    #[test]
    fn valid_config_passes() {
        assert_eq!(valid().validate(), Ok(()));
        let full = SessionConfig {
            highpass_cutoff: Some(3.0),
            disable_highpass: true,
            action_low: vec![-1.0, -2.0],
            action_high: vec![1.0],
            shift_limit: Some(0.5),
            lr_decay: Some(1.0),
            max_episodes: 3,
            normalize_response: true,
            response_rms_rate: Some(1.0),
            response_clip: Some(2.5),
            shift_leak: Some(0.0),
            trust_region: Some(1.0),
            ..valid()
        };
        assert_eq!(full.validate(), Ok(()));
    }

    #[test]
    fn action_dim_must_be_in_range() {
        rejects(
            SessionConfig {
                action_dim: 0,
                ..valid()
            },
            "action_dim:",
        );
        rejects(
            SessionConfig {
                action_dim: MAX_ACTION_DIM + 1,
                ..valid()
            },
            "action_dim:",
        );
        let widest = SessionConfig {
            action_dim: MAX_ACTION_DIM,
            frequency: vec![60.0],
            ..valid()
        };
        assert_eq!(widest.validate(), Ok(()));
    }

    #[test]
    fn dt_must_be_finite_positive() {
        for dt in [0.0, -0.01, f64::NAN, f64::INFINITY] {
            rejects(SessionConfig { dt, ..valid() }, "dt:");
        }
    }

    #[test]
    fn amplitude_rules() {
        rejects(
            SessionConfig {
                amplitude: vec![],
                ..valid()
            },
            "amplitude:",
        );
        rejects(
            SessionConfig {
                amplitude: vec![0.1; 3],
                ..valid()
            },
            "amplitude:",
        );
        for bad in [-0.1, f64::NAN, f64::INFINITY] {
            rejects(
                SessionConfig {
                    amplitude: vec![0.1, bad],
                    ..valid()
                },
                "amplitude[1]:",
            );
        }
        assert_eq!(
            SessionConfig {
                amplitude: vec![0.0],
                ..valid()
            }
            .validate(),
            Ok(())
        );
    }

    #[test]
    fn frequency_rules() {
        rejects(
            SessionConfig {
                frequency: vec![],
                ..valid()
            },
            "frequency:",
        );
        rejects(
            SessionConfig {
                frequency: vec![1.0; 3],
                ..valid()
            },
            "frequency:",
        );
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            rejects(
                SessionConfig {
                    frequency: vec![bad],
                    ..valid()
                },
                "frequency[0]:",
            );
        }
        let nyquist = SessionConfig {
            frequency: vec![60.0, 400.0],
            ..valid()
        };
        assert_eq!(
            nyquist.validate(),
            Err(CoreError::InvalidConfig(
                "frequency[1]: expected w * dt < pi (Nyquist), got 400 * 0.01 = 4".into()
            ))
        );
        // w * dt == pi exactly is already aliased.
        rejects(
            SessionConfig {
                dt: 1.0,
                frequency: vec![PI],
                ..valid()
            },
            "frequency[0]:",
        );
    }

    #[test]
    fn learning_rate_rules() {
        rejects(
            SessionConfig {
                learning_rate: vec![],
                ..valid()
            },
            "learning_rate:",
        );
        rejects(
            SessionConfig {
                learning_rate: vec![0.1; 5],
                ..valid()
            },
            "learning_rate:",
        );
        for bad in [-1e-9, f64::NAN, f64::NEG_INFINITY] {
            rejects(
                SessionConfig {
                    learning_rate: vec![bad, 0.1],
                    ..valid()
                },
                "learning_rate[0]:",
            );
        }
        assert_eq!(
            SessionConfig {
                learning_rate: vec![0.0],
                ..valid()
            }
            .validate(),
            Ok(())
        );
    }

    #[test]
    fn highpass_cutoff_rules() {
        for bad in [0.0, -6.0, f64::NAN, f64::INFINITY] {
            rejects(
                SessionConfig {
                    highpass_cutoff: Some(bad),
                    ..valid()
                },
                "highpass_cutoff:",
            );
        }
        // Validated even when the filter is disabled: a bad value is a client bug either way.
        rejects(
            SessionConfig {
                highpass_cutoff: Some(-1.0),
                disable_highpass: true,
                ..valid()
            },
            "highpass_cutoff:",
        );
    }

    #[test]
    fn default_highpass_cutoff_is_tenth_of_lowest_frequency() {
        assert_eq!(valid().effective_highpass_cutoff(), 6.0);
        let set = SessionConfig {
            highpass_cutoff: Some(2.5),
            ..valid()
        };
        assert_eq!(set.effective_highpass_cutoff(), 2.5);
    }

    #[test]
    fn bound_rules() {
        rejects(
            SessionConfig {
                action_low: vec![0.0; 3],
                ..valid()
            },
            "action_low:",
        );
        rejects(
            SessionConfig {
                action_high: vec![0.0; 3],
                ..valid()
            },
            "action_high:",
        );
        rejects(
            SessionConfig {
                action_low: vec![f64::NAN],
                ..valid()
            },
            "action_low[0]:",
        );
        rejects(
            SessionConfig {
                action_low: vec![0.0, f64::INFINITY],
                ..valid()
            },
            "action_low[1]:",
        );
        rejects(
            SessionConfig {
                action_high: vec![f64::NAN],
                ..valid()
            },
            "action_high[0]:",
        );
        rejects(
            SessionConfig {
                action_high: vec![f64::NEG_INFINITY],
                ..valid()
            },
            "action_high[0]:",
        );
        rejects(
            SessionConfig {
                action_low: vec![-1.0, 1.0],
                action_high: vec![1.0],
                ..valid()
            },
            "action_low[1]:",
        );
        rejects(
            SessionConfig {
                action_low: vec![0.5],
                action_high: vec![1.0, 0.2],
                ..valid()
            },
            "action_low[1]:",
        );
        rejects(
            SessionConfig {
                action_low: vec![f64::NEG_INFINITY, 0.0],
                ..valid()
            },
            "action_low[0]:",
        );
        rejects(
            SessionConfig {
                action_high: vec![f64::INFINITY],
                ..valid()
            },
            "action_high[0]:",
        );
        let one_sided = SessionConfig {
            action_low: vec![f64::MIN, 0.0],
            ..valid()
        };
        assert_eq!(one_sided.validate(), Ok(()));
    }

    #[test]
    fn shift_limit_rules() {
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            rejects(
                SessionConfig {
                    shift_limit: Some(bad),
                    ..valid()
                },
                "shift_limit:",
            );
        }
    }

    #[test]
    fn lr_decay_rules() {
        for bad in [0.0, -0.5, 1.0 + 1e-12, f64::NAN, f64::INFINITY] {
            rejects(
                SessionConfig {
                    lr_decay: Some(bad),
                    ..valid()
                },
                "lr_decay:",
            );
        }
        assert_eq!(
            SessionConfig {
                lr_decay: Some(1e-300),
                ..valid()
            }
            .validate(),
            Ok(())
        );
    }

    #[test]
    fn response_rms_rate_rules() {
        for bad in [0.0, -0.1, 1.0 + 1e-12, f64::NAN, f64::INFINITY] {
            rejects(
                SessionConfig {
                    response_rms_rate: Some(bad),
                    ..valid()
                },
                "response_rms_rate:",
            );
        }
        for good in [1e-9, 0.05, 1.0] {
            let config = SessionConfig {
                response_rms_rate: Some(good),
                ..valid()
            };
            assert_eq!(config.validate(), Ok(()));
        }
    }

    #[test]
    fn response_clip_and_trust_region_rules() {
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            rejects(
                SessionConfig {
                    response_clip: Some(bad),
                    ..valid()
                },
                "response_clip:",
            );
            rejects(
                SessionConfig {
                    trust_region: Some(bad),
                    ..valid()
                },
                "trust_region:",
            );
        }
    }

    #[test]
    fn shift_leak_rules() {
        for bad in [-1e-12, 1.0, 2.0, f64::NAN, f64::INFINITY] {
            rejects(
                SessionConfig {
                    shift_leak: Some(bad),
                    ..valid()
                },
                "shift_leak:",
            );
        }
        for good in [0.0, 0.005, 0.999_999] {
            let config = SessionConfig {
                shift_leak: Some(good),
                ..valid()
            };
            assert_eq!(config.validate(), Ok(()));
        }
    }

    #[test]
    fn normalization_fields_are_checked_without_normalize_response() {
        rejects(
            SessionConfig {
                normalize_response: false,
                response_clip: Some(-3.0),
                ..valid()
            },
            "response_clip:",
        );
    }

    #[test]
    fn lane_broadcasts() {
        assert_eq!(lane(&[], 3, -1.0), -1.0);
        assert_eq!(lane(&[7.0], 3, -1.0), 7.0);
        assert_eq!(lane(&[1.0, 2.0, 3.0], 2, -1.0), 3.0);
    }
}
