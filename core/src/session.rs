//! [`Session`]: the per-session state machine (probe, report, end of episode) of CONTRACT.md sections 1
//! and 1b.

use crate::config::{SessionConfig, DEFAULT_RESPONSE_CLIP, DEFAULT_RESPONSE_RMS_RATE};
use crate::highpass::Washout;
use crate::lanes::{Field, Lanes, StepRule};
use crate::CoreError;

mod saved;

pub use saved::SavedSession;

/// Guard of the response normalization `h / sqrt(m + 1e-12)` (CONTRACT.md section 1b).
const MEAN_SQUARE_GUARD: f64 = 1e-12;

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
    /// m, the running mean square of the filtered response (`normalize_response`); `None` until the first
    /// non-zero response seeds it. Kept across episodes: the scale of Q outlives one episode.
    mean_square: Option<f64>,
    step: u64,
    episodes: u64,
    nonfinite_skips: u64,
    probe_pending: bool,
    /// True right after a report was applied (no probe or episode end since): step `t - 1` may be replayed.
    report_replayable: bool,
}

/// The config's scalar fields and the shapes of its per-dimension ones. The per-dimension values
/// themselves live broadcast in the [`Lanes`]: keeping the config's own vectors too would cost an idle
/// D = 6 session five more allocations, about a quarter of its 1 KiB budget.
#[derive(Clone, Debug, PartialEq)]
struct Settings {
    dt: f64,
    highpass_cutoff: Option<f64>,
    disable_highpass: bool,
    lr_decay: Option<f64>,
    max_episodes: u64,
    normalize_response: bool,
    response_rms_rate: Option<f64>,
    response_clip: Option<f64>,
    shift_leak: Option<f64>,
    trust_region: Option<f64>,
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
                normalize_response: config.normalize_response,
                response_rms_rate: config.response_rms_rate,
                response_clip: config.response_clip,
                shift_leak: config.shift_leak,
                trust_region: config.trust_region,
                shapes: Field::ALL.map(|field| Shape::of(field.of(&config))),
            },
            mean_square: None,
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
            normalize_response: s.normalize_response,
            response_rms_rate: s.response_rms_rate,
            response_clip: s.response_clip,
            shift_leak: s.shift_leak,
            trust_region: s.trust_region,
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

    /// m, the running mean square of the filtered response; `None` until seeded (or without
    /// `normalize_response`).
    pub fn response_mean_square(&self) -> Option<f64> {
        self.mean_square
    }

    /// Whether the config has `normalize_response` (then m drives the step and outlives episodes).
    pub fn normalizes_response(&self) -> bool {
        self.settings.normalize_response
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
        action_scale: &[f64],
        episode_start: bool,
    ) -> Result<(), CoreError> {
        self.check_action(action)?;
        self.check_action_scale(action_scale)?;
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
    /// `probe = clip(a_t + v + K sin(w tau), lo, hi)`. `action_scale` is sigma (empty = 1, else length 1 or
    /// D, finite and > 0): v is first clamped into `min(L, kappa sigma)`, so the applied action
    /// `a_t + v(t)` keeps the trust region of this step's sigma, and the report that answers this probe
    /// uses it too. Probing the same step again replaces the pending action and scale. With `episode_start` and `t > 0` or a pending probe, the episode is ended
    /// first (like [`end_episode`](Self::end_episode)) and `step` must be 0. Algorithm 1's applied action
    /// for this step is then [`applied_action`](Self::applied_action).
    pub fn probe(
        &mut self,
        step: u64,
        action: &[f64],
        action_scale: &[f64],
        episode_start: bool,
        out: &mut Vec<f64>,
    ) -> Result<(), CoreError> {
        self.check_probe(step, action, action_scale, episode_start)?;
        if episode_start && (self.step > 0 || self.probe_pending) {
            self.end_episode();
        }
        if self.is_pass_through() {
            self.lanes.hold(action, out);
        } else {
            // This probe's sigma bounds v already for the applied action a_t + v(t): with a
            // shrinking sigma, the bound of the last report would be too loose.
            self.lanes.set_scale(action_scale);
            self.lanes.clamp_shift(self.step_rule());
            let tau = self.step as f64 * self.settings.dt;
            self.lanes.probe(action, tau, out);
        }
        self.probe_pending = true;
        self.report_replayable = false;
        Ok(())
    }

    /// Appends Algorithm 1's applied action for the last probe: `clip(a_t + v(t), lo, hi)`, the shift before
    /// this step's report (`clip(a_t)` in pass-through). Right after a report it is `clip(a_t + v(t + 1))`.
    pub fn applied_action(&self, out: &mut Vec<f64>) {
        self.lanes.push_action(self.is_pass_through(), out);
    }

    /// Appends the applied action a probe of `action` with scale `action_scale` would give if the
    /// shift were `shift`: `clip(a_t + clamp(shift, -bound, bound), lo, hi)`, the bits of
    /// [`probe`](Self::probe) then [`applied_action`](Self::applied_action) outside pass-through.
    /// Reads only the config; checks `action` and `action_scale` as a probe does, and that `shift`
    /// has D finite values, appending nothing on an error.
    pub fn applied_with_shift(
        &self,
        shift: &[f64],
        action: &[f64],
        action_scale: &[f64],
        out: &mut Vec<f64>,
    ) -> Result<(), CoreError> {
        self.check_ahead(shift, action, action_scale)?;
        self.lanes
            .applied_with(shift, action, action_scale, self.step_rule(), out);
        Ok(())
    }

    /// Appends the probe of step `step` a session with shift `shift` would give for `action` and
    /// `action_scale` (`clip(a_t + clamp(shift, -bound, bound) + K sin(w step dt), lo, hi)`) to
    /// `probes`, and its applied action to `applied`: the bits of [`probe`](Self::probe) then
    /// [`applied_action`](Self::applied_action) outside pass-through, by the same code on a copy
    /// of the lanes. Reads only the config; checks as
    /// [`applied_with_shift`](Self::applied_with_shift) does, appending nothing on an error.
    pub fn probe_with_shift(
        &self,
        shift: &[f64],
        step: u64,
        action: &[f64],
        action_scale: &[f64],
        probes: &mut Vec<f64>,
        applied: &mut Vec<f64>,
    ) -> Result<(), CoreError> {
        self.check_ahead(shift, action, action_scale)?;
        let mut lanes = self.lanes.clone();
        lanes.set_shift(shift);
        lanes.set_scale(action_scale);
        lanes.clamp_shift(self.step_rule());
        lanes.probe(action, step as f64 * self.settings.dt, probes);
        lanes.push_action(false, applied);
        Ok(())
    }

    /// The checks of a step computed ahead: the action and scale as a probe's, and a shift of D
    /// finite values.
    fn check_ahead(
        &self,
        shift: &[f64],
        action: &[f64],
        action_scale: &[f64],
    ) -> Result<(), CoreError> {
        self.check_action(action)?;
        self.check_action_scale(action_scale)?;
        if shift.len() != self.action_dim() {
            return Err(CoreError::InvalidArgument(format!(
                "shift: expected length {} (action_dim), got {}",
                self.action_dim(),
                shift.len()
            )));
        }
        if let Some(i) = shift.iter().position(|v| !v.is_finite()) {
            return Err(CoreError::InvalidArgument(format!(
                "shift[{i}]: expected a finite number, got {}",
                shift[i]
            )));
        }
        Ok(())
    }

    /// Checks a report without changing anything.
    pub fn check_report(
        &self,
        step: u64,
        q_value: f64,
        q_reference: Option<f64>,
    ) -> Result<(), CoreError> {
        if !q_value.is_finite() {
            return Err(CoreError::InvalidArgument(format!(
                "q_value: expected a finite number, got {q_value}"
            )));
        }
        if let Some(reference) = q_reference.filter(|r| !r.is_finite()) {
            return Err(CoreError::InvalidArgument(format!(
                "q_reference: expected a finite number (or unset), got {reference}"
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
    /// The response is `x = q - q_reference` when a reference `Q(s_t, a_t + v(t))` is given, else `q`;
    /// `h = H[x]`. Section 1: `v <- clamp(v + alpha_e s h, -L, L)`; section 1b adds the normalization
    /// (`normalize_response`), the leak and the trust region (see [`SessionConfig`]). The update is skipped
    /// if any element of v (or m) would be non-finite (v is then only kept inside this report's bound
    /// `min(L, kappa sigma)`); then `action = clip(a_t + v, lo, hi)` and
    /// `t <- t + 1`. A report for step `t - 1` right after it was applied returns the same action again
    /// and updates nothing.
    pub fn report(
        &mut self,
        step: u64,
        q_value: f64,
        q_reference: Option<f64>,
        out: &mut Vec<f64>,
    ) -> Result<ReportOutcome, CoreError> {
        self.check_report(step, q_value, q_reference)?;
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
            let x = q_reference.map_or(q_value, |reference| q_value - reference);
            let h = match &mut self.washout {
                Some(washout) => washout.apply(x),
                None => x,
            };
            nonfinite_skipped = !self.update(h, out);
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
        self.apply_decay();
        self.episodes
    }

    /// alpha_e = alpha * gamma_a^e for the current e. A restored session computes it exactly as the
    /// saved one did, so its rate has the same bits.
    fn apply_decay(&mut self) {
        let decay = self
            .settings
            .lr_decay
            .unwrap_or(1.0)
            .powf(self.episodes as f64);
        self.lanes.set_rate(decay);
    }

    /// Moves v (and m) for the filtered response `h`; appends the improved action. False when the update
    /// was skipped because v or m would have become non-finite.
    fn update(&mut self, h: f64, out: &mut Vec<f64>) -> bool {
        let rule = self.step_rule();
        let s = &self.settings;
        if !s.normalize_response {
            return self.lanes.update(h, rule, out);
        }
        let rate = s.response_rms_rate.unwrap_or(DEFAULT_RESPONSE_RMS_RATE);
        let clip = s.response_clip.unwrap_or(DEFAULT_RESPONSE_CLIP);
        let mean_square = match self.mean_square {
            None if h != 0.0 => Some(h * h),
            None => None,
            Some(m) => Some((1.0 - rate) * m + rate * (h * h)),
        };
        let g = mean_square.map_or(0.0, |m| {
            (h / (m + MEAN_SQUARE_GUARD).sqrt()).clamp(-clip, clip)
        });
        // An overflowed m would silence every later response (g = h / inf = 0): skip the report instead,
        // exactly like an update that would make v non-finite. m moves only together with v.
        if !mean_square.map_or(true, f64::is_finite) || !g.is_finite() {
            self.lanes.skip_update(rule, out);
            return false;
        }
        let updated = self.lanes.update(g, rule, out);
        if updated {
            self.mean_square = mean_square;
        }
        updated
    }

    fn step_rule(&self) -> StepRule {
        let s = &self.settings;
        StepRule {
            scaled: s.normalize_response,
            keep: s.shift_leak.map_or(1.0, |lambda| 1.0 - lambda),
            limit: self.shift_limit,
            trust: s.trust_region.unwrap_or(f64::INFINITY),
        }
    }

    fn check_action_scale(&self, scale: &[f64]) -> Result<(), CoreError> {
        let dim = self.action_dim();
        if !matches!(scale.len(), 0 | 1) && scale.len() != dim {
            return Err(CoreError::InvalidArgument(format!(
                "action_scale: expected length 0 (all 1), 1 (broadcast) or {dim} (action_dim), got {}",
                scale.len()
            )));
        }
        match scale.iter().position(|x| !(x.is_finite() && *x > 0.0)) {
            Some(i) => Err(CoreError::InvalidArgument(format!(
                "action_scale[{i}]: expected a finite number > 0, got {}",
                scale[i]
            ))),
            None => Ok(()),
        }
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
