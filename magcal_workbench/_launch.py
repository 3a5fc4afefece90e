"""The ``magcal-workbench`` console script: check the workbench extra is installed, then start the app.

The engine installs without the browser app's packages (``pip install -e .``); the workbench needs the
``workbench`` extra. Without it the user gets one line saying what to install instead of an ImportError traceback.
"""

from __future__ import annotations

import importlib
import sys

#: Packages of the ``workbench`` extra (pyproject.toml), by the name they are imported under.
WORKBENCH_PACKAGES = ("viser", "trimesh", "plotly", "matplotlib", "websockets")

MISSING_EXTRA = 'magcal-workbench needs the workbench extra: pip install -e ".[workbench]"'


def missing_packages() -> list[str]:
    """The packages of the workbench extra that cannot be imported."""
    missing = []
    for name in WORKBENCH_PACKAGES:
        try:
            importlib.import_module(name)
        except ImportError:
            missing.append(name)
    return missing


def main(argv=None) -> int:
    """Start the workbench (:func:`magcal_workbench.app.main`), or say in one line that its extra is missing (exit 1)."""
    missing = missing_packages()
    if missing:
        print(f"{MISSING_EXTRA} (not installed: {', '.join(missing)})", file=sys.stderr)
        return 1
    from .app import main as app_main

    return app_main(argv)


if __name__ == "__main__":
    sys.exit(main())
