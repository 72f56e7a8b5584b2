//! A saved session restored anywhere continues with the same bits as the one that kept running
//! (`Session::save`, `Session::restore`); a restore refuses any state no session could be in; a
//! resumed session (`Session::resume`) steps as the session whose episode count and response
//! scale it took.

use esa_core::{CoreError, SavedSession, Session, SessionConfig};
use proptest::prelude::*;

/// Section 1's law, and section 1b's with every field, with and without the high-pass.
fn configs() -> Vec<SessionConfig> {
    let plain = SessionConfig::new(2, 0.05, vec![0.2], vec![20.0, 9.0], vec![0.3, 0.1]);
    let full = SessionConfig {
        action_low: vec![-1.0],
        action_high: vec![1.0, 2.0],
        shift_limit: Some(0.5),
        lr_decay: Some(0.8),
        max_episodes: 4,
        normalize_response: true,
        response_rms_rate: Some(0.2),
        response_clip: Some(2.0),
        shift_leak: Some(0.01),
        trust_region: Some(1.5),
        ..plain.clone()
    };
    let raw = SessionConfig {
        disable_highpass: true,
        lr_decay: Some(0.5),
        normalize_response: true,
        ..plain.clone()
    };
    vec![plain, full, raw]
}

/// One request of a trainer (or of a client that retries and misbehaves).
#[derive(Clone, Debug)]
enum Request {
    Probe {
        start: bool,
        action: [f64; 2],
        scale: Option<f64>,
    },
    Report {
        q: f64,
        reference: Option<f64>,
        replay: bool,
    },
    EndEpisode,
}

fn request() -> impl Strategy<Value = Request> {
    let value = prop_oneof![8 => -5.0..5.0f64, 1 => Just(0.0), 1 => Just(1e200)];
    prop_oneof![
        4 => (prop::bool::weighted(0.1), [-2.0..2.0f64, -2.0..2.0f64], prop::option::of(0.1..2.0f64))
            .prop_map(|(start, action, scale)| Request::Probe { start, action, scale }),
        4 => (value.clone(), prop::option::of(value), prop::bool::weighted(0.1))
            .prop_map(|(q, reference, replay)| Request::Report { q, reference, replay }),
        1 => Just(Request::EndEpisode),
    ]
}

/// Applies `request` (refused ones change nothing) and returns every output, errors included.
fn apply(session: &mut Session, request: &Request) -> (Vec<f64>, Option<CoreError>) {
    let mut out = Vec::new();
    let result = match *request {
        Request::Probe {
            start,
            action,
            scale,
        } => {
            let step = if start { 0 } else { session.step() };
            let scale: Vec<f64> = scale.into_iter().collect();
            let probed = session.probe(step, &action, &scale, start, &mut out);
            session.applied_action(&mut out);
            probed
        }
        Request::Report {
            q,
            reference,
            replay,
        } => {
            let step = if replay {
                session.step().saturating_sub(1)
            } else {
                session.step()
            };
            session.report(step, q, reference, &mut out).map(drop)
        }
        Request::EndEpisode => {
            out.push(session.end_episode() as f64);
            Ok(())
        }
    };
    (out, result.err())
}

proptest! {
    #[test]
    fn a_restored_session_continues_bit_for_bit(
        config in 0usize..3,
        before in prop::collection::vec(request(), 0..60),
        after in prop::collection::vec(request(), 1..60),
    ) {
        let mut running = Session::new(configs()[config].clone()).unwrap();
        for request in &before {
            apply(&mut running, request);
        }
        let saved = running.save();
        let mut restored = Session::restore(saved.clone()).unwrap();
        prop_assert_eq!(&restored, &running);
        prop_assert_eq!(restored.save(), saved);
        for request in &after {
            let (expected, expected_err) = apply(&mut running, request);
            let (got, err) = apply(&mut restored, request);
            prop_assert_eq!(
                expected.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                got.iter().map(|x| x.to_bits()).collect::<Vec<_>>()
            );
            prop_assert_eq!(expected_err, err);
        }
        prop_assert_eq!(restored, running);
    }
}

#[test]
fn a_resumed_session_steps_as_the_one_it_continues() {
    let config = configs()[1].clone();
    let mut lived = Session::new(config.clone()).unwrap();
    let step = |session: &mut Session, t: u64| {
        let mut out = Vec::new();
        let action = [0.3 * (t as f64).sin(), -0.2];
        session.probe(t, &action, &[0.5], t == 0, &mut out).unwrap();
        session
            .report(t, (t as f64 * 0.7).cos(), Some(0.1), &mut out)
            .unwrap();
        out
    };
    for _ in 0..3 {
        for t in 0..20 {
            step(&mut lived, t);
        }
    }
    // The fourth episode starts with the next probe; its shift and filter start afresh.
    let mut resumed = Session::resume(config, 3, lived.response_mean_square()).unwrap();
    assert!(resumed.response_mean_square().is_some());
    assert_eq!(resumed.episodes_completed(), 3);
    for t in 0..20 {
        let (expected, got) = (step(&mut lived, t), step(&mut resumed, t));
        assert_eq!(
            expected.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            got.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            "step {t}"
        );
    }
    assert_eq!(resumed.save(), {
        let mut saved = lived.save();
        saved.nonfinite_skips = 0;
        saved
    });
}

#[test]
fn resume_past_max_episodes_is_a_pass_through() {
    let session = Session::resume(configs()[1].clone(), 4, None).unwrap();
    assert!(session.is_pass_through());
    assert_eq!(session.step(), 0);
}

#[test]
fn resume_checks_the_mean_square() {
    let cases = [
        (0, Some(1.0), "expected none without normalize_response"),
        (1, Some(-1.0), "expected a finite number >= 0, got -1"),
        (1, Some(f64::NAN), "expected a finite number >= 0"),
        (1, Some(f64::INFINITY), "expected a finite number >= 0"),
    ];
    for (config, m, message) in cases {
        let err = Session::resume(configs()[config].clone(), 0, m).unwrap_err();
        assert!(
            err.to_string().contains("response_mean_square") && err.to_string().contains(message),
            "{err}"
        );
    }
    assert!(Session::resume(configs()[1].clone(), u64::MAX, Some(0.0)).is_ok());
    let bad = SessionConfig {
        dt: -1.0,
        ..configs()[0].clone()
    };
    assert!(matches!(
        Session::resume(bad, 0, None),
        Err(CoreError::InvalidConfig(_))
    ));
}

#[test]
fn restore_refuses_a_state_no_session_could_be_in() {
    let mut session = Session::new(configs()[1].clone()).unwrap();
    let mut out = Vec::new();
    session.probe(0, &[0.1, 0.2], &[], true, &mut out).unwrap();
    session.report(0, 1.0, None, &mut out).unwrap();
    let good = session.save();
    assert!(good.report_replayable && good.washout.is_some());
    type Spoil = fn(&mut SavedSession);
    let cases: [(Spoil, &str); 12] = [
        (|s| s.shift.push(0.0), "shift: expected length 2"),
        (
            |s| s.shift[1] = f64::NAN,
            "shift[1]: expected a finite number",
        ),
        (|s| s.held_action[0] = f64::INFINITY, "held_action[0]"),
        (
            |s| s.held_sine[0] = 1.5,
            "held_sine[0]: expected a number in [-1, 1]",
        ),
        (
            |s| s.held_scale[1] = 0.0,
            "held_scale[1]: expected a finite number > 0",
        ),
        (|s| s.held_scale.clear(), "held_scale: expected length 2"),
        (
            |s| s.response_mean_square = Some(-2.0),
            "response_mean_square",
        ),
        (|s| s.probe_pending = true, "expected at most one, got both"),
        (
            |s| {
                s.step = 0;
            },
            "report_replayable: expected a step >= 1",
        ),
        (
            |s| s.washout = None,
            "washout: expected the filter's memory",
        ),
        (
            |s| {
                if let Some(memory) = &mut s.washout {
                    memory.previous_output = f64::NAN;
                }
            },
            "washout: expected a finite previous input and output",
        ),
        (|s| s.config.amplitude = vec![-1.0], "amplitude"),
    ];
    for (spoil, message) in cases {
        let mut saved = good.clone();
        spoil(&mut saved);
        let err = Session::restore(saved).unwrap_err();
        assert!(err.to_string().contains(message), "{message}: {err}");
    }
    let mut raw = Session::new(configs()[2].clone()).unwrap().save();
    assert!(raw.washout.is_none());
    raw.washout = good.washout;
    let err = Session::restore(raw).unwrap_err();
    assert!(err.to_string().contains("washout: expected none"), "{err}");
    let mut plain = Session::new(configs()[0].clone()).unwrap().save();
    plain.response_mean_square = Some(1.0);
    assert!(Session::restore(plain).is_err());
}
