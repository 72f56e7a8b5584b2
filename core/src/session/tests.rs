use approx::assert_relative_eq;

use super::*;

const DT: f64 = 0.01;
const W: [f64; 2] = [60.0, 75.0];
const K: f64 = 0.2;
const ALPHA: f64 = 0.25;

fn base() -> SessionConfig {
    SessionConfig::new(2, DT, vec![K], W.to_vec(), vec![ALPHA])
}

fn session(config: SessionConfig) -> Session {
    Session::new(config).expect("test config is valid")
}

fn probe(session: &mut Session, step: u64, action: &[f64], episode_start: bool) -> Vec<f64> {
    let mut out = Vec::new();
    session
        .probe(step, action, &[], episode_start, &mut out)
        .expect("probe accepted");
    out
}

fn report(session: &mut Session, step: u64, q: f64) -> (Vec<f64>, ReportOutcome) {
    let mut out = Vec::new();
    let outcome = session
        .report(step, q, None, &mut out)
        .expect("report accepted");
    (out, outcome)
}

/// One probe + report at the session's current step.
fn pair(session: &mut Session, action: &[f64], q: f64) -> (Vec<f64>, Vec<f64>) {
    let t = session.step();
    let p = probe(session, t, action, false);
    (p, report(session, t, q).0)
}

/// The session's sine is within one ulp of libm's (see `sine.rs`); results built on it match to this.
const TOL: f64 = 1e-14;

/// libm's `sin(w * (t * dt))`, the reference for the session's fast sine.
fn sine(w: f64, t: u64) -> f64 {
    (w * (t as f64 * DT)).sin()
}

/// Runs `request`, asserts it fails, that the session is exactly as before, and that `out` got nothing.
fn refused(
    session: &mut Session,
    request: impl FnOnce(&mut Session, &mut Vec<f64>) -> Result<(), CoreError>,
) -> CoreError {
    let before = session.clone();
    let mut out = vec![42.0];
    let err = request(session, &mut out).expect_err("request must be refused");
    assert_eq!(
        *session, before,
        "a refused request changed the session ({err})"
    );
    assert_eq!(out, vec![42.0], "a refused request wrote output ({err})");
    err
}

fn refused_probe(session: &mut Session, step: u64, action: &[f64], start: bool) -> CoreError {
    refused(session, |s, out| s.probe(step, action, &[], start, out))
}

fn refused_report(session: &mut Session, step: u64, q: f64) -> CoreError {
    refused(session, |s, out| s.report(step, q, None, out).map(drop))
}

#[test]
fn new_rejects_invalid_config() {
    let err = Session::new(SessionConfig { dt: 0.0, ..base() }).expect_err("dt = 0 is invalid");
    assert!(matches!(err, CoreError::InvalidConfig(m) if m.starts_with("dt:")));
}

#[test]
fn fresh_session_state() {
    let s = session(base());
    assert_eq!(
        (s.action_dim(), s.step(), s.episodes_completed()),
        (2, 0, 0)
    );
    assert_eq!(s.shift(), &[0.0, 0.0]);
    assert!(!s.probe_pending());
    assert!(!s.is_pass_through());
    assert_eq!(s.config(), base());
}

#[test]
fn probe_follows_the_law() {
    let mut s = session(SessionConfig {
        amplitude: vec![0.2, 0.3],
        ..base()
    });
    let a = [2.0, -1.0];
    pair(&mut s, &a, 0.0);
    pair(&mut s, &a, 1.5);
    let v = s.shift().to_vec();
    assert!(v.iter().any(|&x| x != 0.0), "the second report moves v");
    let p = probe(&mut s, 2, &a, false);
    for i in 0..2 {
        let k = [0.2, 0.3][i];
        assert_relative_eq!(p[i], a[i] + (v[i] + k * sine(W[i], 2)), epsilon = TOL);
    }
    assert!(s.probe_pending());
}

#[test]
fn broadcast_equals_explicit_vectors() {
    let explicit = SessionConfig {
        amplitude: vec![K, K],
        learning_rate: vec![ALPHA, ALPHA],
        action_low: vec![-3.0, -3.0],
        action_high: vec![3.0, 3.0],
        ..base()
    };
    let broadcast = SessionConfig {
        action_low: vec![-3.0],
        action_high: vec![3.0],
        ..base()
    };
    let (mut x, mut y) = (session(explicit), session(broadcast));
    for t in 0..50 {
        let a = [0.1 * t as f64, -0.05 * t as f64];
        let q = (t as f64 * 0.37).sin();
        assert_eq!(pair(&mut x, &a, q), pair(&mut y, &a, q));
    }
}

#[test]
fn first_report_of_an_episode_never_moves_v() {
    // s = sin(0) = 0 at t = 0, and the washout starts at rest, so v stays 0 whatever q is.
    let mut s = session(SessionConfig {
        disable_highpass: true,
        ..base()
    });
    let (action, outcome) = {
        probe(&mut s, 0, &[1.0, 2.0], true);
        report(&mut s, 0, 1e6)
    };
    assert_eq!(s.shift(), &[0.0, 0.0]);
    assert_eq!(action, vec![1.0, 2.0]);
    assert_eq!(outcome, ReportOutcome::default());
    assert_eq!((s.step(), s.probe_pending()), (1, false));
}

#[test]
fn disabled_highpass_uses_q_directly() {
    let mut s = session(SessionConfig {
        disable_highpass: true,
        ..base()
    });
    pair(&mut s, &[0.0, 0.0], 5.0);
    let (_, action) = pair(&mut s, &[1.0, 1.0], 2.0);
    for i in 0..2 {
        let v = ALPHA * sine(W[i], 1) * 2.0;
        assert_relative_eq!(s.shift()[i], v, epsilon = TOL);
        assert_relative_eq!(action[i], 1.0 + v, epsilon = TOL);
    }
}

#[test]
fn highpass_starts_at_rest_and_follows_the_washout() {
    let beta = 1.0 / (1.0 + 6.0 * DT);
    let qs = [10.0, 12.0, 11.0, -3.0, 4.0];
    let mut s = session(base());
    for episode in 0..2 {
        // A different q level on the first report of each episode must not leak into the next steps.
        let offset = 100.0 * episode as f64;
        let (mut y, mut x_prev, mut v) = (0.0, qs[0] + offset, [0.0; 2]);
        for (t, &q) in qs.iter().enumerate() {
            let q = q + offset;
            y = if t == 0 { 0.0 } else { beta * (y + q - x_prev) };
            x_prev = q;
            for (v, w) in v.iter_mut().zip(W) {
                *v += ALPHA * sine(w, t as u64) * y;
            }
            pair(&mut s, &[0.0, 0.0], q);
            for (got, want) in s.shift().iter().zip(v) {
                assert_relative_eq!(*got, want, epsilon = 1e-12);
            }
        }
        s.end_episode();
    }
}

#[test]
fn clipping_bounds_probe_and_action() {
    let config = SessionConfig {
        amplitude: vec![1.0],
        disable_highpass: true,
        action_low: vec![-0.5, f64::MIN],
        action_high: vec![0.5],
        ..base()
    };
    let mut s = session(config);
    pair(&mut s, &[0.0, 0.0], 0.0);
    let p = probe(&mut s, 1, &[3.0, -3.0], false);
    assert_eq!(p[0], 0.5);
    assert_relative_eq!(p[1], -3.0 + sine(W[1], 1), epsilon = TOL);
    let (action, _) = report(&mut s, 1, 0.0);
    assert_eq!(action, vec![0.5, -3.0]);
    let (p, action) = pair(&mut s, &[-7.0, 9.0], 0.0);
    assert_eq!(p[0], -0.5);
    assert_eq!(action, vec![-0.5, 0.5]);
}

#[test]
fn unbounded_outputs_saturate_instead_of_overflowing() {
    let mut s = session(SessionConfig {
        amplitude: vec![f64::MAX],
        ..base()
    });
    pair(&mut s, &[0.0, 0.0], 0.0);
    let (p, action) = pair(&mut s, &[f64::MAX, f64::MAX], 1.0);
    assert_eq!(
        p,
        vec![f64::MAX, f64::MAX],
        "a + K s overflows in both dimensions at t = 1"
    );
    assert!(action.iter().all(|x| x.is_finite()));
}

#[test]
fn shift_limit_clamps_v() {
    let config = SessionConfig {
        learning_rate: vec![1e3],
        disable_highpass: true,
        shift_limit: Some(0.3),
        ..base()
    };
    let mut s = session(config);
    for t in 0..40 {
        pair(&mut s, &[0.0, 0.0], if t % 2 == 0 { 50.0 } else { -50.0 });
        assert!(
            s.shift().iter().all(|v| v.abs() <= 0.3),
            "v = {:?}",
            s.shift()
        );
    }
    assert!(
        s.shift().iter().any(|v| v.abs() == 0.3),
        "the limit is reached with this alpha"
    );
}

/// v after one report of `q` at step 1 of the current episode, without high-pass.
fn shift_after_step_one(s: &mut Session, q: f64) -> Vec<f64> {
    pair(s, &[0.0, 0.0], 0.0);
    pair(s, &[0.0, 0.0], q);
    let v = s.shift().to_vec();
    s.end_episode();
    v
}

#[test]
fn learning_rate_decays_per_completed_episode() {
    let mut s = session(SessionConfig {
        disable_highpass: true,
        lr_decay: Some(0.5),
        ..base()
    });
    for e in 0..4 {
        assert_eq!(s.episodes_completed(), e);
        let v = shift_after_step_one(&mut s, 3.0);
        for i in 0..2 {
            assert_relative_eq!(
                v[i],
                ALPHA * 0.5f64.powi(e as i32) * sine(W[i], 1) * 3.0,
                epsilon = 1e-15
            );
        }
    }
}

#[test]
fn no_decay_when_unset() {
    let mut s = session(SessionConfig {
        disable_highpass: true,
        ..base()
    });
    let first = shift_after_step_one(&mut s, 3.0);
    for _ in 0..3 {
        assert_eq!(shift_after_step_one(&mut s, 3.0), first);
    }
}

#[test]
fn pass_through_after_max_episodes() {
    let config = SessionConfig {
        max_episodes: 2,
        disable_highpass: true,
        action_low: vec![-1.0],
        action_high: vec![1.0],
        ..base()
    };
    let mut s = session(config);
    assert!(shift_after_step_one(&mut s, 3.0).iter().all(|&v| v != 0.0));
    assert!(!s.is_pass_through());
    assert!(shift_after_step_one(&mut s, 3.0).iter().all(|&v| v != 0.0));
    assert!(s.is_pass_through());
    for t in 0..5 {
        let (p, action) = pair(&mut s, &[0.25, 4.0], 1e3);
        assert_eq!(p, vec![0.25, 1.0]);
        assert_eq!(action, vec![0.25, 1.0]);
        assert_eq!(s.shift(), &[0.0, 0.0]);
        assert_eq!(s.step(), t + 1);
    }
    // The protocol is unchanged: a report still needs its probe.
    assert_eq!(
        refused_report(&mut s, 5, 1.0),
        CoreError::NoPendingProbe { step: 5 }
    );
    assert_eq!(s.end_episode(), 3);
    assert!(s.is_pass_through());
}

#[test]
fn unlimited_episodes_never_pass_through() {
    let mut s = session(base());
    for _ in 0..10 {
        s.end_episode();
    }
    assert!(!s.is_pass_through());
}

#[test]
fn step_mismatch_is_refused() {
    let mut s = session(base());
    pair(&mut s, &[0.0, 0.0], 1.0);
    let err = refused_probe(&mut s, 0, &[0.0, 0.0], false);
    assert_eq!(
        err,
        CoreError::StepMismatch {
            expected: 1,
            got: 0
        }
    );
    assert_eq!(err.to_string(), "step mismatch: expected step 1, got 0");
    let err = refused_probe(&mut s, 2, &[0.0, 0.0], false);
    assert_eq!(
        err,
        CoreError::StepMismatch {
            expected: 1,
            got: 2
        }
    );
    probe(&mut s, 1, &[0.0, 0.0], false);
    let err = refused_report(&mut s, 2, 1.0);
    assert_eq!(
        err,
        CoreError::StepMismatch {
            expected: 1,
            got: 2
        }
    );
    let err = refused_report(&mut s, u64::MAX, 1.0);
    assert_eq!(
        err,
        CoreError::StepMismatch {
            expected: 1,
            got: u64::MAX
        }
    );
}

#[test]
fn report_without_probe_is_refused() {
    let mut s = session(base());
    let err = refused_report(&mut s, 0, 1.0);
    assert_eq!(err, CoreError::NoPendingProbe { step: 0 });
    assert_eq!(
        err.to_string(),
        "no pending probe at step 0: call Probe before Report"
    );
    pair(&mut s, &[0.0, 0.0], 1.0);
    assert_eq!(
        refused_report(&mut s, 1, 1.0),
        CoreError::NoPendingProbe { step: 1 }
    );
}

#[test]
fn probe_retry_replaces_the_pending_action() {
    let mut s = session(SessionConfig {
        disable_highpass: true,
        ..base()
    });
    pair(&mut s, &[0.0, 0.0], 1.0);
    let first = probe(&mut s, 1, &[1.0, 1.0], false);
    assert_eq!(
        probe(&mut s, 1, &[1.0, 1.0], false),
        first,
        "the probe is deterministic"
    );
    let replaced = probe(&mut s, 1, &[2.0, -2.0], false);
    for i in 0..2 {
        assert_relative_eq!(
            replaced[i],
            [2.0, -2.0][i] + K * sine(W[i], 1),
            epsilon = TOL
        );
    }
    let (action, _) = report(&mut s, 1, 1.0);
    for i in 0..2 {
        assert_eq!(action[i], [2.0, -2.0][i] + s.shift()[i]);
    }
}

#[test]
fn report_retry_replays_without_updating() {
    let mut s = session(base());
    pair(&mut s, &[0.0, 0.0], 1.0);
    probe(&mut s, 1, &[0.5, 0.5], false);
    let (action, outcome) = report(&mut s, 1, 7.0);
    assert!(!outcome.replayed);
    let after = s.clone();
    for q in [7.0, -1e300] {
        let (again, outcome) = report(&mut s, 1, q);
        assert_eq!(again, action);
        assert_eq!(
            outcome,
            ReportOutcome {
                replayed: true,
                nonfinite_skipped: false
            }
        );
        assert_eq!(s, after, "a replay updates nothing");
    }
    // The replayed q must still be valid.
    assert!(matches!(
        refused_report(&mut s, 1, f64::NAN),
        CoreError::InvalidArgument(m) if m.starts_with("q_value:")
    ));
    // Once the next probe arrives, step t - 1 is history.
    probe(&mut s, 2, &[0.5, 0.5], false);
    assert_eq!(
        refused_report(&mut s, 1, 7.0),
        CoreError::StepMismatch {
            expected: 2,
            got: 1
        }
    );
}

#[test]
fn report_retry_is_impossible_after_an_episode_end() {
    let mut s = session(base());
    pair(&mut s, &[0.0, 0.0], 1.0);
    s.end_episode();
    assert_eq!(
        refused_report(&mut s, 0, 1.0),
        CoreError::NoPendingProbe { step: 0 }
    );
}

#[test]
fn end_episode_resets_the_episode_state() {
    let mut s = session(SessionConfig {
        disable_highpass: true,
        ..base()
    });
    pair(&mut s, &[0.0, 0.0], 1.0);
    pair(&mut s, &[0.0, 0.0], 1.0);
    probe(&mut s, 2, &[0.0, 0.0], false);
    assert_eq!(s.end_episode(), 1);
    assert_eq!(
        (s.step(), s.probe_pending(), s.shift()),
        (0, false, &[0.0, 0.0][..])
    );
    assert_eq!(s.end_episode(), 2);
}

#[test]
fn episode_start_ends_a_running_episode() {
    let mut s = session(SessionConfig {
        disable_highpass: true,
        ..base()
    });
    pair(&mut s, &[0.0, 0.0], 1.0);
    pair(&mut s, &[0.0, 0.0], 1.0);
    assert_ne!(s.shift(), &[0.0, 0.0]);
    let p = probe(&mut s, 0, &[1.0, 2.0], true);
    assert_eq!(p, vec![1.0, 2.0], "v was reset and s(0) = 0");
    assert_eq!(
        (s.episodes_completed(), s.step(), s.probe_pending()),
        (1, 0, true)
    );
    assert_eq!(s.shift(), &[0.0, 0.0]);
}

#[test]
fn episode_start_on_a_fresh_episode_changes_nothing() {
    let mut s = session(base());
    let mut plain = s.clone();
    assert_eq!(
        probe(&mut s, 0, &[1.0, 2.0], true),
        probe(&mut plain, 0, &[1.0, 2.0], false)
    );
    assert_eq!(s, plain);
    assert_eq!(s.episodes_completed(), 0);
    s.end_episode();
    probe(&mut s, 0, &[1.0, 2.0], true);
    assert_eq!(
        s.episodes_completed(),
        1,
        "an explicit end followed by episode_start counts once"
    );
}

#[test]
fn episode_start_with_a_pending_step_zero_probe_ends_that_episode() {
    // CONTRACT.md: "t > 0 or a pending probe" ends the episode, even at t = 0.
    let mut s = session(base());
    probe(&mut s, 0, &[1.0, 2.0], true);
    probe(&mut s, 0, &[1.0, 2.0], true);
    assert_eq!(
        (s.episodes_completed(), s.step(), s.probe_pending()),
        (1, 0, true)
    );
}

#[test]
fn episode_start_requires_step_zero_and_a_refusal_changes_nothing() {
    let mut s = session(base());
    pair(&mut s, &[0.0, 0.0], 1.0);
    pair(&mut s, &[0.0, 0.0], 2.0);
    let err = refused_probe(&mut s, 2, &[0.0, 0.0], true);
    assert_eq!(
        err,
        CoreError::StepMismatch {
            expected: 0,
            got: 2
        }
    );
    assert_eq!(s.episodes_completed(), 0);
    let err = refused_probe(&mut s, 0, &[0.0, f64::NAN], true);
    assert!(matches!(err, CoreError::InvalidArgument(_)));
    assert_eq!((s.episodes_completed(), s.step()), (0, 2));
}

#[test]
fn nonfinite_update_is_skipped() {
    let config = SessionConfig {
        learning_rate: vec![1e300],
        disable_highpass: true,
        ..base()
    };
    let mut s = session(config);
    pair(&mut s, &[0.0, 0.0], 1e308);
    probe(&mut s, 1, &[1.0, 1.0], false);
    let (action, outcome) = report(&mut s, 1, 1e308);
    assert_eq!(
        outcome,
        ReportOutcome {
            replayed: false,
            nonfinite_skipped: true
        }
    );
    assert_eq!(s.shift(), &[0.0, 0.0]);
    assert_eq!(action, vec![1.0, 1.0]);
    assert_eq!((s.step(), s.nonfinite_skips()), (2, 1));
    probe(&mut s, 2, &[1.0, 1.0], false);
    let (_, outcome) = report(&mut s, 2, 1e-300);
    assert!(!outcome.nonfinite_skipped, "a moderate q updates as usual");
    assert_ne!(s.shift(), &[0.0, 0.0]);
}

#[test]
fn highpass_overflow_skips_once_and_recovers() {
    // Tiny alpha: only the overflowed filter output can make the update non-finite.
    let mut s = session(SessionConfig {
        learning_rate: vec![1e-300],
        ..base()
    });
    pair(&mut s, &[0.0, 0.0], -f64::MAX);
    let t = s.step();
    probe(&mut s, t, &[0.0, 0.0], false);
    assert!(report(&mut s, t, f64::MAX).1.nonfinite_skipped);
    for q in [f64::MAX, 1.0, 2.0] {
        let t = s.step();
        probe(&mut s, t, &[0.0, 0.0], false);
        assert!(
            !report(&mut s, t, q).1.nonfinite_skipped,
            "the washout restarted at rest"
        );
    }
    assert!(s.shift().iter().all(|v| v.is_finite()));
}

#[test]
fn shift_limit_turns_an_overflow_into_the_limit() {
    // clamp(+-inf, -L, L) is finite, so with a shift limit the update is applied, not skipped.
    let config = SessionConfig {
        learning_rate: vec![1e300],
        disable_highpass: true,
        shift_limit: Some(2.0),
        ..base()
    };
    let mut s = session(config);
    pair(&mut s, &[0.0, 0.0], 0.0);
    probe(&mut s, 1, &[0.0, 0.0], false);
    let (action, outcome) = report(&mut s, 1, 1e308);
    assert!(!outcome.nonfinite_skipped);
    assert_eq!(s.shift(), &[2.0, 2.0]);
    assert_eq!(action, vec![2.0, 2.0]);
}

#[test]
fn bad_action_is_refused() {
    let mut s = session(base());
    pair(&mut s, &[0.0, 0.0], 1.0);
    for bad in [&[0.0][..], &[0.0, 0.0, 0.0], &[]] {
        let err = refused_probe(&mut s, 1, bad, false);
        assert_eq!(
            err,
            CoreError::InvalidArgument(format!(
                "action: expected length 2 (action_dim), got {}",
                bad.len()
            ))
        );
    }
    for x in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let err = refused_probe(&mut s, 1, &[0.0, x], false);
        assert_eq!(
            err,
            CoreError::InvalidArgument(format!("action[1]: expected a finite number, got {x}"))
        );
        assert!(s.check_probe(1, &[x, 0.0], &[], false).is_err());
    }
    assert_eq!(s.check_probe(1, &[0.0, 0.0], &[], false), Ok(()));
}

#[test]
fn nonfinite_q_is_refused() {
    let mut s = session(base());
    probe(&mut s, 0, &[0.0, 0.0], false);
    for q in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let err = refused_report(&mut s, 0, q);
        assert_eq!(
            err,
            CoreError::InvalidArgument(format!("q_value: expected a finite number, got {q}"))
        );
    }
    assert_eq!(s.check_report(0, 1.0, None), Ok(()));
}

#[test]
fn outputs_are_appended() {
    let mut s = session(base());
    let mut out = vec![9.0];
    s.probe(0, &[1.0, 2.0], &[], false, &mut out)
        .expect("probe");
    s.report(0, 0.0, None, &mut out).expect("report");
    assert_eq!(out, vec![9.0, 1.0, 2.0, 1.0, 2.0]);
}

// ---- CONTRACT.md section 1b: applied action, action scale, paired response, normalization, leak, trust ----

fn report_paired(session: &mut Session, step: u64, q: f64, reference: Option<f64>) -> Vec<f64> {
    let mut out = Vec::new();
    session
        .report(step, q, reference, &mut out)
        .expect("report accepted");
    out
}

fn probe_scaled(session: &mut Session, step: u64, action: &[f64], scale: &[f64]) -> Vec<f64> {
    let mut out = Vec::new();
    session
        .probe(step, action, scale, false, &mut out)
        .expect("probe accepted");
    out
}

fn applied(session: &Session) -> Vec<f64> {
    let mut out = Vec::new();
    session.applied_action(&mut out);
    out
}

/// Filter off, so h = x and every expectation is a closed form.
fn raw(config: SessionConfig) -> SessionConfig {
    SessionConfig {
        disable_highpass: true,
        ..config
    }
}

#[test]
fn applied_action_is_the_shift_before_the_update() {
    let mut s = session(SessionConfig {
        action_low: vec![-1.0],
        action_high: vec![1.0],
        ..raw(base())
    });
    probe(&mut s, 0, &[0.5, -0.5], false);
    assert_eq!(applied(&s), vec![0.5, -0.5], "v(0) = 0");
    report(&mut s, 0, 3.0);
    let v1 = s.shift().to_vec();
    probe(&mut s, 1, &[0.9, 0.0], false);
    let expected: Vec<f64> = [0.9, 0.0]
        .iter()
        .zip(&v1)
        .map(|(a, v)| (a + v).clamp(-1.0, 1.0))
        .collect();
    assert_eq!(applied(&s), expected);
    // The report's action uses v(t + 1); the probe's applied action does not depend on Q.
    let after = report(&mut s, 1, 2.0).0;
    assert_eq!(applied(&s), after);
}

#[test]
fn applied_action_in_pass_through_is_the_clipped_sample() {
    let mut s = session(SessionConfig {
        max_episodes: 1,
        action_low: vec![-1.0],
        action_high: vec![1.0],
        ..base()
    });
    s.end_episode();
    probe(&mut s, 0, &[3.0, 0.25], false);
    assert_eq!(applied(&s), vec![1.0, 0.25]);
}

#[test]
fn unset_section_1b_fields_and_unit_scale_give_section_1_bit_for_bit() {
    let plain = base();
    let explicit = SessionConfig {
        shift_leak: Some(0.0),
        response_rms_rate: Some(0.3),
        response_clip: Some(0.1),
        ..base()
    };
    let (mut a, mut b) = (session(plain), session(explicit));
    for t in 0..50 {
        let action = [0.1 * t as f64, -0.2];
        let pa = probe(&mut a, t, &action, false);
        let pb = probe_scaled(&mut b, t, &action, &[1.0]);
        assert_eq!(pa, pb);
        let q = -(pa[0] - 0.3).powi(2) + (t as f64).sin();
        assert_eq!(report(&mut a, t, q).0, report(&mut b, t, q).0);
    }
    assert_eq!(a.shift(), b.shift());
}

#[test]
fn q_reference_makes_the_response_a_difference() {
    let (mut paired, mut direct) = (session(raw(base())), session(raw(base())));
    for t in 0..20 {
        probe(&mut paired, t, &[0.0, 0.0], false);
        probe(&mut direct, t, &[0.0, 0.0], false);
        let q = 1.5 + t as f64;
        let reference = 0.25 * t as f64;
        assert_eq!(
            report_paired(&mut paired, t, q, Some(reference)),
            report_paired(&mut direct, t, q - reference, None)
        );
    }
}

#[test]
fn normalized_step_seeds_m_with_the_first_nonzero_response() {
    let config = SessionConfig {
        normalize_response: true,
        ..raw(base())
    };
    let mut s = session(config);
    // t = 0: sin(0) = 0 in both dims, but m is still seeded by h = 4.
    probe_scaled(&mut s, 0, &[0.0, 0.0], &[0.5]);
    report_paired(&mut s, 0, 4.0, None);
    assert_eq!(s.response_mean_square(), Some(16.0));
    assert_eq!(s.shift(), &[0.0, 0.0]);
    // t = 1: m = 0.95 * 16 + 0.05 * 4 = 15.4, g = -2 / sqrt(15.4 + 1e-12) (inside the clip of 3).
    probe_scaled(&mut s, 1, &[0.0, 0.0], &[0.5, 2.0]);
    report_paired(&mut s, 1, -2.0, None);
    let m = 0.95 * 16.0 + 0.05 * 4.0;
    assert_eq!(s.response_mean_square(), Some(m));
    let g = -2.0 / (m + 1e-12_f64).sqrt();
    for (i, (&v, sigma)) in s.shift().iter().zip([0.5, 2.0]).enumerate() {
        let expected = ALPHA * sigma * sine(W[i], 1) * g;
        assert_relative_eq!(v, expected, epsilon = TOL);
    }
}

#[test]
fn normalized_response_is_clipped_and_zero_until_seeded() {
    let config = SessionConfig {
        normalize_response: true,
        response_rms_rate: Some(1.0),
        response_clip: Some(0.5),
        ..raw(base())
    };
    let mut s = session(config);
    probe(&mut s, 0, &[0.0, 0.0], false);
    report(&mut s, 0, 0.0);
    assert_eq!(s.response_mean_square(), None, "h = 0 does not seed m");
    probe(&mut s, 1, &[0.0, 0.0], false);
    report(&mut s, 1, 7.0);
    // rho = 1: m = h^2, g = h / |h| = 1, clipped to 0.5.
    assert_eq!(s.response_mean_square(), Some(49.0));
    for (i, &v) in s.shift().iter().enumerate() {
        assert_relative_eq!(v, ALPHA * sine(W[i], 1) * 0.5, epsilon = TOL);
    }
}

#[test]
fn mean_square_survives_episode_ends() {
    let mut s = session(SessionConfig {
        normalize_response: true,
        ..raw(base())
    });
    probe(&mut s, 0, &[0.0, 0.0], false);
    report(&mut s, 0, 2.0);
    s.end_episode();
    assert_eq!(s.response_mean_square(), Some(4.0));
    assert_eq!(s.shift(), &[0.0, 0.0]);
}

#[test]
fn leak_decays_the_shift_before_the_step() {
    let lambda = 0.25;
    let mut s = session(SessionConfig {
        shift_leak: Some(lambda),
        ..raw(base())
    });
    pair(&mut s, &[0.0, 0.0], 1.0);
    let v1 = s.shift().to_vec();
    pair(&mut s, &[0.0, 0.0], 1.0);
    for (i, (&v, &before)) in s.shift().iter().zip(&v1).enumerate() {
        assert_relative_eq!(
            v,
            (1.0 - lambda) * before + ALPHA * sine(W[i], 1),
            epsilon = TOL
        );
    }
}

#[test]
fn trust_region_bounds_v_by_kappa_sigma_and_the_shift_limit() {
    let mut s = session(SessionConfig {
        trust_region: Some(2.0),
        shift_limit: Some(0.3),
        ..raw(base())
    });
    for t in 0..30 {
        probe_scaled(&mut s, t, &[0.0, 0.0], &[0.1, 1.0]);
        report(&mut s, t, 1e9 * if t % 2 == 0 { 1.0 } else { -1.0 });
        assert!(
            s.shift()[0].abs() <= 0.2,
            "kappa sigma = 0.2: {:?}",
            s.shift()
        );
        assert!(
            s.shift()[1].abs() <= 0.3,
            "L = 0.3 < kappa sigma: {:?}",
            s.shift()
        );
    }
    assert_eq!(s.shift()[0].abs(), 0.2);
}

#[test]
fn a_later_probe_scale_replaces_the_pending_one() {
    let mut s = session(SessionConfig {
        trust_region: Some(1.0),
        ..raw(base())
    });
    probe_scaled(&mut s, 0, &[0.0, 0.0], &[1e-3]);
    probe_scaled(&mut s, 0, &[0.0, 0.0], &[]);
    probe(&mut s, 0, &[0.0, 0.0], false);
    report(&mut s, 0, 1.0);
    probe(&mut s, 1, &[0.0, 0.0], false);
    report(&mut s, 1, 1e6);
    // sigma = 1 (the last probe sent none): bound 1, not 1e-3.
    assert!(s.shift().iter().any(|v| v.abs() > 1e-3), "{:?}", s.shift());
}

#[test]
fn bad_action_scale_is_refused_and_changes_nothing() {
    let mut s = session(base());
    for scale in [
        vec![0.0],
        vec![-1.0],
        vec![f64::NAN],
        vec![f64::INFINITY],
        vec![1.0, f64::NEG_INFINITY],
        vec![1.0, 1.0, 1.0],
    ] {
        let err = refused(&mut s, |s, out| s.probe(0, &[0.0, 0.0], &scale, false, out));
        assert!(
            matches!(&err, CoreError::InvalidArgument(m) if m.starts_with("action_scale")),
            "{err}"
        );
    }
}

#[test]
fn non_finite_q_reference_is_refused_and_changes_nothing() {
    let mut s = session(base());
    probe(&mut s, 0, &[0.0, 0.0], false);
    for reference in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let err = refused(&mut s, |s, out| {
            s.report(0, 1.0, Some(reference), out).map(drop)
        });
        assert!(
            matches!(&err, CoreError::InvalidArgument(m) if m.starts_with("q_reference")),
            "{err}"
        );
    }
}

#[test]
fn an_overflowing_mean_square_skips_the_report_and_keeps_m() {
    let mut s = session(SessionConfig {
        normalize_response: true,
        ..raw(base())
    });
    pair(&mut s, &[0.0, 0.0], 1.0);
    pair(&mut s, &[0.0, 0.0], 1.0);
    let (m, v) = (s.response_mean_square(), s.shift().to_vec());
    probe(&mut s, 2, &[0.0, 0.0], false);
    let mut out = Vec::new();
    let outcome = s
        .report(2, f64::MAX, Some(-f64::MAX), &mut out)
        .expect("finite inputs are accepted");
    assert!(outcome.nonfinite_skipped);
    assert_eq!((s.response_mean_square(), s.shift()), (m, &v[..]));
    assert_eq!(s.step(), 3);
    assert!(out.iter().all(|x| x.is_finite()));
}

#[test]
fn config_round_trips_the_section_1b_fields() {
    let config = SessionConfig {
        normalize_response: true,
        response_rms_rate: Some(0.2),
        response_clip: Some(1.5),
        shift_leak: Some(0.0),
        trust_region: Some(0.75),
        ..base()
    };
    assert_eq!(session(config.clone()).config(), config);
}

#[test]
fn a_probe_clamps_v_into_its_own_trust_region() {
    let mut s = session(SessionConfig {
        trust_region: Some(1.0),
        ..raw(base())
    });
    probe_scaled(&mut s, 0, &[0.0, 0.0], &[1.0]);
    report(&mut s, 0, 1e12);
    probe_scaled(&mut s, 1, &[0.0, 0.0], &[1.0]);
    report(&mut s, 1, -1e12);
    assert!(s.shift().iter().any(|v| v.abs() > 0.5), "{:?}", s.shift());
    // sigma shrank: the applied action of this step must stay within kappa * 0.01.
    probe_scaled(&mut s, 2, &[0.0, 0.0], &[0.01]);
    for &a in &applied(&s) {
        assert!(a.abs() <= 0.01, "applied {a}");
    }
}
