"""Regenerate the committed Python stubs from ``proto/esa/v1/esa.proto``.

Usage::

    python scripts/gen_proto.py          # rewrite the stubs
    python scripts/gen_proto.py --check  # exit 1 if the committed stubs are stale

The generator is pinned (``GENERATOR``): the oldest grpcio-tools whose output sets the
package's dependency floor (protobuf). It conflicts with newer protobuf runtimes, so
``make proto`` / ``make proto-check`` run this script in a venv of its own (.venv-proto).

The messages (``esa_pb2``) live privately inside ``esa_client._proto``; no grpcio service
module is generated (the client's gRPC is the extension's Rust client). The proto is compiled
with ``-I proto`` so the descriptor keeps its canonical name ``esa/v1/esa.proto`` (the name
reflection and other languages use).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from importlib import metadata
from pathlib import Path

from grpc_tools import protoc

CLIENT_ROOT = Path(__file__).resolve().parent.parent
PROTO_ROOT = CLIENT_ROOT.parent / "proto"
PROTO_FILE = PROTO_ROOT / "esa" / "v1" / "esa.proto"
STUB_DIR = CLIENT_ROOT / "src" / "esa_client" / "_proto" / "esa" / "v1"
STUBS = ("esa_pb2.py", "esa_pb2.pyi")
# Keep in step with the floor in pyproject.toml (protobuf>= its protoc's runtime).
GENERATOR = "1.49.1"


def generate() -> dict[str, str]:
    """Compile the proto and return the generated files by name."""
    version = metadata.version("grpcio-tools")
    if version != GENERATOR:
        raise SystemExit(f"grpcio-tools {version}, not {GENERATOR}: run `make proto`")
    with tempfile.TemporaryDirectory() as out:
        args = [
            "grpc_tools.protoc",
            f"-I{PROTO_ROOT}",
            f"--python_out={out}",
            f"--pyi_out={out}",
            str(PROTO_FILE),
        ]
        if protoc.main(args) != 0:
            raise SystemExit(f"protoc failed on {PROTO_FILE}")
        return {name: (Path(out) / "esa" / "v1" / name).read_text() for name in STUBS}


def main() -> int:
    """Write or check the stubs; returns the process exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only compare, write nothing")
    check = parser.parse_args().check
    stale = []
    for name, text in generate().items():
        path = STUB_DIR / name
        if check:
            if not path.exists() or path.read_text() != text:
                stale.append(name)
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
    if stale:
        print(f"stale stubs: {', '.join(stale)}; run scripts/gen_proto.py")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
