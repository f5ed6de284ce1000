"""Start-up of the web app and the command line does not import the heavy libraries.

``bradyscope serve``, the worker, every CLI command and every test that starts one of
them as a subprocess pays for the imports of ``app.main`` and ``app.cli``. SciPy's
signal, interpolate, optimize and stats packages (about 1.5 s together on a slow
machine) and PyAV are imported inside the functions that use them, in core/ and
app/; matplotlib and WeasyPrint are imported where a plot or a PDF is made. A
module-level import of any of them on the start-up path fails here, naming it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Imported only where they are used, never by importing app.main or app.cli.
LAZY_MODULES = (
    "av",
    "matplotlib",
    "scipy.interpolate",
    "scipy.optimize",
    "scipy.signal",
    "scipy.stats",
    "weasyprint",
)


def test_app_and_cli_start_without_the_heavy_libraries() -> None:
    # A fresh interpreter: this test process has long imported all of them.
    code = (
        "import json, sys\n"
        "import app.main, app.cli\n"
        f"print(json.dumps(sorted(m for m in {LAZY_MODULES!r} if m in sys.modules)))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    imported = json.loads(done.stdout.strip().splitlines()[-1])
    assert imported == [], (
        f"importing app.main and app.cli imports {imported}: import them inside the"
        " functions that use them (python -X importtime shows which module pulls them in)"
    )
