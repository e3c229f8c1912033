"""The top folder of a lagsindy checkout: the project, not the package.

Python reads this file only when it runs in the folder that *contains* the checkout
(the clone's parent): ``import lagsindy`` then finds this folder before the installed
package. Without this file Python would take the folder for an empty namespace
package, and ``from lagsindy import CandidateLibrary`` would fail with "cannot import
name 'CandidateLibrary' from 'lagsindy' (unknown location)". So this file loads the
installed lagsindy in its place (an editable install of this checkout included), or,
when lagsindy is not installed, stops with an ImportError that says what to do.
The package itself is the folder ``lagsindy/`` next to this file.
"""

import importlib.machinery
import importlib.util
import os
import sys


def _installed_spec(name, here):
    """The spec of package ``name`` found by Python's finders, looking past the
    folder that holds this checkout; None when there is none."""
    parent = os.path.dirname(here)
    path = [p for p in sys.path if os.path.abspath(p or os.curdir) != parent]
    for finder in sys.meta_path:
        if finder is importlib.machinery.PathFinder:
            spec = finder.find_spec(name, path)
        elif hasattr(finder, "find_spec"):
            try:
                spec = finder.find_spec(name, None)
            except Exception:  # a third-party finder that cannot answer
                continue
        else:
            continue
        origin = getattr(spec, "origin", None)
        if (
            spec is not None
            and origin not in (None, "namespace")
            and os.path.abspath(origin) != os.path.abspath(__file__)
        ):
            return spec
    return None


def _replace_by_the_package():
    here = os.path.dirname(os.path.abspath(__file__))
    if not os.path.isfile(os.path.join(here, "lagsindy", "__init__.py")):
        return  # not a lagsindy checkout after all: stay an empty package
    spec = _installed_spec(__name__, here)
    if spec is None:
        raise ImportError(
            f"'import {__name__}' found the folder {here}, the top folder of a "
            "lagsindy checkout (the project, not the package), because Python runs "
            f"in {os.path.dirname(here)}; and lagsindy is not installed. Install it "
            f'(pip install -e "{here}"), or run Python from inside the checkout '
            f"({here}), where the package folder lagsindy/ is found."
        )
    module = importlib.util.module_from_spec(spec)
    sys.modules[__name__] = module  # the import statement returns this module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[__name__]
        raise


if __name__ == "lagsindy":
    _replace_by_the_package()
