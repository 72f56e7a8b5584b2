//! Algorithm 1's whole step in one all-or-nothing call: the probe batch, the critic at the probes
//! (and at the applied actions, as references), and the report batch. The critic is either linear
//! in the action, `Q_i(a) = gain_i . a + offset_i` at each item's state (ESAPPO's advantage head has
//! this form), or concave quadratic in the action clipped to a box ([`QuadraticCritic`], ESAPPO's
//! quadratic head), both evaluated here, or any critic the client evaluated itself at probes it
//! computed ahead ([`probes_ahead`]). The in-process engine and the server's StepStream messages
//! (`step_linear_batch`, `step_batch`) all run [`step`], so they give the same bits.

use std::borrow::Cow;

use crate::batch::{self, BatchError};
use crate::{CoreError, ReportOutcome, Session};

/// What [`step`] reports: the critic's values at a step's probes (and at its applied actions).
pub trait StepCritic {
    /// Checks the critic against the items' action dimensions before anything is probed.
    fn check(&self, dims: &[usize]) -> Result<(), BatchError>;

    /// `(q_values, q_references)` at the probes and the applied actions (both concatenated like
    /// the actions, of the items' action dimensions `dims`): one value per item each, the
    /// references empty for none.
    fn values(
        &self,
        dims: &[usize],
        probes: &[f64],
        applied: &[f64],
    ) -> (Cow<'_, [f64]>, Cow<'_, [f64]>);
}

/// `Q_i(a) = gain_i . a + offset_i` at each item's state.
#[derive(Clone, Copy, Debug)]
pub struct LinearCritic<'a> {
    /// `gain_i`, concatenated in item order (each item's action dimension): the wire's
    /// `critic_gains`.
    pub gains: &'a [f64],
    /// `offset_i`, one per item: the wire's `critic_offsets`.
    pub offsets: &'a [f64],
    /// Also report the critic at the applied actions `clip(a_t + v(t))` as each item's
    /// `q_reference` (CONTRACT.md section 1b's paired response).
    pub paired: bool,
}

impl LinearCritic<'_> {
    /// `Q_i` at `actions` (concatenated like the gains), one value per item.
    fn at(&self, dims: &[usize], actions: &[f64]) -> Vec<f64> {
        let mut start = 0;
        dims.iter()
            .zip(self.offsets)
            .map(|(&dim, &offset)| {
                let end = start + dim;
                let dot: f64 = self.gains[start..end]
                    .iter()
                    .zip(&actions[start..end])
                    .map(|(g, a)| g * a)
                    .sum();
                start = end;
                dot + offset
            })
            .collect()
    }
}

impl StepCritic for LinearCritic<'_> {
    /// The lengths against the sessions' dimensions, and that every value is finite.
    fn check(&self, dims: &[usize]) -> Result<(), BatchError> {
        let total: usize = dims.iter().sum();
        check_coefficients(&[
            ("critic_gains", self.gains, total),
            ("critic_offsets", self.offsets, dims.len()),
        ])
    }

    fn values(
        &self,
        dims: &[usize],
        probes: &[f64],
        applied: &[f64],
    ) -> (Cow<'_, [f64]>, Cow<'_, [f64]>) {
        closed_form_values(
            |actions| self.at(dims, actions),
            self.paired,
            probes,
            applied,
        )
    }
}

/// Each field's length against what the sessions need, and that every value is finite.
fn check_coefficients(fields: &[(&str, &[f64], usize)]) -> Result<(), BatchError> {
    for &(field, values, expected) in fields {
        if values.len() != expected {
            return Err(BatchError::Request(format!(
                "{field}: expected {expected} values, got {}",
                values.len()
            )));
        }
        if let Some(bad) = values.iter().find(|v| !v.is_finite()) {
            return Err(BatchError::Request(format!(
                "{field}: expected finite values, got {bad}"
            )));
        }
    }
    Ok(())
}

/// A closed-form critic's values at the probes, and at the applied actions when `paired`.
fn closed_form_values<'a>(
    at: impl Fn(&[f64]) -> Vec<f64>,
    paired: bool,
    probes: &[f64],
    applied: &[f64],
) -> (Cow<'a, [f64]>, Cow<'a, [f64]>) {
    let references = if paired { at(applied) } else { Vec::new() };
    (at(probes).into(), references.into())
}

/// `Q_i(a) = offset_i + sum_j (gain_ij x_j + curvature_ij x_j^2)` with `x = clip(a, low, high)`
/// at each item's state: a critic concave in each dimension of the action (`curvature <= 0`),
/// evaluated at the action the environment executes (flat in a dimension past the box).
#[derive(Clone, Copy, Debug)]
pub struct QuadraticCritic<'a> {
    /// `gain_i`, concatenated in item order (each item's action dimension).
    pub gains: &'a [f64],
    /// `curvature_i`, concatenated like the gains; every value `<= 0`.
    pub curvatures: &'a [f64],
    /// `offset_i`, one per item.
    pub offsets: &'a [f64],
    /// The box's lower bounds, concatenated like the gains (`-inf` where open), or empty for an
    /// unbounded box.
    pub lows: &'a [f64],
    /// Its upper bounds, as `lows` (`+inf` where open; empty when `lows` is).
    pub highs: &'a [f64],
    /// Also report the critic at the applied actions as each item's `q_reference`.
    pub paired: bool,
}

impl QuadraticCritic<'_> {
    /// `Q_i` at `actions` (concatenated like the gains), one value per item.
    fn at(&self, dims: &[usize], actions: &[f64]) -> Vec<f64> {
        let (mut gains, mut curvatures) = (self.gains.iter(), self.curvatures.iter());
        let mut points = actions.iter();
        // Empty for an unbounded box: the action itself.
        let mut bounds = self.lows.iter().zip(self.highs);
        dims.iter()
            .zip(self.offsets)
            .map(|(&dim, &offset)| {
                let sum: f64 = gains
                    .by_ref()
                    .take(dim)
                    .zip(curvatures.by_ref().take(dim))
                    .zip(points.by_ref().take(dim))
                    .map(|((&gain, &curvature), &action)| {
                        // max then min (numpy's clip; unlike clamp, it never panics).
                        let x = match bounds.next() {
                            Some((&low, &high)) => action.max(low).min(high),
                            None => action,
                        };
                        gain * x + curvature * x * x
                    })
                    .sum();
                sum + offset
            })
            .collect()
    }
}

impl StepCritic for QuadraticCritic<'_> {
    /// The lengths against the sessions' dimensions, finite coefficients, curvatures `<= 0`, and
    /// bounds (none or one pair per value) with `low <= high`.
    fn check(&self, dims: &[usize]) -> Result<(), BatchError> {
        let total: usize = dims.iter().sum();
        check_coefficients(&[
            ("critic_gains", self.gains, total),
            ("critic_curvatures", self.curvatures, total),
            ("critic_offsets", self.offsets, dims.len()),
        ])?;
        if let Some(bad) = self.curvatures.iter().find(|&&c| c > 0.0) {
            return Err(BatchError::Request(format!(
                "critic_curvatures: expected values <= 0, got {bad}"
            )));
        }
        let bounds = self.lows.len();
        if self.highs.len() != bounds || !(bounds == 0 || bounds == total) {
            return Err(BatchError::Request(format!(
                "critic_bounds: expected 0 or {total} lows and as many highs, got {bounds} and {}",
                self.highs.len()
            )));
        }
        if let Some((low, high)) = self
            .lows
            .iter()
            .zip(self.highs)
            .find(|(low, high)| low.is_nan() || high.is_nan() || low > high)
        {
            return Err(BatchError::Request(format!(
                "critic_bounds: expected low <= high (neither NaN), got {low} and {high}"
            )));
        }
        Ok(())
    }

    fn values(
        &self,
        dims: &[usize],
        probes: &[f64],
        applied: &[f64],
    ) -> (Cow<'_, [f64]>, Cow<'_, [f64]>) {
        closed_form_values(
            |actions| self.at(dims, actions),
            self.paired,
            probes,
            applied,
        )
    }
}

/// The critic's values as the client evaluated them, at the probes it computed ahead with
/// [`probes_ahead`] (the server's probes, bit for bit) and at the applied actions.
#[derive(Clone, Copy, Debug)]
pub struct CriticValues<'a> {
    /// `Q_i` at item i's probe, one per item: the wire's `q_values` (a ReportBatch's).
    pub q_values: &'a [f64],
    /// `Q_i` at item i's applied action, one per item, or empty for none: the wire's
    /// `q_references` (a ReportBatch's).
    pub q_references: &'a [f64],
}

impl StepCritic for CriticValues<'_> {
    /// The lengths only: the report checks each value (and names the item of a bad one).
    fn check(&self, dims: &[usize]) -> Result<(), BatchError> {
        batch::check_report_lengths(
            dims.len(),
            dims.len(),
            self.q_values.len(),
            self.q_references.len(),
        )
    }

    fn values(
        &self,
        _dims: &[usize],
        _probes: &[f64],
        _applied: &[f64],
    ) -> (Cow<'_, [f64]>, Cow<'_, [f64]>) {
        (self.q_values.into(), self.q_references.into())
    }
}

/// One step of Algorithm 1 for `critic`: [`batch::probe`], then [`batch::report`] of the critic at
/// the probes (at the applied actions too, as references, when it gives them) with the probes'
/// steps. Appends the probes and the applied actions `clip(a_t + v(t))` like [`batch::probe`];
/// each session is then at step `t + 1` with no probe pending, and its shift is `v(t + 1)`.
///
/// All-or-nothing: the critic is checked before the probe, and a report refused after it (a
/// non-finite value, or a finite critic whose value overflows at a far probe) puts the sessions
/// back as they were.
#[allow(clippy::too_many_arguments)] // ProbeBatch's fields, the critic and the outputs
pub fn step(
    sessions: &mut [&mut Session],
    steps: &[u64],
    actions: &[f64],
    episode_starts: &[bool],
    action_scales: &[f64],
    critic: &impl StepCritic,
    probes: &mut Vec<f64>,
    applied: &mut Vec<f64>,
    on_outcome: impl FnMut(usize, ReportOutcome),
) -> Result<(), BatchError> {
    batch::check_probe_lengths(sessions.len(), steps.len(), episode_starts.len())?;
    let dims: Vec<usize> = sessions
        .iter()
        .map(|session| session.action_dim())
        .collect();
    critic.check(&dims)?;
    let before: Vec<Session> = sessions.iter().map(|session| (**session).clone()).collect();
    let marks = (probes.len(), applied.len());
    batch::probe(
        sessions,
        steps,
        actions,
        episode_starts,
        action_scales,
        probes,
        applied,
    )?;
    let (q_values, references) = critic.values(&dims, &probes[marks.0..], &applied[marks.1..]);
    let mut improved = Vec::new();
    let reported = batch::report(
        sessions,
        steps,
        &q_values,
        &references,
        &mut improved,
        on_outcome,
    );
    if let Err(err) = reported {
        for (session, saved) in sessions.iter_mut().zip(before) {
            **session = saved;
        }
        probes.truncate(marks.0);
        applied.truncate(marks.1);
        return Err(err);
    }
    Ok(())
}

/// Algorithm 1's applied actions of a step whose shifts are known ahead: for each item,
/// `clip(a_t + clamp(v, -bound, bound), lo, hi)` with `bound = min(L, kappa sigma)` of this step's
/// sigma, exactly as [`Session::probe`] then [`Session::applied_action`] compute it. `shifts` and
/// `action_scales` are concatenated like `actions` (`action_scales` empty for all 1). A client of
/// the pipelined step computes its actions with this from the shifts `v(t)` the previous step's
/// answer carried (0 at an episode start), without waiting for the server.
///
/// `sessions` gives each item's config; their state is not read, so a client passes fresh
/// sessions of its configs. In pass-through (`e >= E > 0`) the server applies `clip(a_t)`; v is
/// 0 there, so this gives the same numbers (only the sign of a zero `a_t` can differ).
pub fn applied_ahead(
    sessions: &[Session],
    shifts: &[f64],
    actions: &[f64],
    action_scales: &[f64],
    applied: &mut Vec<f64>,
) -> Result<(), BatchError> {
    let mark = applied.len();
    let result = each_ahead(sessions, shifts, actions, action_scales, |item| {
        item.session
            .applied_with_shift(item.shift, item.action, item.scale, applied)
    });
    if result.is_err() {
        applied.truncate(mark);
    }
    result
}

/// [`applied_ahead`], and the probes `clip(a_t + clamp(v) + K sin(w t dt), lo, hi)` of step
/// `steps[i]` (0 at an episode start): the bits of [`Session::probe`] at that step with that
/// shift. A client of the pipelined step for a critic it evaluates itself computes the probes with
/// this, evaluates its critic there, and sends the values with the step (`step_batch`).
///
/// In pass-through the server probes `clip(a_t)` and its report changes nothing, so the values
/// at these probes are not used.
pub fn probes_ahead(
    sessions: &[Session],
    shifts: &[f64],
    steps: &[u64],
    actions: &[f64],
    action_scales: &[f64],
    probes: &mut Vec<f64>,
    applied: &mut Vec<f64>,
) -> Result<(), BatchError> {
    if steps.len() != sessions.len() {
        return Err(BatchError::Request(format!(
            "steps: expected {} values, got {}",
            sessions.len(),
            steps.len()
        )));
    }
    let marks = (probes.len(), applied.len());
    let result = each_ahead(sessions, shifts, actions, action_scales, |item| {
        item.session.probe_with_shift(
            item.shift,
            steps[item.index],
            item.action,
            item.scale,
            probes,
            applied,
        )
    });
    if result.is_err() {
        probes.truncate(marks.0);
        applied.truncate(marks.1);
    }
    result
}

/// One item of a step computed ahead.
struct AheadItem<'a> {
    index: usize,
    session: &'a Session,
    shift: &'a [f64],
    action: &'a [f64],
    scale: &'a [f64],
}

/// Checks the lengths of a step computed ahead, then runs `item` on each item in order, stopping
/// at the first error (naming its item).
fn each_ahead(
    sessions: &[Session],
    shifts: &[f64],
    actions: &[f64],
    action_scales: &[f64],
    mut item: impl FnMut(AheadItem<'_>) -> Result<(), CoreError>,
) -> Result<(), BatchError> {
    let total: usize = sessions.iter().map(Session::action_dim).sum();
    for (field, values) in [("shifts", shifts), ("actions", actions)] {
        if values.len() != total {
            return Err(BatchError::Request(format!(
                "{field}: expected {total} values, got {}",
                values.len()
            )));
        }
    }
    if !action_scales.is_empty() && action_scales.len() != total {
        return Err(BatchError::Request(format!(
            "action_scales: expected 0 or {total} values, got {}",
            action_scales.len()
        )));
    }
    let mut start = 0;
    for (index, session) in sessions.iter().enumerate() {
        let end = start + session.action_dim();
        let scale = action_scales.get(start..end).unwrap_or_default();
        let (Some(shift), Some(action)) = (shifts.get(start..end), actions.get(start..end)) else {
            // Unreachable after the length checks; an error all the same, never a panic.
            return Err(BatchError::Request(format!("item {index}: out of range")));
        };
        let ahead = AheadItem {
            index,
            session,
            shift,
            action,
            scale,
        };
        item(ahead).map_err(|error| BatchError::Item { index, error })?;
        start = end;
    }
    Ok(())
}
