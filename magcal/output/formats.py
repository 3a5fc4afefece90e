"""The export formats: one :class:`ExportFormat` per format, registered by name in
:data:`magcal.output.formats.EXPORT_FORMATS`.

A format says what it is -- its name (``magcal export --format NAME``), a title and a description of what it
writes, the file's name in a bundle and the page's download, the label of the workbench's button, when it refuses
a calibration -- and writes an :class:`Export` from a calibration (:meth:`ExportFormat.write`). The command line's
``--format`` choices, the bundle (:func:`magcal.output.bundle.export_all`) and the workbench's Export section list
the formats from here.

The built-in formats (ArduPilot, PX4, the C header) are registered by :mod:`magcal.output.export`, which this
package imports first. An installed package adds its own in the entry-point group ``magcal.export_formats``
(``[project.entry-points."magcal.export_formats"] toy = "my_pkg.formats:TOY"``, an :class:`ExportFormat` or a
module registering some with ``EXPORT_FORMATS.register``): :func:`load_entry_points` loads them, once, where the
formats are listed (``magcal export``, the workbench). CONTRIBUTING.md has the recipe.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from magcal.core.errors import MagcalError
from magcal.core.registry import Loaded, Registry

#: The entry-point group installed packages declare their export formats in.
ENTRY_POINT_GROUP = "magcal.export_formats"

#: ``magcal export --format`` values that are not formats of this registry (:data:`magcal.cli.export.DATA_FORMATS`).
RESERVED_NAMES = ("mask", "all")
#: The other files of a bundle (:mod:`magcal.output.bundle`, the workbench's ``session.json``): no format's file.
RESERVED_FILE_NAMES = (
    "calibration.json",
    "corrected.csv",
    "corrected.parquet",
    "raw_mask.csv",
    "README.txt",
    "session.json",
)


@dataclass
class Export:
    """An export: the text to write, the parameters by name, and what could not be carried.

    Attributes
    ----------
    format : str
        The format's name.
    text : str
        The file's content.
    parameters : dict
        The values written, by the format's parameter names.
    sensors : list
        Per exported sensor, what the format made of it (:class:`magcal.output.export.SensorExport` for the
        firmware formats).
    dropped : list of str
        What the calibration holds that the format could not carry (exported with ``force`` only).
    notes : list of str
        What the user should know to load the file.
    current_column : str or None
        The column a motor compensation is per (``current_A`` or ``throttle``), when one is written.
    """

    format: str
    text: str
    parameters: dict
    sensors: list
    dropped: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    current_column: str | None = None


@dataclass(frozen=True, eq=False)
class ExportFormat:
    """One export format.

    Attributes
    ----------
    name : str
        ``magcal export --format NAME``: lower-case letters, digits, ``_`` or ``-``.
    title : str
        A few words: what the file is (the bundle's README lists it so).
    description : str
        What it writes, one sentence (``magcal export --help``).
    file_name : str
        The file's name in ``magcal export --format all``'s zip and the workbench's download (no folder).
    button : str
        The workbench's button label.
    refuses : str
        When it refuses a calibration (what the target cannot hold), one sentence.
    writer : callable
        ``writer(calibration, sensors=None, slots=None, force=False, source=..., **options) -> Export``: the
        file's text and what it holds; raises :class:`~magcal.core.errors.MagcalError` for what the target cannot
        hold (unless ``force``) naming what would be lost. ``options`` are ``magcal export``'s firmware options
        (``throttle_full_scale``, ``custom_rotation``): a format that has no use for one ignores it.
    """

    name: str
    title: str
    description: str
    file_name: str
    button: str
    refuses: str
    writer: Callable | None = None

    def write(self, calibration, sensors=None, slots=None, force=False, source="calibration", **options) -> Export:
        """The export of ``calibration`` in this format (see :attr:`writer`)."""
        if self.writer is None:
            raise MagcalError(f"export format {self.name!r} has no writer")
        result = self.writer(calibration, sensors=sensors, slots=slots, force=force, source=source, **options)
        if not isinstance(result, Export) or not isinstance(result.text, str):
            raise MagcalError(
                f"export format {self.name!r}: its writer returned {type(result).__name__}, not an Export"
            )
        return result


def _check(fmt: ExportFormat, registry) -> None:
    """A format's name is free, its texts are given and its file name is a plain name no other file of a bundle
    has."""
    if fmt.name in RESERVED_NAMES:
        raise MagcalError(f"export format {fmt.name!r}: the name is magcal export's own --format {fmt.name}")
    for attribute in ("title", "description", "file_name", "button", "refuses"):
        if not isinstance(getattr(fmt, attribute), str) or not getattr(fmt, attribute).strip():
            raise MagcalError(f"export format {fmt.name!r}: give its {attribute} (a non-empty text)")
    if any(c in fmt.file_name for c in "/\\\0") or fmt.file_name in (".", ".."):
        raise MagcalError(f"export format {fmt.name!r}: file_name {fmt.file_name!r} must be a plain file name")
    if not callable(fmt.writer) and type(fmt).write is ExportFormat.write:
        raise MagcalError(f"export format {fmt.name!r}: give its writer (a function returning an Export)")
    taken = {f.file_name: f.name for f in registry.values() if f.name != fmt.name}
    taken.update({name: "the bundle" for name in RESERVED_FILE_NAMES})
    if fmt.file_name in taken:
        raise MagcalError(f"export format {fmt.name!r}: file_name {fmt.file_name!r} is {taken[fmt.file_name]!r}'s")


#: Every export format by name, in the order they were registered (the built-ins first).
EXPORT_FORMATS: Registry[ExportFormat] = Registry("export format", ENTRY_POINT_GROUP, ExportFormat, _check)


def register_format(fmt: ExportFormat, replace: bool = False) -> ExportFormat:
    """Add an export format to :data:`EXPORT_FORMATS` (returns it)."""
    return EXPORT_FORMATS.register(fmt, replace=replace, depth=2)


def get_format(name: str) -> ExportFormat:
    """The format called ``name``, or a :class:`MagcalError` listing the formats (``--format NAME: use one of
    ...``)."""
    return EXPORT_FORMATS.lookup(name, "--format")


def load_entry_points(force: bool = False) -> Loaded:
    """Add the formats installed packages declare in ``magcal.export_formats`` (once): see
    :meth:`magcal.core.registry.Registry.load_entry_points` (the names added, and the skipped ones' ``notes``)."""
    return EXPORT_FORMATS.load_entry_points(force=force)


class _Descriptions(Mapping):
    """A read-only view ``name -> description`` of the registered formats (``magcal.output.export.FORMATS``)."""

    def __getitem__(self, name):
        return EXPORT_FORMATS[name].description

    def __iter__(self):
        return iter(EXPORT_FORMATS)

    def __len__(self):
        return len(EXPORT_FORMATS)


class _FileNames(Mapping):
    """A read-only view ``name -> file_name`` of the registered formats (``magcal.output.bundle.PARAMETER_FILES``)."""

    def __getitem__(self, name):
        return EXPORT_FORMATS[name].file_name

    def __iter__(self):
        return iter(EXPORT_FORMATS)

    def __len__(self):
        return len(EXPORT_FORMATS)


#: ``name -> what it writes`` of every registered format.
DESCRIPTIONS: Mapping[str, str] = _Descriptions()
#: ``name -> file name`` of every registered format.
FILE_NAMES: Mapping[str, str] = _FileNames()
