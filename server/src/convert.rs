//! The server's side of the wire/core conversions (`esa_proto::convert`): a
//! request's config is required.

use esa_core::SessionConfig;

use crate::error::Error;
use crate::pb;

pub use esa_proto::convert::{config_to_proto, session_snapshot};

/// The core config for a request's `config` field, which is required.
pub fn config_from_proto(config: Option<pb::SessionConfig>) -> Result<SessionConfig, Error> {
    let c = config.ok_or_else(|| {
        Error::InvalidArgument("config: required, expected a SessionConfig, got none".into())
    })?;
    Ok(esa_proto::convert::config_from_proto(c))
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
        assert_eq!(err.code(), crate::error::Code::InvalidArgument);
        assert!(err.to_string().contains("config"));
    }
}
