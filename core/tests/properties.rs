//! Properties over any valid config and any request sequence: outputs are finite and inside the action
//! bounds, v stays inside the shift limit, refused requests change nothing, and `check_*` agree with the
//! requests they check.

use std::f64::consts::PI;

use esa_core::{Session, SessionConfig};
use proptest::collection::vec;
use proptest::prelude::*;

/// Any finite double, weighted towards ordinary magnitudes but with the extremes well represented.
fn finite() -> impl Strategy<Value = f64> {
    use proptest::num::f64::{NORMAL, SUBNORMAL, ZERO};
    prop_oneof![
        4 => -10.0..10.0f64,
        2 => NORMAL | SUBNORMAL | ZERO,
        1 => prop_oneof![Just(f64::MAX), Just(-f64::MAX), Just(1e308), Just(-1e308)],
    ]
}

fn non_finite() -> impl Strategy<Value = f64> {
    prop_oneof![Just(f64::NAN), Just(f64::INFINITY), Just(f64::NEG_INFINITY)]
}

/// A per-dimension field as a client may send it: one broadcast value or D values.
fn per_dim(
    dim: usize,
    value: impl Strategy<Value = f64> + Clone,
) -> impl Strategy<Value = Vec<f64>> {
    prop_oneof![vec(value.clone(), 1), vec(value, dim)]
}

/// Optional bounds: none, one side (possibly with `f64::MIN` elements: unbounded there), or both with lo < hi.
fn bounds(dim: usize) -> impl Strategy<Value = (Vec<f64>, Vec<f64>)> {
    let side = prop_oneof![4 => -100.0..100.0f64, 1 => Just(f64::MIN)];
    prop_oneof![
        Just((Vec::new(), Vec::new())),
        per_dim(dim, side.clone()).prop_map(|lo| (lo, Vec::new())),
        per_dim(dim, side).prop_map(|hi| (Vec::new(), hi.iter().map(|x| -x).collect())),
        prop::bool::ANY.prop_flat_map(move |broadcast| {
            let len = if broadcast { 1 } else { dim };
            (vec(-100.0..100.0f64, len), vec(1e-6..100.0f64, len)).prop_map(|(lo, width)| {
                let hi = lo.iter().zip(&width).map(|(l, w)| l + w).collect();
                (lo, hi)
            })
        }),
    ]
}

fn config() -> impl Strategy<Value = SessionConfig> {
    (1usize..=8, 1e-4..0.5f64).prop_flat_map(|(dim, dt)| {
        let gains = prop_oneof![6 => 0.0..10.0f64, 1 => Just(0.0), 1 => Just(1e300)];
        let rates = prop_oneof![6 => 0.0..1e3f64, 1 => Just(0.0), 1 => Just(1e300)];
        let optional_positive = prop::option::of(prop_oneof![1e-3..1e3f64, Just(1e300)]);
        (
            per_dim(dim, gains),
            per_dim(
                dim,
                (1e-3..0.999f64).prop_map(move |fraction| fraction * PI / dt),
            ),
            per_dim(dim, rates),
            (optional_positive.clone(), prop::bool::ANY),
            bounds(dim),
            optional_positive,
            prop::option::of(prop_oneof![1e-3..=1.0f64, Just(1.0)]),
            0u64..4,
        )
            .prop_map(
                move |(
                    amplitude,
                    frequency,
                    learning_rate,
                    highpass,
                    (low, high),
                    limit,
                    decay,
                    max,
                )| {
                    SessionConfig {
                        highpass_cutoff: highpass.0,
                        disable_highpass: highpass.1,
                        action_low: low,
                        action_high: high,
                        shift_limit: limit,
                        lr_decay: decay,
                        max_episodes: max,
                        ..SessionConfig::new(dim as u32, dt, amplitude, frequency, learning_rate)
                    }
                },
            )
    })
}

/// Which step a request names, relative to the session's state when it is sent.
#[derive(Clone, Debug)]
enum StepChoice {
    Current,
    Previous,
    Any(u64),
}

#[derive(Clone, Debug)]
enum Request {
    Probe {
        step: StepChoice,
        action: Vec<f64>,
        episode_start: bool,
    },
    Report {
        step: StepChoice,
        q: f64,
    },
    EndEpisode,
}

fn step_choice() -> impl Strategy<Value = StepChoice> {
    prop_oneof![
        8 => Just(StepChoice::Current),
        1 => Just(StepChoice::Previous),
        1 => any::<u64>().prop_map(StepChoice::Any),
    ]
}

fn request(dim: usize) -> impl Strategy<Value = Request> {
    let good_action = vec(finite(), dim);
    let wrong_length = (0usize..=dim + 1)
        .prop_filter("wrong length", move |n| *n != dim)
        .prop_flat_map(|n| vec(finite(), n));
    let with_non_finite = (vec(finite(), dim), 0..dim, non_finite()).prop_map(|(mut a, i, x)| {
        a[i] = x;
        a
    });
    let action = prop_oneof![10 => good_action, 1 => wrong_length, 1 => with_non_finite];
    let q = prop_oneof![10 => finite(), 1 => non_finite()];
    prop_oneof![
        5 => (step_choice(), action, prop::bool::weighted(0.05))
            .prop_map(|(step, action, episode_start)| Request::Probe { step, action, episode_start }),
        5 => (step_choice(), q).prop_map(|(step, q)| Request::Report { step, q }),
        1 => Just(Request::EndEpisode),
    ]
}

fn scenario() -> impl Strategy<Value = (SessionConfig, Vec<Request>)> {
    config().prop_flat_map(|config| {
        let dim = config.action_dim as usize;
        (Just(config), vec(request(dim), 1..120))
    })
}

/// The broadcast bound of dimension `i`, infinite when unset.
fn bound(values: &[f64], i: usize, unset: f64) -> f64 {
    match values {
        [] => unset,
        [only] => *only,
        _ => values[i],
    }
}

fn assert_valid_output(config: &SessionConfig, out: &[f64]) -> Result<(), TestCaseError> {
    prop_assert_eq!(out.len(), config.action_dim as usize);
    for (i, &x) in out.iter().enumerate() {
        let (lo, hi) = (
            bound(&config.action_low, i, f64::NEG_INFINITY),
            bound(&config.action_high, i, f64::INFINITY),
        );
        prop_assert!(x.is_finite(), "output[{}] = {} is not finite", i, x);
        prop_assert!(
            lo <= x && x <= hi,
            "output[{}] = {} outside [{}, {}]",
            i,
            x,
            lo,
            hi
        );
    }
    Ok(())
}

fn resolve(session: &Session, step: &StepChoice) -> u64 {
    match step {
        StepChoice::Current => session.step(),
        StepChoice::Previous => session.step().wrapping_sub(1),
        StepChoice::Any(step) => *step,
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 1024, ..ProptestConfig::default() })]

    #[test]
    fn outputs_stay_finite_and_bounded_and_refusals_change_nothing((config, requests) in scenario()) {
        let mut session = Session::new(config.clone()).expect("generated config is valid");
        // The session keeps no copy of the config; GetSession and idempotent CreateSession rely on
        // rebuilding it exactly, bit for bit, with every vector at the length it was given.
        prop_assert_eq!(format!("{:?}", session.config()), format!("{:?}", &config));
        let limit = config.shift_limit.unwrap_or(f64::INFINITY);
        let mut last_report: Option<(u64, Vec<f64>)> = None;
        for request in &requests {
            let before = session.clone();
            let mut out = Vec::new();
            let accepted = match request {
                Request::Probe { step, action, episode_start } => {
                    let step = match (episode_start, step) {
                        (true, StepChoice::Current) => 0,
                        _ => resolve(&session, step),
                    };
                    let checked = session.check_probe(step, action, *episode_start);
                    let result = session.probe(step, action, *episode_start, &mut out);
                    prop_assert_eq!(&checked, &result);
                    if result.is_ok() {
                        assert_valid_output(&config, &out)?;
                        prop_assert!(session.probe_pending());
                        last_report = None;
                    }
                    result.is_ok()
                }
                Request::Report { step, q } => {
                    let step = resolve(&session, step);
                    let checked = session.check_report(step, *q);
                    let result = session.report(step, *q, &mut out);
                    prop_assert_eq!(&checked, &result.as_ref().map(drop).map_err(Clone::clone));
                    if let Ok(outcome) = &result {
                        assert_valid_output(&config, &out)?;
                        if outcome.replayed {
                            prop_assert_eq!(&session, &before, "a replay updated the session");
                            prop_assert_eq!(last_report.as_ref(), Some(&(step, out.clone())));
                        } else {
                            prop_assert_eq!(session.step(), step + 1);
                            last_report = Some((step, out.clone()));
                        }
                    }
                    result.is_ok()
                }
                Request::EndEpisode => {
                    prop_assert_eq!(session.end_episode(), before.episodes_completed() + 1);
                    last_report = None;
                    true
                }
            };
            if !accepted {
                prop_assert_eq!(&session, &before, "a refused request changed the session");
                prop_assert!(out.is_empty(), "a refused request wrote output");
            }
            prop_assert_eq!(session.shift().len(), config.action_dim as usize);
            for &v in session.shift() {
                prop_assert!(v.is_finite() && -limit <= v && v <= limit, "v = {} outside [-{}, {}]", v, limit, limit);
            }
            if session.is_pass_through() {
                prop_assert!(session.shift().iter().all(|&v| v == 0.0));
            }
        }
    }
}
