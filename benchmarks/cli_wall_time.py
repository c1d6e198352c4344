"""The wall time a user waits for whole commands: process start, imports, checks, inference,
evaluation and writing, with a warm and with an empty compile cache (issue 27, 5).

The standard problem: the built-in ``three_branch`` example, 3 pulls of 3 s at 10 ms, 2 mm
displacement + 0.05 N force noise, written once by ``treeinfer simulate`` (not timed). Each
``infer`` command line (``--commands``; by default the default command, the calibrated path of
issue 27 and Boltzmann from uniform draws) runs as a fresh process

* **cold**: with ``TREEINFER_JAX_CACHE`` a new empty folder of its own (every XLA program is
  compiled, the step choice is computed);
* **warm**: again, with the folder the cold run filled (a new recording of the same shape
  would also find its programs there; the step choice too, as for a rerun),

in turn (A B C, A B C, ...: a drift of the shared machine's speed hits every command alike),
``--repeats`` times; every run gets its own output folder. ``--session`` also times the
README's "typical session" (the ``bash`` block after "A typical session:", each line with
``treeinfer`` replaced by ``python -m treeinfer``, run in a new folder with a new cache), each
command and the total, ``evaluate --kfold 3`` among them.

``--baseline REV`` times the default command of an older treeinfer (git revision REV, unpacked
with ``git archive``) in the same run, interleaved. Each run's CPU seconds (user + system) are
printed next to its wall seconds: on a shared machine the wall time carries the other users'
load (the 1-minute load average before each run is recorded), the CPU time much less.

Prints a table and writes JSON (``--json``, default ``benchmarks/results/cli_wall_time.json``)
with the commands, the exit codes, the machine and the git commit. No timed assertions:
timings on a shared machine are figures to compare side by side, not pass/fail.

    python -m benchmarks.cli_wall_time [--repeats 2] [--commands default,calibrated] [--session]
    python -m benchmarks.cli_wall_time --commands default --baseline 44434eb  # before/after
    python -m benchmarks.cli_wall_time --extra 'mine=--likelihood gaussian --particles 32'
    python -m benchmarks.cli_wall_time --commands default --variant \
        background_off=TREEINFER_BACKGROUND=off  # the second thread's share, same run
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
COMMANDS = {  # label: flags after `infer --tree T --data D --out R`
    "default": [],
    "calibrated": ["--likelihood", "gaussian", "--noise-force", "auto", "--init", "laplace"],
    "boltzmann_uniform": ["--likelihood", "boltzmann", "--init", "uniform"],
}
DATA = ["--n-traj", "3", "--duration", "3", "--dt", "0.01", "--seed", "0"]
NOISE = ["--noise-displacement", "0.002", "--noise-force", "0.05"]


def _data(seed: int) -> list[str]:
    """:data:`DATA` with ``simulate --seed`` set to ``seed``."""
    return [*DATA[:-1], str(seed)]


def _env(cache: Path, src: Path = ROOT, extra: dict | None = None) -> dict:
    """``src``'s treeinfer (default this checkout's; ``PYTHONPATH``: an editable install
    elsewhere must not win) with ``cache`` as its compile cache (and ``extra`` variables)."""
    env = {**os.environ, **(extra or {})}
    env["PYTHONPATH"] = str(src) + os.pathsep + env.get("PYTHONPATH", "")
    env["TREEINFER_JAX_CACHE"] = str(cache)
    return env


def timed(
    cmd: list[str], cwd: Path, cache: Path, log: Path, src: Path = ROOT, extra_env=None
) -> dict:
    """Run ``cmd``; its exit code, wall seconds (process start to exit) and CPU seconds (user +
    system of the process and its children: on a shared machine the wall time counts the other
    users' load too, the CPU time much less), the 1-minute load average before it, output in
    ``log``."""
    import resource

    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        rc = subprocess.run(
            cmd, cwd=cwd, env=_env(cache, src, extra_env), stdout=f, stderr=subprocess.STDOUT
        )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {
        "command": shlex.join(cmd),
        "exit": rc.returncode,
        "wall_s": wall,
        "cpu_s": cpu,
        "load_before": load,
    }


def source_of(rev: str, work: Path) -> Path:
    """A folder holding treeinfer as of git revision ``rev`` (``git archive``), for timing an
    older version side by side with this checkout in the same run."""
    out = work / f"src_{rev}"
    if not (out / "treeinfer").is_dir():
        out.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(
            ["git", "archive", rev, "treeinfer"], cwd=ROOT, capture_output=True, check=False
        )
        if archive.returncode != 0:
            raise SystemExit(f"--baseline {rev}: git archive failed: {archive.stderr.decode()}")
        subprocess.run(["tar", "-x", "-C", str(out)], input=archive.stdout, check=True)
    return out


def readme_session() -> list[str]:
    """The README's typical session: the lines of the ``bash`` block after "A typical session",
    or (the README since session 12) the ``treeinfer`` lines of every ``bash`` block of its
    section "From a recording to a prediction", continuation lines joined, without the imports
    of a user's own files (``import-csv``, ``import-bag``: the session simulates its data)."""
    text = (ROOT / "README.md").read_text()
    if "A typical session" not in text:
        return _section_session(text)
    start = text.index("A typical session")
    block = text[
        text.index("```bash", start) + len("```bash") : text.index(
            "```", text.index("```bash", start) + 7
        )
    ]
    lines = [ln.strip() for ln in block.strip().splitlines() if ln.strip()]
    if not lines or not all(ln.startswith("treeinfer ") for ln in lines):
        raise SystemExit(
            f"README.md: the typical session's block is not treeinfer commands: {lines}"
        )
    return lines


def _section_session(text: str) -> list[str]:
    start = text.index("## From a recording to a prediction")
    end = text.find("\n## ", start + 3)
    section = text[start : end if end > 0 else len(text)]
    lines, pos = [], 0
    while (i := section.find("```bash", pos)) >= 0:
        j = section.index("```", i + 7)
        block = section[i + 7 : j].replace("\\\n", " ")
        lines += [" ".join(ln.split()) for ln in block.splitlines() if ln.strip()]
        pos = j + 3
    lines = [
        ln for ln in lines if not ln.startswith(("treeinfer import-csv", "treeinfer import-bag"))
    ]
    if not lines or not all(ln.startswith("treeinfer ") for ln in lines):
        raise SystemExit(f"README.md: the session's blocks are not treeinfer commands: {lines}")
    return lines


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--commands", default=",".join(COMMANDS), help="of " + ", ".join(COMMANDS))
    ap.add_argument(
        "--extra",
        action="append",
        default=[],
        metavar="LABEL=FLAGS",
        help="another infer command line to compare (repeatable)",
    )
    ap.add_argument(
        "--baseline",
        action="append",
        default=[],
        metavar="REV",
        help="also time the default command with treeinfer as of git revision REV (e.g. "
        "44434eb, the default before issue 27's speed work), interleaved with the others "
        "(repeatable)",
    )
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="LABEL=VAR=VALUE",
        help="also time the default command with environment variable VAR set to VALUE, "
        "interleaved with the others (repeatable), e.g. background=TREEINFER_BACKGROUND=off",
    )
    ap.add_argument("--repeats", type=int, default=1, help="cold+warm pairs per command")
    ap.add_argument(
        "--data-seed", type=int, default=0, help="the standard problem's simulate --seed"
    )
    ap.add_argument("--no-warm", action="store_true", help="cold runs only")
    ap.add_argument("--session", action="store_true", help="also the README's typical session")
    ap.add_argument("--work", type=Path, help="scratch folder (default: a new temporary one)")
    ap.add_argument(
        "--json", type=Path, default=ROOT / "benchmarks" / "results" / "cli_wall_time.json"
    )
    args = ap.parse_args(argv)
    commands = {}
    for label in filter(None, (c.strip() for c in args.commands.split(","))):
        if label not in COMMANDS:
            ap.error(f"--commands: unknown {label!r}; known: {', '.join(COMMANDS)}")
        commands[label] = COMMANDS[label]
    for item in args.extra:
        label, _, flags = item.partition("=")
        if not label or not _:
            ap.error(f"--extra: expected LABEL=FLAGS, got {item!r}")
        commands[label] = shlex.split(flags)
    work = args.work or Path(tempfile.mkdtemp(prefix="cli_wall_time_"))
    work.mkdir(parents=True, exist_ok=True)
    py = [sys.executable, "-m", "treeinfer"]
    tree = ROOT / "treeinfer" / "examples" / "three_branch.yaml"
    data = work / "data"
    prep = timed(
        py
        + [
            "simulate",
            "--tree",
            str(tree),
            "--out",
            str(data),
            *_data(args.data_seed),
            *NOISE,
            "--force",
        ],  # fmt: skip
        work,
        work / "cache_data",
        work / "simulate.log",
    )
    if prep["exit"] != 0:
        raise SystemExit(f"simulate failed (exit {prep['exit']}): see {work / 'simulate.log'}")
    sources = {label: ROOT for label in commands}
    for rev in args.baseline:
        label = f"default@{rev}"
        commands[label], sources[label] = COMMANDS["default"], source_of(rev, work)
    envs: dict = {label: {} for label in commands}
    for item in args.variant:
        label, _, setting = item.partition("=")
        var, _, value = setting.partition("=")
        if not label or not var or not _:
            ap.error(f"--variant: expected LABEL=VAR=VALUE, got {item!r}")
        commands[label], sources[label], envs[label] = COMMANDS["default"], ROOT, {var: value}
    rows: dict = {
        label: {"flags": flags, "cold": [], "warm": []} for label, flags in commands.items()
    }
    for rep in range(args.repeats):
        for label, flags in commands.items():
            cache = work / f"cache_{label}_{rep}"  # new and empty: the cold run
            for phase in ("cold",) if args.no_warm else ("cold", "warm"):
                out = work / f"run_{label}_{rep}_{phase}"
                cmd = py + ["infer", "--tree", str(tree), "--data", str(data), "--out", str(out)]
                r = timed(
                    cmd + flags, work, cache, work / f"{out.name}.log", sources[label],
                    envs.get(label),
                )  # fmt: skip
                rows[label][phase].append(r)
                print(
                    f"{label:20s} {phase}: {r['wall_s']:7.1f} s wall, {r['cpu_s']:7.1f} s CPU "
                    f"(load {r['load_before']:.1f}), exit {r['exit']}",
                    flush=True,
                )
    session = None
    if args.session:
        sdir = work / "session"
        sdir.mkdir(exist_ok=True)
        session = []
        for i, line in enumerate(readme_session()):
            cmd = py + shlex.split(line)[1:]
            r = timed(cmd, sdir, work / "cache_session", work / f"session_{i}.log")
            r["readme_line"] = line
            session.append(r)
            print(f"session {line[:60]:60s} {r['wall_s']:7.1f} s, exit {r['exit']}", flush=True)
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    res = {
        "problem": "three_branch example, 3 pulls of 3 s at 10 ms, 2 mm + 0.05 N noise (simulate "
        + shlex.join(_data(args.data_seed) + NOISE)
        + ")",
        "commit": commit,
        "machine": platform.platform(),
        "cpu_count": os.cpu_count(),
        "jax_platforms": os.environ.get("JAX_PLATFORMS"),
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
        "commands": rows,
        "variants": {k: v for k, v in envs.items() if v},
        "session": session,
    }
    print()
    print(
        f"{'command':22s} {'cold wall s':>12s} {'cold CPU s':>11s} {'warm wall s':>12s} "
        f"{'warm CPU s':>11s}  exit codes  flags (medians)"
    )
    import statistics

    def med(xs, key):
        return statistics.median([x[key] for x in xs]) if xs else float("nan")

    for label, r in rows.items():
        codes = sorted({x["exit"] for p in ("cold", "warm") for x in r[p]})
        print(
            f"{label:22s} {med(r['cold'], 'wall_s'):12.1f} {med(r['cold'], 'cpu_s'):11.1f} "
            f"{med(r['warm'], 'wall_s'):12.1f} {med(r['warm'], 'cpu_s'):11.1f}  {codes!s:10s}  "
            + shlex.join(r["flags"])
        )
    if session:
        total = sum(x["wall_s"] for x in session)
        print(
            f"README typical session: {total:.1f} s in all (cold cache), exit codes "
            f"{[x['exit'] for x in session]}"
        )
        for x in session:
            print(f"  {x['wall_s']:7.1f} s  {x['readme_line']}")
        res["session_total_s"] = total
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(res, indent=2) + "\n")
    print(f"wrote {args.json}")
    return res


if __name__ == "__main__":
    main()
