//! Conversions between the wire types (`v1`) and esa-core's, shared by everything that
//! serves the contract (the server, the in-process engine). Values are copied as sent;
//! validation is the core's job (`SessionConfig::validate`).

use esa_core::{CoreError, Session, SessionConfig};

use crate::v1;

/// The core config of a wire config.
pub fn config_from_proto(c: v1::SessionConfig) -> SessionConfig {
    SessionConfig {
        action_dim: c.action_dim,
        dt: c.dt,
        amplitude: c.amplitude,
        frequency: c.frequency,
        learning_rate: c.learning_rate,
        highpass_cutoff: c.highpass_cutoff,
        disable_highpass: c.disable_highpass,
        action_low: c.action_low,
        action_high: c.action_high,
        shift_limit: c.shift_limit,
        lr_decay: c.lr_decay,
        max_episodes: c.max_episodes,
        normalize_response: c.normalize_response,
        response_rms_rate: c.response_rms_rate,
        response_clip: c.response_clip,
        shift_leak: c.shift_leak,
        trust_region: c.trust_region,
    }
}

/// The wire form of a session's config, as it was given at creation.
pub fn config_to_proto(c: &SessionConfig) -> v1::SessionConfig {
    v1::SessionConfig {
        action_dim: c.action_dim,
        dt: c.dt,
        amplitude: c.amplitude.clone(),
        frequency: c.frequency.clone(),
        learning_rate: c.learning_rate.clone(),
        highpass_cutoff: c.highpass_cutoff,
        disable_highpass: c.disable_highpass,
        action_low: c.action_low.clone(),
        action_high: c.action_high.clone(),
        shift_limit: c.shift_limit,
        lr_decay: c.lr_decay,
        max_episodes: c.max_episodes,
        normalize_response: c.normalize_response,
        response_rms_rate: c.response_rms_rate,
        response_clip: c.response_clip,
        shift_leak: c.shift_leak,
        trust_region: c.trust_region,
    }
}

/// A session's config and state, as `GetSession` answers them.
pub fn session_snapshot(session: &Session) -> v1::GetSessionResponse {
    v1::GetSessionResponse {
        config: Some(config_to_proto(&session.config())),
        step: session.step(),
        episodes_completed: session.episodes_completed(),
        shift: session.shift().to_vec(),
        probe_pending: session.probe_pending(),
        response_mean_square: session.response_mean_square(),
    }
}

/// The session a CreateSession asks for: a new one, or with `progress` one that resumes a lost
/// session's episode count and mean square (`Session::resume`).
pub fn new_session(
    config: SessionConfig,
    progress: Option<v1::SessionProgress>,
) -> Result<Session, CoreError> {
    match progress {
        None => Session::new(config),
        Some(p) => Session::resume(config, p.episodes_completed, p.response_mean_square),
    }
}

/// What a batch answer carries of each session's progress: the completed episodes, and the mean
/// squares with -1 for an unset one (empty when no session normalizes its response).
pub fn batch_progress<S: std::ops::Deref<Target = Session>>(
    sessions: &[S],
) -> (Vec<u64>, Vec<f64>) {
    let episodes = sessions.iter().map(|s| s.episodes_completed()).collect();
    let normalizing = sessions.iter().any(|s| s.normalizes_response());
    let mean_squares = if normalizing {
        sessions
            .iter()
            .map(|s| s.response_mean_square().unwrap_or(UNSET_MEAN_SQUARE))
            .collect()
    } else {
        Vec::new()
    };
    (episodes, mean_squares)
}

/// How a batch answer writes an unset mean square (a set one is never negative).
pub const UNSET_MEAN_SQUARE: f64 = -1.0;
