"""``treeinfer import-pul``: static winch pulling tests (``.pul``) -> force and signed tilts on
one time base + the test's set-up (:func:`treeinfer.data.import_pul.import_pul`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..data.import_pul import import_pul
from ..data.pull_test import MAX_GAP_S
from .common import COMMAND_HELP, EXIT_OK, add_command_parser

_IMPORT_PUL_EPILOG = """\
examples:
  treeinfer import-pul ../shared/data/mangrove/pull_tests/halloran_10.pul --out data/mangrove
  treeinfer import-pul tests/*.pul --trees trees.csv --out data/pulls --force

Each FILE becomes OUT/<name>.csv (time s, force N along the cable, tilt_root and tilt_trunk in
rad, signed along the pull, NaN in gaps) and OUT/<name>.json (set-up: sling and inclinometer
heights, cable angle; channels; ramp and release phases; every step applied). The set-up comes
from the metadata table's row whose pul_file is the file's stem (Hill et al. 2024,
doi:10.1016/j.ecoleng.2024.107259; see docs/pulling_tests.md).
"""


def configure_import_pul(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "import-pul",
        help=COMMAND_HELP["import-pul"],
        description="Convert static winch pulling tests in the .pul format (cable force, two "
        "2-axis inclinometers) into force and signed tilt along the pull on one time base, "
        "with each test's set-up from the metadata table.",
        epilog=_IMPORT_PUL_EPILOG,
    )
    p.add_argument("sources", nargs="+", metavar="FILE", help=".pul file(s), one test each")
    p.add_argument(
        "--out", required=True, type=Path, metavar="DIR", help="data folder to write into"
    )
    p.add_argument(
        "--trees",
        type=Path,
        metavar="CSV",
        help="the tests' metadata table (default: trees.csv beside FILE or one folder up)",
    )
    p.add_argument(
        "--max-gap",
        type=float,
        default=MAX_GAP_S,
        metavar="S",
        help="no interpolation of an inclinometer across readings more than S seconds apart",
    )
    p.add_argument("--force", action="store_true", help="replace same-named outputs in DIR")
    return p


def run_import_pul(args: argparse.Namespace) -> int:
    res = import_pul(
        args.sources, args.out, trees=args.trees, max_gap=args.max_gap, overwrite=args.force
    )
    for t in res.tests:
        print(f"{t.name}: {t.n} samples, peak {t.force.max() / 1000:.2f} kN")
        for s in t.steps:
            print(f"  {s}")
    print(f"wrote {len(res.paths)} file(s) into {args.out}/")
    return EXIT_OK
