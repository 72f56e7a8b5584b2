//! Warnings that a client can trigger at its request rate are logged at most once per period;
//! the occurrences in between are counted, and reported with the next line logged or by a
//! periodic summary, so a misbehaving client cannot fill the disk with logs.

use std::time::{Duration, Instant};

use parking_lot::Mutex;

/// How often a throttled warning may be logged.
pub const WARNING_PERIOD: Duration = Duration::from_secs(10);

/// One kind of warning, rate-limited.
pub struct Throttle {
    period: Duration,
    state: Mutex<State>,
}

struct State {
    last_logged: Option<Instant>,
    suppressed: u64,
}

impl Throttle {
    /// A warning logged at most once per `period`.
    pub const fn new(period: Duration) -> Self {
        Self {
            period,
            state: Mutex::new(State {
                last_logged: None,
                suppressed: 0,
            }),
        }
    }

    /// Records one occurrence. `Some(n)`: log it now, mentioning the `n` occurrences suppressed
    /// since the last one logged; `None`: stay quiet (it is counted).
    pub fn admit(&self) -> Option<u64> {
        let now = Instant::now();
        let mut state = self.state.lock();
        if state
            .last_logged
            .is_some_and(|last| now.duration_since(last) < self.period)
        {
            state.suppressed += 1;
            return None;
        }
        state.last_logged = Some(now);
        Some(std::mem::take(&mut state.suppressed))
    }

    /// For a periodic summary: the occurrences suppressed since the last line logged, once a
    /// period has passed since it; `None` when there is nothing to report yet.
    pub fn summary(&self) -> Option<u64> {
        let now = Instant::now();
        let mut state = self.state.lock();
        let due = state
            .last_logged
            .is_some_and(|last| now.duration_since(last) >= self.period);
        (due && state.suppressed > 0).then(|| {
            state.last_logged = Some(now);
            std::mem::take(&mut state.suppressed)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn logs_once_per_period_and_counts_the_rest() {
        let throttle = Throttle::new(Duration::from_millis(200));
        assert_eq!(throttle.admit(), Some(0));
        assert_eq!((0..999).filter_map(|_| throttle.admit()).count(), 0);
        assert_eq!(throttle.summary(), None, "the period has not passed");
        std::thread::sleep(Duration::from_millis(250));
        assert_eq!(throttle.summary(), Some(999));
        assert_eq!(throttle.summary(), None, "reported once");
        assert_eq!(
            throttle.admit(),
            None,
            "the summary counts as a line logged"
        );
        std::thread::sleep(Duration::from_millis(250));
        assert_eq!(throttle.admit(), Some(1));
    }
}
