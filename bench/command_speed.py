"""Benchmark: the ``lfrig`` command end to end, as a user runs it, and the docs' speed table.

    .venv/bin/python bench/command_speed.py [--cases help backgammon ...] [--runs 3] [--work DIR]
        [--json OUT.json] [--update-docs] [--against TREE]

Each run is a fresh process of ``.venv/bin/lfrig`` (imports, reading, the estimate, every output
file and the exit included), timed from outside: wall seconds, CPU seconds (user + sys of the child,
from ``os.wait4``: a measure the load of other users inflates less than wall time) and the child's
peak RSS. One warm-up run per case first fills numba's compilation cache and is not counted; the
table gives the median of ``--runs`` runs (peak RSS: the largest). The machine (CPU, cores, memory,
Python, numba) and the load average before and after each case are recorded. Linux counts a child's
peak RSS from its parent's size at the fork, so this script imports nothing heavy (~20 MiB): a
smaller figure than that cannot show.

Cases (``--cases``, default all but ``capture``, which needs the demo capture; ``all`` for every one):

- ``help``: ``lfrig --help``, the cost every command pays before it starts;
- ``info``: ``lfrig info`` on backgammon: imports, the 81 views' files read and checked (one decoded);
- ``backgammon``: ``lfrig reconstruct BACKGAMMON -o OUT --quiet`` (matching entropy, the default);
- ``baseline``: the same with ``--method baseline``;
- ``export``: ``lfrig export OUT --ply OUT/mesh.ply`` of the backgammon result (a mesh);
- ``capture``: ``lfrig reconstruct`` on the 1198x906 rectified demo capture that
  ``bench/capture_speed.py`` makes (``lfrig demo --binning 1``; made once into
  ``--capture-work`` when missing, which takes minutes).

``--against TREE`` compares this checkout with another one of lfrig (e.g. ``git worktree add
/tmp/before HEAD~3``; both run on this checkout's ``.venv``, each with its own sources: ``python -c``
in the tree's folder with it on ``PYTHONPATH``): after a warm-up of each, the runs of a case
alternate between the two (this, other, other, this, ...), so that a machine whose speed drifts
between hours touches both alike, and the table gives both medians and their ratio. The other
tree's numba cache is its own (its first warm-up compiles).

``--json OUT.json`` writes every run's numbers; ``--update-docs`` rewrites the table between the
``<!-- speed-table -->`` markers of ``docs/entropy-results.md`` (:data:`DOC`), so the docs' figures
come from this script and not from a hand. ``--from-json A.json B.json ...`` runs nothing: it joins
the results of earlier ``--json`` files (cases measured at different times) for ``--update-docs``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LFRIG = Path(sys.executable).with_name("lfrig")
BACKGAMMON = ROOT.parent / "shared" / "data" / "hci" / "stratified" / "backgammon"
DOC = ROOT / "docs" / "entropy-results.md"
BEGIN = "<!-- speed-table -->"
END = "<!-- /speed-table -->"
#: The table's header: the block's format that ``tests/test_command_speed.py`` checks.
COLUMNS = ("case", "command", "wall s", "CPU s", "peak RSS MiB")
#: A data row: a case name, a command in backticks, then wall, CPU and peak RSS as numbers.
ROW = re.compile(r"^\| [a-z-]+ \| `lfrig [^`|]+` \| \d+\.\d\d \| \d+\.\d\d \| \d+ \|$")


@dataclass(frozen=True)
class Case:
    """One command to time: ``argv`` after ``lfrig``, with ``{work}``, ``{bg}`` and ``{capture}`` filled in;
    ``shown`` is how the docs' table writes it."""

    name: str
    argv: tuple[str, ...]
    shown: str
    needs: str | None = None  # a case whose output this one reads


CASES = {
    "help": Case("help", ("--help",), "lfrig --help"),
    "info": Case("info", ("info", "{bg}"), "lfrig info backgammon"),
    "backgammon": Case("backgammon", ("reconstruct", "{bg}", "-o", "{work}/backgammon", "--quiet"),
                       "lfrig reconstruct backgammon -o OUT --quiet"),
    "baseline": Case("baseline", ("reconstruct", "{bg}", "-o", "{work}/baseline", "--quiet", "--method", "baseline"),
                     "lfrig reconstruct backgammon -o OUT --quiet --method baseline"),
    "export": Case("export", ("export", "{work}/backgammon", "--ply", "{work}/backgammon/mesh.ply"),
                   "lfrig export OUT --ply OUT/mesh.ply", needs="backgammon"),
    "capture": Case("capture", ("reconstruct", "{capture}/rectified", "-o", "{work}/capture", "--quiet"),
                    "lfrig reconstruct CAPTURE_1198x906 -o OUT --quiet"),
}
DEFAULT_CASES = ("help", "info", "backgammon", "baseline", "export")


def machine() -> dict:
    """What the numbers were measured on."""
    cpu = next((line.split(":", 1)[1].strip() for line in _lines("/proc/cpuinfo") if line.startswith("model name")),
               platform.processor() or "unknown")
    memory_kib = next((int(line.split()[1]) for line in _lines("/proc/meminfo") if line.startswith("MemTotal:")), 0)
    from importlib import metadata

    try:  # not imported: this process stays small, and a child's peak RSS starts from it (below)
        numba_version = metadata.version("numba")
    except metadata.PackageNotFoundError:
        numba_version = None
    return {"cpu": cpu, "cores": os.cpu_count(), "memory_gib": round(memory_kib / 2**20, 1),
            "python": platform.python_version(), "numba": numba_version, "system": platform.platform()}


def _lines(path: str) -> list[str]:
    try:
        return Path(path).read_text().splitlines()
    except OSError:
        return []


#: ``lfrig`` as a module of the tree ``python -c`` runs it in (:func:`tree_side`).
TREE_MAIN = "import sys; from rig.main import main; sys.exit(main())"


@dataclass(frozen=True)
class Side:
    """How to start ``lfrig``: the command before its arguments, the folder it runs in and the
    environment's additions."""

    command: tuple[str, ...]
    cwd: Path
    env: tuple[tuple[str, str], ...] = ()


#: The installed ``lfrig`` of this checkout, as a user runs it.
INSTALLED = Side((str(LFRIG),), ROOT)


def tree_side(tree: Path) -> Side:
    """``lfrig`` from the sources of ``tree`` (a checkout of lfrig) on this interpreter: ``python -c``
    run in ``tree``, which is also first on ``PYTHONPATH`` (``-c`` puts the folder it runs in first
    on ``sys.path``, before any editable install). Bytecode is written (``PYTHONDONTWRITEBYTECODE``
    off), so that the warm-up leaves both trees' imports reading ``.pyc`` files, as numba's cache
    is written into each tree's ``__pycache__`` too."""
    tree = tree.resolve()
    if not (tree / "rig" / "main.py").is_file() or not (tree / "recon").is_dir():
        raise SystemExit(f"--against {tree}: not a checkout of lfrig (no rig/main.py and recon/)")
    return Side((sys.executable, "-c", TREE_MAIN), tree, (("PYTHONPATH", str(tree)), ("PYTHONDONTWRITEBYTECODE", "")))


def run_once(argv: list[str], *, env: dict[str, str], side: Side = INSTALLED) -> dict:
    """One fresh ``lfrig`` process: wall seconds, its CPU seconds and peak RSS (MiB), from ``wait4``."""
    env = {**env, **dict(side.env)}
    with open(os.devnull, "wb") as null:
        started = time.perf_counter()
        child = subprocess.Popen([*side.command, *argv], cwd=side.cwd, env=env, stdout=null, stderr=subprocess.PIPE)
        err = child.stderr.read()
        _, status, usage = os.wait4(child.pid, 0)
        wall = time.perf_counter() - started
        child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode != 0:
        raise SystemExit(f"lfrig {' '.join(argv)} failed ({child.returncode}):\n{err.decode(errors='replace')}")
    return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "peak_mib": usage.ru_maxrss / 1024}


def _argv(case: Case, work: Path, capture: Path) -> list[str]:
    return [a.format(work=work, bg=BACKGAMMON, capture=capture) for a in case.argv]


def _summary(timed: list[dict]) -> dict:
    """The runs of one side: every run, the medians of wall and CPU seconds, the largest peak."""
    return {"runs": timed, "wall_s": statistics.median(r["wall_s"] for r in timed),
            "cpu_s": statistics.median(r["cpu_s"] for r in timed), "peak_mib": max(r["peak_mib"] for r in timed)}


def _loads(before: tuple[float, ...]) -> dict:
    return {"load_before": [round(v, 2) for v in before], "load_after": [round(v, 2) for v in os.getloadavg()]}


def measure(case: Case, *, runs: int, work: Path, capture: Path, env: dict[str, str]) -> dict:
    """Warm-up, then ``runs`` timed runs of ``case``; medians, the largest peak and the load around them."""
    argv = _argv(case, work, capture)
    load_before = os.getloadavg()
    run_once(argv, env=env)  # warm-up: numba compiles into its cache, the files are in the page cache
    timed = [run_once(argv, env=env) for _ in range(runs)]
    return {"case": case.name, "command": case.shown, "argv": argv, **_summary(timed), **_loads(load_before)}


def compare(case: Case, *, runs: int, work: Path, capture: Path, env: dict[str, str], against: Side) -> dict:
    """A warm-up of each side, then ``runs`` runs of ``case`` on each, alternating (this checkout
    first in even rounds, the other first in odd ones): each side's :func:`_summary`."""
    argv = _argv(case, work, capture)
    sides = {"this": tree_side(ROOT), "against": against}  # both started the same way
    load_before = os.getloadavg()
    for side in sides.values():
        run_once(argv, env=env, side=side)
    timed: dict[str, list[dict]] = {name: [] for name in sides}
    for i in range(runs):
        for name in (("this", "against") if i % 2 == 0 else ("against", "this")):
            timed[name].append(run_once(argv, env=env, side=sides[name]))
    return {"case": case.name, "command": case.shown, "argv": argv, "against_tree": str(against.cwd),
            **{name: _summary(t) for name, t in timed.items()}, **_loads(load_before)}


def render_table(report: dict) -> str:
    """The docs' block (markers included) for a report of :func:`main`."""
    m = report["machine"]
    loads = [r["load_before"][0] for r in report["results"]] + [r["load_after"][0] for r in report["results"]]
    about = (f"Written by `bench/command_speed.py --update-docs`: a fresh `lfrig` process per run, numba's "
             f"cache warm, median of {report['runs']} runs (peak RSS: the largest); {m['cores']} cores "
             f"({m['cpu']}), {m['memory_gib']:g} GiB, Python {m['python']}, numba {m['numba']}; load average "
             f"{min(loads):.1f}-{max(loads):.1f} during the runs; {report['date']}.")
    lines = [
        BEGIN,
        *textwrap.wrap(about, width=100, break_long_words=False, break_on_hyphens=False),
        "",
        "| " + " | ".join(COLUMNS) + " |",
        "|" + "---|" * len(COLUMNS),
    ]
    for r in report["results"]:
        lines.append(f"| {r['case']} | `{r['command']}` | {r['wall_s']:.2f} | {r['cpu_s']:.2f} | {r['peak_mib']:.0f} |")
    lines.append(END)
    return "\n".join(lines)


def table_block(text: str) -> str:
    """The block between the markers (markers included); ``ValueError`` when they are not there once each."""
    if text.count(BEGIN) != 1 or text.count(END) != 1 or text.index(BEGIN) > text.index(END):
        raise ValueError(f"{DOC.name} must hold {BEGIN} ... {END} once, in that order")
    return text[text.index(BEGIN):text.index(END) + len(END)]


def check_block(block: str) -> list[str]:
    """What is wrong with a speed-table block's format (empty when nothing): the header, and rows
    that each give a case, a command and three numbers."""
    lines = block.splitlines()
    problems = []
    header = "| " + " | ".join(COLUMNS) + " |"
    if header not in lines:
        return [f"no header line {header!r}"]
    rows = lines[lines.index(header) + 2:-1]
    if lines[lines.index(header) + 1] != "|" + "---|" * len(COLUMNS):
        problems.append("the line under the header is not the table's rule")
    if not rows:
        problems.append("no rows")
    problems += [f"row {row!r} is not | case | `lfrig ...` | wall | CPU | RSS |" for row in rows if not ROW.match(row)]
    return problems


def update_docs(report: dict, doc: Path = DOC) -> None:
    """Rewrite the speed table of ``doc`` from ``report``."""
    text = doc.read_text(encoding="utf-8")
    block = render_table(report)
    problems = check_block(block)
    if problems:
        raise SystemExit("; ".join(problems))
    doc.write_text(text.replace(table_block(text), block), encoding="utf-8")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES), choices=[*CASES, "all"])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--work", type=Path, default=ROOT / "runs" / "command-speed",
                        help="folder for the runs' outputs (emptied first)")
    parser.add_argument("--capture-work", type=Path, default=ROOT / "runs" / "capture-speed",
                        help="the demo capture of bench/capture_speed.py (made when missing)")
    parser.add_argument("--json", type=Path, metavar="OUT.json", help="write every run's numbers here")
    parser.add_argument("--update-docs", action="store_true", help=f"rewrite the speed table in {DOC.relative_to(ROOT)}")
    parser.add_argument("--from-json", type=Path, nargs="+", metavar="REPORT.json",
                        help="run nothing: join these --json reports (in this order) for --update-docs")
    parser.add_argument("--against", type=Path, metavar="TREE",
                        help="another checkout of lfrig to compare with, the runs alternating between the two")
    args = parser.parse_args()
    if args.runs < 1:
        raise SystemExit(f"--runs {args.runs}: give at least 1")
    if args.against is not None and (args.update_docs or args.from_json):
        raise SystemExit("--against compares two checkouts; the docs' table is of one (leave out --update-docs and --from-json)")
    against = tree_side(args.against) if args.against is not None else None
    if args.from_json:
        reports = [json.loads(path.read_text(encoding="utf-8")) for path in args.from_json]
        report = dict(reports[0], results=[r for rep in reports for r in rep["results"]])
        if len({rep["runs"] for rep in reports}) != 1 or len({rep["machine"]["cpu"] for rep in reports}) != 1:
            raise SystemExit("--from-json: the reports differ in --runs or machine; measure them alike")
        report["date"] = max(rep["date"] for rep in reports)
        if args.update_docs:
            update_docs(report)
            print(f"updated {DOC.relative_to(ROOT)}")
        return
    names = list(CASES) if "all" in args.cases else list(dict.fromkeys(args.cases))
    for name in list(names):
        needed = CASES[name].needs
        if needed and needed not in names:
            names.insert(names.index(name), needed)
    if "capture" in names and not (args.capture_work / "rectified").is_dir():
        # in a child: made here, its imports and renderer would stay in this process, and every timed
        # child's peak RSS counts from this process's size at the fork (1,043 MiB for the capture's
        # 878)
        make = ("import sys; from pathlib import Path; sys.path.insert(0, sys.argv[1]); "
                "from capture_speed import make_capture; make_capture(Path(sys.argv[2]))")
        subprocess.run([sys.executable, "-c", make, str(ROOT / "bench"), str(args.capture_work.resolve())], check=True)
    work = args.work.resolve()
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    env = dict(os.environ)
    report = {"date": time.strftime("%Y-%m-%d", time.gmtime()), "runs": args.runs, "machine": machine(),
              "results": []}
    print(f"median of {args.runs} runs after a warm-up; {report['machine']['cores']} cores; "
          f"load {os.getloadavg()[0]:.1f} at start")
    if against is not None:
        report["against"] = str(against.cwd)
        print(f"this checkout ({ROOT}) against {against.cwd}, alternating; wall / CPU s")
        print(f"{'case':<11} {'this':>13} {'against':>13} {'wall ratio':>10} {'load':>9}")
    else:
        print(f"{'case':<11} {'wall s':>7} {'cpu s':>7} {'peak MiB':>9} {'load':>9}")
    for name in names:
        kwargs = {"runs": args.runs, "work": work, "capture": args.capture_work.resolve(), "env": env}
        if against is not None:
            result = compare(CASES[name], **kwargs, against=against)
            a, b = result["this"], result["against"]
            numbers = (f"{a['wall_s']:6.2f}/{a['cpu_s']:6.2f} {b['wall_s']:6.2f}/{b['cpu_s']:6.2f} "
                       f"{a['wall_s'] / b['wall_s']:10.3f}")
        else:
            result = measure(CASES[name], **kwargs)
            numbers = f"{result['wall_s']:7.2f} {result['cpu_s']:7.2f} {result['peak_mib']:9.0f}"
        report["results"].append(result)
        print(f"{name:<11} {numbers} {result['load_before'][0]:4.1f}-{result['load_after'][0]:<4.1f}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    if args.update_docs:
        update_docs(report)
        print(f"updated {DOC.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
