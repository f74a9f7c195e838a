"""Open a rig whatever its container, and find the marker layout that belongs to it."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from ..model import MarkerLayout, Rig
from .gltf import read_rig
from .layout import default_layout_path, read_layout, sidecar_layout_path
from .objfolder import read_obj_folder
from .usd import SUFFIXES as USD_SUFFIXES
from .usd import read_rig as read_usd_rig

RIG_FORMATS = (".glb, .gltf, .usd/.usda/.usdc/.usdz (UsdSkel blend shapes), or a folder of OBJs "
               "(neutral.obj + one OBJ per shape)")


def load_rig(path) -> Rig:
    """Read a rig from a GLB/glTF file, a UsdSkel USD file or an OBJ folder; ValueError names the
    accepted formats (ImportError naming the ``[usd]`` extra for USD without usd-core)."""
    path = Path(path)
    if path.is_dir():
        return read_obj_folder(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such rig file")
    if path.suffix.lower() in (".glb", ".gltf"):
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
