"""Sizes of what a user downloads and runs: the wheel, the bundled server, the extension.

Measures the files as the last builds left them: the newest ``dist/esa_client-*.whl``
(``make wheel``), the esa-server of the cargo profile ``dist`` that the wheel bundles
(``target/dist/esa-server``), the release build ``make build`` makes
(``target/release/esa-server``) and the in-place extension
(``client-py/src/esa_client/_native.abi3.so``), and inside the wheel the server and the
extension it carries (uncompressed). Missing files are left out of the JSON (``make wheel``
builds the first two).

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
    """Sizes of the wheel, the bundled server and the extension."""

    out: str = "bench/results/sizes.json"
    """JSON of the sizes."""


def sizes(root: Path) -> dict[str, dict[str, object]]:
    """``{artifact: {"path": ..., "bytes": ...}}`` for each artifact that exists."""
    wheels = sorted(root.glob("dist/esa_client-*.whl"), key=lambda p: p.stat().st_mtime)
    artifacts = {
        "wheel": wheels[-1] if wheels else None,
        "server_dist": root / "target/dist/esa-server",
        "server_release": root / "target/release/esa-server",
        "extension": root / "client-py/src/esa_client/_native.abi3.so",
    }
    found: dict[str, dict[str, object]] = {
        name: {"path": str(path.relative_to(root)), "bytes": path.stat().st_size}
        for name, path in artifacts.items()
        if path is not None and path.is_file()
    }
    if wheels:
        with zipfile.ZipFile(wheels[-1]) as wheel:
            for info in wheel.infolist():
                name = Path(info.filename).name
                key = {"esa-server": "wheel_server", "_native.abi3.so": "wheel_extension"}
                if name in key:
                    found[key[name]] = {
                        "path": f"{wheels[-1].name}:{info.filename}",
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
