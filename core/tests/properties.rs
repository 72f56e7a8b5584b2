//! Properties over any valid config and any request sequence: outputs are finite and inside the action
//! bounds, v stays inside the shift limit and the trust region (`|v| <= kappa * sigma`, CONTRACT.md
//! section 1b), refused requests change nothing, and `check_*` agree with the requests they check. With
//! `normalize_response`, Q and `c1 * Q + c0` give the same actions. The applied action a client computes
//! ahead from the shift (`Session::applied_with_shift`, `Session::probe_with_shift`) is the probe's,
//! bit for bit, and so is the probe computed ahead.

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
            section_1b(),
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
                    extra,
                )| {
                    SessionConfig {
                        highpass_cutoff: highpass.0,
                        disable_highpass: highpass.1,
                        action_low: low,
                        action_high: high,
                        shift_limit: limit,
                        lr_decay: decay,
                        max_episodes: max,
                        normalize_response: extra.normalize_response,
                        response_rms_rate: extra.response_rms_rate,
                        response_clip: extra.response_clip,
                        shift_leak: extra.shift_leak,
                        trust_region: extra.trust_region,
                        ..SessionConfig::new(dim as u32, dt, amplitude, frequency, learning_rate)
                    }
                },
            )
    })
}

/// The fields of CONTRACT.md section 1b, each unset or any valid value (extremes included).
#[derive(Clone, Debug)]
struct Section1b {
    normalize_response: bool,
    response_rms_rate: Option<f64>,
    response_clip: Option<f64>,
    shift_leak: Option<f64>,
    trust_region: Option<f64>,
}

fn section_1b() -> impl Strategy<Value = Section1b> {
    let positive = prop_oneof![1e-3..1e3f64, Just(1e300), Just(f64::MIN_POSITIVE)];
    (
        prop::bool::ANY,
        prop::option::of(prop_oneof![1e-6..=1.0f64, Just(1.0)]),
        prop::option::of(positive.clone()),
        prop::option::of(prop_oneof![0.0..0.999f64, Just(0.0)]),
        prop::option::of(positive),
    )
        .prop_map(|(normalize_response, rate, clip, leak, trust)| Section1b {
            normalize_response,
            response_rms_rate: rate,
            response_clip: clip,
            shift_leak: leak,
            trust_region: trust,
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
        scale: Vec<f64>,
        episode_start: bool,
    },
    Report {
        step: StepChoice,
        q: f64,
        reference: Option<f64>,
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
    let sigma = prop_oneof![8 => 1e-3..10.0f64, 1 => Just(1e300), 1 => Just(f64::MIN_POSITIVE)];
    let bad_sigma = prop_oneof![Just(0.0), Just(-1.0), non_finite()];
    let scale = prop_oneof![
        4 => Just(Vec::new()),
        4 => vec(sigma.clone(), 1),
        4 => vec(sigma.clone(), dim),
        1 => (vec(sigma, dim), 0..dim, bad_sigma).prop_map(|(mut s, i, x)| {
            s[i] = x;
            s
        }),
        1 => (dim + 1..dim + 3).prop_flat_map(|n| vec(1e-3..10.0f64, n)),
    ];
    let q = prop_oneof![10 => finite(), 1 => non_finite()];
    let reference = prop_oneof![4 => Just(None), 4 => finite().prop_map(Some), 1 => non_finite().prop_map(Some)];
    prop_oneof![
        5 => (step_choice(), action, scale, prop::bool::weighted(0.05)).prop_map(
            |(step, action, scale, episode_start)| Request::Probe { step, action, scale, episode_start }
        ),
        5 => (step_choice(), q, reference)
            .prop_map(|(step, q, reference)| Request::Report { step, q, reference }),
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
        let trust = config.trust_region.unwrap_or(f64::INFINITY);
        // sigma of the pending probe, and of the last report (its bound holds until the next report).
        let (mut pending_scale, mut bound_scale) = (vec![1.0; config.action_dim as usize], vec![1.0; config.action_dim as usize]);
        let mut last_report: Option<(u64, Vec<f64>)> = None;
        for request in &requests {
            let before = session.clone();
            let mut out = Vec::new();
            let accepted = match request {
                Request::Probe { step, action, scale, episode_start } => {
                    let step = match (episode_start, step) {
                        (true, StepChoice::Current) => 0,
                        _ => resolve(&session, step),
                    };
                    let checked = session.check_probe(step, action, scale, *episode_start);
                    // What a client of the pipelined step applies, from the shift alone (0 once
                    // the probe ends the episode).
                    let ends_episode = *episode_start && (before.step() > 0 || before.probe_pending());
                    let shift = if ends_episode { vec![0.0; action.len()] } else { before.shift().to_vec() };
                    let mut ahead = Vec::new();
                    let predicted = before.applied_with_shift(&shift, action, scale, &mut ahead);
                    // And the probe, for a critic the client evaluates itself.
                    let (mut probe_ahead, mut probe_applied) = (Vec::new(), Vec::new());
                    let probed_ahead = before.probe_with_shift(&shift, step, action, scale, &mut probe_ahead, &mut probe_applied);
                    prop_assert_eq!(&predicted, &probed_ahead);
                    let result = session.probe(step, action, scale, *episode_start, &mut out);
                    prop_assert_eq!(&checked, &result);
                    if predicted.is_err() {
                        prop_assert!(result.is_err(), "the probe took what applied_with_shift refused");
                        prop_assert!(ahead.is_empty() && probe_ahead.is_empty() && probe_applied.is_empty());
                    }
                    if result.is_ok() {
                        assert_valid_output(&config, &out)?;
                        prop_assert!(session.probe_pending());
                        let mut applied = Vec::new();
                        session.applied_action(&mut applied);
                        assert_valid_output(&config, &applied)?;
                        if session.is_pass_through() {
                            // v = 0 there: the same numbers (a zero's sign aside).
                            prop_assert_eq!(&ahead, &applied);
                        } else {
                            let bits = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                            prop_assert_eq!(bits(&ahead), bits(&applied), "the action computed ahead");
                            prop_assert_eq!(bits(&probe_applied), bits(&applied), "the action probed ahead");
                            prop_assert_eq!(bits(&probe_ahead), bits(&out), "the probe computed ahead");
                        }
                        pending_scale = (0..action.len()).map(|i| bound(scale, i, 1.0)).collect();
                        if !session.is_pass_through() {
                            // The probe's sigma bounds v from now on (Algorithm 1's action uses it).
                            bound_scale.clone_from(&pending_scale);
                            for (&v, &sigma) in session.shift().iter().zip(&bound_scale) {
                                let b = limit.min(trust * sigma);
                                prop_assert!(-b <= v && v <= b, "v = {} outside +-{} after a probe", v, b);
                            }
                        }
                        last_report = None;
                    }
                    result.is_ok()
                }
                Request::Report { step, q, reference } => {
                    let step = resolve(&session, step);
                    let checked = session.check_report(step, *q, *reference);
                    let result = session.report(step, *q, *reference, &mut out);
                    prop_assert_eq!(&checked, &result.as_ref().map(drop).map_err(Clone::clone));
                    if let Ok(outcome) = &result {
                        assert_valid_output(&config, &out)?;
                        if outcome.replayed {
                            prop_assert_eq!(&session, &before, "a replay updated the session");
                            prop_assert_eq!(last_report.as_ref(), Some(&(step, out.clone())));
                        } else {
                            prop_assert_eq!(session.step(), step + 1);
                            last_report = Some((step, out.clone()));
                            if !session.is_pass_through() {
                                bound_scale.clone_from(&pending_scale);
                            }
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
            for (&v, &sigma) in session.shift().iter().zip(&bound_scale) {
                let bound = limit.min(trust * sigma);
                prop_assert!(v.is_finite() && -bound <= v && v <= bound, "v = {} outside [-{}, {}]", v, bound, bound);
            }
            if let Some(m) = session.response_mean_square() {
                prop_assert!(m.is_finite() && m >= 0.0, "m = {}", m);
            }
            if session.is_pass_through() {
                prop_assert!(session.shift().iter().all(|&v| v == 0.0));
            }
        }
    }
}

/// A config for the scale-invariance property: normalized, every other 1b field unset or set, and no
/// action bounds (so clipping never hides a difference in v). Magnitudes stay ordinary: the property is
/// about Q's scale, not about overflow, which the property above covers.
fn normalized_config() -> impl Strategy<Value = SessionConfig> {
    (1usize..=4, 1e-3..0.05f64).prop_flat_map(|(dim, dt)| {
        (
            per_dim(dim, 0.05..0.5f64),
            per_dim(
                dim,
                (0.05..0.9f64).prop_map(move |fraction| fraction * PI / dt),
            ),
            per_dim(dim, 0.0..0.5f64),
            (prop::option::of(0.1..10.0f64), prop::bool::ANY),
            prop::option::of(0.1..2.0f64),
            prop::option::of(0.01..=1.0f64),
            prop::option::of(0.5..5.0f64),
            prop::option::of(0.0..0.1f64),
            prop::option::of(0.1..3.0f64),
        )
            .prop_map(
                move |(
                    amplitude,
                    frequency,
                    learning_rate,
                    highpass,
                    limit,
                    rate,
                    clip,
                    leak,
                    trust,
                )| {
                    SessionConfig {
                        highpass_cutoff: highpass.0,
                        disable_highpass: highpass.1,
                        shift_limit: limit,
                        normalize_response: true,
                        response_rms_rate: rate,
                        response_clip: clip,
                        shift_leak: leak,
                        trust_region: trust,
                        ..SessionConfig::new(dim as u32, dt, amplitude, frequency, learning_rate)
                    }
                },
            )
    })
}

/// One step of a scale-invariance run: the sampled action, sigma and the Q "landscape" at the probe.
#[derive(Clone, Debug)]
struct ScaledStep {
    action: Vec<f64>,
    scale: f64,
    state_level: f64,
    episode_start: bool,
}

fn scaled_steps(dim: usize) -> impl Strategy<Value = Vec<ScaledStep>> {
    vec(
        (
            vec(-2.0..2.0f64, dim),
            0.05..2.0f64,
            -5.0..5.0f64,
            prop::bool::weighted(0.03),
        )
            .prop_map(|(action, scale, state_level, episode_start)| ScaledStep {
                action,
                scale,
                state_level,
                episode_start,
            }),
        1..200,
    )
}

/// Runs `steps` with Q scaled by `c1` and offset by `c0`, reporting a paired reference when `paired`;
/// returns every applied action (Algorithm 1's and the report's) and the smallest response mean
/// square m the session held (infinite if it never held one).
fn run_scaled(
    config: &SessionConfig,
    steps: &[ScaledStep],
    c1: f64,
    c0: f64,
    paired: bool,
) -> (Vec<f64>, f64) {
    let mut session = Session::new(config.clone()).expect("valid config");
    let (mut probe, mut actions) = (Vec::new(), Vec::new());
    let mut smallest_m = f64::INFINITY;
    let q = |level: f64, u: &[f64]| {
        c1 * (level - u.iter().map(|x| (x - 0.3) * (x - 0.3)).sum::<f64>()) + c0
    };
    for (t, step) in steps.iter().enumerate() {
        let start = t == 0 || step.episode_start;
        let at = if start { 0 } else { session.step() };
        probe.clear();
        session
            .probe(at, &step.action, &[step.scale], start, &mut probe)
            .expect("probe");
        let applied_from = actions.len();
        session.applied_action(&mut actions);
        let reference = paired.then(|| q(step.state_level, &actions[applied_from..]));
        session
            .report(at, q(step.state_level, &probe), reference, &mut actions)
            .expect("report");
        if let Some(m) = session.response_mean_square() {
            smallest_m = smallest_m.min(m);
        }
    }
    (actions, smallest_m)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    /// CONTRACT.md section 1b: with normalize_response the actions do not depend on Q's scale, nor on its
    /// offset when the washout or the paired reference removes it (up to rounding and the 1e-12 guard).
    #[test]
    fn normalized_actions_do_not_depend_on_the_scale_of_q(
        (config, steps) in normalized_config().prop_flat_map(|c| {
            let dim = c.action_dim as usize;
            (Just(c), scaled_steps(dim))
        }),
        // From 0.1 up: at smaller scales h^2 nears the contract's 1e-12 guard more often (see below).
        c1 in prop_oneof![1e-1..1e4f64, Just(1.0)],
        c0 in -1e3..1e3f64,
        paired in prop::bool::ANY,
    ) {
        let offset = if paired || !config.disable_highpass { c0 } else { 0.0 };
        let (base, base_m) = run_scaled(&config, &steps, 1.0, 0.0, paired);
        let (scaled, scaled_m) = run_scaled(&config, &steps, c1, offset, paired);
        // The guard moves g = h / sqrt(m + 1e-12) by about 1e-12 / (2 m) relative, and the shift feeds that
        // back into later probes (about 10x over a run): the invariance holds where m stays above 1e-4 in
        // both runs. A response near 0 at Q's scale 1 (an action near the quadratic's optimum) leaves it:
        // about 1.4 % of cases, each seen failing at 1e-6.
        prop_assume!(base_m.min(scaled_m) > 1e-4);
        for (i, (a, b)) in base.iter().zip(&scaled).enumerate() {
            prop_assert!((a - b).abs() <= 1e-6 * (1.0 + a.abs()), "action value {}: {} vs {} (c1 {}, c0 {})", i, a, b, c1, offset);
        }
    }
}
