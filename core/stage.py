"""What a pipeline stage is, and the registry every stage and solve method declares itself in.

A stage is one ``param.Parameterized`` object: its parameters are its settings (they become
dashboard widgets, CLI flags and the shot's ``settings[stage]``), and the class says

* ``deps`` — the stages whose results ``run`` may read;
* ``reads(cfg)`` — those it reads in the current configuration (default: all): the key hashes
  only their keys, the pipeline computes and hands over only their results (e.g. ``correspond``
  reads the rig pair's dense correspondence only when the faces are compared densely);
* ``files`` — settings that name files: the cache key hashes their content, not their path;
* ``relevant(cfg)`` — which of its settings change the output in the current configuration (a
  setting of a disabled feature is not in the key, so changing it re-runs nothing);
* ``active(cfg)`` — whether the stage runs at all (an inactive stage yields None and costs
  nothing; e.g. segmentation only for the local method);
* ``derived(cfg)`` — settings whose value follows from the rest of the configuration (the view
  and the key carry the derived value);
* ``content(cfg)`` — what else the result depends on that no setting names (the bundled
  vocabularies' content): hashed into the key;
* ``file_paths(cfg)`` — the file each file setting actually reads (e.g. the default layout a rig
  falls back to when no layout is chosen): the key hashes these, and the shot records them;
* ``run(inputs, s, progress)`` — the pure function: ``inputs[dep]`` are the upstream results,
  ``s`` a :class:`SettingsView` of exactly the settings the key hashes (``relevant(cfg)``, file
  settings as the paths ``file_paths`` reads), taken when the key was computed;
* ``warm_start`` — ``run`` also takes ``warm``, the pipeline's last result of the stage (None at
  first): a hint where an iterative solve starts, never part of the key, so the result must not
  depend on it (e.g. the solve of a unique minimiser, :class:`core.stages.retarget.Solve`).

**The contract.** What a stage's result depends on is declared once, and the declaration is both
the cache key and the only door into the settings: reading a setting ``relevant`` did not name
raises :class:`UndeclaredSetting` instead of giving a result its key does not describe. So a
result changed in place, taken from the cache, or rebuilt fresh from its shot is the same.

``cfg`` is a frozen snapshot of every stage's settings: ``cfg.solve.method``. Stages register
with :func:`register` and are instantiated per pipeline (:class:`core.pipeline.Pipeline`).
Nothing here imports panel.
"""

from __future__ import annotations

import copy
import functools
from typing import ClassVar, Iterable, Optional

import param

#: stage name -> Stage subclass, in registration order (the pipeline sorts by dependencies)
STAGES: dict = {}


@functools.lru_cache(maxsize=None)
def _names(cls) -> tuple:
    """The setting names of a stage class (its parameters but ``name``; classes declare them)."""
    return tuple(k for k in cls.param if k != "name")


def is_table(p: param.Parameter) -> bool:
    """A list or dict setting (edit lists, the per-shape controls): set from a shot or a JSON file,
    never a widget or a command-line flag."""
    return isinstance(p, (param.List, param.Dict))


class UndeclaredSetting(AttributeError):
    """A stage's ``run`` read a setting its cache key does not hash (see :class:`SettingsView`)."""


class SettingsView:
    """The settings a stage's ``run`` may read: exactly those its cache key hashes.

    ``s.alpha`` is the value; reading a setting that is not declared (``Stage.relevant``) raises
    :class:`UndeclaredSetting` naming the stage and the setting, so a stage cannot depend on what
    its key leaves out. :meth:`with_values` adds derived values (e.g. the solve's per-shape bounds
    resolved from the controls) for the functions a stage calls.
    """

    __slots__ = ("_stage", "_values")

    def __init__(self, stage: str, values: dict):
        object.__setattr__(self, "_stage", stage)
        object.__setattr__(self, "_values", dict(values))

    def __getattr__(self, key):
        values = object.__getattribute__(self, "_values")
        if key in values:
            return values[key]
        stage = object.__getattribute__(self, "_stage")
        raise UndeclaredSetting(f"stage {stage!r} read setting {key!r}, which its cache key does not hash now: "
                                f"declare it in the stage's relevant() (or its method's settings)")

    def __setattr__(self, key, value):
        raise AttributeError("a stage's settings are read-only inside run()")

    def __repr__(self):
        return f"SettingsView({self._stage!r}, {sorted(self._values)})"

    def values(self) -> dict:
        """The declared settings as a dict (a copy)."""
        return dict(self._values)

    def with_values(self, **extra) -> "SettingsView":
        """A view with ``extra`` added or replaced (values derived from the declared ones)."""
        return SettingsView(self._stage, {**self._values, **extra})


class Stage(param.Parameterized):
    """Base class of every stage (see the module docstring)."""

    stage_name: ClassVar[str] = ""
    deps: ClassVar[tuple] = ()
    files: ClassVar[tuple] = ()
    #: the result is worth keeping across processes (a rig pair's registration: tens of seconds,
    #: the same for every take): the pipeline's cache keeps it on disk too
    persist: ClassVar[bool] = False
    #: ``run`` takes ``warm=`` (see the module docstring): the last result of this stage the
    #: pipeline returned, a starting point that must not change the result
    warm_start: ClassVar[bool] = False
    #: its share of a run's progress (and so of the time-left estimate): roughly the seconds it
    #: takes on the dense-transfer benchmark (docs/transfer.md), relative; 1 for a quick stage
    cost: ClassVar[float] = 1.0
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

    def tunable_names(self) -> list:
        """The settings that are widgets and command-line flags (not edit lists or tables)."""
        return [k for k in _names(type(self)) if not is_table(self.param[k])]

    def relevant(self, cfg) -> Optional[Iterable[str]]:
        """Settings that change the output now; None = all of them."""
        return None

    def declared(self, cfg) -> tuple:
        """The settings the key hashes and ``run`` may read now (:meth:`relevant`, checked)."""
        own = _names(type(self))
        keep = self.relevant(cfg)
        if keep is None:
            return own
        keep = tuple(keep)
        foreign = [k for k in keep if k not in own]
        if foreign:
            raise ValueError(f"stage {self.stage_name!r} declares settings {foreign} it does not own")
        return keep

    def hidden(self, cfg) -> tuple:
        """Declared settings a person has no use for changing now (the key still hashes them):
        e.g. the weight bounds under a method that does not solve within them. Default: none."""
        return ()

    def active(self, cfg) -> bool:
        return True

    def reads(self, cfg) -> tuple:
        """The dependencies ``run`` reads now (a subset of ``deps``): the key hashes these and
        ``run``'s ``inputs`` hold only these. Default: all of ``deps``."""
        return self.deps

    def derived(self, cfg) -> dict:
        """Settings whose value here follows from the rest of the configuration, not from what the
        user set (the ``auto`` method compares the faces densely): ``run`` sees, and the key
        hashes, these values."""
        return {}

    def content(self, cfg):
        """What the result depends on that no setting names (e.g. the bundled vocabulary files),
        as plain data the key hashes; None: nothing."""
        return None

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


def setting_owners() -> dict:
    """setting name -> (stage name, is a file setting), for every registered stage."""
    return {p: (n, p in cls.files) for n, cls in STAGES.items() for p in _names(cls)}
