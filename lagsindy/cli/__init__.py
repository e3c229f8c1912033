"""The ``lagsindy`` command (also ``python -m lagsindy``).

Subcommands: ``demo``, ``simulate``, ``simulate-model``, ``fit``, ``diagnose``,
``predict`` and ``export`` (:mod:`lagsindy.export.command`); each has ``--help``.
Bad input (a missing file, an unknown column, a wrong shape, NaN, an invalid model file) ends with ONE line on stderr and exit status
2, never a traceback (``--debug`` shows it).

Fast errors, talkative steps: the package imports only the standard library and
numpy at import time, and each command checks its options, file names and the
CSV's header (:mod:`._checks`) before it imports pandas, torch, sympy or
scikit-learn, so such errors come in a fraction of a second. Each step that can take
seconds (loading the fitting code, building the library, estimating derivatives,
fitting, diagnosing) prints a line first, unless ``--quiet``.

Modules: :mod:`.parser` (options, help texts, defaults), one module per command
(:mod:`.demo`, :mod:`.simulate`, :mod:`.fit` with :mod:`.scoring`, :mod:`.diagnose`,
:mod:`.predict`), :mod:`._checks` (the cheap checks) and :mod:`._io` (CSV and model
files in and out). The subcommands look their handler up here when they run
(``_fit``, ``_demo``, ...), so patching ``lagsindy.cli._fit`` takes effect.
"""

from __future__ import annotations

import sys
import warnings

from ._checks import CLIError
from ._io import _load as _load
from ._io import _read_csv as _read_csv
from ._io import _state_and_groups as _state_and_groups
from .demo import _demo as _demo
from .diagnose import _diagnose as _diagnose
from .fit import _fit as _fit
from .fit import _fit_csv as _fit_csv
from .fit import _library as _library
from .fit import _warn_missing_coupling as _warn_missing_coupling
from .parser import SYSTEM_NAMES, build_parser
from .predict import _predict as _predict
from .simulate import _simulate as _simulate
from .simulate import _simulate_model as _simulate_model

__all__ = ["CLIError", "SYSTEM_NAMES", "build_parser", "main"]

# Warnings that are information, not a doubt about the result: --quiet drops them.
_INFO_WARNINGS = (
    "it will compute on the CPU",
    "they used the longest odd window they hold",
)


# The library's Python hints, and what a command-line user types instead (longest
# first: a hint may contain a shorter one).
_CLI_WORDING = (
    (
        "Refit with dissipation=DissipationLibrary(['viscous', 'coulomb']), or run "
        "lagsindy.diagnose,",
        "Run `lagsindy diagnose` on the same data,",
    ),
    (
        "est.joint_dissipation_ records it. To keep the conservative fit, pass "
        "dissipation=DissipationLibrary([]).",
        "To keep the conservative fit, pass --conservative.",
    ),
    ("(lagsindy.estimate_delay)", "(`lagsindy fit --delay auto`)"),
    ("see lagsindy.diagnose", "see `lagsindy diagnose`"),
    ("run lagsindy.diagnose", "run `lagsindy diagnose`"),
    ("pass a longer window=", "pass a longer --window"),
    ("Lower lam or threshold.", "Lower --lam or --threshold."),
    (
        "or formulation='strong' to silence this",
        "or --formulation strong to silence this",
    ),
    (
        "or fixed_term=None to search them all",
        "or leave out --fixed-term to search them all",
    ),
    (
        "unwrap them per trajectory first (angles=",
        "unwrap them per trajectory first (--angles with the names of columns ",
    ),
)


def _one_line(exc, limit: int = 600) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _cli_wording(text: str) -> str:
    """``text`` with the library's Python hints in command-line terms."""
    for python, cli in _CLI_WORDING:
        text = text.replace(python, cli)
    return text


def main(argv=None) -> int:
    """Run the ``lagsindy`` command; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, usage errors
        return int(exc.code or 0)
    prog = f"lagsindy {args.command}"

    quiet = getattr(args, "quiet", False)

    def show(message, category, filename, lineno, file=None, line=None):
        text = _cli_wording(_one_line(message, limit=1000))
        if quiet and any(s in text for s in _INFO_WARNINGS):
            return
        print(f"{prog}: warning: {text}", file=sys.stderr)

    try:
        with warnings.catch_warnings():
            warnings.showwarning = show
            return args.func(args)
    except (CLIError, ValueError, OSError) as exc:
        if args.debug:
            raise
        if isinstance(exc, FileNotFoundError) and exc.filename:
            message = f"file not found: {exc.filename}"
        else:
            message = _one_line(exc)
        print(f"{prog}: error: {message}", file=sys.stderr)
        return 2
    except RuntimeError as exc:  # an integration that failed
        if args.debug:
            raise
        print(f"{prog}: error: {_one_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
