//! `fused_step`: the fused step equals a probe batch and the report batch of the critic at its
//! probes, whether the critic is linear or its values come with the step (at probes computed
//! ahead); the quadratic critic is its closed form at the clipped action; it refuses bad critics
//! without changing anything, and puts the sessions back when the report is refused after the
//! probe.

use esa_core::batch::{self, BatchError};
use esa_core::fused_step::{self, CriticValues, LinearCritic, QuadraticCritic, StepCritic};
use esa_core::{Session, SessionConfig};

fn config() -> SessionConfig {
    SessionConfig {
        action_low: vec![-2.0],
        action_high: vec![2.0],
        normalize_response: true,
        trust_region: Some(1.0),
        ..SessionConfig::new(2, 0.05, vec![0.3], vec![20.0, 13.0], vec![0.4])
    }
}

fn sessions(n: usize) -> Vec<Session> {
    vec![Session::new(config()).expect("valid"); n]
}

fn linear(gains: &[f64], offsets: &[f64], points: &[f64]) -> Vec<f64> {
    gains
        .chunks(2)
        .zip(points.chunks(2))
        .zip(offsets)
        .map(|((g, a), c)| g.iter().zip(a).map(|(g, a)| g * a).sum::<f64>() + c)
        .collect()
}

/// A valid fused step of every session: `(steps, actions, episode_starts, action_scales)` and the
/// critic; returns the probes and the applied actions.
fn step_all(
    sessions: &mut [Session],
    (steps, actions, starts, scales): (&[u64], &[f64], &[bool], &[f64]),
    critic: &impl StepCritic,
) -> (Vec<f64>, Vec<f64>) {
    let (mut probes, mut applied) = (Vec::new(), Vec::new());
    let mut refs: Vec<&mut Session> = sessions.iter_mut().collect();
    fused_step::step(
        &mut refs,
        steps,
        actions,
        starts,
        scales,
        critic,
        &mut probes,
        &mut applied,
        |_, _| {},
    )
    .expect("a valid step");
    (probes, applied)
}

#[test]
fn the_fused_step_is_the_probe_then_the_critics_report() {
    let (mut fused, mut twins, mut given) = (sessions(2), sessions(2), sessions(2));
    // What a client of the pipelined step keeps: its configs, and the last answer's shifts.
    let (configs, mut shifts) = (sessions(2), vec![0.0; 4]);
    for t in 0..50u64 {
        let x = t as f64;
        let actions = [0.3 * x.sin(), -0.2, 1.5 * (0.2 * x).cos(), 0.1];
        let scales = [0.5, 0.2 + 0.01 * x, 0.3, 0.9];
        let (gains, offsets) = ([1.0, -x, 0.2, 2.0], [x, -3.0]);
        let starts = [t % 20 == 0, t % 7 == 0];
        let steps: Vec<u64> = fused
            .iter()
            .zip(starts)
            .map(|(s, start)| if start { 0 } else { s.step() })
            .collect();
        let critic = LinearCritic {
            gains: &gains,
            offsets: &offsets,
            paired: t % 2 == 0,
        };
        let inputs = (steps.as_slice(), &actions[..], &starts[..], &scales[..]);
        let (probes, applied) = step_all(&mut fused, inputs, &critic);

        let (mut twin_probes, mut twin_applied, mut improved) =
            (Vec::new(), Vec::new(), Vec::new());
        let mut refs: Vec<&mut Session> = twins.iter_mut().collect();
        batch::probe(
            &mut refs,
            &steps,
            &actions,
            &starts,
            &scales,
            &mut twin_probes,
            &mut twin_applied,
        )
        .expect("a valid probe");
        let references = if critic.paired {
            linear(&gains, &offsets, &twin_applied)
        } else {
            Vec::new()
        };
        let q = linear(&gains, &offsets, &twin_probes);
        batch::report(&mut refs, &steps, &q, &references, &mut improved, |_, _| {})
            .expect("a valid report");

        // The same step with the values given: probes computed ahead, the critic there.
        let ahead_shifts: Vec<f64> = shifts
            .chunks(2)
            .zip(starts)
            .flat_map(|(v, start)| if start { [0.0; 2] } else { [v[0], v[1]] })
            .collect();
        let (mut ahead_probes, mut ahead_applied) = (Vec::new(), Vec::new());
        fused_step::probes_ahead(
            &configs,
            &ahead_shifts,
            &steps,
            &actions,
            &scales,
            &mut ahead_probes,
            &mut ahead_applied,
        )
        .expect("valid");
        let values = CriticValues {
            q_values: &linear(&gains, &offsets, &ahead_probes),
            q_references: &references,
        };
        let (given_probes, given_applied) = step_all(&mut given, inputs, &values);
        shifts = given.iter().flat_map(|s| s.shift().to_vec()).collect();

        assert_eq!(
            (&probes, &applied),
            (&twin_probes, &twin_applied),
            "t = {t}"
        );
        assert_eq!(
            (&ahead_probes, &ahead_applied),
            (&twin_probes, &twin_applied),
            "t = {t}"
        );
        assert_eq!((given_probes, given_applied), (probes, applied), "t = {t}");
        assert_eq!(fused, twins, "t = {t}");
        assert_eq!(given, twins, "t = {t}");
    }
}

/// Given values, given references, the message's needle and the failing item.
type ValuesCase<'a> = (&'a [f64], &'a [f64], &'a str, Option<usize>);

#[test]
fn bad_critic_values_change_nothing() {
    let mut fused = sessions(2);
    let actions = [1.5, 1.9, 1.2, 1.7];
    let cases: [ValuesCase; 4] = [
        (
            &[1.0],
            &[],
            "q_values: expected 2 values (one per session_ids item), got 1",
            None,
        ),
        (
            &[1.0, 2.0],
            &[1.0],
            "q_references: expected 2 values (one per session_ids item), got 1",
            None,
        ),
        (
            &[1.0, f64::NAN],
            &[],
            "q_value: expected a finite number",
            Some(1),
        ),
        (
            &[1.0, 2.0],
            &[f64::INFINITY, 0.0],
            "q_reference: expected a finite",
            Some(0),
        ),
    ];
    for (q_values, q_references, needle, index) in cases {
        let before = fused.clone();
        let values = CriticValues {
            q_values,
            q_references,
        };
        let (mut probes, mut applied) = (Vec::new(), Vec::new());
        let mut refs: Vec<&mut Session> = fused.iter_mut().collect();
        let err = fused_step::step(
            &mut refs,
            &[0, 0],
            &actions,
            &[],
            &[],
            &values,
            &mut probes,
            &mut applied,
            |_, _| {},
        )
        .expect_err(needle);
        assert!(err.to_string().contains(needle), "{err} lacks {needle}");
        assert_eq!(err.index(), index, "{err}");
        assert_eq!(fused, before, "{needle}");
        assert!(probes.is_empty() && applied.is_empty());
    }
}

#[test]
fn probes_ahead_checks_its_inputs() {
    let fresh = sessions(2);
    let (mut probes, mut applied) = (vec![7.0], Vec::new());
    let err = fused_step::probes_ahead(
        &fresh,
        &[0.0; 4],
        &[0],
        &[0.0; 4],
        &[],
        &mut probes,
        &mut applied,
    )
    .unwrap_err();
    assert_eq!(
        err,
        BatchError::Request("steps: expected 2 values, got 1".into())
    );
    let err = fused_step::probes_ahead(
        &fresh,
        &[0.0; 4],
        &[0, 3],
        &[0.0; 4],
        &[1.0, 1.0, 0.0, 1.0],
        &mut probes,
        &mut applied,
    )
    .unwrap_err();
    assert_eq!(err.index(), Some(1), "{err}");
    assert_eq!(
        (probes.as_slice(), applied.as_slice()),
        (&[7.0][..], &[][..])
    );
}

#[test]
fn bad_critics_and_refused_reports_change_nothing() {
    let mut fused = sessions(2);
    let steps = [0, 0];
    let actions = [1.5, 1.9, 1.2, 1.7];
    let (mut probes, mut applied) = (vec![7.0], vec![8.0]);
    let cases: [(&[f64], &[f64], &str); 5] = [
        (
            &[1.0; 3],
            &[0.0; 2],
            "critic_gains: expected 4 values, got 3",
        ),
        (
            &[1.0; 4],
            &[0.0; 1],
            "critic_offsets: expected 2 values, got 1",
        ),
        (
            &[1.0, f64::NAN, 1.0, 1.0],
            &[0.0; 2],
            "critic_gains: expected finite values",
        ),
        (
            &[1.0; 4],
            &[0.0, f64::INFINITY],
            "critic_offsets: expected finite values",
        ),
        // Finite, but Q at a probe overflows: the report is refused after the probe.
        (&[f64::MAX; 4], &[0.0; 2], "q_value"),
    ];
    for (gains, offsets, needle) in cases {
        let before = fused.clone();
        let critic = LinearCritic {
            gains,
            offsets,
            paired: false,
        };
        let mut refs: Vec<&mut Session> = fused.iter_mut().collect();
        let err = fused_step::step(
            &mut refs,
            &steps,
            &actions,
            &[],
            &[],
            &critic,
            &mut probes,
            &mut applied,
            |_, _| {},
        )
        .expect_err(needle);
        assert!(err.to_string().contains(needle), "{err} lacks {needle}");
        assert_eq!(fused, before, "{needle}");
        assert_eq!(
            (probes.as_slice(), applied.as_slice()),
            (&[7.0][..], &[8.0][..])
        );
    }
}

#[test]
fn applied_ahead_checks_its_inputs() {
    let fresh = sessions(2);
    let mut out = Vec::new();
    let err = fused_step::applied_ahead(&fresh, &[0.0; 3], &[0.0; 4], &[], &mut out).unwrap_err();
    assert_eq!(
        err,
        BatchError::Request("shifts: expected 4 values, got 3".into())
    );
    let err =
        fused_step::applied_ahead(&fresh, &[0.0; 4], &[0.0, 0.0, f64::NAN, 0.0], &[], &mut out)
            .unwrap_err();
    assert_eq!(err.index(), Some(1));
    let err = fused_step::applied_ahead(
        &fresh,
        &[0.0, f64::INFINITY, 0.0, 0.0],
        &[0.0; 4],
        &[],
        &mut out,
    )
    .unwrap_err();
    assert!(err.to_string().contains("shift[1]"), "{err}");
    assert!(out.is_empty());
    let (shifts, actions) = ([0.5, 3.0, 0.0, -3.0], [1.9375, 0.0, 0.0, 0.0]);
    fused_step::applied_ahead(&fresh, &shifts, &actions, &[0.125; 4], &mut out).expect("valid");
    // Clamped into kappa sigma = 0.125, then clipped to [-2, 2].
    assert_eq!(out, vec![2.0, 0.125, 0.0, -0.125]);
}

/// The quadratic critic written out: `offset + sum_j gain_j x_j + curvature_j x_j^2`, `x` the
/// point clipped to `[low, high]` (two dimensions per item).
fn quadratic(critic: &QuadraticCritic<'_>, points: &[f64]) -> Vec<f64> {
    points
        .chunks(2)
        .enumerate()
        .map(|(i, point)| {
            let mut sum = 0.0;
            for (j, &p) in point.iter().enumerate() {
                let k = 2 * i + j;
                let x = p.clamp(critic.lows[k], critic.highs[k]);
                sum += critic.gains[k] * x + critic.curvatures[k] * x * x;
            }
            sum + critic.offsets[i]
        })
        .collect()
}

#[test]
fn the_quadratic_step_is_the_probe_then_its_closed_form_at_the_clipped_probe() {
    let (mut fused, mut twins) = (sessions(2), sessions(2));
    // Bounds inside the sessions' [-2, 2]: some probes and applied actions lie past them.
    let (lows, highs) = ([-1.0, -0.5, -1.0, f64::NEG_INFINITY], [1.0, 0.5, 1.0, 1.2]);
    let mut clipped = 0;
    for t in 0..60u64 {
        let x = t as f64;
        let actions = [1.2 * x.sin(), -0.45, 1.5 * (0.2 * x).cos(), 0.1 * x - 3.0];
        let scales = [0.5, 0.2 + 0.01 * x, 0.3, 0.9];
        let gains = [1.0, -x, 0.2, 2.0];
        let curvatures = [-0.5, 0.0, -2.0 - x, -0.1];
        let offsets = [x, -3.0];
        let starts = [t % 20 == 0, t % 7 == 0];
        let steps: Vec<u64> = fused
            .iter()
            .zip(starts)
            .map(|(s, start)| if start { 0 } else { s.step() })
            .collect();
        let critic = QuadraticCritic {
            gains: &gains,
            curvatures: &curvatures,
            offsets: &offsets,
            lows: &lows,
            highs: &highs,
            paired: t % 2 == 1,
        };
        let inputs = (steps.as_slice(), &actions[..], &starts[..], &scales[..]);
        let (probes, applied) = step_all(&mut fused, inputs, &critic);

        let (mut twin_probes, mut twin_applied, mut improved) =
            (Vec::new(), Vec::new(), Vec::new());
        let mut refs: Vec<&mut Session> = twins.iter_mut().collect();
        batch::probe(
            &mut refs,
            &steps,
            &actions,
            &starts,
            &scales,
            &mut twin_probes,
            &mut twin_applied,
        )
        .expect("a valid probe");
        clipped += twin_probes
            .iter()
            .zip(lows.iter().zip(&highs))
            .filter(|(p, (low, high))| p < low || p > high)
            .count();
        let references = if critic.paired {
            quadratic(&critic, &twin_applied)
        } else {
            Vec::new()
        };
        let q = quadratic(&critic, &twin_probes);
        batch::report(&mut refs, &steps, &q, &references, &mut improved, |_, _| {})
            .expect("a valid report");
        assert_eq!(
            (&probes, &applied),
            (&twin_probes, &twin_applied),
            "t = {t}"
        );
        assert_eq!(fused, twins, "t = {t}");
    }
    assert!(clipped > 10, "only {clipped} probes past the bounds");
}

#[test]
fn an_unbounded_quadratic_critic_is_its_closed_form() {
    let mut fused = sessions(1);
    let mut twins = sessions(1);
    let (gains, curvatures, offsets) = ([0.5, -1.0], [-0.25, -3.0], [2.0]);
    let critic = QuadraticCritic {
        gains: &gains,
        curvatures: &curvatures,
        offsets: &offsets,
        lows: &[],
        highs: &[],
        paired: true,
    };
    let wide = QuadraticCritic {
        lows: &[f64::NEG_INFINITY; 2],
        highs: &[f64::INFINITY; 2],
        ..critic
    };
    let actions = [0.7, -1.1];
    step_all(&mut fused, (&[0], &actions, &[], &[]), &critic);
    step_all(&mut twins, (&[0], &actions, &[], &[]), &wide);
    assert_eq!(fused, twins);
}

#[test]
fn bad_quadratic_critics_change_nothing() {
    let mut fused = sessions(2);
    let actions = [1.5, 1.9, 1.2, 1.7];
    let (mut probes, mut applied) = (vec![7.0], vec![8.0]);
    let ok = [-1.0; 4];
    let (low, high) = ([-1.0; 4], [1.0; 4]);
    // gains, curvatures, offsets, lows, highs, the message's needle.
    type Case<'a> = (
        &'a [f64],
        &'a [f64],
        &'a [f64],
        &'a [f64],
        &'a [f64],
        &'a str,
    );
    let cases: [Case; 10] = [
        (
            &ok[..3],
            &ok,
            &[0.0; 2],
            &low,
            &high,
            "critic_gains: expected 4 values, got 3",
        ),
        (
            &ok,
            &ok[..1],
            &[0.0; 2],
            &low,
            &high,
            "critic_curvatures: expected 4 values, got 1",
        ),
        (
            &ok,
            &ok,
            &[0.0; 3],
            &low,
            &high,
            "critic_offsets: expected 2 values, got 3",
        ),
        (
            &ok,
            &[-1.0, f64::NAN, -1.0, -1.0],
            &[0.0; 2],
            &low,
            &high,
            "critic_curvatures: expected finite values, got NaN",
        ),
        (
            &ok,
            &ok,
            &[0.0, f64::INFINITY],
            &low,
            &high,
            "critic_offsets: expected finite values, got inf",
        ),
        (
            &ok,
            &[-1.0, 0.5, -1.0, -1.0],
            &[0.0; 2],
            &low,
            &high,
            "critic_curvatures: expected values <= 0, got 0.5",
        ),
        (
            &ok,
            &ok,
            &[0.0; 2],
            &low[..2],
            &high,
            "critic_bounds: expected 0 or 4 lows and as many highs, got 2 and 4",
        ),
        (
            &ok,
            &ok,
            &[0.0; 2],
            &[],
            &high,
            "critic_bounds: expected 0 or 4 lows and as many highs, got 0 and 4",
        ),
        (
            &ok,
            &ok,
            &[0.0; 2],
            &[-1.0, 2.0, -1.0, -1.0],
            &high,
            "critic_bounds: expected low <= high (neither NaN), got 2 and 1",
        ),
        (
            &ok,
            &ok,
            &[0.0; 2],
            &[-1.0, f64::NAN, -1.0, -1.0],
            &high,
            "critic_bounds: expected low <= high (neither NaN), got NaN and 1",
        ),
    ];
    for (gains, curvatures, offsets, lows, highs, needle) in cases {
        let before = fused.clone();
        let critic = QuadraticCritic {
            gains,
            curvatures,
            offsets,
            lows,
            highs,
            paired: true,
        };
        let mut refs: Vec<&mut Session> = fused.iter_mut().collect();
        let err = fused_step::step(
            &mut refs,
            &[0, 0],
            &actions,
            &[],
            &[],
            &critic,
            &mut probes,
            &mut applied,
            |_, _| {},
        )
        .expect_err(needle);
        assert!(err.to_string().contains(needle), "{err} lacks {needle}");
        assert_eq!(fused, before, "{needle}");
        assert_eq!(
            (probes.as_slice(), applied.as_slice()),
            (&[7.0][..], &[8.0][..])
        );
    }
}
