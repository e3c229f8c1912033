"""Checks of the command line's input that run before any heavy import.

Only the standard library is imported here: a bad option, a missing file, a missing
column or an unknown system ends the command within a fraction of a second, before
numpy's numerics, pandas, torch, sympy and scikit-learn load (``tests/cli/
test_errors.py`` runs each such error in a fresh interpreter and checks
``sys.modules``). The checks that need the data's values (NaN, text in a numeric
column, rows cut short) come next, with pandas only; the checks that need the
library's parser (``--terms``, ``--fixed-term``) run when the library is built.

Each function raises :class:`CLIError` with the message the user sees.
"""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

from .._names import (
    ACCELERATION_SUFFIX,
    VELOCITY_SUFFIX,
    name_problem,
    repeated_name,
)
from .parser import SYSTEM_NAMES


class CLIError(Exception):
    """A user error: printed as one line, exit status 2."""


_LIBRARY_RE = re.compile(r"(poly|polynomial|sep|separated)(\d+)\Z")
MAX_LIBRARY_DEGREE = 6


def split(text):
    """The comma-separated items of ``text``, stripped (empty items dropped)."""
    return [s.strip() for s in text.split(",") if s.strip()] if text else []


def state_names(coords, *, accelerations=True):
    """Column names of the X layout ``[q..., q_dot..., q_ddot...]``."""
    out = list(coords) + [c + VELOCITY_SUFFIX for c in coords]
    if accelerations:
        out += [c + ACCELERATION_SUFFIX for c in coords]
    return out


def missing_column(source, name, columns):
    """The error for a column ``name`` that ``source`` lacks."""
    columns = list(columns)
    return CLIError(
        f"{source} has no column {name!r} (its columns: "
        f"{', '.join(map(str, columns[:20]))}{' ...' if len(columns) > 20 else ''})"
    )


# ----------------------------------------------------------------------------- files
def check_out(out):
    """Fail early (before a long fit) when the output cannot be written."""
    out = Path(out)
    if out.is_dir():
        raise CLIError(f"--out {out} is a folder; give a file name")
    if not out.parent.is_dir():
        raise CLIError(f"cannot write {out}: the folder {out.parent} does not exist")
    return out


def check_csv_file(path):
    """The CSV file exists, is a file and is not empty."""
    p = Path(path)
    if not p.exists():
        raise CLIError(f"file not found: {path}")
    if p.is_dir():
        raise CLIError(f"{path} is a folder, not a CSV file")
    if p.stat().st_size == 0:
        raise CLIError(f"{path} is empty")
    return p


def csv_header(path):
    """The column names of a CSV file, read from its first lines only.

    Returns None when the header cannot be read cheaply as pandas would read it (a
    file that is not UTF-8, repeated column names): pandas then reads the file and
    reports. Raises :class:`CLIError` for a missing, empty or header-only file.
    """
    p = check_csv_file(path)
    try:
        with open(p, encoding="utf-8-sig", newline="") as f:
            first = f.readline()
            rows = any(line.strip() for line in f)  # stops at the first row
    except (UnicodeDecodeError, OSError):
        return None
    if not first.strip():
        return None  # blank first lines: pandas skips them
    sep = ";" if ("," not in first and ";" in first) else ","
    try:
        names = next(csv.reader([first], delimiter=sep))
    except csv.Error:
        return None
    names = [n.strip() for n in names]
    if len(set(names)) != len(names):
        return None  # pandas renames repeats (x, x.1)
    if not rows:
        raise CLIError(f"{path} has a header but no rows")
    return names


def peek_model(path):
    """``(coordinates, case)`` of a saved model (JSON), read without the loader.

    Raises :class:`CLIError` when the file is missing or not JSON; either item is
    None when it cannot be read (the loader then says what is wrong).
    """
    p = Path(path)
    if not p.is_file():
        raise CLIError(f"model file not found: {path}")
    try:
        doc = json.loads(p.read_bytes().decode("utf-8"))
    except UnicodeDecodeError:
        raise CLIError(f"{path} is not a text (UTF-8) model file") from None
    except json.JSONDecodeError as exc:
        raise CLIError(f"{path} is not valid JSON: {exc}") from None
    except (ValueError, RecursionError, OSError):
        return None, None
    if not isinstance(doc, dict):
        return None, None
    coords, case = doc.get("coordinates"), doc.get("case")
    if not (
        isinstance(coords, list) and coords and all(isinstance(c, str) for c in coords)
    ):
        coords = None
    return coords, case if isinstance(case, str) else None


def check_model_data(case, inputs):
    """A model fitted with (without) forces is used on data with (without) them."""
    if case is None or (inputs is None) == (case != "forces"):
        return
    raise CLIError(
        "the model was fitted "
        + ("with" if case == "forces" else "without")
        + " input forces; diagnose it on data of the same kind (--input or "
        "tau_<q> columns for forced data, --passive for passive data)"
    )


# ----------------------------------------------------------------------------- options
def number(
    value, name, *, low=None, high=None, low_open=False, high_open=False, what=""
):
    """``value`` is finite and within the bounds; else the error names ``--name``."""
    ok = isinstance(value, (int, float)) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value < high if high_open else value <= high
    if not ok:
        raise CLIError(f"--{name} must be {what}, got {value}")
    return value


def coordinates(text):
    """The ``--coordinates`` list, with the naming rules of the library."""
    coords = split(text)
    if not coords:
        raise CLIError("--coordinates needs at least one column name, e.g. x,theta")
    for problem in (*map(name_problem, coords), repeated_name(coords)):
        if problem is not None:
            raise CLIError(problem)
    return coords


def angles(text, coords):
    """The ``--angles`` list (``all``: every coordinate); each a coordinate."""
    out = list(coords) if text == "all" else split(text)
    unknown = [a for a in out if a not in coords]
    if unknown:
        raise CLIError(f"--angles {unknown} are not among --coordinates {coords}")
    return out


def library_spec(text):
    """``(kind, degree)`` of ``--library``: ``("poly", 3)``, ``("separated", 2)``,
    ``("terms", None)``."""
    spec = text.strip().lower()
    if spec in ("terms", "chain"):
        return spec, None
    m = _LIBRARY_RE.match(spec)
    if not m:
        raise CLIError(
            f"--library {text!r} is not known: use polyN (all monomials of "
            "degree 1..N over q, q_dot, sin/cos of angles), separatedN (the paper's "
            "trigonometric x non-trigonometric construction), chain (a chain of "
            "links: CandidateLibrary.chain) or terms (only --terms)"
        )
    degree = int(m.group(2))
    if not 1 <= degree <= MAX_LIBRARY_DEGREE:
        raise CLIError(
            f"--library degree must be between 1 and {MAX_LIBRARY_DEGREE}, got {degree}"
        )
    return ("poly" if m.group(1).startswith("poly") else "separated"), degree


def fit_numbers(args):
    """Range checks of the numeric options of a fit (``fit`` and ``diagnose``)."""
    number(args.lam, "lam", low=0, what="a number >= 0 (the L1 weight)")
    number(
        args.threshold,
        "threshold",
        low=0,
        high=1,
        high_open=True,
        what="in [0, 1) (relative to the largest coefficient)",
    )
    if getattr(args, "dt", None) is not None:
        number(args.dt, "dt", low=0, low_open=True, what="a positive number of seconds")
    clock_options(args)
    window = getattr(args, "window", "auto")
    if window != "auto" and window < 5:
        raise CLIError(
            f"--window must be at least 5 samples (a test function), got {window}"
        )
    held_out = getattr(args, "held_out", None)
    if held_out is not None:
        number(
            held_out,
            "held-out",
            low=0,
            high=1,
            high_open=True,
            what="in [0, 1) (the share of the data held out)",
        )
    horizon = getattr(args, "refine", None)
    if horizon is not None and horizon < 2:
        raise CLIError(f"--refine needs a horizon of >= 2 samples, got {horizon}")
    delay = getattr(args, "delay", None)
    if delay is not None and delay != "auto":
        try:
            value = float(delay)
        except ValueError:
            raise CLIError(
                f"--delay must be a number of seconds or 'auto', got {delay!r}"
            ) from None
        number(value, "delay", what="a finite number of seconds or 'auto'")
    if args.precision < 1:
        raise CLIError(f"--precision must be at least 1 digit, got {args.precision}")


def diagnose_numbers(args):
    """Range checks of ``diagnose``'s own options."""
    number(
        args.min_explained,
        "min-explained",
        low=0,
        high=1,
        low_open=True,
        high_open=True,
        what="in (0, 1) (a share of the held-out residual)",
    )
    if args.max_effects < 0:
        raise CLIError(f"--max-effects must be >= 0, got {args.max_effects}")
    if args.splits < 2:
        raise CLIError(f"--splits must be at least 2 folds, got {args.splits}")
    if args.bootstrap is not None and args.bootstrap < 2:
        raise CLIError(
            f"--bootstrap must be a number of resamples >= 2, got {args.bootstrap}"
        )


def system_name(name):
    """The built-in system ``name`` refers to, as ``lagsindy.systems.get_system``
    resolves it (``cart``, ``cart-pendulum`` and ``cart_pendulum`` alike)."""
    key = name.strip().lower().replace("-", "_").replace(" ", "_")
    matches = [k for k in SYSTEM_NAMES if k == key or k.split("_")[0] == key]
    if len(matches) != 1:
        raise CLIError(f"unknown system {name!r}; available: {sorted(SYSTEM_NAMES)}")
    return matches[0]


# ----------------------------------------------------------------------------- columns
# ``--input`` entries that mark an undriven coordinate (its generalized force is 0).
UNDRIVEN = ("-", "0")


def input_columns(columns, coords, args):
    """Names of the generalized-force columns, or None for passive data.

    ``columns``: the CSV's column names. One entry per coordinate; ``"-"`` marks an
    undriven coordinate (a column of zeros: ``--input force,-`` or ``--undriven
    theta``).
    """
    undriven = split(getattr(args, "undriven", None) or "")
    for name in undriven:
        if name not in coords:
            raise CLIError(
                f"--undriven names {name!r}, which is not a coordinate {coords}"
            )
    if getattr(args, "passive", False):
        if undriven:
            raise CLIError(
                "--undriven marks coordinates with zero force in forced data; "
                "--passive says no coordinate is driven: drop one of them"
            )
        return None
    if args.input:
        cols = ["-" if c in UNDRIVEN else c for c in split(args.input)]
        driven = [c for c in coords if c not in undriven]
        if undriven and len(cols) == len(driven) and len(cols) < len(coords):
            given = iter(cols)  # the driven coordinates' columns, in order
            cols = ["-" if c in undriven else next(given) for c in coords]
        if len(cols) != len(coords):
            raise CLIError(
                f"--input names {len(cols)} column(s) but there are {len(coords)} "
                f"coordinate(s) {coords}: give one generalized-force column per "
                "coordinate, '-' for an undriven one (e.g. --input force,-), or "
                "name the undriven ones with --undriven"
            )
        for c, col in zip(coords, cols):
            if c in undriven and col != "-":
                raise CLIError(
                    f"--undriven {c} but --input gives it the column {col!r}: write "
                    f"'-' for {c} in --input, or drop it from --undriven"
                )
    else:
        named = [f"tau_{c}" for c in coords]
        cols = ["-" if c in undriven else n for c, n in zip(coords, named)]
        if not all(c == "-" or c in columns for c in cols):
            if undriven:
                lacking = [c for c in cols if c != "-" and c not in columns]
                raise CLIError(
                    f"--undriven {','.join(undriven)}: the driven coordinates' force "
                    f"column(s) {lacking} are not in the data; name them with --input"
                )
            return None
    if all(c == "-" for c in cols):
        raise CLIError(
            "every coordinate is marked undriven: that is passive data; use "
            "--passive (or drop --input/--undriven)"
        )
    return cols


def clock_options(args):
    """``--gap-factor`` above 1 and a ``--time`` column name."""
    factor = getattr(args, "gap_factor", None)
    if factor is not None:
        number(factor, "gap-factor", low=1, low_open=True, what="a number > 1 (steps)")
    if not str(getattr(args, "time", "t")).strip():
        raise CLIError("--time needs a column name, e.g. --time timestamp")


def time_column(args):
    """The name of the time column (``--time``, default ``t``)."""
    return str(getattr(args, "time", "t")).strip() or "t"


def derivatives_estimated(columns, coords, args):
    """Whether q_dot and q_ddot are estimated from q (not read from the CSV)."""
    if getattr(args, "derivatives", None) is not None:
        return True
    return not all(n in columns for n in state_names(coords))


def data_columns(columns, coords, args, source):
    """Check that the CSV holds what the command reads; returns the input columns.

    The positions, the input columns (``--input`` or ``tau_<q>``), and, when the
    derivatives are estimated, a time column ``t`` or ``--dt``. ``columns`` None
    (a header that could not be read cheaply): only the options are checked.
    """
    if columns is None:
        return None
    inputs = input_columns(columns, coords, args)
    for name in [*coords, *(c for c in inputs or [] if c != "-")]:
        if name not in columns:
            raise missing_column(source, name, columns)
    time = time_column(args)
    if time != "t" and time not in columns:
        raise missing_column(source, time, columns)
    if (
        derivatives_estimated(columns, coords, args)
        and time not in columns
        and not getattr(args, "dt", None)
    ):
        raise CLIError(
            f"{source} has positions only and no {time!r} column: add a time column "
            f"{time!r}, name it with --time COLUMN, or pass --dt SECONDS (the "
            "sampling interval)"
        )
    return inputs
