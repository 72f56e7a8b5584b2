//! Conversions between the wire types (`pb`) and `esa_core` types. Values are
//! copied as sent; validation is the core's job (`SessionConfig::validate`).

use esa_core::SessionConfig;

use crate::error::Error;
use crate::pb;

/// The core config for a request's `config` field, which is required.
pub fn config_from_proto(config: Option<pb::SessionConfig>) -> Result<SessionConfig, Error> {
    let c = config.ok_or_else(|| {
        Error::InvalidArgument("config: required, expected a SessionConfig, got none".into())
    })?;
    Ok(SessionConfig {
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
    })
}

/// The wire form of a session's config, as it was given at creation.
pub fn config_to_proto(c: &SessionConfig) -> pb::SessionConfig {
    pb::SessionConfig {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_keeps_every_field() {
        let wire = pb::SessionConfig {
            action_dim: 2,
            dt: 0.01,
            amplitude: vec![0.2],
            frequency: vec![60.0, 75.0],
            learning_rate: vec![0.25],
            highpass_cutoff: Some(3.0),
            disable_highpass: true,
            action_low: vec![-1.0],
            action_high: vec![1.0, 2.0],
            shift_limit: Some(0.5),
            lr_decay: Some(0.9),
            max_episodes: 7,
            normalize_response: true,
            response_rms_rate: Some(0.1),
            response_clip: Some(2.0),
            shift_leak: Some(0.0),
            trust_region: Some(1.5),
        };
        let core = config_from_proto(Some(wire.clone())).unwrap();
        assert_eq!(config_to_proto(&core), wire);
    }

    #[test]
    fn missing_config_is_invalid_argument() {
        let err = config_from_proto(None).unwrap_err();
        assert_eq!(err.code(), tonic::Code::InvalidArgument);
        assert!(err.to_string().contains("config"));
    }
}
