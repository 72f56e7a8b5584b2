"""The example Zenoh configs of deploy/ stay valid (parsed only: they name real networks)."""

import re
import socket
import time
from pathlib import Path

import pytest
import zenoh

from esa_client import EsaClient, SessionConfig
from esa_client.sidecar import ServerProcess

DEPLOY = Path(__file__).resolve().parents[2] / "deploy" / "zenoh"
CONFIGS = sorted(DEPLOY.glob("*.json5"))
CONFIG = SessionConfig(action_dim=1, dt=0.05, amplitude=0.2, frequency=10.0, learning_rate=0.1)


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_example_configs_parse_once_filled_in(path, tmp_path):
    text = path.read_text()
    settings = "\n".join(line for line in text.splitlines() if not line.strip().startswith("//"))
    placeholders = set(re.findall(r"<[a-z-]+>", settings))
    assert placeholders <= {"<router-address>", "<router-host>", "<other-router-host>"}
    filled = tmp_path / path.name
    filled.write_text(re.sub(r"<[a-z-]+>", "127.0.0.1", settings))
    config = zenoh.Config.from_file(str(filled))
    assert config.get_json("scouting/multicast/enabled") == "false"
    assert config.get_json("scouting/gossip/enabled") == "false"


def test_every_role_has_an_example():
    assert [p.name for p in CONFIGS] == [
        "router-tls.json5",
        "router.json5",
        "server-tls.json5",
        "server.json5",
        "trainer-tls.json5",
        "trainer.json5",
    ]


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_the_example_server_waits_for_a_router_that_starts_later(server_bin, tmp_path):
    port = free_port()
    text = (DEPLOY / "server.json5").read_text().replace("<router-host>", "127.0.0.1")
    config_path = tmp_path / "server.json5"
    config_path.write_text(text.replace(":7447", f":{port}"))
    server = ServerProcess(server_bin, extra_args=["--zenoh", "--zenoh-config", str(config_path)])
    try:
        time.sleep(1.5)
        server.check_running()  # it used to exit at once
        router_config = zenoh.Config()
        for key, value in (
            ("mode", '"router"'),
            ("listen/endpoints", f'["tcp/127.0.0.1:{port}"]'),
            ("scouting/multicast/enabled", "false"),
            ("scouting/gossip/enabled", "false"),
        ):
            router_config.insert_json5(key, value)
        with zenoh.open(router_config):
            server.announced("listening on ", 15.0)
            with EsaClient.connect(
                f"tcp/127.0.0.1:{port}", transport="zenoh", timeout=5.0
            ) as trainer:
                assert trainer.create_session(CONFIG).id
    finally:
        server.stop()
