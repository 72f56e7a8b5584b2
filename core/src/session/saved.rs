//! [`SavedSession`]: everything a [`Session`] holds, so that a server can stop, and it or a newer
//! version can continue every session exactly where it was; and [`Session::resume`], a new
//! episode for a session whose state is lost but whose episode count and response scale are known.

use crate::config::SessionConfig;
use crate::highpass::WashoutMemory;
use crate::lanes::Held;
use crate::CoreError;

use super::Session;

/// Everything a [`Session`] holds: its config and its state, as plain values.
///
/// [`Session::save`] gives it and [`Session::restore`] takes it back, checking it first: a session
/// restored from it answers every later request with the same bits as the one saved. The values
/// derived from the config (the broadcast lanes, the filter's pole, the episode's learning rate)
/// are not saved but computed again from it.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SavedSession {
    /// The config as given at creation.
    pub config: SessionConfig,
    /// t, the step inside the current episode.
    pub step: u64,
    /// e, the completed episodes.
    pub episodes_completed: u64,
    /// Whether a probe for step t awaits its report.
    pub probe_pending: bool,
    /// Whether the report of step `t - 1` was the last thing applied (a repeat of it is a replay).
    pub report_replayable: bool,
    /// Reports whose update was skipped because it would have been non-finite.
    pub nonfinite_skips: u64,
    /// m, the running mean square of the filtered response; `None` while unset.
    pub response_mean_square: Option<f64>,
    /// v, D values.
    pub shift: Vec<f64>,
    /// The sampled action `a_t` of the last probe, D values (0 before the first).
    pub held_action: Vec<f64>,
    /// `sin(w tau)` of the last probe, D values.
    pub held_sine: Vec<f64>,
    /// sigma of the last probe, D values (1 before the first).
    pub held_scale: Vec<f64>,
    /// The washout's memory; `None` exactly when the config disables the high-pass.
    pub washout: Option<WashoutMemory>,
}

impl Session {
    /// Everything this session holds, to [`restore`](Self::restore) it later, elsewhere.
    pub fn save(&self) -> SavedSession {
        let held = self.lanes.held();
        SavedSession {
            config: self.config(),
            step: self.step,
            episodes_completed: self.episodes,
            probe_pending: self.probe_pending,
            report_replayable: self.report_replayable,
            nonfinite_skips: self.nonfinite_skips,
            response_mean_square: self.mean_square,
            shift: self.shift().to_vec(),
            held_action: held.action,
            held_sine: held.sine,
            held_scale: held.scale,
            washout: self.washout.as_ref().map(|washout| washout.memory()),
        }
    }

    /// The session `saved` describes, after checking that a session could have reached that state:
    /// a valid config, D finite values in each vector (sigma > 0, `|sin| <= 1`), a filter memory
    /// exactly when the config has a filter, m only with `normalize_response` and then finite and
    /// >= 0, and at most one of a pending probe and a replayable report. Errors name the field.
    pub fn restore(saved: SavedSession) -> Result<Session, CoreError> {
        let mut session = Session::new(saved.config)?;
        let dim = session.action_dim();
        let finite = |x: f64| x.is_finite();
        check_values("shift", &saved.shift, dim, "a finite number", finite)?;
        check_values(
            "held_action",
            &saved.held_action,
            dim,
            "a finite number",
            finite,
        )?;
        check_values(
            "held_sine",
            &saved.held_sine,
            dim,
            "a number in [-1, 1]",
            |s| (-1.0..=1.0).contains(&s),
        )?;
        check_values(
            "held_scale",
            &saved.held_scale,
            dim,
            "a finite number > 0",
            |x| x.is_finite() && x > 0.0,
        )?;
        session.check_mean_square(saved.response_mean_square)?;
        if saved.probe_pending && saved.report_replayable {
            return Err(invalid(
                "probe_pending and report_replayable: expected at most one, got both".into(),
            ));
        }
        if saved.report_replayable && saved.step == 0 {
            return Err(invalid(
                "report_replayable: expected a step >= 1 (the report of step - 1), got step 0"
                    .into(),
            ));
        }
        match (&mut session.washout, saved.washout) {
            (Some(washout), Some(memory)) => {
                if !(memory.previous_input.is_finite() && memory.previous_output.is_finite()) {
                    return Err(invalid(format!(
                        "washout: expected a finite previous input and output, got {} and {}",
                        memory.previous_input, memory.previous_output
                    )));
                }
                washout.set_memory(memory);
            }
            (None, None) => {}
            (Some(_), None) => {
                return Err(invalid(
                    "washout: expected the filter's memory (the config has a high-pass), got none"
                        .into(),
                ))
            }
            (None, Some(_)) => {
                return Err(invalid(
                    "washout: expected none (the config disables the high-pass), got a memory"
                        .into(),
                ))
            }
        }
        let held = Held {
            action: saved.held_action,
            sine: saved.held_sine,
            scale: saved.held_scale,
        };
        session.lanes.set_held(&saved.shift, &held);
        session.step = saved.step;
        session.episodes = saved.episodes_completed;
        session.apply_decay();
        session.nonfinite_skips = saved.nonfinite_skips;
        session.probe_pending = saved.probe_pending;
        session.report_replayable = saved.report_replayable;
        session.mean_square = saved.response_mean_square;
        Ok(session)
    }

    /// A session of `config` at the start of an episode (step 0, v = 0, filter at rest) that has
    /// completed `episodes_completed` episodes and whose response normalization has the running mean
    /// square `response_mean_square` (`None`: unset): what a lost session keeps when its client
    /// recreates it. Checks the config, and m as [`restore`](Self::restore) does.
    pub fn resume(
        config: SessionConfig,
        episodes_completed: u64,
        response_mean_square: Option<f64>,
    ) -> Result<Session, CoreError> {
        let mut session = Session::new(config)?;
        session.check_mean_square(response_mean_square)?;
        session.episodes = episodes_completed;
        session.apply_decay();
        session.mean_square = response_mean_square;
        Ok(session)
    }

    /// m may only be set with `normalize_response`, and then be finite and >= 0, as a report leaves it.
    fn check_mean_square(&self, mean_square: Option<f64>) -> Result<(), CoreError> {
        match mean_square {
            None => Ok(()),
            Some(_) if !self.settings.normalize_response => Err(invalid(
                "response_mean_square: expected none without normalize_response, got a value"
                    .into(),
            )),
            Some(m) if !(m.is_finite() && m >= 0.0) => Err(invalid(format!(
                "response_mean_square: expected a finite number >= 0, got {m}"
            ))),
            Some(_) => Ok(()),
        }
    }
}

fn invalid(message: String) -> CoreError {
    CoreError::InvalidArgument(message)
}

/// `values` has `dim` elements, each passing `ok` (described as `expected`).
fn check_values(
    field: &str,
    values: &[f64],
    dim: usize,
    expected: &str,
    ok: impl Fn(f64) -> bool,
) -> Result<(), CoreError> {
    if values.len() != dim {
        return Err(invalid(format!(
            "{field}: expected length {dim} (action_dim), got {}",
            values.len()
        )));
    }
    match values.iter().position(|&x| !ok(x)) {
        Some(i) => Err(invalid(format!(
            "{field}[{i}]: expected {expected}, got {}",
            values[i]
        ))),
        None => Ok(()),
    }
}
