"""The launcher's first second (start fast): the command line read, the page served and its address
printed, saying ``loading FILE...``, before the engine's heavy parts are imported and the data read.

``magcal-workbench`` (:mod:`magcal_workbench._launch`) calls :func:`begin` first: it imports only viser and the
handshake guard, starts the server with the token the page's address will carry, and prints that address. A
CSV is then previewed (:meth:`Early.show_preview`: a few thousand lines spread through the file,
:func:`magcal.data.io.read_csv_preview`, drawn as the raw clouds) while the rest is read; the
:class:`~magcal_workbench.app.Workbench` is then built on the same server (:func:`magcal_workbench.app.main` with
``early``), draws its scene over the preview, and the status line goes.
"""

from __future__ import annotations

import argparse
import os
import secrets
import stat
import sys

from . import timing
from .defaults import DEFAULT_MAX_UPLOAD_MB, MAX_POINTS, MAX_STORE_BYTES
from .guard import Gate, guarded_viser_server, is_loopback, page_url
from .markup import safe_code


def host_warning(host: str) -> str | None:
    """The warning printed when the workbench is served beyond this machine (None for loopback)."""
    if is_loopback(host):
        return None
    return (
        f"WARNING: serving on {host}: anyone who can reach this address can see and change the session "
        "(data, model, files). Use the default 127.0.0.1 unless you mean to share it."
    )


NO_TOKEN_WARNING = (
    "WARNING: --no-token: the page asks for no token; any program or user that can reach the port can see and "
    "change the session and start live sources"
)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="magcal-workbench", description="Calibrate magnetometers in the browser: fit, diagnose, add effects."
    )
    p.add_argument("file", nargs="?", help="data CSV (default: the bundled demo)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1, this machine only)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; 0 picks a free one)")
    p.add_argument(
        "--no-token",
        action="store_true",
        help="do not ask for the secret token in the page's address (any process or user that can reach the "
        "port can then use the workbench; a warning is printed)",
    )
    p.add_argument(
        "--allow-host",
        action="append",
        default=[],
        metavar="NAME",
        help="beyond 127.0.0.1: a further name the page may be reached by (e.g. a proxy's); this machine's own "
        "names and addresses are always accepted",
    )
    p.add_argument("--session-dir", default=None, help="where sessions are saved (default ~/.magcal/sessions)")
    p.add_argument("--no-session", action="store_true", help="do not save or reopen sessions")
    p.add_argument("--fresh", action="store_true", help="ignore a saved session of the same file")
    p.add_argument("--lesson", default=None, help="open a lesson by name (see assets/lessons)")
    p.add_argument(
        "--max-upload-mb",
        type=float,
        default=DEFAULT_MAX_UPLOAD_MB,
        metavar="MB",
        help=f"largest file the page may upload, MB (default {DEFAULT_MAX_UPLOAD_MB:g})",
    )
    p.add_argument(
        "--max-sessions-mb",
        type=float,
        default=MAX_STORE_BYTES / 1e6,
        metavar="MB",
        help="bound of the session folder, MB: the oldest sessions are deleted to stay within it "
        f"(default {MAX_STORE_BYTES / 1e6:g})",
    )
    p.add_argument(
        "--max-points",
        type=int,
        default=MAX_POINTS,
        metavar="N",
        help=f"most points drawn per sensor's cloud; larger files are shown decimated, fitted whole "
        f"(default {MAX_POINTS})",
    )
    p.add_argument(
        "--live",
        default=None,
        metavar="SOURCE",
        help="calibrate live from an instrument: serial:///dev/ttyUSB0?baud=115200&columns=x,y,z, "
        "udp://127.0.0.1:14550?mavlink, tcp://HOST:PORT, sim://chi2017?rate=50 (docs/export.md)",
    )
    p.add_argument(
        "--live-allow",
        action="append",
        default=[],
        metavar="SOURCE",
        help="a live source the page may start besides the ones it is offered (simulated presets, serial ports "
        "found, UDP/TCP on 127.0.0.1, the session folder's recordings), e.g. udp://0.0.0.0:14550?mavlink; repeat "
        "for several",
    )
    p.add_argument(
        "--record",
        default=None,
        metavar="PATH",
        help="with --live: the CSV recording (a new file; default live-DATE-TIME.csv in the session "
        "folder's recordings, or here with --no-session)",
    )
    p.add_argument(
        "--effects-file",
        action="append",
        default=[],
        metavar="PATH",
        help="a Python file defining your own effects (runs its code; repeat for several files); the page may load "
        "these files again, any other only when you confirm it in this terminal; docs/user-effects.md",
    )
    p.add_argument(
        "--timing",
        action="store_true",
        help="log the server's named spans (fit, held-out, scene, plots, ...) to standard error, one line each "
        "(benchmarks/page_latency.py reads them)",
    )
    return p


class Early:
    """The server started before the workbench exists: its token, its address, the ``loading`` status line and
    the preview's scene.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line (:func:`build_parser`).
    """

    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.host = args.host
        #: The secret in the page's address (None with ``--no-token``): the workbench takes it over.
        self.token = None if args.no_token else secrets.token_urlsafe(32)
        self.server = guarded_viser_server(args.host, args.port, False, Gate(args.host, self.token, args.allow_host))
        self._status = self.server.gui.add_markdown(f"**loading {self.data_name()}...**")
        #: The scene drawn from the preview (:class:`magcal_workbench.scene.SceneView`), None until one is drawn.
        self.scene_view = None

    def data_name(self) -> str:
        """What the status line calls the data (markdown): the file's base name or the lesson's, escaped as code
        (a file name is untrusted text), or the demo."""
        if self.args.lesson:
            return f"the lesson {safe_code(self.args.lesson)}"
        return safe_code(os.path.basename(self.args.file)) if self.args.file else "the demo"

    @property
    def url(self) -> str:
        """The page's address with its token."""
        return page_url(self.host, self.server.get_port(), self.token)

    def say(self, text: str) -> None:
        """Replace the status line (markdown; the caller escapes what it quotes)."""
        self._status.content = text

    def show_preview(self) -> None:
        """Draw a CSV's preview as the raw clouds (:mod:`magcal_workbench.preview`); nothing for a lesson, the demo or a file the preview cannot read (the whole read reports its problems)."""
        if not self.args.file or self.args.lesson:
            return
        from .preview import draw_preview  # the engine's reader and the scene: imported after the address

        with timing.span("preview"):
            view = draw_preview(self.server, self.args.file, self.args.max_points)
        if view is not None:
            self.scene_view, n = view
            self.say(f"**loading {self.data_name()}...** (a preview of {n:,} samples drawn)")

    def done(self) -> None:
        """The workbench is built: the status line goes."""
        self._status.remove()

    def stop(self) -> None:
        """Stop the server (the start failed after the address was printed)."""
        self.server.stop()


def _regular_file(path: str) -> bool:
    """Whether ``path`` is a readable regular file: a yes/no before the address is printed, without importing
    magcal (``magcal.core.files.check_regular_file``, which words the refusal, costs the engine's import, ~0.3 s);
    :func:`magcal_workbench.app.main` reports a no with that message."""
    try:
        return stat.S_ISREG(os.stat(path).st_mode) and os.access(path, os.R_OK)
    except OSError:
        return False


def begin(argv=None) -> Early | None:
    """Read the command line, start the server and print its address (with the warnings before it); exits
    as argparse does on a bad option, ``--help`` included. None when the command line has a problem that
    :func:`magcal_workbench.app.main` reports (a file that cannot be read, a bound that is not positive): the
    launcher then hands it over without an early server, and no address is printed."""
    args = build_parser().parse_args(argv)
    if (args.file and not _regular_file(args.file)) or not args.max_upload_mb > 0 or args.max_points < 1:
        return None
    if args.timing:
        timing.enable()
    warning = host_warning(args.host)
    if warning:
        print(f"magcal-workbench: {warning}", file=sys.stderr)
    if args.no_token:
        print(f"magcal-workbench: {NO_TOKEN_WARNING}", file=sys.stderr)
    early = Early(args)
    print(f"magcal-workbench: open {early.url} in a browser (Ctrl-C stops)", flush=True)
    return early
