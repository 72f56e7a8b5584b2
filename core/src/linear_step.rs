//! Algorithm 1's whole step for a critic linear in the action, `Q_i(a) = gain_i . a + offset_i`
//! at each item's state (ESAPPO's advantage head has this form): the probe batch, the critic at
//! the probes (and at the applied actions, as references), and the report batch, in one
//! all-or-nothing call. The in-process engine and the server's `step_linear_batch` StepStream
//! message both run [`step`], so the two give the same bits.

use crate::batch::{self, BatchError};
use crate::{ReportOutcome, Session};

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
    /// The lengths against the sessions' dimensions, and that every value is finite.
    fn check(&self, sessions: &[&mut Session]) -> Result<(), BatchError> {
        let total: usize = sessions.iter().map(|s| s.action_dim()).sum();
        for (field, values, expected) in [
            ("critic_gains", self.gains, total),
            ("critic_offsets", self.offsets, sessions.len()),
        ] {
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

    /// `Q_i` at `actions` (concatenated like the gains), one value per item.
    fn values(&self, sessions: &[&mut Session], actions: &[f64]) -> Vec<f64> {
        let mut start = 0;
        sessions
            .iter()
            .zip(self.offsets)
            .map(|(session, &offset)| {
                let end = start + session.action_dim();
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

/// One step of Algorithm 1 for `critic`: [`batch::probe`], then [`batch::report`] of the critic at
/// the probes (at the applied actions too, as references, when `critic.paired`) with the probes'
/// steps. Appends the probes and the applied actions `clip(a_t + v(t))` like [`batch::probe`];
/// each session is then at step `t + 1` with no probe pending, and its shift is `v(t + 1)`.
///
/// All-or-nothing: the critic is checked before the probe, and a report refused after it (a
/// finite critic whose value overflows at a far probe) puts the sessions back as they were.
#[allow(clippy::too_many_arguments)] // ProbeBatch's fields, the critic and the outputs
pub fn step(
    sessions: &mut [&mut Session],
    steps: &[u64],
    actions: &[f64],
    episode_starts: &[bool],
    action_scales: &[f64],
    critic: &LinearCritic<'_>,
    probes: &mut Vec<f64>,
    applied: &mut Vec<f64>,
    on_outcome: impl FnMut(usize, ReportOutcome),
) -> Result<(), BatchError> {
    batch::check_probe_lengths(sessions.len(), steps.len(), episode_starts.len())?;
    critic.check(sessions)?;
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
    let q_values = critic.values(sessions, &probes[marks.0..]);
    let references = if critic.paired {
        critic.values(sessions, &applied[marks.1..])
    } else {
        Vec::new()
    };
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
    let (mark, mut start) = (applied.len(), 0);
    for (index, session) in sessions.iter().enumerate() {
        let end = start + session.action_dim();
        let scale = action_scales.get(start..end).unwrap_or_default();
        let item = (shifts.get(start..end), actions.get(start..end));
        let (Some(shift), Some(action)) = item else {
            // Unreachable after the length checks; an error all the same, never a panic.
            applied.truncate(mark);
            return Err(BatchError::Request(format!("item {index}: out of range")));
        };
        if let Err(error) = session.applied_with_shift(shift, action, scale, applied) {
            applied.truncate(mark);
            return Err(BatchError::Item { index, error });
        }
        start = end;
    }
    Ok(())
}
