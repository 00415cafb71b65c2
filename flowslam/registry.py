"""Plug-ins by name: ``--frontend NAME``, ``--backend NAME`` and ``--format NAME``.

Every plug-in, the built-ins included, is an entry point of an installed package, in
one of three groups::

    [project.entry-points."flowslam.frontends"]     # factory(config) -> Frontend
    my-icp = "my_package.frontend:make_frontend"
    [project.entry-points."flowslam.backends"]      # factory(config) -> Backend
    [project.entry-points."flowslam.datasets"]      # a reader (see flowslam.datasets)

flowslam's own are declared in its ``pyproject.toml``. Entry points are read once per
process and imported only when used (kiss-icp, gtsam and torch stay out of start-up).
A name taken by flowslam cannot be replaced by another package (``flowslam plugins``
shows the ones ignored). A third-party plug-in that cannot be imported is an
``InputError`` naming the plug-in and its package; it never breaks the others.

A library user registers their own in-process with a factory that takes the
pipeline config::

    from flowslam.registry import register_frontend

    @register_frontend("my-icp")
    def make_my_icp(config):
        return MyIcpFrontend(...)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Callable

from flowslam.errors import InputError

Factory = Callable[[Any], Any]

GROUPS = {"frontend": "flowslam.frontends", "backend": "flowslam.backends", "dataset": "flowslam.datasets"}
"""Plug-in kind -> entry-point group."""
BUILTIN_PACKAGE = "flowslam"
IN_PROCESS = "(in-process)"
"""The package shown for plug-ins registered with ``register_frontend`` / ``register_backend``."""

_UNLOADED = object()


@dataclass(eq=False)
class Plugin:
    """One named plug-in: where it comes from and, once loaded, the object it names."""

    kind: str
    """'frontend', 'backend' or 'dataset'."""
    name: str
    package: str
    """The distribution that declares it (``flowslam`` for the built-ins), or ``IN_PROCESS``."""
    target: str
    """``module:attribute`` of the entry point (or of the in-process factory)."""
    entry_point: EntryPoint | None = None
    _object: Any = field(default=_UNLOADED, repr=False)

    @property
    def builtin(self) -> bool:
        return self.package == BUILTIN_PACKAGE

    def load(self) -> Any:
        """The factory (or reader) itself, imported on first use. A third-party plug-in
        that fails to import is an ``InputError``; a built-in's failure propagates as is."""
        if self._object is _UNLOADED:
            try:
                self._object = self.entry_point.load()
            except Exception as error:
                if self.builtin:
                    raise
                reason = f"{type(error).__name__}: {error}".splitlines()[0]
                raise InputError(
                    None, f"{self.kind} plug-in {self.name!r} of package {self.package!r} ({self.target}) "
                    f"cannot be loaded: {reason}",
                ) from error
        return self._object


@cache
def _discovered() -> dict[str, tuple[dict[str, Plugin], tuple[Plugin, ...]]]:
    """Per kind: the entry-point plug-ins by name (flowslam's first, then the others by
    package and name), and those ignored because their name was already taken."""
    found: dict[str, tuple[dict[str, Plugin], tuple[Plugin, ...]]] = {}
    all_points = entry_points()
    for kind, group in GROUPS.items():
        plugins = [
            Plugin(kind, ep.name, ep.dist.name if ep.dist else "?", ep.value, ep)
            for ep in all_points.select(group=group)
        ]
        plugins.sort(key=lambda p: (not p.builtin, p.package.lower(), p.name))
        chosen: dict[str, Plugin] = {}
        ignored = []
        for plugin in plugins:
            if plugin.name in chosen:
                ignored.append(plugin)
            else:
                chosen[plugin.name] = plugin
        found[kind] = (chosen, tuple(ignored))
    return found


_TABLES: dict[str, dict[str, Plugin]] = {}
"""Frontends and backends usable by name: the entry points plus in-process registrations."""


def _table(kind: str) -> dict[str, Plugin]:
    if kind not in _TABLES:
        _TABLES[kind] = dict(_discovered()[kind][0])
    return _TABLES[kind]


def entry_point_plugins(kind: str) -> list[Plugin]:
    """The plug-ins of ``kind`` declared by installed packages (flowslam's first)."""
    return list(_discovered()[kind][0].values())


def ignored_plugins(kind: str) -> list[Plugin]:
    """Entry points of ``kind`` whose name another package (flowslam first) already provides."""
    return list(_discovered()[kind][1])


def plugins(kind: str) -> list[Plugin]:
    """Every plug-in of ``kind`` usable by name, sorted by name (datasets: entry points only;
    see ``flowslam.datasets.available_formats`` for the in-process ones)."""
    table = _table(kind) if kind in ("frontend", "backend") else _discovered()[kind][0]
    return sorted(table.values(), key=lambda p: p.name)


def _register(kind: str, name: str, factory: Factory | None):
    def deco(f: Factory) -> Factory:
        table = _table(kind)
        if name in table and table[name]._object is not f:
            raise ValueError(f"{kind} {name!r} is already registered (by {table[name].package})")
        table[name] = Plugin(kind, name, IN_PROCESS, f"{f.__module__}:{f.__qualname__}", _object=f)
        return f

    return deco(factory) if factory is not None else deco


def register_frontend(name: str, factory: Factory | None = None):
    """Register a frontend factory ``factory(config) -> Frontend`` (usable as a decorator)."""
    return _register("frontend", name, factory)


def register_backend(name: str, factory: Factory | None = None):
    """Register a backend factory ``factory(config) -> Backend`` (usable as a decorator)."""
    return _register("backend", name, factory)


def unknown_name(kind: str, name: str, available: list[str]) -> InputError:
    """The error for a name no plug-in provides (with a hint when flowslam's own entry
    points are missing, i.e. its installed metadata is out of date)."""
    hint = ""
    if not any(p.builtin for p in entry_point_plugins(kind)):
        hint = f" (flowslam's own {GROUPS[kind]} entry points are missing: reinstall it, e.g. `pip install -e .`)"
    return InputError(None, f"unknown {kind} {name!r}; available: {', '.join(available) or 'none'}{hint}")


def _resolve(kind: str, name: str) -> Factory:
    table = _table(kind)
    if name not in table:
        raise unknown_name(kind, name, sorted(table))
    return table[name].load()


def make_frontend(name: str, config: Any):
    """Instantiate the frontend registered as ``name``."""
    return _resolve("frontend", name)(config)


def make_backend(name: str, config: Any):
    """Instantiate the backend registered as ``name``."""
    return _resolve("backend", name)(config)


def frontend_names() -> list[str]:
    return sorted(_table("frontend"))


def backend_names() -> list[str]:
    return sorted(_table("backend"))
