"""RL Zoo3 with ESA (``python -m esa_client.rl_zoo``), ``esa=`` as a dict, and saved models that
keep where the sessions lived (``esa_client``) out of the file."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")

from esa_client import EsaConfig  # noqa: E402
from esa_client.sb3 import ESAPPO, ESASAC, ESATD3  # noqa: E402
from esa_client.transports.in_process import InProcessTransport  # noqa: E402


def test_esa_dict_applies_over_the_family_default() -> None:
    sac = ESASAC("MlpPolicy", "Pendulum-v1", esa={"amplitude": 0.2}, learning_starts=10)
    assert sac.esa == EsaConfig.off_policy(amplitude=0.2)
    ppo = ESAPPO(
        "MlpPolicy", "Pendulum-v1", esa={"amplitude": 0.2, "trust_region": 0.5}, n_steps=64
    )
    assert ppo.esa == EsaConfig.ppo(amplitude=0.2, trust_region=0.5)
    td3 = ESATD3("MlpPolicy", "Pendulum-v1", esa={"preset": "paper", "amplitude": 0.1})
    assert td3.esa == EsaConfig.paper(amplitude=0.1)


@pytest.mark.parametrize(
    ("esa", "match"),
    [
        ({"amplitud": 0.2}, "unknown EsaConfig field"),
        ({"amplitude": -1.0}, "amplitude"),
        ({"preset": "fast"}, "preset"),
        ("amplitude=0.2", "EsaConfig or a dict"),
    ],
)
def test_a_bad_esa_dict_is_refused_like_esaconfig(esa: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ESASAC("MlpPolicy", "Pendulum-v1", esa=esa)  # type: ignore[arg-type]


def test_saved_models_keep_no_client(client, tmp_path: Path) -> None:
    model = ESASAC("MlpPolicy", "Pendulum-v1", esa={"amplitude": 0.2}, esa_client=client.address)
    path = tmp_path / "model.zip"
    model.save(path)
    model.esa_close()
    with zipfile.ZipFile(path) as archive:
        data = json.loads(archive.read("data"))
        raw = archive.read("data").decode()
    assert "esa_client" not in data
    assert client.address.removeprefix("unix:") not in raw
    assert "esa" in data  # the hyperparameters are kept

    loaded = ESASAC.load(path)
    assert loaded.esa == EsaConfig.off_policy(amplitude=0.2)
    assert isinstance(loaded.esa_client.transport, InProcessTransport)
    moved = ESASAC.load(path, esa_client=client)
    assert moved.esa_client is client


def test_rl_zoo_trains_an_esa_algorithm_from_yaml(tmp_path: Path) -> None:
    pytest.importorskip("rl_zoo3")
    conf = tmp_path / "esa.yml"
    conf.write_text(
        "Pendulum-v1:\n"
        "  n_timesteps: 300\n"
        "  policy: 'MlpPolicy'\n"
        "  learning_starts: 100\n"
        "  batch_size: 32\n"
        "  esa:\n"
        "    amplitude: 0.2\n"
        "    trust_region: 0.5\n"
    )
    command = [sys.executable, "-m", "esa_client.rl_zoo", "train", "--algo", "esasac"]
    command += ["--env", "Pendulum-v1", "-conf", str(conf), "-f", "logs", "--seed", "0"]
    command += ["--eval-freq", "-1", "--num-threads", "1"]
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    saved = next((tmp_path / "logs" / "esasac").glob("Pendulum-v1_*/Pendulum-v1.zip"))
    model = ESASAC.load(saved)
    assert model.esa == EsaConfig.off_policy(amplitude=0.2, trust_region=0.5)


def test_rl_zoo_train_defaults_to_the_base_algorithms_hyperparameters(tmp_path: Path) -> None:
    pytest.importorskip("rl_zoo3")
    command = [sys.executable, "-m", "esa_client.rl_zoo", "train", "--algo", "esappo"]
    command += ["--env", "Pendulum-v1", "-n", "256", "-f", "logs", "--eval-freq", "-1"]
    command += ["--num-threads", "1", "--hyperparams", "n_envs:1", "n_steps:128"]
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert list((tmp_path / "logs" / "esappo").glob("Pendulum-v1_*/Pendulum-v1.zip"))


def test_rl_zoo_usage() -> None:
    from esa_client import rl_zoo

    with pytest.raises(SystemExit, match="usage"):
        rl_zoo.main([])
