"""What a page shows of a retargeting result, as one stage of the pipeline.

The dashboard draws a result from one plain dict — the weights and their frames, the rigs and
markers the viewers play, the evaluation, what the edit card needs. It is a pure function of the
retargeting stages' results, so it is a stage like them: keyed by their keys, cached with them,
made once for every page showing the same result (the pages of a shared shot) and never stale
(a page's own cache of these dicts, keyed by hand, could be). The views add what they make of it
(NaN-free tracks, curve columns) under ``derived``, once for every page sharing it.

A page adds what is its own (its timings, the warnings of its run) to a copy of the dict.
"""

from __future__ import annotations

import numpy as np

from ..stage import Stage, register
from .methods import method_of

#: the retargeting stages a snapshot shows
SHOWN = ("load", "correspond", "shapes", "frames", "stabilize", "calibrate", "personalize", "segment", "solve", "edit",
         "synthesize", "evaluate")


@register("snapshot")
class Snapshot(Stage):
    """The dict a page draws a retargeting result from (see the module docstring)."""

    deps = SHOWN

    def active(self, cfg):
        return not method_of(cfg).dense

    def run(self, inputs, s, progress=None):
        ld, st = inputs["load"], inputs["stabilize"]["source"]
        tm = inputs["calibrate"]["target"]
        syn, solve = inputs["synthesize"], inputs["solve"]
        return {
            "times": st.times - st.times[0], "fps": st.fps, "weights": np.asarray(syn["weights"]), "valid": syn["valid"],
            "first_frame": inputs["frames"]["first"], "target_rig": ld["target_rig"],
            "target_names": list(ld["target_rig"].names), "source_rig": ld["source_rig"],
            "source_weights": st.source_weights, "source_markers": st.positions,
            "marker_names": list(st.names),
            # the points the faces are compared at: the markers, or dense correspondence's face points
            "target_layout": inputs["shapes"]["layout"].select(tm.names),
            "source_layout": (inputs["correspond"]["source_layout"].select(tm.names)
                              if inputs["correspond"]["source_layout"] else None),
            "evaluate": inputs["evaluate"], "segment": inputs["segment"], "method": solve["method"],
            "personalize": inputs["personalize"], "calibrated_deltas": tm.calibrated, "raw_deltas": tm.deltas,
            "solver_names": list(inputs["calibrate"]["rig"].names),
            "source_neutral": st.neutral,  # the shapes of the (K_solver, M, 3) deltas
            "solve_info": solve["info"],
            # an edit is solved under the method's own bounds: the edit slider spans them
            "edit_bounds": (solve["edit"]["lower"], solve["edit"]["upper"]),
            "derived": {},  # what views make of it, made once for every page sharing it (dashboard.session.derived)
        }
