//! Example 1 of the ESA paper (Section II) run through the core with the paper's parameters:
//! constant sampled action a = (2, 2), Q = -J(probe), dt = 0.01, w = (60, 75) rad/s, K = 0.2,
//! alpha = 0.25, default high-pass (w_h = min(w) / 10 = 6 rad/s).

use esa_core::{Session, SessionConfig};

const DT: f64 = 0.01;
const SAMPLED: [f64; 2] = [2.0, 2.0];

/// The objective to minimize, `J(u, tau)`; the session maximizes `Q = -J`.
type Objective = fn(&[f64], f64) -> f64;

fn static_objective(u: &[f64], _tau: f64) -> f64 {
    (u[0] - 0.1).powi(2) + (u[1] - 0.5).powi(2)
}

fn moving_objective(u: &[f64], tau: f64) -> f64 {
    (u[0] - 0.1 * tau).powi(2) + (u[1] - 0.5 * tau).powi(2)
}

/// Runs `steps` probe/report pairs and returns `J(improved action at step t, t * dt)` for every t.
fn run(objective: Objective, steps: u64) -> Vec<f64> {
    let config = SessionConfig::new(2, DT, vec![0.2], vec![60.0, 75.0], vec![0.25]);
    let mut session = Session::new(config).expect("Example 1 config is valid");
    let (mut probe, mut action) = (Vec::with_capacity(2), Vec::with_capacity(2));
    (0..steps)
        .map(|t| {
            let tau = t as f64 * DT;
            probe.clear();
            session
                .probe(t, &SAMPLED, &[], t == 0, &mut probe)
                .expect("probe");
            action.clear();
            session
                .report(t, -objective(&probe, tau), None, &mut action)
                .expect("report");
            objective(&action, tau)
        })
        .collect()
}

#[test]
fn static_objective_converges_within_300_reports() {
    let j = run(static_objective, 300);
    assert_eq!(
        j[0],
        static_objective(&SAMPLED, 0.0),
        "the first report cannot move v (sin 0 = 0)"
    );
    let last = j[299];
    assert!(
        last <= 1e-3,
        "J(improved action) after 300 reports = {last:e}, expected <= 1e-3"
    );
}

#[test]
fn time_varying_objective_is_tracked_every_whole_second() {
    let j = run(moving_objective, 801);
    for second in 2..=8u64 {
        let at = j[(second * 100) as usize];
        assert!(
            at <= 0.05,
            "J at tau = {second} s is {at:e}, expected <= 0.05"
        );
    }
}
