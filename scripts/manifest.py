"""Write the manifest of a frozen result folder: the command that made it, the commit, the machine, the date.

Every folder under ``results/`` is a snapshot that a command regenerates; its ``manifest.json`` says
which command, at which commit, on what machine and when, so that a reader can tell a current
figure from a stale one and re-run it. Run it after the command, in the same checkout:

    python scripts/manifest.py results/cycles --command "mitsuba-p3 evaluate ..."
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
from pathlib import Path

KEYS = ("command", "commit", "date", "machine")


def git_commit(root: Path) -> str:
    """The checkout's commit, with ``+changes`` when tracked files differ from it."""
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True)
    if head.returncode:
        return "unknown (not a git checkout)"
    dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", "mitsuba_p3", "scripts"],
                           cwd=root).returncode
    return head.stdout.strip() + ("+changes" if dirty else "")


def machine() -> str:
    """CPU cores and model, and the GPU where nvidia-smi finds one."""
    cpu = platform.processor() or platform.machine()
    words = f"{len(os.sched_getaffinity(0))} CPU cores ({cpu}), {platform.system()} {platform.release()}"
    try:
        gpu = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                             text=True, timeout=10)
        if gpu.returncode == 0 and gpu.stdout.strip():
            words += f", GPU {gpu.stdout.strip().splitlines()[0]}"
    except (OSError, subprocess.TimeoutExpired):
        pass
    return words


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--command", required=True, help="the command (or commands, '; '-separated) that made it")
    parser.add_argument("--machine", help="where it ran, when not here (default: this machine)")
    args = parser.parse_args()
    if not args.folder.is_dir():
        parser.error(f"{args.folder} is not a folder")
    manifest = {"command": args.command, "commit": git_commit(Path(__file__).resolve().parents[1]),
                "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                "machine": args.machine or machine()}
    (args.folder / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    print(json.dumps(manifest))


if __name__ == "__main__":
    main()
