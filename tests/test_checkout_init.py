"""The checkout's top-level ``__init__.py``: Python run from the clone's parent (#44).

``import lagsindy`` there finds the clone's top folder first. Without the file it was
an empty namespace package ("cannot import name 'CandidateLibrary' from 'lagsindy'
(unknown location)"); with it, the installed package loads in its place, or an
ImportError says what happened and what to do.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(
    not hasattr(os, "symlink") or sys.platform == "win32",
    reason="needs symbolic links",
)


@pytest.fixture
def parent(tmp_path):
    """A folder holding the checkout as ``lagsindy`` (a link to this checkout)."""
    (tmp_path / "lagsindy").symlink_to(ROOT, target_is_directory=True)
    return tmp_path


def _python(parent, code, *flags, pythonpath=None):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if pythonpath is not None:
        env["PYTHONPATH"] = pythonpath
    return subprocess.run(
        [sys.executable, *flags, "-c", code],
        cwd=parent,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_the_package_loads_in_place_of_the_checkout_folder(parent):
    code = (
        "import lagsindy\n"
        "from lagsindy import CandidateLibrary, __version__\n"
        "from lagsindy.cli import main\n"
        "print(lagsindy.__file__)\n"
    )
    # with this checkout on the path (as an editable install of it would give)
    proc = _python(parent, code, pythonpath=str(ROOT))
    assert proc.returncode == 0, proc.stderr
    loaded = Path(proc.stdout.strip())
    assert loaded == ROOT / "lagsindy" / "__init__.py"


def test_not_installed_says_what_to_do(parent):
    # -S: no site-packages, so no installed lagsindy; '' (the parent) is on the path
    proc = _python(parent, "import lagsindy", "-S")
    assert proc.returncode != 0
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("ImportError: 'import lagsindy' found the folder "), last
    assert "top folder of a lagsindy checkout" in last
    assert "lagsindy is not installed" in last and "pip install -e" in last
    assert "unknown location" not in proc.stderr


def test_the_checkout_folder_is_not_a_package_from_inside():
    """From the checkout itself, ``lagsindy`` is the package folder as always."""
    proc = subprocess.run(
        [sys.executable, "-c", "import lagsindy; print(lagsindy.__file__)"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert Path(proc.stdout.strip()) == ROOT / "lagsindy" / "__init__.py"
