//! [`Session`]: the per-session state machine (probe, report, end of episode) of CONTRACT.md section 1.

use crate::config::SessionConfig;
use crate::highpass::Washout;
use crate::lanes::{Field, Lanes};
use crate::CoreError;

/// What a successful [`Session::report`] did besides returning the improved action.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ReportOutcome {
    /// True when this was a safe retry of step `t - 1`: the same action was returned, nothing updated.
    pub replayed: bool,
    /// True when the shift update was skipped because it would have made v non-finite.
    pub nonfinite_skipped: bool,
}

/// ESA state of one session: the shift v, the washout memory and the probe/report protocol.
///
/// Every method validates first and changes nothing when it returns an error.
#[derive(Clone, Debug, PartialEq)]
pub struct Session {
    settings: Settings,
    lanes: Lanes,
    /// `None` when the config disables the high-pass (H is the identity).
    washout: Option<Washout>,
    /// L, or +inf when unset (clamping to +-inf is the identity and keeps NaN visible).
    shift_limit: f64,
    step: u64,
    episodes: u64,
    nonfinite_skips: u64,
    probe_pending: bool,
    /// True right after a report was applied (no probe or episode end since): step `t - 1` may be replayed.
    report_replayable: bool,
}

/// The config's scalar fields and the shapes of its per-dimension ones. The per-dimension values
/// themselves live broadcast in the [`Lanes`]: keeping the config's own vectors too would cost an idle
/// D = 6 session five more allocations, about a quarter of issue 7's 1 KiB budget.
#[derive(Clone, Debug, PartialEq)]
struct Settings {
    dt: f64,
    highpass_cutoff: Option<f64>,
    disable_highpass: bool,
    lr_decay: Option<f64>,
    max_episodes: u64,
    /// How each field was given, indexed by `Field as usize` (the order of [`Field::ALL`]), so
    /// [`Session::config`] returns it as sent.
    shapes: [Shape; 5],
}

/// How a per-dimension field was given: empty, one broadcast value, or one value per dimension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Shape {
    Unset,
    Broadcast,
    PerDimension,
}

impl Shape {
    fn of(values: &[f64]) -> Shape {
        match values.len() {
            0 => Shape::Unset,
            1 => Shape::Broadcast,
            _ => Shape::PerDimension,
        }
    }

    /// The field as given, from its D lane values.
    fn rebuild(self, lanes: &[f64]) -> Vec<f64> {
        match self {
            Shape::Unset => Vec::new(),
            Shape::Broadcast => lanes.iter().take(1).copied().collect(),
            Shape::PerDimension => lanes.to_vec(),
        }
    }
}

impl Session {
    /// Validates `config` and starts the first episode at step 0 with v = 0.
    pub fn new(config: SessionConfig) -> Result<Session, CoreError> {
        config.validate()?;
        let washout = (!config.disable_highpass)
            .then(|| Washout::new(config.effective_highpass_cutoff(), config.dt));
        Ok(Session {
            lanes: Lanes::new(&config),
            washout,
            shift_limit: config.shift_limit.unwrap_or(f64::INFINITY),
            settings: Settings {
                dt: config.dt,
                highpass_cutoff: config.highpass_cutoff,
                disable_highpass: config.disable_highpass,
                lr_decay: config.lr_decay,
                max_episodes: config.max_episodes,
                shapes: Field::ALL.map(|field| Shape::of(field.of(&config))),
            },
            step: 0,
            episodes: 0,
            nonfinite_skips: 0,
            probe_pending: false,
            report_replayable: false,
        })
    }

    /// The config as it was given (vectors not broadcast).
    pub fn config(&self) -> SessionConfig {
        let s = &self.settings;
        let given = |field: Field| s.shapes[field as usize].rebuild(self.lanes.field(field));
        SessionConfig {
            action_dim: self.lanes.dim() as u32,
            dt: s.dt,
            amplitude: given(Field::Amplitude),
            frequency: given(Field::Frequency),
            learning_rate: given(Field::LearningRate),
            highpass_cutoff: s.highpass_cutoff,
            disable_highpass: s.disable_highpass,
            action_low: given(Field::ActionLow),
            action_high: given(Field::ActionHigh),
            // A valid limit is finite; the infinite one stands for "unset".
            shift_limit: Some(self.shift_limit).filter(|l| l.is_finite()),
            lr_decay: s.lr_decay,
            max_episodes: s.max_episodes,
        }
    }

    /// D.
    pub fn action_dim(&self) -> usize {
        self.lanes.dim()
    }

    /// t, the step inside the current episode.
    pub fn step(&self) -> u64 {
        self.step
    }

    /// e, the number of episodes this session has completed.
    pub fn episodes_completed(&self) -> u64 {
        self.episodes
    }

    /// v, length D.
    pub fn shift(&self) -> &[f64] {
        self.lanes.shift()
    }

    /// Whether a probe for step t awaits its report.
    pub fn probe_pending(&self) -> bool {
        self.probe_pending
    }

    /// How many reports skipped their shift update because it would have made v non-finite.
    pub fn nonfinite_skips(&self) -> u64 {
        self.nonfinite_skips
    }

    /// True once `e >= E > 0`: probes and actions are the clipped sampled action, v no longer moves.
    pub fn is_pass_through(&self) -> bool {
        self.settings.max_episodes > 0 && self.episodes >= self.settings.max_episodes
    }

    /// Checks a probe without changing anything, so a batch can validate every item before applying any.
    pub fn check_probe(
        &self,
        step: u64,
        action: &[f64],
        episode_start: bool,
    ) -> Result<(), CoreError> {
        self.check_action(action)?;
        // An episode start resets t to 0 before the step is compared.
        let expected = if episode_start { 0 } else { self.step };
        if step != expected {
            return Err(CoreError::StepMismatch {
                expected,
                got: step,
            });
        }
        Ok(())
    }

    /// Probes step `t` with the sampled action `a_t`; appends the D probe values to `out`.
    ///
    /// `probe = clip(a_t + v + K sin(w tau), lo, hi)`. Probing the same step again replaces the pending
    /// action. With `episode_start` and `t > 0` or a pending probe, the episode is ended first (like
    /// [`end_episode`](Self::end_episode)) and `step` must be 0.
    pub fn probe(
        &mut self,
        step: u64,
        action: &[f64],
        episode_start: bool,
        out: &mut Vec<f64>,
    ) -> Result<(), CoreError> {
        self.check_probe(step, action, episode_start)?;
        if episode_start && (self.step > 0 || self.probe_pending) {
            self.end_episode();
        }
        if self.is_pass_through() {
            self.lanes.hold(action, out);
        } else {
            let tau = self.step as f64 * self.settings.dt;
            self.lanes.probe(action, tau, out);
        }
        self.probe_pending = true;
        self.report_replayable = false;
        Ok(())
    }

    /// Checks a report without changing anything.
    pub fn check_report(&self, step: u64, q_value: f64) -> Result<(), CoreError> {
        if !q_value.is_finite() {
            return Err(CoreError::InvalidArgument(format!(
                "q_value: expected a finite number, got {q_value}"
            )));
        }
        if self.is_replay(step) {
            return Ok(());
        }
        if step != self.step {
            return Err(CoreError::StepMismatch {
                expected: self.step,
                got: step,
            });
        }
        if !self.probe_pending {
            return Err(CoreError::NoPendingProbe { step });
        }
        Ok(())
    }

    /// Reports `q = Q(s_t, probe)` for the pending probe; appends the D improved-action values to `out`.
    ///
    /// `v <- clamp(v + alpha_e s H[q], -L, L)` (skipped if any element would be non-finite), then
    /// `action = clip(a_t + v, lo, hi)` and `t <- t + 1`. A report for step `t - 1` right after it was
    /// applied returns the same action again and updates nothing.
    pub fn report(
        &mut self,
        step: u64,
        q_value: f64,
        out: &mut Vec<f64>,
    ) -> Result<ReportOutcome, CoreError> {
        self.check_report(step, q_value)?;
        if self.is_replay(step) {
            self.lanes.push_action(self.is_pass_through(), out);
            return Ok(ReportOutcome {
                replayed: true,
                nonfinite_skipped: false,
            });
        }
        let mut nonfinite_skipped = false;
        if self.is_pass_through() {
            self.lanes.push_action(true, out);
        } else {
            let h = match &mut self.washout {
                Some(washout) => washout.apply(q_value),
                None => q_value,
            };
            nonfinite_skipped = !self.lanes.update(h, self.shift_limit, out);
            if nonfinite_skipped {
                self.nonfinite_skips = self.nonfinite_skips.saturating_add(1);
            }
        }
        self.step = self.step.saturating_add(1);
        self.probe_pending = false;
        self.report_replayable = true;
        Ok(ReportOutcome {
            replayed: false,
            nonfinite_skipped,
        })
    }

    /// Ends the episode: `e += 1`, `t = 0`, `v = 0`, washout at rest, no pending probe. Returns the new e.
    pub fn end_episode(&mut self) -> u64 {
        self.episodes = self.episodes.saturating_add(1);
        self.step = 0;
        self.lanes.reset_shift();
        if let Some(washout) = &mut self.washout {
            washout.reset();
        }
        self.probe_pending = false;
        self.report_replayable = false;
        let decay = self
            .settings
            .lr_decay
            .unwrap_or(1.0)
            .powf(self.episodes as f64);
        self.lanes.set_rate(decay);
        self.episodes
    }

    fn check_action(&self, action: &[f64]) -> Result<(), CoreError> {
        if action.len() != self.action_dim() {
            return Err(CoreError::InvalidArgument(format!(
                "action: expected length {} (action_dim), got {}",
                self.action_dim(),
                action.len()
            )));
        }
        match action.iter().position(|x| !x.is_finite()) {
            Some(i) => Err(CoreError::InvalidArgument(format!(
                "action[{i}]: expected a finite number, got {}",
                action[i]
            ))),
            None => Ok(()),
        }
    }

    fn is_replay(&self, step: u64) -> bool {
        self.report_replayable && self.step.checked_sub(1) == Some(step)
    }
}

#[cfg(test)]
mod tests;
