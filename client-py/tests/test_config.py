"""Validation of SessionConfig (esa-core's, where it is built) and EsaConfig, and the proto
round trip."""

import math
import sys

import numpy as np
import pytest

from esa_client import EsaConfig, SessionConfig

BASE = dict(action_dim=2, dt=0.05, amplitude=0.2, frequency=10.0, learning_rate=0.5)


@pytest.mark.parametrize(
    "change",
    [
        dict(action_dim=0),
        dict(action_dim=4097),
        dict(dt=0.0),
        dict(dt=math.nan),
        dict(amplitude=-0.1),
        dict(amplitude=[]),
        dict(amplitude=[0.1, 0.2, 0.3]),
        dict(frequency=0.0),
        dict(frequency=math.pi / 0.05),
        dict(learning_rate=math.inf),
        dict(highpass_cutoff=0.0),
        dict(action_low=1.0, action_high=1.0),
        dict(action_low=math.inf),
        dict(action_low=-math.inf),
        dict(action_high=[1.0, math.inf]),
        dict(action_high=[math.nan, 1.0]),
        dict(shift_limit=-1.0),
        dict(lr_decay=0.0),
        dict(lr_decay=1.5),
        dict(max_episodes=-1),
        dict(amplitude=[[0.1, 0.2]]),
        dict(action_dim=2.0),
        dict(action_dim=True),
        dict(dt="0.05"),
        dict(trust_region="1"),
        dict(normalize_response=1),
    ],
)
def test_invalid_fields_raise_value_error_naming_the_field(change):
    with pytest.raises(ValueError, match="expected"):
        SessionConfig(**{**BASE, **change})


def test_proto_round_trip_keeps_vectors_as_given():
    config = SessionConfig(
        **{**BASE, "amplitude": [0.1, 0.3]},
        highpass_cutoff=0.7,
        action_low=-1.0,
        action_high=[1.0, 2.0],
        shift_limit=0.5,
        lr_decay=0.9,
        max_episodes=3,
    )
    message = config.to_proto()
    assert list(message.amplitude) == [0.1, 0.3]
    assert list(message.frequency) == [10.0]
    assert message.HasField("lr_decay") and not SessionConfig(**BASE).to_proto().HasField(
        "lr_decay"
    )
    assert SessionConfig.from_proto(message) == config
    np.testing.assert_array_equal(config.vector("action_high"), [1.0, 2.0])
    np.testing.assert_array_equal(SessionConfig(**BASE).vector("action_low"), [-np.inf, -np.inf])


def test_esa_config_spreads_a_scalar_frequency_over_dimensions():
    esa = EsaConfig(frequency=10 * math.pi)
    config = esa.session_config(3, dt=0.04, action_low=-3.0, action_high=3.0)
    assert config.frequency == pytest.approx((10 * math.pi, 7.5 * math.pi, 5 * math.pi))
    assert esa.session_config(1, dt=0.04).frequency == (10 * math.pi,)
    assert EsaConfig(frequency=[1.0, 2.0]).session_config(2, 0.04).frequency == (1.0, 2.0)


def test_esa_config_maps_open_box_bounds_to_finite_ones():
    esa = EsaConfig()
    config = esa.session_config(
        2, dt=0.04, action_low=[-np.inf, -1.0], action_high=[np.inf, np.inf]
    )
    assert config.action_low == (-sys.float_info.max, -1.0)
    assert config.action_high == ()
    with pytest.raises(ValueError, match=r"action_low\[0\]: expected a finite number"):
        esa.session_config(1, dt=0.04, action_low=[np.inf])


def test_esa_config_dt_overrides_and_nyquist_is_explained():
    assert EsaConfig(dt=0.01).session_config(1, dt=0.5).dt == 0.01
    with pytest.raises(ValueError, match="Nyquist"):
        EsaConfig(frequency=10 * math.pi).session_config(1, dt=0.2)


@pytest.mark.parametrize(
    "change, field",
    [
        (dict(amplitude=-1.0), "amplitude"),
        (dict(amplitude=[0.1, math.nan]), "amplitude"),
        (dict(frequency=0.0), "frequency"),
        (dict(frequency=-31.4), "frequency"),
        (dict(learning_rate=math.nan), "learning_rate"),
        (dict(learning_rate=-0.1), "learning_rate"),
        (dict(highpass_cutoff=-1.0), "highpass_cutoff"),
        (dict(lr_decay=2.0), "lr_decay"),
        (dict(max_episodes=-3), "max_episodes"),
        (dict(shift_limit=0.0), "shift_limit"),
        (dict(response_rms_rate=0.0), "response_rms_rate"),
        (dict(response_clip=math.inf), "response_clip"),
        (dict(shift_leak=1.0), "shift_leak"),
        (dict(trust_region=-1.0), "trust_region"),
        (dict(gate=1.5), "gate"),
        (dict(gate=True), "gate"),
        (dict(paired_response="yes"), "paired_response"),
        (dict(use_policy_std=1), "use_policy_std"),
        (dict(dt=0.0), "dt"),
        (dict(dt=0.05, frequency=100.0), "Nyquist"),
        (dict(amplitude=[0.1, 0.2], learning_rate=[0.1, 0.2, 0.3]), "length"),
    ],
)
def test_esa_config_rejects_every_bad_field_when_built(change, field):
    with pytest.raises(ValueError, match="expected") as raised:
        EsaConfig(**change)
    assert field in str(raised.value)


def test_esa_config_accepts_per_dimension_vectors_before_the_env_is_known():
    esa = EsaConfig(amplitude=[0.1, 0.2, 0.3], frequency=[30.0, 20.0, 10.0])
    assert esa.session_config(3, dt=0.01).amplitude == (0.1, 0.2, 0.3)
    with pytest.raises(ValueError, match="amplitude"):
        esa.session_config(2, dt=0.01)


def test_paper_preset_is_section_1_with_the_papers_settings():
    paper = EsaConfig.paper()
    config = paper.session_config(2, dt=0.01)
    assert (paper.amplitude, paper.frequency) == (0.2, 10 * math.pi)
    assert not config.normalize_response
    assert config.trust_region is None and config.shift_leak is None
    assert not paper.paired_response and not paper.use_policy_std and paper.gate is None
    assert EsaConfig.paper(amplitude=0.1).amplitude == 0.1
    with pytest.raises(ValueError, match="amplitude"):
        EsaConfig.paper(amplitude=-0.1)


def test_the_default_is_the_bounded_scale_free_law():
    config = EsaConfig().session_config(2, dt=0.01)
    assert config.normalize_response
    assert config.trust_region is not None and config.shift_leak is not None


def test_a_config_is_rebuilt_from_its_own_fields():
    import dataclasses

    unbounded = SessionConfig(**BASE)
    changed = dataclasses.replace(unbounded, trust_region=1.0)
    assert changed.action_low == () and changed.trust_region == 1.0
    bounded = SessionConfig(**BASE, action_low=-1.0, action_high=[1.0, 2.0])
    assert dataclasses.replace(bounded) == bounded
    with pytest.raises(ValueError, match="amplitude: expected length 1"):
        dataclasses.replace(unbounded, amplitude=())
