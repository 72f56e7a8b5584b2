//! All-or-nothing batches over many sessions (CONTRACT.md section 2: `ProbeBatch`, `ReportBatch`).
//!
//! A batch names N sessions and carries one item per session, its per-element fields concatenated in
//! item order. Every item is validated before any session changes: a batch that returns an error has
//! changed no session and appended nothing to the outputs. Errors that belong to one item carry its
//! index as data ([`BatchError::Item`]).
//!
//! Finding the sessions (ids, NOT_FOUND, an id repeated in one batch) is the caller's job: the
//! functions here take the sessions already resolved, in item order, as `&mut [&mut Session]`, so a
//! session cannot appear twice. A server checks the request's lengths first with
//! [`check_probe_lengths`] / [`check_report_lengths`] (they need no session), then looks the sessions
//! up, then calls [`probe`] / [`report`], which check the lengths again (cheaply) and do the rest, in
//! this order:
//!
//! - probe: item count, `steps`, `episode_starts`; (lookup); the sessions' action values added up,
//!   `actions` and `action_scales` against that total; then each item ([`Session::check_probe`]).
//! - report: item count, `steps`, `q_values`, `q_references`; (lookup); then each item
//!   ([`Session::check_report`]); then the sessions' action values added up.
//!
//! The error messages are those of `esa-server`: [`BatchError::Request`] displays as the bare
//! message (gRPC INVALID_ARGUMENT), [`BatchError::Item`] as `item {index}: {error}` with the code of
//! its [`CoreError`].

use crate::{CoreError, ReportOutcome, Session};

/// Most items (sessions) one batch may carry.
pub const MAX_BATCH_ITEMS: usize = 65_536;

/// Most action values one batch may carry: the action dimensions of its sessions added up.
pub const MAX_BATCH_VALUES: usize = 1 << 20;

/// Why a batch was refused. Nothing changed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum BatchError {
    /// The request as a whole is malformed (item count, a field's length, too many action values):
    /// INVALID_ARGUMENT. The message starts with the field's name.
    #[error("{0}")]
    Request(String),
    /// Item `index` was refused by its session.
    #[error("item {index}: {error}")]
    Item {
        /// Position of the failing item in the batch.
        index: usize,
        /// What its session said.
        error: CoreError,
    },
}

impl BatchError {
    /// The failing item's position, `None` for an error of the whole request.
    pub fn index(&self) -> Option<usize> {
        match self {
            BatchError::Request(_) => None,
            BatchError::Item { index, .. } => Some(*index),
        }
    }

    fn item(index: usize, error: CoreError) -> Self {
        BatchError::Item { index, error }
    }
}

/// The checks of a probe batch of `n` items that need no session: `n` in `1..=MAX_BATCH_ITEMS`,
/// `steps` has `n` values, `episode_starts` none (all false) or `n`.
pub fn check_probe_lengths(
    n: usize,
    steps: usize,
    episode_starts: usize,
) -> Result<(), BatchError> {
    check_batch_len(n)?;
    check_field_len("steps", steps, n)?;
    if episode_starts != 0 {
        check_field_len("episode_starts", episode_starts, n)?;
    }
    Ok(())
}

/// The checks of a report batch of `n` items that need no session: `n` in `1..=MAX_BATCH_ITEMS`,
/// `steps` and `q_values` have `n` values, `q_references` none (no reference) or `n`.
pub fn check_report_lengths(
    n: usize,
    steps: usize,
    q_values: usize,
    q_references: usize,
) -> Result<(), BatchError> {
    check_batch_len(n)?;
    check_field_len("steps", steps, n)?;
    check_field_len("q_values", q_values, n)?;
    if q_references != 0 {
        check_field_len("q_references", q_references, n)?;
    }
    Ok(())
}

/// Probes every session of a batch at once; all-or-nothing.
///
/// Item `i` is `sessions[i]` probed at `steps[i]` with its `action_dim` values of `actions` (the items'
/// actions concatenated in order), `episode_starts[i]` (empty = all false) and, unless
/// `action_scales` is empty, its `action_dim` values of `action_scales` (concatenated like
/// `actions`; the length-1 broadcast of a single probe does not exist in a batch). Appends the
/// probes, concatenated, to `probes` and Algorithm 1's applied actions
/// ([`Session::applied_action`]) to `applied`.
pub fn probe(
    sessions: &mut [&mut Session],
    steps: &[u64],
    actions: &[f64],
    episode_starts: &[bool],
    action_scales: &[f64],
    probes: &mut Vec<f64>,
    applied: &mut Vec<f64>,
) -> Result<(), BatchError> {
    let n = sessions.len();
    check_probe_lengths(n, steps.len(), episode_starts.len())?;
    let total = check_batch_values(sessions.iter().map(|s| s.action_dim()).sum())?;
    check_concatenated("actions", actions.len(), total, n)?;
    if !action_scales.is_empty() {
        check_concatenated("action_scales", action_scales.len(), total, n)?;
    }
    let start = |index: usize| episode_starts.get(index).copied().unwrap_or(false);
    // Every item is checked before any session changes: all-or-nothing.
    let (mut rest, mut scales) = (actions, action_scales);
    for (index, (session, &step)) in sessions.iter().zip(steps).enumerate() {
        let (action, scale) = item_values(&mut rest, &mut scales, session.action_dim(), index)?;
        session
            .check_probe(step, action, scale, start(index))
            .map_err(|err| BatchError::item(index, err))?;
    }
    let marks = (probes.len(), applied.len());
    probes.reserve(total);
    applied.reserve(total);
    let (mut rest, mut scales) = (actions, action_scales);
    for (index, (session, &step)) in sessions.iter_mut().zip(steps).enumerate() {
        let applied_item = item_values(&mut rest, &mut scales, session.action_dim(), index)
            .and_then(|(action, scale)| {
                session
                    .probe(step, action, scale, start(index), probes)
                    .map_err(|err| BatchError::item(index, err))
            });
        if let Err(err) = applied_item {
            // Unreachable after the checks above; the outputs still get nothing of the batch.
            probes.truncate(marks.0);
            applied.truncate(marks.1);
            return Err(err);
        }
        session.applied_action(applied);
    }
    Ok(())
}

/// Reports Q to every session of a batch at once; all-or-nothing.
///
/// Item `i` reports `q_values[i]` (with `q_references[i]` unless `q_references` is empty) for
/// `sessions[i]`'s probe of `steps[i]`, or replays the report of the step just applied
/// ([`Session::report`]). Appends the improved actions, concatenated, to `actions`, and tells
/// `on_outcome` each applied item's index and [`ReportOutcome`] (a server counts and logs the
/// non-finite skips).
pub fn report(
    sessions: &mut [&mut Session],
    steps: &[u64],
    q_values: &[f64],
    q_references: &[f64],
    actions: &mut Vec<f64>,
    mut on_outcome: impl FnMut(usize, ReportOutcome),
) -> Result<(), BatchError> {
    let n = sessions.len();
    check_report_lengths(n, steps.len(), q_values.len(), q_references.len())?;
    let reference = |index: usize| q_references.get(index).copied();
    // Every item is checked before any session changes: all-or-nothing.
    for (index, ((session, &step), &q)) in sessions.iter().zip(steps).zip(q_values).enumerate() {
        session
            .check_report(step, q, reference(index))
            .map_err(|err| BatchError::item(index, err))?;
    }
    let total = check_batch_values(sessions.iter().map(|s| s.action_dim()).sum())?;
    let mark = actions.len();
    actions.reserve(total);
    for (index, ((session, &step), &q)) in sessions.iter_mut().zip(steps).zip(q_values).enumerate()
    {
        match session.report(step, q, reference(index), actions) {
            Ok(outcome) => on_outcome(index, outcome),
            Err(err) => {
                // Unreachable after the checks above; the output still gets nothing of the batch.
                actions.truncate(mark);
                return Err(BatchError::item(index, err));
            }
        }
    }
    Ok(())
}

fn check_batch_len(n: usize) -> Result<usize, BatchError> {
    if n == 0 || n > MAX_BATCH_ITEMS {
        return Err(BatchError::Request(format!(
            "session_ids: expected 1 to {MAX_BATCH_ITEMS} items per batch, got {n}"
        )));
    }
    Ok(n)
}

/// The action values of a batch (the dimensions of its sessions added up) are bounded too, so that
/// the largest legal request has a size.
fn check_batch_values(total: usize) -> Result<usize, BatchError> {
    if total > MAX_BATCH_VALUES {
        return Err(BatchError::Request(format!(
            "session_ids: the sessions' action_dim add up to {total}, expected at most \
             {MAX_BATCH_VALUES} action values per batch; split the batch"
        )));
    }
    Ok(total)
}

fn check_field_len(field: &str, len: usize, n: usize) -> Result<(), BatchError> {
    if len != n {
        return Err(BatchError::Request(format!(
            "{field}: expected {n} values (one per session_ids item), got {len}"
        )));
    }
    Ok(())
}

/// A concatenated per-element field must hold exactly the batch's action values.
fn check_concatenated(field: &str, len: usize, total: usize, n: usize) -> Result<(), BatchError> {
    if len != total {
        return Err(BatchError::Request(format!(
            "{field}: expected {total} values (the action_dim of the {n} sessions \
             added up), got {len}"
        )));
    }
    Ok(())
}

/// Splits item `index`'s `d` action values off `actions`, and its `d` scales off `scales` unless
/// the batch has none.
fn item_values<'a>(
    actions: &mut &'a [f64],
    scales: &mut &'a [f64],
    d: usize,
    index: usize,
) -> Result<(&'a [f64], &'a [f64]), BatchError> {
    let action = take(actions, d, index, "actions")?;
    let scale = if scales.is_empty() {
        &[][..]
    } else {
        take(scales, d, index, "action_scales")?
    };
    Ok((action, scale))
}

/// Splits the next `d` values of `field` off `rest` (item `index`'s part).
fn take<'a>(
    rest: &mut &'a [f64],
    d: usize,
    index: usize,
    field: &str,
) -> Result<&'a [f64], BatchError> {
    let (head, tail) = rest.split_at_checked(d).ok_or_else(|| {
        BatchError::item(
            index,
            CoreError::InvalidArgument(format!("{field}: too few values for this item")),
        )
    })?;
    *rest = tail;
    Ok(head)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::SessionConfig;

    fn config(dim: u32) -> SessionConfig {
        SessionConfig {
            action_low: vec![-1.0],
            action_high: vec![1.0],
            trust_region: Some(0.5),
            normalize_response: true,
            ..SessionConfig::new(dim, 0.01, vec![0.2], vec![60.0], vec![0.25])
        }
    }

    fn sessions(dims: &[u32]) -> Vec<Session> {
        dims.iter()
            .map(|&d| Session::new(config(d)).expect("valid config"))
            .collect()
    }

    fn refs(sessions: &mut [Session]) -> Vec<&mut Session> {
        sessions.iter_mut().collect()
    }

    fn probe_all(
        sessions: &mut [Session],
        steps: &[u64],
        actions: &[f64],
        starts: &[bool],
        scales: &[f64],
    ) -> Result<(Vec<f64>, Vec<f64>), BatchError> {
        let (mut probes, mut applied) = (Vec::new(), Vec::new());
        probe(
            &mut refs(sessions),
            steps,
            actions,
            starts,
            scales,
            &mut probes,
            &mut applied,
        )?;
        Ok((probes, applied))
    }

    fn report_all(
        sessions: &mut [Session],
        steps: &[u64],
        q: &[f64],
        references: &[f64],
    ) -> Result<Vec<f64>, BatchError> {
        let mut actions = Vec::new();
        report(
            &mut refs(sessions),
            steps,
            q,
            references,
            &mut actions,
            |_, _| {},
        )?;
        Ok(actions)
    }

    /// Runs `request` on a copy of `sessions`, asserts it fails and changed nothing; returns the error.
    fn refused(
        sessions: &[Session],
        request: impl FnOnce(
            &mut [&mut Session],
            &mut Vec<f64>,
            &mut Vec<f64>,
        ) -> Result<(), BatchError>,
    ) -> BatchError {
        let mut copy = sessions.to_vec();
        let (mut a, mut b) = (vec![7.0], vec![8.0]);
        let err = request(&mut refs(&mut copy), &mut a, &mut b).expect_err("must be refused");
        assert_eq!(copy, sessions, "a refused batch changed a session ({err})");
        assert_eq!(
            (a, b),
            (vec![7.0], vec![8.0]),
            "a refused batch appended output"
        );
        err
    }

    #[test]
    fn a_batch_equals_its_items_one_by_one() {
        let dims = [1, 3, 2];
        let (mut batched, mut single) = (sessions(&dims), sessions(&dims));
        for t in 0..40u64 {
            let starts = [t == 0, t == 0 || t == 17, false];
            let steps: Vec<u64> = (0..3)
                .map(|i| if starts[i] { 0 } else { batched[i].step() })
                .collect();
            let actions: Vec<f64> = (0..6).map(|i| (t as f64 * 0.1 + i as f64).sin()).collect();
            let scales: Vec<f64> = (0..6).map(|i| 0.2 + 0.05 * i as f64).collect();
            let (probes, applied) =
                probe_all(&mut batched, &steps, &actions, &starts, &scales).unwrap();
            let (mut want_probes, mut want_applied, mut offset) = (Vec::new(), Vec::new(), 0);
            for (i, s) in single.iter_mut().enumerate() {
                let d = s.action_dim();
                let range = offset..offset + d;
                s.probe(
                    steps[i],
                    &actions[range.clone()],
                    &scales[range],
                    starts[i],
                    &mut want_probes,
                )
                .unwrap();
                s.applied_action(&mut want_applied);
                offset += d;
            }
            assert_eq!((&probes, &applied), (&want_probes, &want_applied));
            let q: Vec<f64> = probes.iter().take(3).map(|p| -p * p).collect();
            let references = [0.1, -0.2, 0.3];
            let reference_slice: &[f64] = if t % 2 == 0 { &references } else { &[] };
            let improved = report_all(&mut batched, &steps, &q, reference_slice).unwrap();
            let mut want = Vec::new();
            for (i, s) in single.iter_mut().enumerate() {
                s.report(steps[i], q[i], reference_slice.get(i).copied(), &mut want)
                    .unwrap();
            }
            assert_eq!(improved, want);
            assert_eq!(batched, single);
        }
    }

    #[test]
    fn outputs_are_appended() {
        let mut s = sessions(&[2]);
        let (mut probes, mut applied) = (vec![9.0], vec![]);
        probe(
            &mut refs(&mut s),
            &[0],
            &[0.1, 0.2],
            &[],
            &[],
            &mut probes,
            &mut applied,
        )
        .unwrap();
        assert_eq!((probes.len(), applied.len()), (3, 2));
        assert_eq!(probes[0], 9.0);
    }

    #[test]
    fn request_errors_have_no_index() {
        let s = sessions(&[2, 1]);
        let cases: Vec<(BatchError, &str)> =
            vec![
            (
                refused(&[], |ss, p, a| probe(ss, &[], &[], &[], &[], p, a)),
                "session_ids: expected 1 to 65536 items per batch, got 0",
            ),
            (
                refused(&s, |ss, p, a| probe(ss, &[0], &[0.0; 3], &[], &[], p, a)),
                "steps: expected 2 values (one per session_ids item), got 1",
            ),
            (
                refused(&s, |ss, p, a| {
                    probe(ss, &[0, 0], &[0.0; 3], &[true], &[], p, a)
                }),
                "episode_starts: expected 2 values (one per session_ids item), got 1",
            ),
            (
                refused(&s, |ss, p, a| probe(ss, &[0, 0], &[0.0; 2], &[], &[], p, a)),
                "actions: expected 3 values (the action_dim of the 2 sessions added up), got 2",
            ),
            (
                refused(&s, |ss, p, a| {
                    probe(ss, &[0, 0], &[0.0; 3], &[], &[1.0; 2], p, a)
                }),
                "action_scales: expected 3 values (the action_dim of the 2 sessions added up), \
                 got 2",
            ),
            (
                refused(&s, |ss, p, _| report(ss, &[0, 0], &[1.0], &[], p, |_, _| {})),
                "q_values: expected 2 values (one per session_ids item), got 1",
            ),
            (
                refused(&s, |ss, p, _| {
                    report(ss, &[0, 0], &[1.0, 2.0], &[1.0; 3], p, |_, _| {})
                }),
                "q_references: expected 2 values (one per session_ids item), got 3",
            ),
        ];
        for (err, message) in cases {
            assert_eq!(err, BatchError::Request(message.into()));
            assert_eq!(err.index(), None);
            assert_eq!(err.to_string(), message);
        }
    }

    #[test]
    fn the_batch_size_is_bounded() {
        assert!(check_probe_lengths(MAX_BATCH_ITEMS, MAX_BATCH_ITEMS, 0).is_ok());
        let err = check_probe_lengths(MAX_BATCH_ITEMS + 1, MAX_BATCH_ITEMS + 1, 0).unwrap_err();
        assert_eq!(
            err.to_string(),
            "session_ids: expected 1 to 65536 items per batch, got 65537"
        );
        assert!(check_report_lengths(0, 0, 0, 0).is_err());
        // 257 sessions of D = 4096 hold more than MAX_BATCH_VALUES action values.
        let mut big: Vec<Session> = (0..257)
            .map(|_| Session::new(config(4096)).unwrap())
            .collect();
        let total = 257 * 4096;
        let err = probe(
            &mut refs(&mut big),
            &[0; 257],
            &vec![0.0; total],
            &[],
            &[],
            &mut Vec::new(),
            &mut Vec::new(),
        )
        .unwrap_err();
        assert_eq!(err.index(), None);
        assert!(err.to_string().contains("add up to 1052672"), "{err}");
    }

    #[test]
    fn item_errors_carry_the_index_and_change_nothing() {
        let mut s = sessions(&[2, 1, 2]);
        probe_all(&mut s, &[0; 3], &[0.0; 5], &[], &[]).unwrap();
        let nan = [0.0, 0.0, 0.0, 0.0, f64::NAN];
        let err = refused(&s, |ss, p, a| probe(ss, &[0; 3], &nan, &[], &[], p, a));
        assert_eq!(err.index(), Some(2));
        assert!(matches!(
            err,
            BatchError::Item {
                error: CoreError::InvalidArgument(_),
                ..
            }
        ));
        assert_eq!(
            err.to_string(),
            "item 2: invalid argument: action[1]: expected a finite number, got NaN"
        );
        let err = refused(&s, |ss, p, a| {
            probe(
                ss,
                &[0; 3],
                &[0.0; 5],
                &[],
                &[1.0, 1.0, 0.0, 1.0, 1.0],
                p,
                a,
            )
        });
        assert_eq!(err.index(), Some(1));
        // A probe retry of step 0 is fine, step 1 is not (the report is missing).
        let err = refused(&s, |ss, p, a| {
            probe(ss, &[0, 1, 0], &[0.0; 5], &[], &[], p, a)
        });
        assert_eq!(
            err,
            BatchError::Item {
                index: 1,
                error: CoreError::StepMismatch {
                    expected: 0,
                    got: 1
                }
            }
        );
        // An episode start resets the expected step to 0 first.
        let err = refused(&s, |ss, p, a| {
            probe(ss, &[0, 0, 5], &[0.0; 5], &[false, false, true], &[], p, a)
        });
        assert_eq!(err.index(), Some(2));
        let err = refused(&s, |ss, p, _| {
            report(ss, &[0; 3], &[1.0, f64::INFINITY, 0.0], &[], p, |_, _| {})
        });
        assert_eq!(err.index(), Some(1));
        let err = refused(&s, |ss, p, _| {
            report(ss, &[0; 3], &[1.0; 3], &[0.0, 0.0, f64::NAN], p, |_, _| {})
        });
        assert_eq!(err.index(), Some(2));
        let err = refused(&s, |ss, p, _| {
            report(ss, &[0, 0, 1], &[1.0; 3], &[], p, |_, _| {})
        });
        assert_eq!(err.index(), Some(2));
        report_all(&mut s, &[0; 3], &[1.0; 3], &[]).unwrap();
        // Step 0 may be replayed now; a report for step 1 has no probe.
        let err = refused(&s, |ss, p, _| {
            report(ss, &[0, 1, 0], &[1.0; 3], &[], p, |_, _| {})
        });
        assert_eq!(
            err,
            BatchError::Item {
                index: 1,
                error: CoreError::NoPendingProbe { step: 1 }
            }
        );
    }

    #[test]
    fn the_first_failing_item_is_named() {
        let mut s = sessions(&[1, 1, 1]);
        probe_all(&mut s, &[0; 3], &[0.0; 3], &[], &[]).unwrap();
        let err = refused(&s, |ss, p, _| {
            report(ss, &[0, 3, 4], &[1.0, 1.0, f64::NAN], &[], p, |_, _| {})
        });
        assert_eq!(err.index(), Some(1));
    }

    #[test]
    fn replays_and_skips_are_reported_per_item() {
        let mut s = sessions(&[1, 1]);
        probe_all(&mut s, &[0, 0], &[0.0, 0.0], &[], &[]).unwrap();
        let first = report_all(&mut s, &[0, 0], &[1.0, 2.0], &[]).unwrap();
        probe_all(&mut s, &[1, 0], &[0.0, 0.0], &[false, true], &[]).unwrap();
        let mut outcomes = Vec::new();
        let mut actions = Vec::new();
        report(
            &mut refs(&mut s),
            &[1, 0],
            &[1.0, 2.0],
            &[],
            &mut actions,
            |index, outcome| outcomes.push((index, outcome.replayed)),
        )
        .unwrap();
        assert_eq!(outcomes, vec![(0, false), (1, false)]);
        // Item 0 replays step 1 (same action again), item 1 replays step 0.
        let mut outcomes = Vec::new();
        let mut again = Vec::new();
        report(
            &mut refs(&mut s),
            &[1, 0],
            &[5.0, 5.0],
            &[],
            &mut again,
            |index, outcome| outcomes.push((index, outcome.replayed)),
        )
        .unwrap();
        assert_eq!(outcomes, vec![(0, true), (1, true)]);
        assert_eq!(again, actions);
        assert_eq!(first.len(), 2);
    }
}
