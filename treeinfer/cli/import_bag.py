"""``treeinfer import-bag``: cut a ROS bag into trajectory CSVs.

The work is done by :func:`treeinfer.data.import_bag.import_bag`."""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

from ..data.import_bag import _triple, import_bag
from .common import (
    COMMAND_HELP,
    EXIT_OK,
    add_command_parser,
    add_grasp_point_options,
)
from .options import add_deprecated

# ==== import-bag ==================================================================================
_IMPORT_BAG_EPILOG = """\
examples:
  treeinfer import-bag pulls.bag --out data/real
  treeinfer import-bag rosbag2_folder --out data/real --force-topic /wrench --pose-topic /tf \\
      --tf-child-frame tool0 --force-sign -1

Each pull (force above the rest threshold for at least --min-pull-duration) becomes one
trajectory CSV (time,force,displacement) on a fixed --dt grid, projected on the gravity axis.
"""


def configure_import_bag(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "import-bag",
        help=COMMAND_HELP["import-bag"],
        description="Read the force (WrenchStamped) and end-effector pose (PoseStamped, "
        "TransformStamped or /tf) streams from a ROS bag, resample them to a fixed step, project "
        "them on the gravity axis and write one trajectory CSV per pull. No ROS install needed.",
        epilog=_IMPORT_BAG_EPILOG,
    )
    return configure_parser(p)


def run_import_bag(args: argparse.Namespace) -> int:
    run_from_args(args)
    return EXIT_OK


def _dt_or_source(text: str):
    if text.strip().lower() == "source":
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds or 'source', got {text!r}") from None


def configure_parser(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``import-bag`` arguments to ``parser`` (a subcommand parser)."""
    parser.add_argument("bag", help="ROS1 .bag file or ROS2 bag folder")
    parser.add_argument(
        "--out",
        required=True,
        type=Path,
        metavar="DIR",
        help="output folder for the trajectory CSVs",
    )
    parser.add_argument("--force-topic", help="WrenchStamped/Wrench topic (auto-detected)")
    parser.add_argument(
        "--pose-topic", help="PoseStamped/TransformStamped/TF topic (auto-detected)"
    )
    parser.add_argument("--tf-child-frame", help="end-effector frame when the pose comes from /tf")
    parser.add_argument(
        "--dt",
        type=_dt_or_source,
        default=0.01,
        metavar="S|source",
        help="output time step in s (0.01); 'source': the slower stream's own message interval",
    )
    parser.add_argument(
        "--gravity-axis",
        type=_triple,
        default=(0.0, 0.0, -1.0),
        help="gravity direction in the pose frame, e.g. '0,0,-1' (default); write "
        "--gravity-axis=-1,0,0 when the first number is negative",
    )
    parser.add_argument(
        "--force-axis",
        type=_triple,
        default=None,
        help="gravity direction in the wrench frame (default: --gravity-axis)",
    )
    parser.add_argument(
        "--force-sign",
        type=int,
        choices=(1, -1),
        default=1,
        help="+1: reading is the force on the branch (default); -1: force on the robot",
    )
    parser.add_argument(
        "--rest-force-threshold",
        type=float,
        default=None,
        help="N; default max(5%% of max |force|, 0.2 N)",
    )
    parser.add_argument("--min-pull-duration", type=float, default=0.2, help="s (0.2)")
    parser.add_argument(
        "--lead-in", type=float, default=0.25, help="s of rest kept before each pull"
    )
    parser.add_argument(
        "--max-upsample",
        type=float,
        default=2.0,
        metavar="R",
        help="print a notice when --dt is more than R times finer than a stream's rate (2)",
    )
    parser.add_argument(
        "--no-tare",
        dest="tare",
        action="store_false",
        help="keep the force's rest level (default: estimated and subtracted)",
    )
    parser.add_argument(
        "--min-peak-fraction",
        type=float,
        default=0.2,
        metavar="F",
        help="drop excursions peaking below F of the largest pull as blips (0.2)",
    )
    parser.add_argument(
        "--displacement-mode",
        dest="displacement",
        choices=("projection", "distance"),
        default="projection",
        help="projection on the pull direction (default) or distance from the rest pose",
    )
    parser.add_argument(
        "--direction",
        type=_triple,
        default=None,
        metavar="X,Y,Z",
        help="pull direction in the pose frame (default: --gravity-axis, a downward pull)",
    )
    add_grasp_point_options(parser)
    parser.add_argument("--force", action="store_true", help="replace a non-empty output folder")
    add_deprecated(
        parser,
        "--displacement",
        "--displacement-mode",
        "--displacement-column names a column in import-csv",
    )
    return parser


def run_from_args(args: argparse.Namespace) -> list[Path]:
    """Run ``import-bag`` from parsed arguments; prints the notices and the written files."""
    from ..io.atomic import check_output_dir

    # --force never replaces the folder holding the bag itself (issue 14)
    check_output_dir(args.out, args.force, "import-bag output", inputs=[args.bag])
    notices: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        paths = _import(args, notices)
    for n in notices:
        print(f"note: {n}")
    for w in caught:  # warnings that are not notices already (skipped pulls, ...)
        if str(w.message) not in notices:
            print(f"warning: {w.message}")
    for p in paths:
        print(p)
    return paths


def _import(args: argparse.Namespace, notices: list[str]) -> list[Path]:
    return import_bag(
        args.bag,
        args.out,
        force_topic=args.force_topic,
        pose_topic=args.pose_topic,
        dt=args.dt,
        gravity_axis=args.gravity_axis,
        rest_force_threshold=args.rest_force_threshold,
        min_pull_duration=args.min_pull_duration,
        force=args.force,
        tf_child_frame=args.tf_child_frame,
        force_sign=args.force_sign,
        force_axis=args.force_axis,
        lead_in=args.lead_in,
        tare=args.tare,
        min_peak_fraction=args.min_peak_fraction,
        max_upsample=args.max_upsample,
        displacement=args.displacement,
        direction=args.direction,
        grasp_branch=args.grasp_branch,
        grasp_fraction=args.grasp_fraction,
        grasp_distance=args.grasp_distance,
        notices=notices,
    )
