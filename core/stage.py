"""What a pipeline stage is, and the registry every stage and solve method declares itself in.

A stage is one ``param.Parameterized`` object: its parameters are its settings (they become
dashboard widgets, CLI flags and the shot's ``settings[stage]``), and the class says

* ``deps`` — the stages whose results ``run`` reads;
* ``files`` — settings that name files: the cache key hashes their content, not their path;
* ``relevant(cfg)`` — which settings change the output in the current configuration (a setting
  of a disabled feature is not in the key, so changing it re-runs nothing);
* ``active(cfg)`` — whether the stage runs at all (an inactive stage yields None and costs
  nothing; e.g. segmentation only for the local method);
* ``file_paths(cfg)`` — the file each file setting actually reads (e.g. the default layout a rig
  falls back to when no layout is chosen): the key hashes these, and the shot records them;
* ``run(inputs, s, progress)`` — the pure function: ``inputs[dep]`` are the upstream results,
  ``s`` a frozen copy of the stage's settings taken when the key was computed.

``cfg`` is a frozen snapshot of every stage's settings: ``cfg.solve.method``. Stages register
with :func:`register` and are instantiated per pipeline (:class:`core.pipeline.Pipeline`).
Nothing here imports panel.
"""

from __future__ import annotations

import copy
import functools
from types import SimpleNamespace
from typing import ClassVar, Iterable, Optional

import param

#: stage name -> Stage subclass, in registration order (the pipeline sorts by dependencies)
STAGES: dict = {}


@functools.lru_cache(maxsize=None)
def _names(cls) -> tuple:
    """The setting names of a stage class (its parameters but ``name``; classes declare them)."""
    return tuple(k for k in cls.param if k != "name")


class Stage(param.Parameterized):
    """Base class of every stage (see the module docstring)."""

    stage_name: ClassVar[str] = ""
    deps: ClassVar[tuple] = ()
    files: ClassVar[tuple] = ()
    #: dashboard card the stage's settings belong to, and its title
    group: ClassVar[str] = ""
    title: ClassVar[str] = ""

    def settings(self) -> dict:
        """This stage's setting values (deep copies: lists of edits are not shared)."""
        # getattr per name, not param.values(): half the time, and a pipeline snapshots every
        # stage's settings several times for each change (a shared shot: on every page)
        return {k: copy.deepcopy(getattr(self, k)) for k in _names(type(self))}

    def setting_names(self) -> list:
        return list(_names(type(self)))

    def relevant(self, cfg) -> Optional[Iterable[str]]:
        """Settings that change the output now; None = all of them."""
        return None

    def active(self, cfg) -> bool:
        return True

    def file_paths(self, cfg) -> dict:
        """file setting -> the path it reads now ("" for none); default: the setting's value."""
        own = getattr(cfg, self.stage_name)
        return {f: getattr(own, f) for f in self.files}

    def run(self, inputs: dict, s, progress=None) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError


def register(name: str):
    """Class decorator: register a :class:`Stage` subclass under ``name``.

    Setting names must be unique across stages (``configure(alpha=...)``, ``--alpha`` and the
    shot address them by name alone); a clash raises at import time.
    """

    def deco(cls):
        if not issubclass(cls, Stage):
            raise TypeError(f"{cls.__name__}: a stage must subclass core.stage.Stage")
        if name in STAGES and STAGES[name] is not cls:
            raise ValueError(f"stage {name!r} registered twice ({STAGES[name].__name__}, {cls.__name__})")
        mine = {p for p in cls.param if p != "name"}
        for other, ocls in STAGES.items():
            if other == name:
                continue
            clash = mine & {p for p in ocls.param if p != "name"}
            if clash:
                raise ValueError(f"stage {name!r}: settings {sorted(clash)} already belong to stage {other!r}")
        cls.stage_name = name
        STAGES[name] = cls
        return cls

    return deco


def frozen(values: dict) -> SimpleNamespace:
    """A namespace of setting values (the ``s`` a stage's ``run`` reads)."""
    return SimpleNamespace(**values)
