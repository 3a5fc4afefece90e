"""The ``magcal-workbench`` console script: check the workbench extra is installed, then start the app.

The engine installs without the browser app's packages (``pip install -e .``); the workbench needs the
``workbench`` extra. Without it the user gets one line saying what to install instead of an ImportError traceback.

Start fast: the page is served and its address printed (:func:`magcal_workbench.startup.begin`) before
the app's heavy parts are imported; a CSV's preview is drawn while the rest is imported and read
(:mod:`magcal_workbench.preview`); :func:`magcal_workbench.app.main` then builds the workbench on that server.
"""

from __future__ import annotations

import importlib.util
import sys

#: Packages of the ``workbench`` extra (pyproject.toml), by the name they are imported under.
WORKBENCH_PACKAGES = ("viser", "trimesh", "plotly", "matplotlib", "websockets")

MISSING_EXTRA = 'magcal-workbench needs the workbench extra: pip install -e ".[workbench]"'


def missing_packages() -> list[str]:
    """The packages of the workbench extra that cannot be imported (found without importing them: plotly and
    matplotlib alone take a second, and the page's address is printed before they are needed)."""
    missing = []
    for name in WORKBENCH_PACKAGES:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):  # a package made unimportable (sys.modules[name] = None)
            found = False
        if not found:
            missing.append(name)
    return missing


def main(argv=None) -> int:
    """Start the workbench (:func:`magcal_workbench.app.main`), or say in one line that its extra is missing (exit 1)."""
    missing = missing_packages()
    if missing:
        print(f"{MISSING_EXTRA} (not installed: {', '.join(missing)})", file=sys.stderr)
        return 1
    from . import startup

    # the page served and its address printed first, then the file's preview drawn
    early = startup.begin(argv)
    if early is not None:
        early.show_preview()
    with startup.timing.span("import"):
        from .app import main as app_main

    return app_main(argv) if early is None else app_main(argv, early=early)


if __name__ == "__main__":
    sys.exit(main())
