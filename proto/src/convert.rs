//! Conversions between the wire types (`v1`) and esa-core's, shared by everything that
//! serves the contract (the server, the in-process engine). Values are copied as sent;
//! validation is the core's job (`SessionConfig::validate`).

use esa_core::{Session, SessionConfig};

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
