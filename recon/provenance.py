"""How a result was made: lfrig's version, the command, the input's identity, timings, the machine.

One builder, :func:`provenance`, makes the record that ``result.json`` (key ``provenance``), the
batch summary and the PLY header carry::

    {"lfrig_version": "0.1.0+g5dd87be",
     "command": ["lfrig", "reconstruct", "LF_DIR", "-o", "OUT"],
     "started_utc": "2026-11-27T16:30:17+00:00",
     "input": {"kind": "capture", "path": "/abs/LF_DIR", "journal_sha256": "..."},
     "timings_s": {"read": 0.4, "estimate": 12.1, "write": 0.3},
     "machine": {"python": "3.12.7", "platform": "Linux-...", "cpus": 2, "numba_threads": 2,
                 "kernels": {"sweep": "C"}}}

``input.kind`` is ``"capture"`` (lfrig's capture layout: the SHA-256 of its journal
``manifest.jsonl``, which itself holds every view's checksum), ``"benchmark"`` (the 4D Light Field
Benchmark's layout: ``files_sha256`` over the light-field files' names and contents,
:func:`lightfield_files`), ``"batch"`` or ``"unknown"``. Nothing here imports anything heavy.
"""

from __future__ import annotations

import hashlib
import os
import platform
import re
import subprocess
import sys
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path
from typing import Any

#: The files a light-field reader uses (``recon.lf.benchmark``: benchmark layout; ``recon.lf.capture``:
#: capture layout), relative to the light-field folder. Not e.g. a benchmark's high-resolution truth.
LIGHTFIELD_FILE = re.compile(
    r"^(input_Cam\d{3}\.png|parameters\.cfg|gt_disp_lowres\.pfm|manifest\.jsonl|views/u\d+_v\d+\.png)$"
)
#: The journal of lfrig's capture layout (``recon.lf.capture.MANIFEST``).
JOURNAL = "manifest.jsonl"


def lightfield_files(source: Path) -> list[str]:
    """Relative paths (``/``-separated, sorted) of the files a reader uses in a light-field folder."""
    source = Path(source)
    found = []
    for path in source.rglob("*"):
        rel = path.relative_to(source).as_posix()
        if path.is_file() and LIGHTFIELD_FILE.match(rel):
            found.append(rel)
    return sorted(found)


@lru_cache(maxsize=1)
def lfrig_version() -> str:
    """lfrig's version from the installed package's metadata; from a git checkout, with the commit
    as a PEP 440 local label (``0.1.0+g5dd87be``, ``+dirty`` is not checked)."""
    from importlib import metadata

    root = Path(__file__).resolve().parent.parent
    # the installed metadata, not a build's leftover ``lfrig.egg-info`` in the checkout (or the cwd)
    path = [entry for entry in sys.path if entry and Path(entry).resolve() != root and Path(entry).is_dir()]
    found = next(iter(metadata.distributions(name="lfrig", path=path)), None)
    version = found.version if found is not None else "unknown"
    commit = _git_commit(root)
    return f"{version}+g{commit}" if commit else version


def _git_commit(root: Path) -> str | None:
    """The short commit of the checkout at ``root``, or ``None`` (not a checkout, no git, too slow)."""
    if not (root / ".git").exists():
        return None
    try:
        done = subprocess.run(["git", "-C", str(root), "rev-parse", "--short=7", "HEAD"], capture_output=True,
                              text=True, timeout=2, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    commit = done.stdout.strip()
    return commit if done.returncode == 0 and re.fullmatch(r"[0-9a-f]{7,40}", commit) else None


#: The command line the ``lfrig`` entry point was given (:func:`set_command`), or ``None``.
_command: list[str] | None = None


def set_command(command: Sequence[str]) -> None:
    """Record the command line this process runs (the ``lfrig`` entry point does, before any work)."""
    global _command
    _command = [str(part) for part in command]


def current_command() -> list[str]:
    """The command line this process runs: what :func:`set_command` recorded, else ``sys.argv`` with
    the program by its file name."""
    if _command is not None:
        return list(_command)
    argv = list(sys.argv) or [""]
    return [Path(argv[0]).name or "python", *argv[1:]]


def utc_now() -> str:
    """The current time, ISO 8601 in UTC to the second (``2026-11-27T16:30:17+00:00``)."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file's content."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def input_identity(path: str | os.PathLike | None, *, kind: str | None = None,
                   known_sha256: Mapping[str, str] | None = None) -> dict[str, Any]:
    """``{"kind", "path", "journal_sha256" | "files_sha256"}`` of a light-field folder.

    A capture (a folder with ``manifest.jsonl``) is identified by its journal's SHA-256; a benchmark
    folder by ``files_sha256``: SHA-256 over ``name NUL content-sha256 LF`` of every light-field file
    (:func:`lightfield_files`), so renaming, replacing or editing a view changes it. ``path`` is the
    absolute folder. ``None`` gives ``{"kind": "unknown", "path": None}``. ``known_sha256``: the
    content SHA-256 of files already read (relative path -> hex digest, e.g. the benchmark reader's
    ``metadata["views_sha256"]``), taken instead of reading those files again.
    """
    if path is None:
        return {"kind": kind or "unknown", "path": None}
    folder = Path(path).resolve()
    journal = folder / JOURNAL
    if journal.is_file():
        return {"kind": kind or "capture", "path": str(folder), "journal_sha256": file_sha256(journal)}
    digest = hashlib.sha256()
    for rel in lightfield_files(folder):
        content = (known_sha256 or {}).get(rel) or file_sha256(folder / rel)
        digest.update(f"{rel}\0{content}\n".encode())
    return {"kind": kind or "benchmark", "path": str(folder), "files_sha256": digest.hexdigest()}


def machine() -> dict[str, Any]:
    """``{"python", "platform", "cpus", "numba_threads", "kernels"}`` of this process: numba's
    threads as its configuration says (without importing numba's compiler when it is not loaded
    yet), and how each kernel compiled ahead of time that this process asked for ran
    (:func:`recon.native.status`: ``{"sweep": "C"}``, or ``"numba: WHY"`` where the C one could not
    be had; empty when none was asked for)."""
    from recon.native import status, thread_count

    return {"python": platform.python_version(), "platform": platform.platform(), "cpus": os.cpu_count() or 1,
            "numba_threads": thread_count(), "kernels": status()}


def provenance(
    *,
    input: Mapping[str, Any],
    timings_s: Mapping[str, float],
    command: Sequence[str] | None = None,
    started_utc: str | None = None,
) -> dict[str, Any]:
    """The provenance record (see the module docstring).

    Parameters
    ----------
    input
        :func:`input_identity` of what was read.
    timings_s
        Seconds per step, e.g. ``{"read": 0.4, "estimate": 12.1}``; rounded to milliseconds.
    command
        The command line as a list of strings; default :func:`current_command`.
    started_utc
        ISO 8601 UTC start time; default now (:func:`utc_now`).
    """
    return {
        "lfrig_version": lfrig_version(),
        "command": [str(part) for part in (current_command() if command is None else command)],
        "started_utc": started_utc or utc_now(),
        "input": dict(input),
        "timings_s": {str(step): round(float(seconds), 3) for step, seconds in timings_s.items()},
        "machine": machine(),
    }


def ply_comments(record: Mapping[str, Any] | None) -> list[str]:
    """The provenance part of a PLY header's ``comment`` lines (one fact per line, ASCII, no line
    breaks): version, command and input. Not the time, so that the same command on the same input
    writes the same file."""
    if not record:
        return []
    lines = [f"lfrig_version {record.get('lfrig_version')}"]
    command = record.get("command")
    if command:
        lines.append("command " + " ".join(_quote(part) for part in command))
    source = record.get("input") or {}
    if source.get("path"):
        lines.append(f"source {source.get('kind')} {source['path']}")
    for key in ("journal_sha256", "files_sha256"):
        if source.get(key):
            lines.append(f"source_{key} {source[key]}")
    return [ascii_line(line) for line in lines]


def _quote(part: str) -> str:
    import shlex

    return shlex.quote(str(part))


def ascii_line(text: str) -> str:
    """``text`` on one line of printable ASCII (a PLY header is ASCII; others are escaped)."""
    return "".join(c if " " <= c <= "~" else f"\\x{ord(c):02x}" if ord(c) < 256 else f"\\u{ord(c):04x}"
                   for c in str(text))
