"""``treeinfer warmup``: fill the persistent compilation cache with the programs an ``infer`` run
of a given tree, data shape and options will need, from synthetic data of that shape, so the
first field recording starts without waiting on the compiler.

It runs the run itself (``treeinfer simulate`` then ``treeinfer infer`` with the given infer
options, into a temporary folder that is deleted): a list of programs kept by hand would drift
from what ``infer`` compiles, and a real run is the only complete list. Data sets of the same
shape bucket (:mod:`treeinfer.sim.startup`) then reuse the programs (``tests/test_cold_start.py``).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import treeinfer

from ..errors import ConfigError
from ..io import interrupt
from ..io.limits import check_command_size
from .common import COMMAND_HELP, EXIT_OK, EXIT_POOR_FIT, _say, add_command_parser
from .options import add_deprecated

# infer options warmup sets itself (the synthetic data and a throwaway run folder)
_OWN = ("--data", "--out", "--resume", "--force")
# infer options that also shape the synthetic data: handed to `simulate` as well
_SHARED = ("--model", "--repair-inertia", "--grasp-fraction", "--force-interp", "--backend")

_EPILOG = """\
examples:
  treeinfer warmup --tree tree.yaml --n-traj 3 --steps 300 -- \\
      --init importance --particles 128
  treeinfer warmup --tree tree.yaml --n-traj 4 --steps 500 --dt 0.005 -- --init importance

Everything after `--` is passed to `treeinfer infer` unchanged: give the options your field runs
will use (particles, --init, sampler, backend, step, likelihood ...), since the compiled programs
depend on them. A recording is served from the cache when its number of pulls and of samples fall
in the same buckets as the warmup's (pulls: 1, 2, 3, 4, 6, 8, 12, ...; samples: the next of
2^k x {1, 1.25, 1.5, 1.75}, at least 64; e.g. 257-320 samples share one bucket), its sample
interval is the same, and the run takes the same path (an importance run whose weights fail falls
back to the sampler, whose programs the warmup compiles only if its own run fell back too).
The cache folder is TREEINFER_JAX_CACHE (default ~/.cache/treeinfer/jax/<versions>); `off`
disables it, and then warmup has nothing to fill.
"""


def configure_warmup(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "warmup",
        COMMAND_HELP["warmup"],
        "Compile, into the persistent compilation cache, every program a `treeinfer infer` run "
        "of this tree, data shape and infer options needs, by running one on synthetic data of "
        "that shape (`treeinfer simulate`, then `treeinfer infer` into a temporary folder, "
        "deleted afterwards). Run it once after installing, on the robot's computer: its first "
        "field recording then starts warm. Prints how many programs it compiled (and the "
        "slowest), how many it found already cached, the cache folder and the time taken.",
        _EPILOG,
    )
    p.add_argument("--tree", type=Path, required=True, help="tree description (YAML/JSON)")
    p.add_argument(
        "--n-traj", dest="trajectories", type=int, default=3, metavar="N", help="number of pulls"
    )
    p.add_argument("--steps", type=int, default=300, metavar="T", help="samples per pull")
    p.add_argument(
        "--dt", type=float, default=0.01, metavar="S", help="s between samples, as recorded"
    )
    p.add_argument(
        "--allow-large",
        action="store_true",
        help="go past the size limit (treeinfer.io.limits) checked before any work",
    )
    add_deprecated(p, "--trajectories", "--n-traj", "the number of pulls in every command")
    p.add_argument(
        "infer_options",
        nargs=argparse.REMAINDER,
        metavar="-- INFER OPTIONS",
        help="options of `treeinfer infer` (after `--`), as the field runs will use them",
    )
    return p


def _check(args) -> list[str]:
    """The infer options (``--`` dropped); ConfigError naming the field for bad input."""
    if args.trajectories < 1:
        raise ConfigError(f"--n-traj: must be an integer >= 1, got {args.trajectories}")
    if args.steps < 3:
        raise ConfigError(f"--steps: must be an integer >= 3, got {args.steps}")
    if not (args.dt > 0 and args.dt < float("inf")):
        raise ConfigError(f"--dt: must be a positive number of seconds, got {args.dt}")
    rest = list(args.infer_options)
    if rest and rest[0] == "--":
        rest = rest[1:]
    for flag in rest:
        name = flag.split("=", 1)[0]
        if name in _OWN:
            raise ConfigError(f"infer option {name}: warmup sets it itself; leave it out")
        if name == "--tree":
            raise ConfigError("infer option --tree: give the tree as warmup's own --tree")
    return rest


def _shared_options(rest: list[str]) -> list[str]:
    """The infer options that also apply to ``simulate`` (the model, grasp point, backend)."""
    out = []
    for i, flag in enumerate(rest):
        name = flag.split("=", 1)[0]
        if name in _SHARED:
            out.append(flag)
            if "=" not in flag and i + 1 < len(rest):
                out.append(rest[i + 1])
    return out


def run_warmup(args: argparse.Namespace) -> int:
    from ..sim.compile_stats import compile_stats
    from .main import main

    rest = _check(args)
    check_command_size("warmup", args)  # before anything is simulated or compiled
    t0 = time.perf_counter()
    cache = treeinfer.enable_compilation_cache()
    if cache is None:
        raise ConfigError(
            "TREEINFER_JAX_CACHE: the persistent compilation cache is off; warmup has nothing "
            "to fill (unset it or name a folder)"
        )
    stats = compile_stats()
    mark = stats.mark()
    work = Path(tempfile.mkdtemp(prefix="treeinfer-warmup-"))
    interrupt.register(work)  # removed even when a second Ctrl-C ends the process at once
    try:
        data, out = work / "data", work / "run"
        duration = (args.steps - 1) * args.dt
        _say(
            f"warmup: {args.trajectories} synthetic pulls x {args.steps} samples (dt "
            f"{args.dt:g} s), then `treeinfer infer {' '.join(rest)}`"
        )
        sim_args = ["simulate", "--tree", str(args.tree), "--out", str(data),
                    "--n-traj", str(args.trajectories), "--duration", repr(duration),
                    "--dt", repr(args.dt), "--seed", "0", "--noise-displacement", "0.002",
                    *_shared_options(rest)]  # fmt: skip
        rc = main(sim_args)
        if rc != EXIT_OK:
            raise ConfigError(f"warmup: simulating the synthetic data failed (exit {rc})")
        infer_args = ["infer", "--tree", str(args.tree), "--data", str(data), "--out", str(out),
                      "--no-progress", "--allow-poor-fit", *rest]  # fmt: skip
        rc = main(infer_args)
        if rc not in (EXIT_OK, EXIT_POOR_FIT):
            raise ConfigError(f"warmup: the infer run on the synthetic data failed (exit {rc})")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    s = stats.since(mark)
    # the synthetic run's own report (its fit verdict, warnings) is printed above: say that only
    # its programs are kept, so a fit warning on made-up data is not read as one about the tree
    print("warmup: the synthetic run above is discarded; only its compiled programs are kept")
    slow = ", ".join(f"{n} {t:.1f} s" for n, t in s["compiled"][:5])
    print(
        f"compiled {s['xla_compiles']} programs in {s['compile_s']:.1f} s"
        + (f" (slowest: {slow})" if slow else "")
    )
    print(f"already in the cache: {s['cache_hits']} programs")
    print(f"cache folder: {cache}")
    print(f"warmup took {time.perf_counter() - t0:.1f} s")
    return EXIT_OK
