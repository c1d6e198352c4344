"""``treeinfer import-csv``: logger CSVs -> trajectory CSVs + pulls.yaml
(:func:`treeinfer.data.import_csv.import_csv`).
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

from ..data.import_csv import import_csv
from .common import COMMAND_HELP, EXIT_OK, add_command_parser, add_grasp_point_options
from .options import add_deprecated

_IMPORT_CSV_EPILOG = """\
examples:
  treeinfer import-csv log_low.csv --out data/stem --time-column millis --force-column load_g \\
      --displacement-column pos_mm --units time=ms,force=gf,displacement=mm --dt 0.5 --tare \\
      --zero-displacement contact --trim --grasp-branch link0 --grasp-distance 0.12 \\
      --direction horizontal
  treeinfer import-csv a.csv b.csv --out data/x --force-column 1 --displacement-column 2 \\
      --time-column none --dt 0.01

Each source becomes OUT/<name>.csv (time,force,displacement in s, N, m on a uniform grid) and
an entry in OUT/pulls.yaml (grasp point and direction); run it once per grasp point into the
same folder. Every transformation is printed and recorded in OUT/import.json.
units: time s|ms; force N|mN|kN|gf|kgf|lbf; displacement m|cm|mm|in.
"""


def _column(text: str):
    return None if text.strip().lower() == "none" else text


def configure_import_csv(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "import-csv",
        help=COMMAND_HELP["import-csv"],
        description="Convert a logger's CSV files (any column names and units, a wrapping or "
        "jittery time column, a force offset, idle time) into treeinfer trajectory CSVs and "
        "the data folder's pulls.yaml, printing every transformation applied.",
        epilog=_IMPORT_CSV_EPILOG,
    )
    p.add_argument("sources", nargs="+", metavar="SRC", help="logger CSV file(s), one pull each")
    p.add_argument(
        "--out", required=True, type=Path, metavar="DIR", help="data folder to write into"
    )
    p.add_argument(
        "--time-column",
        dest="time",
        type=_column,
        default="time",
        metavar="COL",
        help="time column, by header name or 0-based index; 'none' with --dt",
    )
    p.add_argument(
        "--force-column",
        dest="force_col",
        default="force",
        metavar="COL",
        help="force column, by header name or 0-based index (--force means overwrite)",
    )
    p.add_argument(
        "--displacement-column",
        dest="displacement",
        default="displacement",
        metavar="COL",
        help="displacement column, by header name or 0-based index",
    )
    p.add_argument("--units", metavar="Q=U,...", help="e.g. time=ms,force=gf,displacement=mm")
    p.add_argument(
        "--dt",
        type=float,
        metavar="S",
        help="s; rebuild a uniform time base i*S (time column missing or unreliable)",
    )
    p.add_argument("--tare", action="store_true", help="subtract the force at rest")
    p.add_argument(
        "--zero-displacement",
        choices=("first", "contact", "none"),
        default="first",
        help="measure displacement from the first sample (default) or from contact",
    )
    p.add_argument("--trim", action="store_true", help="drop idle samples at the start and end")
    add_grasp_point_options(p)
    p.add_argument("--direction", metavar="D", help="down | horizontal | X,Y,Z (pulls.yaml)")
    p.add_argument("--delimiter", metavar="C", help="field separator (default: sniffed)")
    p.add_argument("--force", action="store_true", help="replace same-named CSVs in DIR")
    add_deprecated(p, "--time", "--time-column")
    add_deprecated(p, "--displacement", "--displacement-column")
    return p


def run_import_csv(args: argparse.Namespace) -> int:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = import_csv(
            args.sources,
            args.out,
            time=args.time,
            force=args.force_col,
            displacement=args.displacement,
            units=args.units,
            dt=args.dt,
            tare=args.tare,
            zero_displacement=None if args.zero_displacement == "none" else args.zero_displacement,
            trim=args.trim,
            grasp_branch=args.grasp_branch,
            grasp_fraction=args.grasp_fraction,
            grasp_distance=args.grasp_distance,
            direction=args.direction,
            delimiter=args.delimiter,
            overwrite=args.force,
        )
    print(res.report())
    for w in caught:
        print(f"warning: {w.message}")
    print(f"wrote {len(res.paths)} trajectory file(s) and {res.sidecar.name} into {args.out}/")
    return EXIT_OK
