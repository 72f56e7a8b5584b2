//! Extremum-Seeking Action selection (ESA): the per-session update law of the esa service.
//!
//! Pure math and state, no I/O: the `esa-server` crate wraps it in gRPC. The normative description is
//! CONTRACT.md section 1 (`docs/CONTRACT.md`), after Algorithm 1 of the ESA paper.
//!
//! # The update law
//!
//! Each session keeps a shift `v` (one value per action dimension) that is reset at every episode start.
//! At step `t` (`tau = t * dt`) with the policy's sampled action `a_t`:
//!
//! 1. **Probe**: `s = sin(w * tau)`, `probe = clip(a_t + v + K s, lo, hi)`. The trainer evaluates
//!    `q = Q(state, probe)` with its critic.
//! 2. **Report** `q`: `h = H[q]` (a first-order washout that removes the slow level of Q),
//!    `v <- clamp(v + alpha_e s h, -L, L)` with `alpha_e = alpha * gamma_a^e`, and the improved action
//!    `clip(a_t + v, lo, hi)` is what the trainer applies to the environment; `t <- t + 1`.
//!
//! Correlating the probe's sinusoid with the high-passed Q value estimates the gradient of Q, so `v`
//! climbs it: each sample is improved locally while the policy itself learns as usual. After
//! `max_episodes` completed episodes the session passes actions through unchanged.
//!
//! ```
//! use esa_core::{Session, SessionConfig};
//!
//! // Maximize Q(u) = -(u - 0.3)^2 starting from the sampled action a = 1.
//! let config = SessionConfig::new(1, 0.01, vec![0.2], vec![60.0], vec![0.25]);
//! let mut session = Session::new(config)?;
//! let (mut probe, mut action) = (Vec::with_capacity(1), Vec::with_capacity(1));
//! for t in 0..500 {
//!     probe.clear();
//!     session.probe(t, &[1.0], &[], t == 0, &mut probe)?;
//!     let q = -(probe[0] - 0.3) * (probe[0] - 0.3);
//!     action.clear();
//!     session.report(t, q, None, &mut action)?;
//! }
//! assert!((action[0] - 0.3).abs() < 0.05, "improved action {} should approach 0.3", action[0]);
//! # Ok::<(), esa_core::CoreError>(())
//! ```
//!
//! Every method validates before it changes anything: a request that returns an error leaves the
//! session exactly as it was, and outputs are always finite.

pub mod batch;
mod config;
mod error;
pub mod footprint;
pub mod fused_step;
mod highpass;
mod lanes;
pub mod quadratic_head;
mod session;
mod sine;

pub use config::{SessionConfig, MAX_ACTION_DIM};
pub use error::CoreError;
pub use highpass::{Washout, WashoutMemory};
pub use session::{ReportOutcome, SavedSession, Session};
