//! What one session costs in memory, so that a server can budget sessions in bytes rather than count.

use crate::Session;

/// Columns of a session's one heap allocation, the D x 10 state matrix of `lanes.rs`: K, w, alpha_e,
/// lo, hi, alpha, v, s, a and sigma.
const STATE_COLUMNS: usize = 10;

/// Bytes a [`Session`] of `action_dim` dimensions occupies: the inline value plus its state matrix.
/// The allocator's per-allocation overhead, and whatever holds the session, are the caller's to add.
pub const fn session_bytes(action_dim: usize) -> usize {
    std::mem::size_of::<Session>() + action_dim * STATE_COLUMNS * std::mem::size_of::<f64>()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_state_matrix_dominates_large_sessions() {
        assert_eq!(session_bytes(4096) - session_bytes(0), 4096 * 80);
        assert!(session_bytes(1) < 1024);
    }
}
