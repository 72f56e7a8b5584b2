//! The single error type of the crate.

/// Why a config was rejected or a probe/report was refused.
///
/// A request that fails with any of these leaves the session exactly as it was.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CoreError {
    /// A [`SessionConfig`](crate::SessionConfig) field broke a rule; the message starts with the field name.
    #[error("invalid config: {0}")]
    InvalidConfig(String),
    /// A request argument had the wrong length or a non-finite value; the message names the argument.
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// The request's step is not the session's current step `t`.
    #[error("step mismatch: expected step {expected}, got {got}")]
    StepMismatch {
        /// The step the session is at (0 after an `episode_start`).
        expected: u64,
        /// The step the caller sent.
        got: u64,
    },
    /// A report arrived for the current step but no probe is pending.
    #[error("no pending probe at step {step}: call Probe before Report")]
    NoPendingProbe {
        /// The step the caller sent (equal to the session's `t`).
        step: u64,
    },
}
