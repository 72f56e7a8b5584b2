"""Sizes of what a user downloads and runs: the client wheel, the server wheel, the binaries.

Measures the files as the last builds left them: the newest ``dist/esa_client-*.whl`` and
``dist/esa_server-*.whl`` (``make wheel``: the extension, and the esa-server executable of
the server's own wheel), the release build ``make build`` makes
(``target/release/esa-server``) and the in-place extension
(``client-py/src/esa_client/_native.abi3.so``), and inside the wheels the extension and the
server they carry (uncompressed). Missing files are left out of the JSON.

Usage::

    python bench/python/artifact_sizes.py [--out bench/results/sizes.json]
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import tyro

REPO_ROOT = Path(__file__).resolve().parents[2]


@dataclass
class Args:
    """Sizes of the wheels, the server and the extension."""

    out: str = "bench/results/sizes.json"
    """JSON of the sizes."""


def sizes(root: Path) -> dict[str, dict[str, object]]:
    """``{artifact: {"path": ..., "bytes": ...}}`` for each artifact that exists."""
    newest = {
        name: sorted(root.glob(f"dist/{stem}-*.whl"), key=lambda p: p.stat().st_mtime)[-1:]
        for name, stem in (("wheel", "esa_client"), ("server_wheel", "esa_server"))
    }
    artifacts = {
        **{name: found[0] for name, found in newest.items() if found},
        "server_release": root / "target/release/esa-server",
        "extension": root / "client-py/src/esa_client/_native.abi3.so",
    }
    found: dict[str, dict[str, object]] = {
        name: {"path": str(path.relative_to(root)), "bytes": path.stat().st_size}
        for name, path in artifacts.items()
        if path.is_file()
    }
    inside = {"esa-server": "wheel_server", "_native.abi3.so": "wheel_extension"}
    for wheels in newest.values():
        for path in wheels:
            with zipfile.ZipFile(path) as wheel:
                for info in wheel.infolist():
                    key = inside.get(Path(info.filename).name)
                    if key is not None:
                        found[key] = {
                            "path": f"{path.name}:{info.filename}",
                            "bytes": info.file_size,
                        }
    return found


def main() -> None:
    """Writes the sizes found to ``--out``."""
    args = tyro.cli(Args)
    found = sizes(REPO_ROOT)
    for name, entry in found.items():
        print(f"{name:<15} {entry['bytes'] / 2**20:8.2f} MiB  {entry['path']}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(found, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
