"""What a benchmark number was measured on: machine, versions, commit, time; strict JSON."""

from __future__ import annotations

import datetime
import math
import os
import platform
import subprocess
from pathlib import Path
from typing import Any

import torch

REPO_ROOT = Path(__file__).resolve().parents[1]


def git_commit(root: str | Path = REPO_ROOT) -> str:
    """`git rev-parse HEAD` of the checkout (+ "-dirty" with uncommitted changes), or "unknown"."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return f"{head}-dirty" if dirty else (head or "unknown")


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def machine_info(device: torch.device) -> dict[str, Any]:
    """The machine a number was measured on: GPU name, or CPU model and core count."""
    info: dict[str, Any] = {
        "device": str(device),
        "host_cpu": cpu_model(),
        "cpu_cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
    }
    if device.type == "cuda":
        info["name"] = torch.cuda.get_device_name(device)
        info["cpu_numbers"] = False
    else:
        info["name"] = (
            f"CPU: {info['host_cpu']} ({info['cpu_cores']} cores, "
            f"{info['torch_threads']} torch threads)"
        )
        info["cpu_numbers"] = True
    return info


def versions() -> dict[str, str]:
    try:
        import warp

        warp_version = warp.__version__
    except ImportError:
        warp_version = "not installed"
    from fastenerf import __version__

    return {
        "torch": torch.__version__,
        "warp": warp_version,
        "python": platform.python_version(),
        "fastenerf": __version__,
    }


def session_info(device: torch.device, commit: str | None = None) -> dict[str, Any]:
    """One benchmark call: machine, versions, commit, start time (UTC)."""
    return {
        "machine": machine_info(device),
        "versions": versions(),
        "git_commit": commit or git_commit(),
        "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def finite(x: Any) -> bool:
    """True for a finite number (None, NaN and inf are "no value")."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def jsonable(obj: Any) -> Any:
    """`obj` with non-finite floats as None, so the files are strict JSON."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    return obj


def write_report(out: Path, name: str, res: dict[str, Any], md: str) -> None:
    """A benchmark's results: OUT/NAME.json (strict JSON) and OUT/NAME.md, each written
    atomically, and the markdown printed."""
    from fastenerf.io import atomic_path, write_json

    write_json(Path(out) / f"{name}.json", jsonable(res))
    with atomic_path(Path(out) / f"{name}.md") as tmp:
        tmp.write_text(md)
    print(md)
