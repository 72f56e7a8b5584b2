"""The committed stubs are exactly what scripts/gen_proto.py produces from the proto."""

import subprocess
from pathlib import Path

import pytest

from esa_client._proto.esa.v1 import esa_pb2

CLIENT_ROOT = Path(__file__).resolve().parents[1]
# The pinned generator's venv (make proto / make proto-check; make lint creates it).
PROTO_PYTHON = CLIENT_ROOT.parent / ".venv-proto" / "bin" / "python"


@pytest.mark.skipif(not PROTO_PYTHON.exists(), reason="no .venv-proto: run make proto-check")
def test_regenerating_gives_identical_files():
    result = subprocess.run(
        [str(PROTO_PYTHON), str(CLIENT_ROOT / "scripts" / "gen_proto.py"), "--check"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_stubs_keep_the_canonical_proto_name():
    assert esa_pb2.DESCRIPTOR.name == "esa/v1/esa.proto"
    assert esa_pb2.DESCRIPTOR.package == "esa.v1"
    service = esa_pb2.DESCRIPTOR.services_by_name["EsaService"]
    assert {m.name for m in service.methods} == {
        "CreateSession",
        "Probe",
        "Report",
        "EndEpisode",
        "CloseSession",
        "GetSession",
        "ProbeBatch",
        "ReportBatch",
        "StepStream",
    }
