"""Dataset readers (one class per module) and the format-guessing factory.

``open_dataset(path)`` guesses the format from the path (user-registered formats
first, then): a ``.bag`` file, or a folder with ``metadata.yaml`` / ``*.db3`` /
``*.mcap`` -> ``rosbag``; a folder with ``sequences/`` or ``velodyne/`` -> ``kitti``;
a folder with ``sensors/lidar/`` -> ``argoverse2``; any other folder -> ``folder``
(a folder of scan files). ``format=`` (``dataset.format`` in the run config,
``flowslam run --format``) overrides the guess.

Readers are plug-ins (``flowslam.registry``): entry points of the group
``flowslam.datasets``, the built-ins included, each naming a :class:`Reader` (or a
reader class, used only with ``format=NAME``). A third-party package adds a format with::

    [project.entry-points."flowslam.datasets"]
    ring = "my_package.ring:READER"      # READER = Reader(RingScans, detect=is_ring)

Formats are tried in this order: in-process ones (``register_format``), third-party
entry points (by package and name; one that fails to import is skipped with a warning),
then the built-ins in ``_GUESS_ORDER``.

The reader modules (and their heavy dependencies rosbags / pyarrow) are
imported only when a dataset of that format is opened.
"""

from __future__ import annotations

import importlib
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from flowslam.config.dataset import DatasetConfig
from flowslam.frame import Dataset, Frame
from flowslam.errors import InputError

__all__ = [
    "Dataset", "Frame", "Reader", "open_dataset", "frame_range", "available_formats", "register_format",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Reader:
    """A dataset format: what a ``flowslam.datasets`` entry point names."""

    open: Callable[..., Dataset]
    """``open(path, **options) -> Dataset`` (typically the reader class)."""
    detect: Callable[[Path], bool] | None = None
    """``detect(path) -> bool``: this format is guessed for ``path``; None = only on request."""
    options: tuple[str, ...] | None = None
    """Keyword options the reader takes; None = pass every option that was given."""


@dataclass(frozen=True)
class _Format:
    name: str
    package: str
    load: Callable[[], Reader]
    """The reader (a plug-in's is imported on first call; ``InputError`` if it cannot be)."""


def _lazy(module: str, cls: str) -> Callable[..., Dataset]:
    def open_(*args: Any, **kwargs: Any) -> Dataset:
        return getattr(importlib.import_module(f"flowslam.datasets.{module}"), cls)(*args, **kwargs)

    open_.__name__ = cls
    return open_


def _has_any(path: Path, *suffixes: str) -> bool:
    return path.is_dir() and any(p.suffix in suffixes for p in path.iterdir())


def _is_rosbag(path: Path) -> bool:
    if path.is_file():
        return path.suffix in (".bag", ".db3", ".mcap")
    return (path / "metadata.yaml").is_file() or _has_any(path, ".db3", ".mcap")


def _is_kitti(path: Path) -> bool:
    return path.is_dir() and (
        (path / "sequences").is_dir() or (path / "velodyne").is_dir() or (path.name == "velodyne")
    )


def _is_argoverse2(path: Path) -> bool:
    return (path / "sensors" / "lidar").is_dir()


def _is_simulated(path: Path) -> bool:
    """A sequence written by ``flowslam simulate`` (a ``manifest.json`` at its root)."""
    from flowslam.datasets.simulated import is_simulated

    return is_simulated(path)


# The built-in readers, named by flowslam's own entry points (pyproject.toml).
ROSBAG = Reader(_lazy("rosbag", "RosBag"), _is_rosbag, ("topic", "gt_topic", "fix_times"))
SIMULATED = Reader(_lazy("simulated", "SimulatedSequence"), _is_simulated, ("sequence", "fix_times"))
KITTI = Reader(_lazy("kitti", "KittiOdometry"), _is_kitti, ("sequence", "vertical_correction_deg", "fix_times"))
ARGOVERSE2 = Reader(_lazy("argoverse2", "Argoverse2Log"), _is_argoverse2, ("fix_times",))
FOLDER = Reader(_lazy("folder", "ScanFolder"), Path.is_dir, ("poses", "fix_times"))

_GUESS_ORDER = ("rosbag", "simulated", "kitti", "argoverse2", "folder")
"""Built-in formats, most specific layout first (a simulated sequence is also a KITTI
layout; any folder is a scan folder)."""

_USER: list[_Format] = []


def _as_reader(obj: Any) -> Reader:
    return obj if isinstance(obj, Reader) else Reader(obj)


def _plugin_formats() -> list[_Format]:
    """The entry-point formats: third-party ones (by package, name), then the built-ins."""
    from flowslam.registry import entry_point_plugins

    plugins = entry_point_plugins("dataset")
    rank = {name: k for k, name in enumerate(_GUESS_ORDER)}
    third_party = [p for p in plugins if not p.builtin]
    builtin = sorted((p for p in plugins if p.builtin), key=lambda p: rank.get(p.name, len(rank)))
    return [_Format(p.name, p.package, lambda p=p: _as_reader(p.load())) for p in third_party + builtin]


def register_format(
    name: str, cls: Callable[..., Dataset], detect_fn: Callable[[Path], bool] | None = None
) -> None:
    """Register a reader ``cls(path, **options)`` under ``name``.

    ``detect_fn(path) -> bool`` makes ``open_dataset`` pick it automatically; user
    formats are tried before the built-in ones (latest registration first). Without
    it the format is used only with ``format=name``. The reader receives the options
    (``topic``, ``gt_topic``, ``sequence``, ``poses``, ``vertical_correction_deg``,
    ``fix_times``) that were set (not None, not False). If it derives from ``Dataset``
    its frames are sanitised with ``dataset.max_coordinate_m``.
    Registering an existing name replaces that entry.
    """
    reader = Reader(cls, detect_fn)
    _USER[:] = [f for f in _USER if f.name != name]
    _USER.insert(0, _Format(name, "(in-process)", lambda: reader))


def _formats() -> list[_Format]:
    user_names = {f.name for f in _USER}
    return _USER + [f for f in _plugin_formats() if f.name not in user_names]


def _guess(path: Path, formats: list[_Format]) -> tuple[_Format, Reader] | None:
    """The first format whose reader detects ``path``; a plug-in that cannot be imported
    is skipped with a warning (it must not stop the others)."""
    for f in formats:
        try:
            reader = f.load()
        except InputError as error:
            log.warning("dataset %s; skipped while guessing the format", error)
            continue
        if reader.detect is not None and reader.detect(path):
            return f, reader
    return None


def available_formats() -> list[str]:
    """Names usable as ``format=`` (user-registered first, then the built-ins)."""
    return [f.name for f in _formats()]


_READER_OPTIONS = {
    "topic": "topic", "gt_topic": "gt_topic", "sequence": "sequence", "poses": "poses",
    "kitti_vertical_correction_deg": "vertical_correction_deg", "fix_times": "fix_times",
}
"""``DatasetConfig`` field -> keyword of the reader classes."""


def open_dataset(path: str | Path, config: DatasetConfig | None = None, **options: Any) -> Dataset:
    """Open the dataset at ``path`` with the ``dataset:`` options of a run config.

    ``config`` is a ``DatasetConfig`` (defaults if None); ``options`` replace its fields
    by name (``format``, ``sequence``, ``topic``, ``gt_topic``, ``poses``,
    ``kitti_vertical_correction_deg``, ``fix_times``, ``max_coordinate_m``). The format
    is guessed from ``path`` unless ``format`` is set (module doc). Raises ``InputError``
    for a missing path, an unknown format, an undetectable format, or an option that the
    chosen reader does not take; readers raise it for bad files and for timestamps that
    do not increase strictly (unless ``fix_times``). Frames are sanitised with
    ``max_coordinate_m`` (``flowslam.frame.sanitize_frame``).
    The frame range (``first_frame``, ``max_frames``) is not the reader's: see
    :func:`frame_range`.
    """
    from flowslam.config.pipeline import validated

    c = config or DatasetConfig()
    if options:
        c = validated(DatasetConfig, {**c.model_dump(), **options}, None)
    path = Path(path)
    if not path.exists():
        raise InputError(path, "does not exist")
    formats = _formats()
    fmt = c.format
    if fmt is not None:
        chosen = next((f for f in formats if f.name == fmt), None)
        if chosen is None:
            raise InputError(path, f"unknown format {fmt!r} (available: {', '.join(f.name for f in formats)})")
        reader = chosen.load()
    else:
        guessed = _guess(path, formats)
        if guessed is None:
            raise InputError(
                path, f"cannot tell the dataset format; set dataset.format (one of {', '.join(f.name for f in formats)})"
            )
        chosen, reader = guessed
    given = {  # identity tests: 0 (e.g. no elevation correction) is an option that is set
        kw: v for field, kw in _READER_OPTIONS.items() if (v := getattr(c, field)) is not None and v is not False
    }
    if reader.options is not None:
        unused = sorted(field for field, kw in _READER_OPTIONS.items() if kw in given and kw not in reader.options)
        if unused:
            raise InputError(
                path, f"option(s) {', '.join(unused)} do not apply to the {chosen.name} format"
                + ("" if fmt else " (detected; set dataset.format to choose another)"),
            )
    dataset = reader.open(path, **given)
    dataset.max_coordinate_m = c.max_coordinate_m
    return dataset


def frame_range(n: int, config: DatasetConfig | None = None) -> range:
    """Indices of a dataset of ``n`` scans that a run processes: ``first_frame`` on, at
    most ``max_frames`` of them."""
    c = config or DatasetConfig()
    stop = n if c.max_frames is None else min(n, c.first_frame + c.max_frames)
    return range(c.first_frame, stop)
