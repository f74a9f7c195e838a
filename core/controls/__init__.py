"""Production solver controls: what animators tune in the tools they already use.

Every control is a pure function of arrays and names (validated at the boundary,
:mod:`core.controls.inputs`) or an option of the solvers (``quadratic``, ``zero``, per-shape
``lower``/``upper``), off by default so that every method solves exactly as before. Where each
acts, and the module that holds it:

=======================  ==================  ===============================================
control                  where               what
=======================  ==================  ===============================================
lower/upper per shape    inside the solve    bounds of range_pf, spacetime, local (box)
                                             (:mod:`~core.controls.table`)
active set               inside the solve    off shapes held at 0: ``zero`` (K,) of every
                                             solver (:meth:`Controls.zero`)
symmetry pairs           inside the solve    ``quadratic = symmetry_matrix(pairs, K, mu_s)``
                                             (:mod:`~core.controls.pairs`)
cancel pairs             around the solve    :func:`cancel_pairs`: second pass(es) with the
                                             weaker of each firing pair held at 0
gain/offset              after the solve     :func:`remap`, clamped to the bounds
temporal filter          after the solve     :func:`filter_weights` (One Euro, Gaussian;
                                             :mod:`~core.controls.filters`)
keyframe reduction       on export           :func:`reduce_keys` -> GLB / CSV writers
                                             (:mod:`~core.controls.keys`)
mirror                   on data             :func:`mirror_weights`, :func:`mirror_markers`,
                                             :func:`mirror_performance`, :func:`mirror_edit`
                                             (:mod:`~core.controls.mirror`)
=======================  ==================  ===============================================

Modules by concept: :mod:`~core.controls.table` (the per-shape controls table and the resolved
:class:`Controls`), :mod:`~core.controls.sides` (left/right in names: which shape mirrors
which), :mod:`~core.controls.pairs` (symmetry and cancel pairs), :mod:`~core.controls.filters`
(temporal filters), :mod:`~core.controls.keys` (keyframe reduction) and
:mod:`~core.controls.mirror` (mirroring takes and edits). Each module's docstring gives its
equations and references; this package re-exports their public names.
"""

from __future__ import annotations

from .filters import (FILTERS, filter_weights, gaussian_response, lowpass_alpha, lowpass_response, one_euro,
                      one_euro_cutoff)
from .keys import INTERPOLATIONS, Keys, evaluate_sampler, reduce_keys
from .mirror import mirror_edit, mirror_markers, mirror_performance, mirror_weights
from .pairs import (cancel_clamp, cancel_conflicts, cancel_pairs, pair_indices, suggested_cancel_pairs, symmetry_matrix,
                    symmetry_pairs)
from .sides import mirror_map, mirror_pairs
from .table import (FORMAT, SHAPE_FIELDS, Controls, default_table, merge_table, read_table, remap, resolve, validate_table,
                    write_table)

__all__ = [
    "SHAPE_FIELDS", "FORMAT", "Controls", "default_table", "validate_table", "read_table", "write_table",
    "merge_table", "resolve", "remap", "mirror_map", "mirror_pairs", "symmetry_pairs", "suggested_cancel_pairs",
    "pair_indices", "symmetry_matrix", "cancel_conflicts", "cancel_pairs", "cancel_clamp", "lowpass_alpha",
    "lowpass_response", "one_euro_cutoff", "gaussian_response", "one_euro", "filter_weights", "FILTERS", "Keys", "reduce_keys",
    "evaluate_sampler", "INTERPOLATIONS", "mirror_weights", "mirror_markers", "mirror_performance", "mirror_edit",
]
