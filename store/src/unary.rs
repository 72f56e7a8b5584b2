//! The unary calls on one session, as both wrappers answer them: a Probe returns the probe and
//! Algorithm 1's applied action, a Report the improved action.

use esa_core::{ReportOutcome, Session};

use crate::Error;

/// What a Probe of one session answers.
#[derive(Clone, Debug, PartialEq)]
pub struct Probed {
    /// `clip(a_t + v + K sin(w tau))`, the action to try.
    pub probe: Vec<f64>,
    /// Algorithm 1's applied action `clip(a_t + v(t))`.
    pub applied: Vec<f64>,
}

/// What a Report to one session answers.
#[derive(Clone, Debug, PartialEq)]
pub struct Reported {
    /// The improved action.
    pub action: Vec<f64>,
    /// Whether it was a replay, or skipped a non-finite update.
    pub outcome: ReportOutcome,
}

/// Probes `session` at `step` (see [`Session::probe`]).
pub fn probe(
    session: &mut Session,
    step: u64,
    action: &[f64],
    action_scale: &[f64],
    episode_start: bool,
) -> Result<Probed, Error> {
    let mut probe = Vec::with_capacity(session.action_dim());
    session.probe(step, action, action_scale, episode_start, &mut probe)?;
    let mut applied = Vec::with_capacity(session.action_dim());
    session.applied_action(&mut applied);
    Ok(Probed { probe, applied })
}

/// Reports Q for the probe of `step` (see [`Session::report`]).
pub fn report(
    session: &mut Session,
    step: u64,
    q_value: f64,
    q_reference: Option<f64>,
) -> Result<Reported, Error> {
    let mut action = Vec::with_capacity(session.action_dim());
    let outcome = session.report(step, q_value, q_reference, &mut action)?;
    Ok(Reported { action, outcome })
}
