"""One spelling per quantity and one meaning per option name across the commands (issue 29):
the argparse types of the quantities several commands take (``--noise-force 0.05N|2%|auto``,
``--noise-displacement 2mm|0.002|auto``, ``--formats png,pdf``), the old option spellings kept
for one release (:func:`add_deprecated`), and ``--force`` in ``predict``, which still recognises
the old ``--force FILE``.

Why hand-written parsers rather than a units library (pint): the units are a handful (N, mN, kN;
m, cm, mm, um), and pint would make ``treeinfer --help`` import a large package; the parsing is
a regular expression and a table, tested in tests/test_cli_options.py.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from pathlib import Path

# = treeinfer.evaluation.plots.FIGURE_FORMATS (tests/test_cli_options.py checks): repeated here so
# that `treeinfer --help` does not import matplotlib
FIGURE_FORMATS = ("png", "pdf", "svg")

FORCE_UNITS = {"N": 1.0, "mN": 1e-3, "kN": 1e3}
LENGTH_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6}

AUTO = "auto"
_SPLIT = re.compile(r"^(.*?)([A-Za-zµ%]*)$")  # "2.5mm" -> ("2.5", "mm"); "1e-3" -> ("1e-3", "")

DISPLACEMENT_NOISE_HELP = "m (0.002 or 2mm; cm, um)"


def _number_and_unit(text: str, what: str) -> tuple[float, str]:
    """``"2mm"`` -> (2.0, "mm"), ``"0.05"`` -> (0.05, ""); ArgumentTypeError for a non-number,
    a negative or non-finite value."""
    s = text.strip()
    try:
        v, unit = float(s), ""
    except ValueError:
        num, unit = _SPLIT.match(s).groups()
        try:
            v = float(num)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0 ({what}), got {text!r}")
    return v, unit


def force_noise(text: str) -> float | str:
    """argparse type of ``--noise-force`` in every command: newtons (``0.05``, ``0.05N``,
    ``50mN``) -> float N; ``2%`` (a share of the largest recorded force) -> ``"2%"``; ``auto``
    -> ``"auto"``. Which forms a command can use is its own check (:func:`refuse_noise_form`)."""
    what = "newtons (e.g. 0.05 or 0.05N; also mN, kN), a share like 2% or 'auto'"
    if text.strip().lower() == AUTO:
        return AUTO
    v, unit = _number_and_unit(text, what)
    if unit == "%":
        if v >= 100:
            raise argparse.ArgumentTypeError(f"a share must be below 100%, got {text!r}")
        return f"{v:g}%"
    scale = FORCE_UNITS.get(unit, FORCE_UNITS["N"] if unit == "" else None)
    if scale is None:
        raise argparse.ArgumentTypeError(
            f"unknown force unit {unit!r} in {text!r}: expected {what}"
            + (" (a displacement unit? this is the force's noise)" if unit in LENGTH_UNITS else "")
        )
    return v * scale


def _length(text: str, allow_auto: bool) -> float | str:
    what = "metres (e.g. 0.002 or 2mm; also m, cm, um)" + (" or 'auto'" if allow_auto else "")
    if allow_auto and text.strip().lower() == AUTO:
        return AUTO
    v, unit = _number_and_unit(text, what)
    if unit == "%":
        raise argparse.ArgumentTypeError(
            f"a share is not a length: give metres, e.g. 0.002 or 2mm, got {text!r}"
        )
    scale = LENGTH_UNITS.get(unit, 1.0 if unit == "" else None)
    if scale is None:
        raise argparse.ArgumentTypeError(
            f"unknown length unit {unit!r} in {text!r}: expected {what}"
            + (" (a force unit? this is the displacement's noise)" if unit in FORCE_UNITS else "")
        )
    return v * scale


def displacement_noise(text: str) -> float | str:
    """argparse type of ``--noise-displacement`` in every command: metres (``0.002``, ``2mm``,
    ``0.2cm``) -> float m, or ``auto`` (commands whose default is decided from the data)."""
    return _length(text, allow_auto=True)


def length(text: str) -> float:
    """argparse type: a length in metres, with an optional unit (``0.12``, ``120mm``)."""
    return float(_length(text, allow_auto=False))


def figure_formats(text: str) -> tuple[str, ...]:
    """argparse type of ``--formats``: ``png,pdf,svg`` -> ("png", "pdf", "svg")."""
    fmts = tuple(dict.fromkeys(f.strip().lower().lstrip(".") for f in text.split(",") if f.strip()))
    bad = [f for f in fmts if f not in FIGURE_FORMATS]
    if bad or not fmts:
        raise argparse.ArgumentTypeError(
            f"expected some of {','.join(FIGURE_FORMATS)} separated by commas, got {text!r}"
        )
    return fmts


def add_formats_option(p: argparse.ArgumentParser, what: str = "figures") -> None:
    """``--formats``: one definition for every command that writes figures."""
    p.add_argument(
        "--formats",
        type=figure_formats,
        default=None,
        metavar="FMT[,FMT]",
        help=f"file formats of the {what}: png, pdf, svg, comma-separated (default png)",
    )


def figure_names(stem: str, formats) -> str:
    """``bands.png`` or ``bands.{png,pdf}``: the figure files a command wrote, for its report."""
    fmts = list(formats or ("png",))
    return f"{stem}.{fmts[0]}" if len(fmts) == 1 else f"{stem}.{{{','.join(fmts)}}}"


def noise_form(value) -> str:
    """The form of a parsed noise value: ``"auto"``, ``"%"`` or ``"number"``."""
    if value == AUTO:
        return AUTO
    if isinstance(value, str) and value.endswith("%"):
        return "%"
    return "number"


def refuse_noise_form(value, flag: str, command: str, allowed: tuple[str, ...], why: str):
    """ConfigError when a command cannot use this form of a noise value (``auto`` in
    ``simulate``, newtons in ``calibrate``): the spelling is the same in every command, the
    forms a command can use are its own; ``why`` says what to give instead."""
    from ..errors import ConfigError

    form = noise_form(value)
    if value is not None and form not in allowed:
        raise ConfigError(f"{flag} {value}: `treeinfer {command}` {why}")
    return value


# ---- old spellings ----------------------------------------------------------------------------
def deprecation(prog: str, old: str, new: str, note: str = "") -> None:
    """The one message of a deprecated spelling (stderr; the command goes on)."""
    print(
        f"DeprecationWarning: `{prog} {old}` is deprecated and will be removed in the next "
        f"release; write {new}" + (f" ({note})" if note else ""),
        file=sys.stderr,
        flush=True,
    )


class DeprecatedOption(argparse.Action):
    """An old spelling of an option: parses exactly as the new one (same dest, type, choices)
    and prints :func:`deprecation`. Hidden from --help; listed in docs/cli.md."""

    def __init__(self, option_strings, dest, new: str = "", note: str = "", **kwargs):
        self.new, self.note = new, note
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        deprecation(parser.prog, option_string, self.new, self.note)
        setattr(namespace, self.dest, self.const if self.nargs == 0 else values)


def add_deprecated(p: argparse.ArgumentParser, old: str, new: str, note: str = "") -> None:
    """Accept ``old`` as a deprecated spelling of ``new`` (already added to ``p``); ``note``
    says what changed when the old name means something else now."""
    a = p._option_string_actions[new]  # argparse's table of option strings (stable since 3.2)
    flag = a.nargs == 0 or getattr(a, "shown_as_flag", False)
    kw = (
        dict(nargs=0, const=True if a.nargs else a.const)
        if flag
        else dict(type=a.type, choices=a.choices)
    )
    p.add_argument(
        old,
        dest=a.dest,
        action=DeprecatedOption,
        new=new,
        note=note,
        default=argparse.SUPPRESS,  # the new option's default stands
        metavar=a.metavar,
        help=argparse.SUPPRESS,
        **kw,
    )


def deprecated_options(p: argparse.ArgumentParser) -> dict[str, tuple[str, str]]:
    """The deprecated spellings of a parser: old -> (new, note)."""
    return {
        s: (a.new, a.note)
        for a in p._actions
        if isinstance(a, DeprecatedOption)
        for s in a.option_strings
    }


class OverwriteOrOldValue(argparse.Action):
    """``--force`` (overwrite) in a command where ``--force VALUE`` meant something else before
    (``predict --force FILE``: the force file). A value after it is never taken silently as
    "overwrite": a number is refused with what changed; anything else is the old spelling of
    ``old_dest``'s option (``--force-csv``), accepted with a deprecation message.

    Why ``nargs='?'``: with a plain flag, ``--force pull.csv`` would end in argparse's
    "unrecognized arguments" without saying what changed."""

    shown_as_flag = True  # --help shows `--force`, not `--force [VALUE]` (treeinfer.cli.common)

    def __init__(self, option_strings, dest, old_dest: str = "", old_flag: str = "", **kwargs):
        self.old_dest, self.old_flag = old_dest, old_flag
        super().__init__(option_strings, dest, nargs="?", const=True, default=False, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        if values is None or values is self.const:  # `--force` alone: argparse gives const
            setattr(namespace, self.dest, True)
            return
        number = None
        if not values.lower().endswith(".csv"):
            try:
                number = _number_and_unit(values, "N")[0]
            except argparse.ArgumentTypeError:
                pass  # not a number: the old spelling of the file option
        if number is not None:
            parser.error(
                f"{option_string} {values}: --force means overwrite (in every command) and takes "
                f"no value; before it was the force file (now {self.old_flag} FILE). To predict "
                "under a force of that size, give a profile, e.g. --profile "
                f"'hold:peak={number:g},ramp=0.5,hold=1,release=0.5' --duration 3"
            )
        deprecation(
            parser.prog,
            f"{option_string} {values}",
            f"{self.old_flag} {values}",
            "--force alone means overwrite, as in every command",
        )
        if getattr(namespace, self.old_dest, None) is not None:
            parser.error(f"give the force file once: {self.old_flag} FILE")
        setattr(namespace, self.old_dest, Path(values))
