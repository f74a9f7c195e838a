"""Paths of the bundled data for tests (a uniquely named module: ``conftest`` is ambiguous
because tests/browser has its own)."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data"
RIGS = DATA / "rigs"
PERFORMANCES = DATA / "performances"
LAYOUTS = DATA / "layouts"
