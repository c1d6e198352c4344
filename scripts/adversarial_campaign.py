#!/usr/bin/env python
# ruff: noqa: E501 -- the tables of cases read best one case per line
"""An adversarial campaign against the treeinfer command line (issue 28); rerun it any time.

Every case runs the real CLI (``python -m treeinfer ...`` with this checkout first on
PYTHONPATH) in a fresh HOME and a fresh folder, under a timeout, and is judged from the outside:

- exit code: 0, 2 (a user error, the expected answer to bad input), 3 or a traceback (a crash),
  130, or no answer within the timeout (a hang);
- data lost: any file the case marked as the user's (inputs, a home folder with ``.ssh``, a
  look-alike run folder) is missing or changed afterwards, and not kept in a ``NAME.old-*``;
- leftovers: a ``*.staging`` folder or ``.*.tmp`` file anywhere in the case's folder;
- unexpected: the exit code is not the one the case expects (2 for hostile input; 0 where the
  input is legal and must work).

Categories: data loss (outputs overlapping inputs, --force over users' folders), damaged run
folders (every file of a real run flipped, truncated, deleted, edited, swapped), crashes (odd
CSVs, hostile trees, model files), hangs (FIFOs, devices, symlink loops, absurd sizes), and
leftovers after failures. The table is printed at the end (markdown); docs/adversarial.md
holds the last recorded one.

    python scripts/adversarial_campaign.py            # the full campaign (a few minutes)
    python scripts/adversarial_campaign.py --quick    # a sample of each category
    python scripts/adversarial_campaign.py --jobs 4 --timeout 30
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import hashlib
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "treeinfer" / "examples" / "two_branch.yaml"


@dataclass
class Case:
    category: str
    name: str
    setup: object  # callable(ws: Path) -> list[str] argv (after `python -m treeinfer`)
    expect: int = 2
    protected: tuple[str, ...] = ()  # relative paths (files or folders) that must survive
    env: dict = field(default_factory=dict)
    # a case that must run inference to be judged (the fit verdict) gets this many timeouts:
    # a full run is no hang
    timeout_scale: float = 1.0


@dataclass
class Outcome:
    case: Case
    rc: int | None
    seconds: float
    crash: bool
    hang: bool
    lost: list[str]
    leftovers: list[str]
    tail: str


# ---- workspace -------------------------------------------------------------------------------
CSV = "time,force,displacement\n" + "".join(
    f"{0.01 * i:.2f},{min(i, 40) * 0.1 * (1 if i < 60 else 0):.3f},{min(i, 40) * 0.0005:.5f}\n"
    for i in range(100)
)


def _workspace(ws: Path) -> None:
    """tree.yaml, data/ (two trajectory CSVs), log.csv (a logger file), home/ with .ssh, a
    user's folder photos/, and lookalike/ (a user's folder holding a copied run config.json
    and marker)."""
    shutil.copy(EXAMPLE, ws / "tree.yaml")
    (ws / "data").mkdir()
    for k in range(2):
        (ws / "data" / f"traj_{k:03d}.csv").write_text(CSV)
    (ws / "log.csv").write_text(CSV)
    (ws / "home" / ".ssh").mkdir(parents=True)
    (ws / "home" / ".ssh" / "id_ed25519").write_text("PRIVATE KEY")
    (ws / "photos").mkdir()
    (ws / "photos" / "a.jpg").write_bytes(os.urandom(64))
    (ws / "lookalike" / ".ssh").mkdir(parents=True)
    (ws / "lookalike" / ".ssh" / "id").write_text("key")
    (ws / "lookalike" / "config.json").write_text(json.dumps({"versions": {"treeinfer": "0.1"}}))
    (ws / "lookalike" / ".treeinfer-output").write_text('{"writer": "treeinfer"}')


def _digest_tree(p: Path) -> dict[str, str]:
    out = {}
    if p.is_file():
        return {"": hashlib.sha256(p.read_bytes()).hexdigest()}
    for q in sorted(p.rglob("*")):
        if q.is_file() and not q.is_symlink():
            out[q.relative_to(p).as_posix()] = hashlib.sha256(q.read_bytes()).hexdigest()
    return out


def _survives(ws: Path, rel: str, before: dict[str, str]) -> bool:
    """``rel`` holds what it held, or a ``rel.old-*`` sibling does (moved aside, not lost)."""
    p = ws / rel
    cands = [p] + sorted(p.parent.glob(p.name + ".old-*"))
    for c in cands:
        if c.exists():
            now = _digest_tree(c)
            if all(now.get(k) == v for k, v in before.items()):
                return True
    return False


def _leftovers(ws: Path) -> list[str]:
    bad = []
    for q in ws.rglob("*"):
        if q.name.endswith(".staging") or (q.name.startswith(".") and q.name.endswith(".tmp")):
            bad.append(q.relative_to(ws).as_posix())
    return bad


def run_case(case: Case, base: Path, timeout: float, run_src: Path | None) -> Outcome:
    ws = Path(tempfile.mkdtemp(prefix="case-", dir=base))
    _workspace(ws)
    if run_src is not None:
        shutil.copytree(run_src, ws / "run", symlinks=True)
    argv = case.setup(ws)
    before = {rel: _digest_tree(ws / rel) for rel in case.protected if (ws / rel).exists()}
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith("TREEINFER_")},
        "HOME": str(ws / "home"),
        "PYTHONPATH": str(ROOT),
        "JAX_PLATFORMS": "cpu",
        "TREEINFER_JAX_CACHE": "off",
        "MPLBACKEND": "Agg",
        **case.env,
    }
    t0 = time.monotonic()
    try:
        r = subprocess.run(
            [sys.executable, "-m", "treeinfer", *map(str, argv)],
            cwd=ws,
            env=env,
            capture_output=True,
            timeout=timeout * case.timeout_scale,
            stdin=subprocess.DEVNULL,
        )
        rc, err, hang = r.returncode, r.stderr.decode(errors="replace"), False
    except subprocess.TimeoutExpired as e:
        rc, hang = None, True
        err = (e.stderr or b"").decode(errors="replace")
    dt = time.monotonic() - t0
    crash = rc is not None and (rc not in (0, 2, 4, 130) or "Traceback" in err)
    lost = [rel for rel, d in before.items() if not _survives(ws, rel, d)]
    left = _leftovers(ws)
    shutil.rmtree(ws, ignore_errors=True)
    return Outcome(case, rc, dt, crash, hang, lost, left, err.strip().splitlines()[-1:])


# ---- the cases -------------------------------------------------------------------------------
def _data_loss() -> list[Case]:
    cases = []
    T = ["--tree", "tree.yaml"]
    # (command argv builder, output flag value, protected) for outputs overlapping inputs
    overlap = {
        "infer --out DATA": (lambda o: ["infer", *T, "--data", "data", "--out", o], "data"),
        "infer --prior-from R --out R": (
            lambda o: ["infer", *T, "--data", "data", "--prior-from", o, "--out", o],
            "lookalike",
        ),
        "infer --out = tree": (lambda o: ["infer", *T, "--data", "data", "--out", o], "tree.yaml"),
        "calibrate --out = tree": (lambda o: ["calibrate", *T, "--out", o], "tree.yaml"),
        "simulate --out = tree": (lambda o: ["simulate", *T, "--out", o], "tree.yaml"),
        "import-csv over its source": (lambda o: ["import-csv", "data/traj_000.csv", "--out", o], "data"),
        "tree --from t --out t": (lambda o: ["tree", "--from", "tree.yaml", "--out", o], "tree.yaml"),
        "tree --mjcf = --from": (
            lambda o: ["tree", "--from", "tree.yaml", "--out", "t2.yaml", "--mjcf", o],
            "tree.yaml",
        ),
        "predict --out = force csv": (
            lambda o: ["predict", "--run", "lookalike", "--force-csv", "data/traj_000.csv", "--out", o],
            "data/traj_000.csv",
        ),
        "evaluate --out DATA": (
            lambda o: ["evaluate", "--run", "lookalike", "--data", "data", "--out", o],
            "data",
        ),
        "suggest --out RUN": (lambda o: ["suggest", "--run", "lookalike", "--out", o], "lookalike"),
        "import-bag --out holding the bag": (lambda o: ["import-bag", "data/traj_000.csv", "--out", o], "data"),
    }  # fmt: skip
    spellings = [
        lambda p: p,
        lambda p: "./" + p,
        lambda p: p + "/" if not p.endswith((".yaml", ".csv")) else p,
        lambda p: "../" + "{ws}" + "/" + p,  # through the parent: resolved by the case
        lambda p: "alias",  # a symlink to it
    ]
    for name, (build, target) in overlap.items():
        for k, spell in enumerate(spellings):
            for force in (False, True):

                def setup(ws, build=build, target=target, spell=spell, force=force):
                    s = spell(target)
                    if s == "alias":
                        os.symlink(ws / target, ws / "alias")
                    s = s.replace("{ws}", ws.name)
                    return build(s) + (["--force"] if force else [])

                cases.append(
                    Case(
                        "data loss",
                        f"{name} [{k}{' --force' if force else ''}]",
                        setup,
                        protected=(target, "tree.yaml", "data"),
                    )  # fmt: skip
                )
    # --force over a user's folder, a look-alike run folder and the home folder
    users = {
        "simulate": lambda o: ["simulate", *T, "--out", o, "--n-traj", "1", "--duration", "0.2"],
        "calibrate": lambda o: ["calibrate", *T, "--out", o, "--datasets", "1"],
        "evaluate": lambda o: ["evaluate", "--run", "lookalike", "--data", "data", "--out", o],
        "predict": lambda o: ["predict", "--run", "lookalike", "--profile", "ramp:peak=1,ramp=0.1",
                              "--duration", "0.2", "--out", o],
        "suggest": lambda o: ["suggest", "--run", "lookalike", "--out", o],
        "demo": lambda o: ["demo", "--quick", "--out", o],
        "infer": lambda o: ["infer", *T, "--data", "data", "--out", o, "--iterations", "1"],
        "import-csv": lambda o: ["import-csv", "log.csv", "--out", o],
    }  # fmt: skip
    for cmd, build in users.items():
        for target in ("photos", "home", "."):
            # import-csv adds files to a folder (legal: exit 0 into photos/), never replaces it
            exp = -1 if cmd == "import-csv" and target != "." else 2
            cases.append(
                Case(
                    "data loss",
                    f"{cmd} --out {target} --force",
                    lambda ws, b=build, t=target: (
                        b(str(ws / t) if t == "home" else t) + ["--force"]
                    ),
                    expect=exp,
                    protected=("photos", "home/.ssh", "tree.yaml", "data"),
                )  # fmt: skip
            )
    return cases


def _damaged_runs(run_files: list[str]) -> list[Case]:
    cases = []

    def damage(kind, rel):
        def setup(ws):
            p = ws / "run" / rel
            b = p.read_bytes()
            if kind == "flip":
                i = len(b) // 2
                p.write_bytes(b[:i] + bytes([b[i] ^ 1]) + b[i + 1 :])
            elif kind == "truncate":
                p.write_bytes(b[: len(b) // 2])
            elif kind == "delete":
                p.unlink()
            elif kind == "append":
                p.write_bytes(b + b" ")
            elif kind == "empty":
                p.write_bytes(b"")
            return ["predict", "--run", "run", "--profile", "ramp:peak=1,ramp=0.1",
                    "--duration", "0.2", "--out", "pred"]  # fmt: skip

        return setup

    for rel in run_files:
        for kind in ("flip", "truncate", "delete", "append", "empty"):
            cases.append(Case("damaged run", f"{kind} {rel}", damage(kind, rel)))

    def edit_json(rel, how):
        def setup(ws):
            p = ws / "run" / rel
            d = json.loads(p.read_text())
            how(d)
            p.write_text(json.dumps(d, indent=2, sort_keys=True) + "\n")
            return ["evaluate", "--run", "run", "--data", "data", "--out", "ev"]

        return setup

    def drop(key):
        return lambda d: d.pop(key, None)

    def scale_means(d):
        for v in d.get("posterior", {}).values():
            v["mean"] = v["mean"] * 10

    edits = {
        ("config.json", "kT x 10"): lambda d: d["problem"].__setitem__("kT", d["problem"]["kT"] * 10),
        ("config.json", "seed changed"): lambda d: d["options"].__setitem__("seed", 99),
        ("config.json", "tree_dict removed"): drop("tree_dict"),
        ("config.json", "integrity removed"): drop("integrity"),
        ("config.json", "format 99"): lambda d: d.__setitem__("format", 99),
        ("summary.json", "posterior means x 10"): scale_means,
        ("summary.json", "unstable list cleared"): lambda d: d.__setitem__("unstable_particles", []),
        ("summary.json", "posterior removed"): drop("posterior"),
    }  # fmt: skip
    for (rel, what), how in edits.items():
        cases.append(Case("damaged run", f"{rel}: {what}", edit_json(rel, how)))
        # the same edit with the manifest regenerated (a careful forger): semantic checks remain
        cases.append(
            Case(
                "damaged run",
                f"{rel}: {what}, manifest removed",
                lambda ws, f=edit_json(rel, how): (ws / "run" / "manifest.json").unlink() or f(ws),
            )  # fmt: skip
        )

    def swap_tree(ws):
        t = (ws / "run" / "tree.yaml").read_text().replace("0.6", "0.7", 1)
        (ws / "run" / "tree.yaml").write_text(t)
        (ws / "run" / "manifest.json").unlink()
        return ["suggest", "--run", "run", "--out", "sg"]

    cases.append(Case("damaged run", "tree.yaml swapped for a same-shape tree", swap_tree))
    for k in range(8):  # random byte edits anywhere in the folder
        rng = random.Random(k)

        def rand(ws, rng=rng):
            files = sorted(p for p in (ws / "run").rglob("*") if p.is_file())
            p = rng.choice(files)
            b = bytearray(p.read_bytes() or b"\0")
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
            p.write_bytes(bytes(b))
            return ["infer", "--tree", "tree.yaml", "--data", "data", "--out", "r2",
                    "--prior-from", "run", "--iterations", "1"]  # fmt: skip

        cases.append(Case("damaged run", f"random bit flip #{k} (infer --prior-from)", rand))
    return cases


def _crashes() -> list[Case]:
    cases = []
    odd_csvs = {
        "empty": "",
        "header only": "time,force,displacement\n",
        "one row": "time,force,displacement\n0,0,0\n",
        "BOM and CRLF": "\ufefftime,force,displacement\r\n" + CSV.replace("\n", "\r\n").split("\r\n", 1)[1],
        "NaN cells": CSV.replace("0.100", "nan"),
        "inf cells": CSV.replace("0.100", "inf"),
        "1e308": CSV.replace("0.100", "1e308"),
        "ragged row": CSV + "1,2\n",
        "semicolons": CSV.replace(",", ";"),
        "latin-1 bytes": None,
        "binary junk": None,
        "duplicate header": "time,force,force,displacement\n0,0,0,0\n",
        "time backwards": "time,force,displacement\n" + "".join(f"{1 - 0.01 * i},{i},{i}\n" for i in range(50)),
        "constant time": "time,force,displacement\n" + "".join(f"0,{i},{i}\n" for i in range(50)),
        "huge line": "time,force,displacement\n" + "1" * 2_000_000 + "\n",
        "quotes": '"time","force","displacement"\n' + "".join(f'"{0.01 * i:.2f}","{0.1 * i:.2f}","{0.001 * i:.3f}"\n' for i in range(50)),
        "only comments": "# nothing\n# here\n",
        "negative zero and exponents": "time,force,displacement\n" + "".join(f"{i}e-2,-0,{i}E-4\n" for i in range(50)),
    }  # fmt: skip
    for name, text in odd_csvs.items():

        def setup(ws, name=name, text=text):
            p = ws / "odd.csv"
            if name == "latin-1 bytes":
                p.write_bytes("time,forcé\n0,1\n".encode("latin-1"))
            elif name == "binary junk":
                p.write_bytes(bytes(random.Random(1).randrange(256) for _ in range(4000)))
            else:
                p.write_text(text, encoding="utf-8")
            return ["import-csv", "odd.csv", "--out", "imp"]

        exp = (
            0
            if name in ("BOM and CRLF", "semicolons", "quotes", "negative zero and exponents")
            else None
        )
        cases.append(
            Case("crash", f"import-csv: {name}", setup, expect=exp if exp is not None else -1)
        )
    trees = {
        "alias bomb": "a: &a [x, x, x, x, x, x, x, x]\n" + "".join(
            f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
            for p, c in zip("abcdefgh", "bcdefghi")),
        "python tag": "!!python/object/apply:os.system ['echo pwned > pwned']\n",
        "deep nesting": "[" * 5000 + "]" * 5000,
        "branches: yes": "branches: yes\n",
        "length 1e300": "branches:\n  - {name: a, length: 1e300, radius: 0.01}\n",
        "cycle": "branches:\n  - {name: a, parent: b, length: 1, radius: 0.01}\n  - {name: b, parent: a, length: 1, radius: 0.01}\n",
        "1000-branch chain": "branches:\n" + "".join(
            f"  - {{name: b{i}, parent: {'null' if i == 0 else f'b{i-1}'}, length: 0.01, radius: 0.002}}\n"
            for i in range(1000)),
        "1000-branch star": "branches:\n  - {name: root, length: 0.5, radius: 0.02}\n" + "".join(
            f"  - {{name: s{i}, parent: root, length: 0.1, radius: 0.002}}\n" for i in range(999)),
    }  # fmt: skip
    for name, text in trees.items():
        for cmd in ("tree", "simulate", "infer"):

            def setup(ws, text=text, cmd=cmd):
                (ws / "bad.yaml").write_text(text)
                if cmd == "tree":
                    return ["tree", "--from", "bad.yaml", "--out", "t.yaml", "--mjcf", "t.xml"]
                if cmd == "simulate":
                    return ["simulate", "--tree", "bad.yaml", "--out", "sim", "--n-traj", "1"]
                return ["infer", "--tree", "bad.yaml", "--data", "data", "--out", "r"]

            cases.append(Case("crash", f"{cmd}: tree {name}", setup, protected=("home",)))

    # a URDF whose mesh path is a symlink loop, an MJCF including itself
    def urdf_loop(ws):
        os.symlink("loop_b", ws / "loop_a")
        os.symlink("loop_a", ws / "loop_b")
        (ws / "m.urdf").write_text(
            '<robot name="r"><link name="base"><visual><geometry><mesh filename="loop_a"/>'
            "</geometry></visual></link></robot>"
        )
        return ["tree", "--model", "m.urdf", "--out", "t.yaml"]

    def mjcf_self_include(ws):
        (ws / "m.xml").write_text('<mujoco><include file="m.xml"/></mujoco>')
        return ["tree", "--model", "m.xml", "--out", "t.yaml"]

    cases += [Case("crash", "URDF mesh symlink loop", urdf_loop),
              Case("crash", "MJCF including itself", mjcf_self_include)]  # fmt: skip
    for flag, val in (("--n-traj", "-1"), ("--duration", "nan"), ("--dt", "0"), ("--seed", "-5"),
                      ("--duration", "1e12"), ("--n-traj", "1000000000")):  # fmt: skip
        cases.append(Case("crash", f"simulate {flag} {val}", lambda ws, f=flag, v=val:
                          ["simulate", "--tree", "tree.yaml", "--out", "s", f, v]))  # fmt: skip
    return cases


def _hangs() -> list[Case]:
    cases = []
    specials = {
        "fifo": lambda p: os.mkfifo(p),
        "/dev/zero": lambda p: os.symlink("/dev/zero", p),
        "/dev/urandom": lambda p: os.symlink("/dev/urandom", p),
    }
    uses = {
        "import-csv SRC": ("x.csv", lambda: ["import-csv", "x.csv", "--out", "imp"]),
        "import-bag BAG": ("x.bag", lambda: ["import-bag", "x.bag", "--out", "imp"]),
        "tree --from": ("x.yaml", lambda: ["tree", "--from", "x.yaml", "--out", "t.yaml"]),
        "infer --tree": ("x.yaml", lambda: ["infer", "--tree", "x.yaml", "--data", "data", "--out", "r"]),
        "data/ holds it": ("data/z.csv", lambda: ["infer", "--tree", "tree.yaml", "--data", "data", "--out", "r", "--iterations", "1"]),
        "simulate --params-json": ("p.json", lambda: ["simulate", "--tree", "tree.yaml", "--out", "s", "--params-json", "p.json"]),
        "predict --force-csv": ("f.csv", lambda: ["predict", "--run", "run", "--force-csv", "f.csv", "--out", "p"]),
        "MJCF <include>": ("inc.xml", None),
        "URDF mesh": ("mesh.stl", None),
        "run/config.json": ("run/config.json", lambda: ["predict", "--run", "run", "--profile", "ramp:peak=1,ramp=0.1", "--duration", "0.2", "--out", "p"]),
        "pulls.yaml": ("data/pulls.yaml", lambda: ["infer", "--tree", "tree.yaml", "--data", "data", "--out", "r"]),
    }  # fmt: skip
    for sname, make in specials.items():
        for uname, (rel, argv) in uses.items():

            def setup(ws, make=make, rel=rel, argv=argv, uname=uname):
                p = ws / rel
                if p.exists() or p.is_symlink():
                    p.unlink()
                make(p)
                if uname == "MJCF <include>":
                    (ws / "m.xml").write_text('<mujoco><include file="inc.xml"/></mujoco>')
                    return ["tree", "--model", "m.xml", "--out", "t.yaml"]
                if uname == "URDF mesh":
                    (ws / "m.urdf").write_text(
                        '<robot name="r"><link name="base"><visual><geometry>'
                        '<mesh filename="mesh.stl"/></geometry></visual></link></robot>'
                    )
                    return ["tree", "--model", "m.urdf", "--out", "t.yaml"]
                return argv()

            # a FIFO in the data folder is named and skipped, not read: infer goes on (exit 0
            # or 2 for the tiny data); every other use must be refused
            cases.append(Case("hang", f"{sname} as {uname}", setup,
                              expect=-1 if uname == "data/ holds it" else 2))  # fmt: skip
    sizes = {
        "calibrate --datasets 1e9": ["calibrate", "--tree", "tree.yaml", "--out", "c", "--datasets", "1000000000"],
        "calibrate --particles 1e9": ["calibrate", "--tree", "tree.yaml", "--out", "c", "--particles", "1000000000", "--smc-particles", "1000000000"],
        "calibrate --n-traj 1e7": ["calibrate", "--tree", "tree.yaml", "--out", "c", "--n-traj", "10000000"],
        "warmup --steps 1e9": ["warmup", "--tree", "tree.yaml", "--steps", "1000000000"],
        "warmup --n-traj 1e8": ["warmup", "--tree", "tree.yaml", "--n-traj", "100000000"],
        "warmup -- --particles 1e9": ["warmup", "--tree", "tree.yaml", "--", "--particles", "1000000000"],
        "suggest --particles 1e9": ["suggest", "--run", "run", "--particles", "1000000000"],
        "tree fractal depth 25": ["tree", "--kind", "fractal", "--depth", "25", "--out", "f.yaml"],
        "tree fractal depth 12 branching 3": ["tree", "--kind", "fractal", "--depth", "12", "--branching", "3", "--out", "f.yaml"],
    }  # fmt: skip
    for name, argv in sizes.items():
        cases.append(Case("hang", name, lambda ws, a=argv: list(a)))
    return cases


def _leftover_cases() -> list[Case]:
    """Failures midway: the output must be absent or complete, no staging folder left."""
    cases = []
    for k, argv in enumerate([
        ["simulate", "--tree", "tree.yaml", "--out", "ro/sim", "--n-traj", "1", "--duration", "0.2"],
        ["import-csv", "log.csv", "--out", "ro/imp"],
        ["tree", "--from", "tree.yaml", "--out", "ro/t.yaml"],
        ["calibrate", "--tree", "tree.yaml", "--out", "ro/c", "--datasets", "1"],
    ]):  # fmt: skip

        def setup(ws, argv=argv):
            (ws / "ro").mkdir()
            os.chmod(ws / "ro", 0o555)  # a read-only destination (root ignores it: then exit 0)
            return argv

        cases.append(Case("leftovers", f"read-only destination #{k}: {argv[0]}", setup, expect=-1))
    for k in range(4):  # a stale staging folder of a killed process beside the destination

        def setup(ws, k=k):
            st = ws / f".sim.{999990 + k}.abcd.staging"
            st.mkdir()
            (st / ".treeinfer-output").write_text('{"writer": "treeinfer", "complete": false}')
            (st / "half.csv").write_text("x")
            return ["simulate", "--tree", "tree.yaml", "--out", "sim", "--n-traj", "1",
                    "--duration", "0.2"]  # fmt: skip

        cases.append(Case("leftovers", f"stale staging of a killed process #{k}", setup, expect=0))
    return cases


LIES_SRC: list[Path] = []  # a simulated training set of the example tree (made once in main)


def _make_lies_source(base: Path, timeout: float) -> Path | None:
    out = base / "lies-src"
    env = {**os.environ, "HOME": str(base), "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu",
           "TREEINFER_JAX_CACHE": "off", "MPLBACKEND": "Agg"}  # fmt: skip
    r = subprocess.run([sys.executable, "-m", "treeinfer", "simulate", "--tree", str(EXAMPLE),
                        "--out", str(out), "--n-traj", "3", "--seed", "1",
                        "--noise-displacement", "0.002", "--noise-force", "0.05"],
                       env=env, capture_output=True, timeout=timeout * 5)  # fmt: skip
    return out if r.returncode == 0 else None


def _lies() -> list[Case]:
    """Recordings that lie (issue 28, section 3): a treeinfer simulation of the example tree
    with one stream's unit, offset, clock or identity changed; ``infer`` must refuse them with
    exit 2 naming the file and column (expect 2); a force in kgf, whose compliance lies inside
    the prior box's range so that no check before sampling can see it, must end in the fit
    verdict poor_fit (expect 4: the fit calls a structured misfit noise)."""
    import csv

    def transform(fn, which=None, dup=False):
        def setup(ws):
            (ws / "lied").mkdir()
            for k, src in enumerate(sorted(LIES_SRC[0].glob("traj_*.csv"))):
                rows = list(csv.DictReader(src.open()))
                t = [float(r["time"]) for r in rows]
                f = [float(r["force"]) for r in rows]
                x = [float(r["displacement"]) for r in rows]
                if which is None or which == k:
                    t, f, x = fn(t, f, x)
                with (ws / "lied" / src.name).open("w") as fh:
                    fh.write("time,force,displacement\n")
                    fh.writelines(f"{a!r},{b!r},{c!r}\n" for a, b, c in zip(t, f, x))
            if dup:
                shutil.copy(ws / "lied" / "traj_000.csv", ws / "lied" / "traj_009.csv")
            shutil.copy(LIES_SRC[0] / "tree.yaml", ws / "tree.yaml")
            return ["infer", "--tree", "tree.yaml", "--data", "lied", "--out", "r",
                    "--no-progress"]  # fmt: skip

        return setup

    def scale(a=1.0, b=1.0, c=1.0):
        return lambda t, f, x: ([v * a for v in t], [v * b for v in f], [v * c for v in x])

    def shift(n):  # n > 0: the displacement n samples early (ahead of the force)
        return lambda t, f, x: (t, f, x[n:] + [x[-1]] * n)

    def offset(df=0.0, dx=0.0):
        return lambda t, f, x: (t, [v + df for v in f], [v + dx for v in x])

    cases = [
        ("displacement in mm", scale(c=1000), None),
        ("displacement in cm", scale(c=100), None),
        ("displacement in inches", scale(c=39.37), None),
        ("force in kN", scale(b=1e-3), None),
        ("force in mN", scale(b=1e3), None),
        ("force in kgf", scale(b=1 / 9.81), None),
        ("force tare not subtracted (+5 N)", offset(df=5.0), None),
        ("displacement from world origin (+5 cm)", offset(dx=0.05), None),
        ("force and displacement swapped", lambda t, f, x: (t, x, f), None),
        ("displacement sign flipped", scale(c=-1), None),
        ("time in minutes", scale(a=1 / 60), None),
        ("displacement 0.4 s ahead of the force", shift(40), None),
        ("one file in mm", scale(c=1000), 1),
        ("one file's force in kN", scale(b=1e-3), 1),
    ]
    fit_only = {"force in kgf"}  # seen only by the fit verdict (exit 4), see the docstring
    out = [Case("data that lie", name, transform(fn, which), expect=4 if name in fit_only else 2,
                timeout_scale=5.0 if name in fit_only else 1.0)
           for name, fn, which in cases]  # fmt: skip
    out.append(Case("data that lie", "the same recording twice", transform(scale(), dup=True)))
    return out


# ---- main ------------------------------------------------------------------------------------
def _make_run(base: Path, timeout: float) -> Path | None:
    out = base / "demo"
    env = {**os.environ, "HOME": str(base), "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu",
           "TREEINFER_JAX_CACHE": "off", "MPLBACKEND": "Agg"}  # fmt: skip
    r = subprocess.run([sys.executable, "-m", "treeinfer", "demo", "--quick", "--out", str(out),
                        "--no-progress"], env=env, capture_output=True, timeout=timeout * 20)  # fmt: skip
    if r.returncode != 0 or not (out / "run" / "manifest.json").is_file():
        print("could not make the reference run:", r.stderr.decode()[-500:], file=sys.stderr)
        return None
    return out / "run"


def _table(results: list[Outcome]) -> str:
    order = ["data loss", "damaged run", "data that lie", "crash", "hang", "leftovers"]
    cats = sorted({o.case.category for o in results}, key=order.index)
    head = ["category", "cases", "exit 2", "exit 0", "crashes (exit 3 / traceback)", "hangs",
            "data lost", "leftovers", "unexpected exit", "slowest answer"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in cats:
        rs = [o for o in results if o.case.category == c]
        unexpected = [o for o in rs if o.case.expect >= 0 and o.rc != o.case.expect and not o.hang]
        lines.append(
            f"| {c} | {len(rs)} | {sum(o.rc == 2 for o in rs)} | {sum(o.rc == 0 for o in rs)} | "
            f"{sum(o.crash for o in rs)} | {sum(o.hang for o in rs)} | "
            f"{sum(bool(o.lost) for o in rs)} | {sum(bool(o.leftovers) for o in rs)} | "
            f"{len(unexpected)} | {max(o.seconds for o in rs):.1f} s |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="every 4th case of each category")
    ap.add_argument("--jobs", type=int, default=max(1, min(4, (os.cpu_count() or 2))))
    ap.add_argument("--timeout", type=float, default=60.0, help="s per case before it is a hang")
    ap.add_argument("--only", help="run only the categories containing this text")
    args = ap.parse_args(argv)
    base = Path(tempfile.mkdtemp(prefix="treeinfer-campaign-"))
    t0 = time.monotonic()
    try:
        print("making a reference run (treeinfer demo --quick) ...", flush=True)
        run = _make_run(base, args.timeout)
        run_files = sorted(
            p.relative_to(run).as_posix() for p in run.rglob("*") if p.is_file()
        ) if run else []  # fmt: skip
        cases = _data_loss() + (_damaged_runs(run_files) if run else []) + _crashes() + _hangs()
        cases += _leftover_cases()
        if not args.only or args.only in "data that lie":
            src = _make_lies_source(base, args.timeout)
            if src is not None:
                LIES_SRC.append(src)
                cases += _lies()
            else:
                print("could not simulate the recordings for 'data that lie'", file=sys.stderr)
        if args.only:
            cases = [c for c in cases if args.only in c.category]
        if args.quick:
            cases = cases[::4]
        print(f"{len(cases)} cases, {args.jobs} at a time, timeout {args.timeout:g} s", flush=True)
        results: list[Outcome] = []
        with cf.ThreadPoolExecutor(args.jobs) as ex:
            futs = [ex.submit(run_case, c, base, args.timeout, run) for c in cases]
            for k, f in enumerate(cf.as_completed(futs), 1):
                o = f.result()
                results.append(o)
                bad = o.crash or o.hang or o.lost or o.leftovers or (
                    o.case.expect >= 0 and o.rc != o.case.expect)  # fmt: skip
                if bad:
                    print(f"  [{o.case.category}] {o.case.name}: rc={o.rc} {o.seconds:.1f}s "
                          f"lost={o.lost} left={o.leftovers} {o.tail}", flush=True)  # fmt: skip
                if k % 25 == 0:
                    print(f"  {k}/{len(cases)} done", flush=True)
        print()
        print(_table(results))
        print(f"\n{len(results)} cases in {time.monotonic() - t0:.0f} s")
        worst = [o for o in results if o.crash or o.hang or o.lost or o.leftovers]
        return 1 if worst else 0
    finally:
        shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
