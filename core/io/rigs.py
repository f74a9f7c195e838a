"""Open a rig whatever its container, and find the marker layout that belongs to it."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Optional, Sequence

from ..model import MarkerLayout, Rig
from .gltf import RIG_SUFFIXES as GLTF_RIG_SUFFIXES, read_rig, write_rig
from .layout import default_layout_path, read_layout, sidecar_layout_path
from .objfolder import read_obj_folder
from .usd import SUFFIXES as USD_SUFFIXES
from .usd import read_rig as read_usd_rig

RIG_FORMATS = (".glb, .gltf, .vrm, .usd/.usda/.usdc/.usdz (UsdSkel blend shapes), or a folder of OBJs "
               "(neutral.obj + one OBJ per shape)")


def load_rig(path) -> Rig:
    """Read a rig from a GLB/glTF file, a UsdSkel USD file or an OBJ folder; ValueError names the
    accepted formats (ImportError naming the ``[usd]`` extra for USD without usd-core)."""
    path = Path(path)
    if path.is_dir():
        return read_obj_folder(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such rig file")
    if path.suffix.lower() in GLTF_RIG_SUFFIXES:
        return read_rig(path)
    if path.suffix.lower() in USD_SUFFIXES:
        return read_usd_rig(path)
    raise ValueError(f"{path}: unsupported rig format {path.suffix!r}; expected {RIG_FORMATS}")


class NoLayoutError(FileNotFoundError):
    """A rig has no marker layout (none chosen, no sidecar, none bundled). ``rig_path`` says which;
    the CLI shows the message (how to make one), the dashboard offers to place the markers."""

    def __init__(self, message: str, rig_path):
        super().__init__(message)
        self.rig_path = str(rig_path)


def read_layout_for(layout_path: Optional[str], rig_path, rig: Rig) -> MarkerLayout:
    """The layout given, else the rig's default (its sidecar ``<rig>.layout.json``, else the bundled
    ``data/layouts/<rig stem>.json``, :func:`core.io.layout.default_layout_path`); checked against ``rig``.

    Raises FileNotFoundError saying how to make one (``face-retarget layout``) when neither exists.
    """
    if layout_path:
        return read_layout(layout_path, rig=rig)
    default = default_layout_path(rig_path)
    if default is None:
        raise NoLayoutError(
            f"no marker layout for rig {Path(rig_path).name}: pass --target-layout/--source-layout, or transfer one with "
            f"`face-retarget layout --from data/layouts/ict_facekit.json --rig {rig_path} --out {sidecar_layout_path(rig_path)}`",
            rig_path)
    return read_layout(default, rig=rig)


def hidden_names(n: int) -> tuple:
    """``("shape_000", "shape_001", ...)``: ``n`` shape names that say nothing of what a shape does."""
    return tuple(f"shape_{k:03d}" for k in range(n))


def write_renamed_rig(rig_path, out_path, names: Optional[Sequence[str]] = None) -> Path:
    """A copy of the rig at ``rig_path`` with its shapes renamed, written as GLB to ``out_path``
    (same neutral, faces and deltas, shapes in the same order), with the rig's marker layout (its
    default, :func:`core.io.layout.default_layout_path`) copied as the copy's sidecar
    ``<out>.layout.json`` naming the copy.

    By default the names are hidden (:func:`hidden_names`): the evaluation's case where no method
    can copy curves by name (issue 29, case C; ``scripts/quality_cases.py``, the tests' fixture).

    Raises
    ------
    ValueError
        ``names`` is not one name per shape of the rig.
    NoLayoutError
        The rig has no layout to carry over.
    """
    rig = load_rig(rig_path)
    names = hidden_names(rig.n_shapes) if names is None else tuple(str(n) for n in names)
    if len(names) != rig.n_shapes:
        raise ValueError(f"names: expected {rig.n_shapes} names (one per shape of {rig.name!r}), got {len(names)}")
    layout = default_layout_path(rig_path)
    if layout is None:
        raise NoLayoutError(f"no marker layout for rig {Path(rig_path).name} to carry over to its renamed copy", rig_path)
    out = Path(out_path)
    write_rig(out, dataclasses.replace(rig, names=names, name=out.stem), normals=False)
    doc = json.loads(Path(layout).read_text(encoding="utf-8"))
    doc["rig"] = out.name
    sidecar_layout_path(out).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return out
