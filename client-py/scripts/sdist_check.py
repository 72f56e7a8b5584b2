"""The sdist check (`make sdist-check`): the esa-client sdist builds from source and imports.

1. takes the newest ``dist/esa_client-*.tar.gz`` (``make wheel`` writes it), or ``--sdist``;
2. creates a clean venv in a temporary directory and ``pip install``s ONLY that sdist: pip
   fetches maturin (the build backend) and the runtime dependencies from the package index and
   maturin compiles esa_client._native with the cargo on PATH (a few minutes);
3. imports esa_client from that venv in isolated mode, outside the checkout, and checks that
   ``esa_client.__version__`` is the sdist's version and that the in-process engine (the
   compiled extension) answers a probe.

The client's sdist carries no esa-server (the esa-server distribution, server-py/, does), so
the check does not spawn one.
Not part of ``make test``: it needs the network and cargo.

Usage: python client-py/scripts/sdist_check.py [--sdist PATH] [--python PY] [--keep]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]

USER_CODE = """
import sys
import esa_client
from esa_client import SessionConfig
from esa_client._native import Engine
expected = sys.argv[1]
assert esa_client.__version__ == expected, (esa_client.__version__, expected)
assert "site-packages" in esa_client.__file__, esa_client.__file__
config = SessionConfig(
    action_dim=2, dt=0.04, amplitude=0.2, frequency=[31.4, 15.7], learning_rate=0.3
)
engine = Engine()
session = engine.create_session(None, config.to_proto().SerializeToString())
print("esa_client", esa_client.__version__, "from", esa_client.__file__, "engine session", session)
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sdist", type=Path, help="check this sdist instead of dist/'s newest")
    parser.add_argument(
        "--python", default=sys.executable, help="interpreter the clean venv is made from"
    )
    parser.add_argument("--keep", action="store_true", help="keep the temporary directory")
    args = parser.parse_args()

    sdist = args.sdist
    if sdist is None:
        found = sorted((REPO_ROOT / "dist").glob("esa_client-*.tar.gz"))
        if not found:
            raise SystemExit(f"no esa_client sdist in {REPO_ROOT / 'dist'}: run `make wheel`")
        sdist = found[-1]
    sdist = sdist.resolve()
    version = sdist.name.removeprefix("esa_client-").removesuffix(".tar.gz")

    tmp = Path(tempfile.mkdtemp(prefix="esa-sdist-check-"))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PYTHONNOUSERSITE"] = "1"
    env.pop("CARGO_TARGET_DIR", None)
    try:
        venv = tmp / "venv"
        subprocess.run([args.python, "-m", "venv", str(venv)], check=True)
        python = str(venv / "bin" / "python")
        start = time.perf_counter()
        subprocess.run(
            [python, "-m", "pip", "install", "--no-binary", "esa-client", str(sdist)],
            check=True,
            cwd=tmp,
            env=env,
        )
        seconds = time.perf_counter() - start
        subprocess.run([python, "-I", "-c", USER_CODE, version], check=True, cwd=tmp, env=env)
    finally:
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"sdist check passed: {sdist.name} built from source and imported ({seconds:.0f} s)")


if __name__ == "__main__":
    main()
