"""The example Zenoh configs of deploy/ stay valid (parsed only: they name real networks)."""

import re
from pathlib import Path

import pytest
import zenoh

DEPLOY = Path(__file__).resolve().parents[2] / "deploy" / "zenoh"
CONFIGS = sorted(DEPLOY.glob("*.json5"))


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
    assert [p.name for p in CONFIGS] == ["router.json5", "server.json5", "trainer.json5"]
