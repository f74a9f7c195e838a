"""The pipeline's contract, as a property over every method and every setting.

One result however it was reached: a pipeline changed in place, one setting (or edit) after
another, gives at every step what a fresh pipeline built from its shot gives; and the cache key
of each stage is exactly what its ``run`` reads:

* a change to a setting a stage does not declare (:meth:`core.stage.Stage.declared`) is a cache
  hit for it (its key stays, it does not run again);
* a change to one it declares is a miss (its key changes).

The fresh pipeline's cache is keyed by :func:`_full_key` (every setting of a stage and of its
dependencies): never stale, so a stage whose narrow key leaves out something
its ``run`` reads makes the two sides differ. Both sides share their caches across the walk (as
the pages of a server do), so a stale entry has every chance to be found.

A walk per method: the sample take (30 frames) through every setting of the pipeline, each set
to other values and back (:data:`STEPS`); the test checks that :data:`STEPS` covers every
setting, so a new setting fails here until it has a step.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from datapaths import LAYOUTS, PERFORMANCES, RIGS
from core.pipeline import METHODS, Pipeline, StageCache, content_key, evict_disk, file_key, setting_owners
from core.stages.methods import METHODS as REGISTRY

TAKE = str(PERFORMANCES / "livelinkface_take_s07.csv")
ROM = str(PERFORMANCES / "livelinkface_rom.csv")
ICT = str(RIGS / "ict_facekit.glb")
ROCKETBOX = str(RIGS / "rocketbox_female_adult_02.glb")
BASE = dict(source=TAKE, source_rig=ICT, target_rig=ROCKETBOX, target_shapes="arkit", last_frame=29,
            transfer_last_frame=5)

#: the retargeting results compared at every step
RETARGET = ["solve", "edit", "synthesize", "evaluate"]
SMILE_L, SMILE_R, FROWN_L, JAW = "AK_44_MouthSmileLeft", "AK_45_MouthSmileRight", "AK_30_MouthFrownLeft", "AK_25_JawOpen"

#: setting -> the steps that walk it (each a dict for ``configure``, or an edit operation
#: ``("add" | "undo" | "redo" | "remove", editor, arg)``); the walk runs them in pipeline order
STEPS = {
    "source": [{"source": ROM}, {"source": TAKE}],
    "source_kind": [{"source_kind": "meshes"}, {"source_kind": "auto"}],  # a CSV is no mesh sequence: both refuse alike
    "source_fps": [{"source_fps": 30.0}, {"source_fps": 0.0}],
    "mirror_source": [{"mirror_source": True}, {"mirror_source": False}],
    "source_rig": [{"source_rig": str(RIGS / "jeeliz_tiger.glb")}, {"source_rig": ICT}],
    "source_layout": [{"source_layout": str(LAYOUTS / "ict_facekit.json")}, {"source_layout": ""}],  # same content: a hit
    "name_map": [{"name_map": str(RIGS.parent / "namemaps" / "arkit_to_jeeliz.json")}, {"name_map": ""}],
    "target_rig": [{"target_rig": str(RIGS / "jeeliz_tiger.glb")}, {"target_rig": ROCKETBOX}],
    "vocabularies": [{"vocabularies": str(RIGS.parent / "namemaps" / "vocabulary_sranipal.json")}, {"vocabularies": ""}],
    "target_layout": [{"target_layout": str(LAYOUTS / "rocketbox_female_adult_02.json")}, {"target_layout": ""}],
    "transfer_crop": [{"transfer_crop": "none"}, {"transfer_crop": "auto"}],
    "transfer_icp": [{"transfer_icp": False}, {"transfer_icp": True}],
    "correspondence": [{"correspondence": "dense"}, {"dense_points": 300}, {"dense_points": 1000},
                       {"correspondence": "markers"}, {"dense_points": 200}],  # the last: not read with markers
    "first_frame": [{"first_frame": 5}, {"first_frame": 0}],
    "last_frame": [{"last_frame": 19}, {"last_frame": 29}],
    "target_shapes": [{"target_shapes": ""}, {"target_shapes": "arkit"}],
    "head_motion": [{"head_motion": "remove"}, {"head_motion": "keep"}, {"head_motion": "auto"}],
    "neutral_frame": [{"neutral_frame": 3}, {"neutral_frame": 0}],
    "calibrate": [{"calibrate": False}, {"rbf_smoothing": 0.05}, {"calibrate": True}, {"rbf_smoothing": 0.0}],
    "motion_scale": [{"motion_scale": "rom"}, {"motion_scale": "covariance"}, {"motion_scale": "matched"},
                     {"motion_scale": "none"}],
    "personalize": [{"align_beta": 0.1}, {"personalize": True}, {"align_gamma": 0.3}, {"rom": ROM}, {"rom": ""},
                    {"personalize": False}],
    "regions": [{"regions": 6}, {"min_region_size": 0.05}, {"mask_smoothing": 3}, {"regions": 12},
                {"min_region_size": 0.01}, {"mask_smoothing": 10}],
    "prior_shapes": [{"prior_shapes": f"{JAW},{SMILE_L},{SMILE_R}"}, {"prior_shapes": ""}],
    "lower": [{"lower": -0.2}, {"upper": 1.2}, {"lower": 0.0}, {"upper": 1.0}],
    "alpha": [{"alpha": 0.1}, {"alpha": 0.01}],
    "beta": [{"beta": 0.05}, {"boundary": "none"}, {"boundary": "neutral"}, {"beta": 0.0}, {"boundary": "perframe"}],
    "ridge": [{"ridge": 1e-2}, {"ridge": 1e-3}],
    "mu": [{"mu": 1.0}, {"lam": 0.1}, {"mu": 0.3}, {"lam": 0.6}],
    "constraint": [{"constraint": "box"}, {"local_temporal": "spacetime"}, {"constraint": "simplex"},
                   {"local_temporal": "perframe"}],
    "geometric_prior": [{"geometric_prior": "pca"}, {"geometric_prior": "l2"}, {"geometric_prior": "geometric"}],
    "spacetime_bounds": [{"spacetime_bounds": False}, {"spacetime_bounds": True}],
    "l1": [{"l1": 1e-4}, {"l1": 0.0}],
    "controls": [{"controls": {"shapes": {SMILE_L: {"gain": 0.5}}}},
                 {"controls": {"shapes": {SMILE_L: {"offset": 0.1, "upper": 0.8}}}},
                 {"controls": {"shapes": {JAW: {"active": False}}}},
                 {"controls": {"cancel": [[SMILE_L, FROWN_L]]}}, {"cancel_threshold": 0.2},
                 {"controls": {}}, {"cancel_threshold": 0.0}],
    "symmetry_weight": [{"symmetry_weight": 0.1}, {"symmetry_weight": 0.0}],
    "weights_filter": [{"weights_filter": "one_euro"}, {"filter_min_cutoff": 3.0}, {"filter_beta": 0.5},
                       {"weights_filter": "gaussian"}, {"sigma": 1.5}, {"weights_filter": "none"},
                       {"sigma": 0.0}, {"filter_min_cutoff": 1.0}, {"filter_beta": 0.0}],
    "name_weight": [{"name_weight": 0.01}, {"name_weight": 0.0}],
    "example_poses": [{"example_poses": [{"frame": 12, "weights": {JAW: 0.6, SMILE_L: 0.3}}]},
                      {"example_poses": [{"frame": 12, "weights": {JAW: 0.6}}, {"frame": 25, "weights": {SMILE_R: 0.8}}]},
                      {"example_poses": []}],
    "edits": [("add", "spacetime", {"frame": 12, "weights": {JAW: 0.7}, "window": [4, 20]}),
              ("add", "spacetime", {"frame": 20, "weights": {SMILE_L: 0.5}, "window": None}),
              ("undo", "spacetime", None), ("redo", "spacetime", None), ("remove", "spacetime", 0),
              ("undo", "spacetime", None)],
    "jitter_window": [{"jitter_window": 3}, {"jitter_window": 1}],
}
#: dense-transfer and normal-map settings: walked by the transfer method (slow), and by every
#: marker method too, where none of them may touch a retargeting stage's key
DENSE_STEPS = {
    "transfer_first_frame": [{"transfer_first_frame": 1}, {"transfer_first_frame": 0}],
    "transfer_last_frame": [{"transfer_last_frame": 4}, {"transfer_last_frame": 5}],
    "transfer_iterations": [{"transfer_iterations": 10}, {"transfer_iterations": 40}],
    "transfer_eps": [{"transfer_eps": 0.01}, {"transfer_max_bases": 5}, {"transfer_eps": 0.001},
                     {"transfer_max_bases": 30}],
    "transfer_alpha": [{"transfer_alpha": 10.0}, {"transfer_feature_lines": False}, {"transfer_alpha": 100.0},
                       {"transfer_feature_lines": True}],
    "transfer_details": [{"transfer_details": "none"}, {"transfer_details": "morphs"}],
    "transfer_edits": [("add", "transfer", {"constraints": [{"kind": "point", "frame": 2, "vertex": 10,
                                                              "target": [0.0, 0.0, 0.001]}],
                                            "window": None, "lam_b": 1.0, "lam_w": 1.0, "lam_e": 1.0}),
                       ("undo", "transfer", None)],
    "detail_edits": [],  # needs picked details of a real transfer: tests/test_detail_edit.py
    "detail_tolerance": [{"detail_tolerance": 0.1}, {"detail_tolerance": 0.05}],
    "transfer_output": [{"transfer_output": "source"}, {"transfer_output": "target"}],
    "normalmap_resolution": [{"normalmap_resolution": 512}, {"normalmap_resolution": 256}],
    "normalmap_reduction": [{"normalmap_reduction": 0.8}, {"normalmap_reduction": 0.9}],
}
#: settings walked inside another setting's steps (they matter only together)
WALKED_WITH = {"dense_points": "correspondence", "rbf_smoothing": "calibrate", "rom": "personalize",
               "align_beta": "personalize", "align_gamma": "personalize", "min_region_size": "regions",
               "mask_smoothing": "regions", "upper": "lower", "boundary": "beta", "lam": "mu",
               "local_temporal": "constraint", "cancel_threshold": "controls", "filter_min_cutoff": "weights_filter",
               "filter_beta": "weights_filter", "sigma": "weights_filter", "transfer_max_bases": "transfer_eps",
               "transfer_feature_lines": "transfer_alpha"}


def _full_key(pipe: Pipeline, name: str, cfg, memo: dict) -> str:
    """The obviously-correct key: every setting of the stage (files by content) and the full keys
    of its dependencies; never stale, often needlessly missing."""
    if name not in memo:
        st = pipe.stages[name]
        if not st.active(cfg):
            memo[name] = content_key(name, "inactive")
        else:
            values = {k: v for k, v in vars(getattr(cfg, name)).items() if k not in st.files}
            values.update(st.derived(cfg))  # what the configuration decides for it (motion_scale under auto)
            values.update({f: file_key(path) for f, path in st.file_paths(cfg).items()})
            memo[name] = content_key(name, values, [_full_key(pipe, d, cfg, memo) for d in st.deps])
    return memo[name]


def _declared(stage, cfg) -> set:
    """The settings a stage declares now (its ``relevant``; None = all of them); none when inactive."""
    if not stage.active(cfg):
        return set()
    keep = stage.relevant(cfg)
    return set(stage.setting_names() if keep is None else keep)


class FullKeyCache(StageCache):
    """A cache keyed by :func:`_full_key` of the pipeline it is bound to."""

    def bind(self, pipe: Pipeline) -> "FullKeyCache":
        cfg, memo = pipe.config(), {}
        self._full = {n: _full_key(pipe, n, cfg, memo) for n in pipe.stages}
        return self

    def compute(self, key, fn, persist=False):
        return super().compute((key[0], self._full[key[0]]), fn, persist)


def _same(a, b, where: str, seen=None):
    """Assert two results are the same: arrays to 1e-9, everything else equal, objects field by field."""
    seen = set() if seen is None else seen
    if id(a) in seen:
        return
    seen.add(id(a))
    assert type(a) is type(b), f"{where}: {type(a).__name__} vs {type(b).__name__}"
    if isinstance(a, np.ndarray):
        assert a.shape == b.shape, f"{where}: shape {a.shape} vs {b.shape}"
        if a.dtype.kind in "fc":
            if not np.allclose(a, b, rtol=0, atol=1e-9, equal_nan=True):
                raise AssertionError(f"{where}: differ by {np.nanmax(np.abs(a - b)):.3g}")
        elif not np.array_equal(a, b):
            raise AssertionError(f"{where}: differ")
    elif isinstance(a, dict):
        assert set(a) == set(b), f"{where}: keys {sorted(map(str, a))} vs {sorted(map(str, b))}"
        for k in a:
            _same(a[k], b[k], f"{where}.{k}", seen)
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), f"{where}: length {len(a)} vs {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]", seen)
    elif isinstance(a, float):
        if not (a == b or (np.isnan(a) and np.isnan(b)) or abs(a - b) <= 1e-9):
            raise AssertionError(f"{where}: {a} vs {b}")
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            _same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}", seen)
    elif hasattr(a, "__dict__") and not callable(a):
        _same(vars(a), vars(b), f"{where}.__dict__", seen)
    else:
        assert a == b, f"{where}: {a!r} vs {b!r}"


def _outcome(pipe: Pipeline, targets: list):
    """The targets' results, or the error a run raises (both sides must fail alike)."""
    try:
        return pipe.results(targets)
    except Exception as e:  # noqa: BLE001 - the error is the outcome compared
        return ("error", type(e).__name__, str(e))


def _apply(pipe: Pipeline, step) -> None:
    if isinstance(step, dict):
        pipe.configure(**step)
        return
    op, editor, arg = step
    if op == "add":
        pipe.add_edit(editor, arg)
    elif op == "undo":
        pipe.undo(editor)
    elif op == "redo":
        pipe.redo_edit(editor)
    else:
        pipe.remove_edit(editor, arg)


def _changed_setting(step) -> str:
    from core.shot import EDITORS

    return next(iter(step)) if isinstance(step, dict) else EDITORS[step[1]]


def _hashed(pipe: Pipeline, name: str, cfg) -> dict:
    """What stage ``name`` reads now, files by content (an explicit path to a rig's default layout
    is the same input as no path)."""
    st = pipe.stages[name]
    values = {k: getattr(getattr(cfg, name), k) for k in _declared(st, cfg)}
    values.update({k: v for k, v in st.derived(cfg).items() if k in values})
    values.update({f: file_key(p) for f, p in st.file_paths(cfg).items() if f in values})
    return values


def _walk(method: str, steps: dict, targets: list, cache: StageCache, fresh_cache: FullKeyCache):
    """Walk ``steps`` on one pipeline of ``method``; at each step compare it with a fresh one."""
    owners = setting_owners()
    pipe = Pipeline(cache=cache, method=method, **BASE)
    _outcome(pipe, targets)
    failures = []
    for group, group_steps in steps.items():
        for step in group_steps:
            cfg0 = pipe.config()
            keys0 = {n: pipe.key(n, _cfg=cfg0) for n in pipe.stages}
            declared0 = {n: _declared(st, cfg0) for n, st in pipe.stages.items()}
            runs0 = dict(pipe.runs)
            _apply(pipe, step)
            cfg1 = pipe.config()
            keys1 = {n: pipe.key(n, _cfg=cfg1) for n in pipe.stages}
            got = _outcome(pipe, targets)
            setting = _changed_setting(step)
            owner = owners[setting][0]
            for n, st in pipe.stages.items():
                declared = declared0[n] | _declared(st, cfg1)
                upstream_same = all(keys0[d] == keys1[d] for d in st.deps) and st.active(cfg0) == st.active(cfg1)
                if n == owner and setting not in declared and upstream_same:
                    assert keys1[n] == keys0[n], f"{method} {step}: {n} does not declare {setting} but its key changed"
                    assert pipe.runs[n] == runs0.get(n, 0), f"{method} {step}: {n} ran again for an undeclared {setting}"
                if n == owner and setting in declared and st.active(cfg0) and st.active(cfg1):
                    if _hashed(pipe, n, cfg0).get(setting) != _hashed(pipe, n, cfg1).get(setting):
                        assert keys1[n] != keys0[n], f"{method} {step}: {n} declares {setting} but its key stayed"
                if n != owner and upstream_same:
                    assert keys1[n] == keys0[n], f"{method} {step}: {n} does not own {setting}, nothing upstream changed"
            fresh = Pipeline.from_shot(pipe.shot(), cache=fresh_cache)
            fresh_cache.bind(fresh)
            want = _outcome(fresh, targets)
            try:
                _same(got, want, f"{method} after {group}: {step}")
            except AssertionError as e:
                failures.append(str(e))
    assert not failures, "in place != fresh from the shot:\n" + "\n".join(failures)


@pytest.fixture(scope="module")
def caches():
    """One cache for the pipelines changed in place and one for the fresh ones, for every walk."""
    return StageCache(max_entries=4096), FullKeyCache(max_entries=4096, disk=None)


def test_steps_cover_every_setting():
    walked = set(STEPS) | set(DENSE_STEPS) | set(WALKED_WITH)
    for steps in (STEPS, DENSE_STEPS):
        for group in steps.values():
            for step in group:
                walked.add(_changed_setting(step))
    missing = sorted(set(setting_owners()) - walked - {"method"})
    assert not missing, f"settings without a step in the contract walk: {missing}"


MARKER_METHODS = [m for m in METHODS if not REGISTRY[m].dense]


#: the settings of the stages from the solve on: a change there costs a solve, not a registration
SOLVE_STEPS = {k: v for k, v in STEPS.items() if setting_owners()[_changed_setting(v[0])][0] in
               ("solve", "edit", "evaluate", "prior")}


@pytest.mark.parametrize("method", MARKER_METHODS)
def test_a_change_of_the_solve_in_place_is_the_result_of_its_shot(method, caches):
    _walk(method, SOLVE_STEPS, RETARGET, *caches)


@pytest.mark.slow
@pytest.mark.parametrize("method", MARKER_METHODS)
def test_a_change_anywhere_in_place_is_the_result_of_its_shot(method, caches):
    _walk(method, {**STEPS, **DENSE_STEPS}, RETARGET, *caches)


@pytest.mark.slow
@pytest.mark.parametrize("method", [m for m in METHODS if REGISTRY[m].dense])
def test_dense_changes_in_place_are_the_result_of_their_shot(method, caches):
    dense = {k: v for k, v in STEPS.items() if k in ("source", "mirror_source", "first_frame", "target_layout")}
    _walk(method, {**dense, **DENSE_STEPS}, ["dense_output", "normalmap_masks", "normalmap_decimate"], *caches)


def test_the_name_method_honours_the_gain_in_place():
    """The case the issue met: with ``names``, a gain change in place changes the result as the
    shot built fresh does (it used to stay, 0.24 away from the fresh result)."""
    pipe = Pipeline(method="names", **BASE)
    w0 = pipe.run("synthesize")["weights"].copy()
    pipe.configure(controls={"shapes": {"AK_22_EyeWideRight": {"gain": 0.5}}})
    w1 = pipe.run("synthesize")["weights"]
    fresh = Pipeline.from_shot(pipe.shot(), cache=StageCache()).run("synthesize")["weights"]
    col = list(pipe.run("load")["target_rig"].names).index("AK_22_EyeWideRight")
    assert np.abs(w1 - w0).max() > 0.01
    np.testing.assert_allclose(w1[:, col], np.clip(0.5 * w0[:, col], 0, 1))
    np.testing.assert_array_equal(w1, fresh)


def test_a_failed_edit_rolls_back_through_the_pipeline():
    """An edit is a transaction: when the run that checks it fails, the edit list, its redo stack
    and every setting changed with it are as before, and the listeners (a review page's store)
    heard nothing; a completed one is heard once, in order."""
    pipe = Pipeline(method="bounded", **BASE)
    heard = []
    pipe.listeners.append(lambda *args: heard.append(args))
    good = {"frame": 12, "weights": {JAW: 0.7}, "window": [4, 20]}
    pipe.add_edit("spacetime", good)
    pipe.add_edit("spacetime", {**good, "frame": 14})
    pipe.undo("spacetime")  # a redo stack to keep
    before, heard[:] = pipe.edits("spacetime"), []
    with pytest.raises(ValueError, match="NoSuchShape"):
        with pipe.transaction():
            pipe.add_edit("spacetime", {"frame": 12, "weights": {"NoSuchShape": 1.0}, "window": None})
            pipe.configure(alpha=0.5)
            pipe.results(["edit"])
    assert pipe.edits("spacetime") == before and pipe.redo["spacetime"] == before.undone
    assert pipe.solve.alpha == 0.01 and heard == []
    with pipe.transaction():
        pipe.add_edit("spacetime", {**good, "frame": 16})
        pipe.results(["edit"])
    assert heard == [("spacetime", "add", {**good, "frame": 16})] and pipe.redo["spacetime"] == []


def test_a_persisted_stage_is_read_back_by_another_process_cache(tmp_path, monkeypatch):
    """A stage marked ``persist`` (a rig pair's registration) is kept on disk by content key and
    read back by a new cache (another process): the same result, no run; a file cut short is
    computed again, never an error."""
    from core.stages.retarget import Shapes

    monkeypatch.setattr(Shapes, "persist", True)  # a cheap stage standing in for the registration
    first = Pipeline(cache=StageCache(disk=tmp_path), method="bounded", **BASE)
    want = first.run("shapes")
    files = list(tmp_path.glob("shapes-*.pkl"))
    assert len(files) == 1 and first.runs["shapes"] == 1
    again = Pipeline(cache=StageCache(disk=tmp_path), method="bounded", **BASE)
    _same(again.run("shapes"), want, "shapes from disk")
    assert again.runs["shapes"] == 0
    files[0].write_bytes(files[0].read_bytes()[:100])
    third = Pipeline(cache=StageCache(disk=tmp_path), method="bounded", **BASE)
    _same(third.run("shapes"), want, "shapes recomputed")
    assert third.runs["shapes"] == 1


def test_disk_eviction_keeps_the_most_recently_used_results(tmp_path):
    """The folder is cut to ``max_bytes``, least recently used first (modification time), never
    a file in ``keep`` and never anything but results (``*.pkl``)."""
    import os

    sizes = {"a": 400, "b": 300, "c": 200, "d": 100}  # a oldest ... d newest
    for i, (name, size) in enumerate(sizes.items()):
        p = tmp_path / f"{name}.pkl"
        p.write_bytes(b"x" * size)
        os.utime(p, (1000 + i, 1000 + i))
    (tmp_path / "notes.txt").write_bytes(b"y" * 5000)
    assert evict_disk(tmp_path, 10_000) == []  # under the bound: nothing goes
    gone = evict_disk(tmp_path, 400, keep=[tmp_path / "b.pkl"])
    assert sorted(p.name for p in gone) == ["a.pkl", "c.pkl"]  # b kept although old; d newest
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.pkl", "d.pkl", "notes.txt"]
    assert evict_disk(tmp_path / "missing", 0) == []


def test_the_disk_cache_is_bounded_and_a_read_counts_as_a_use(tmp_path, monkeypatch):
    """StageCache cuts its folder after every write (an old result of another rig pair goes);
    a result read back from disk is touched, so it outlives an older unused one."""
    import os

    from core.stages.retarget import Shapes

    monkeypatch.setattr(Shapes, "persist", True)
    first = Pipeline(cache=StageCache(disk=tmp_path, disk_max_bytes=1 << 30), method="bounded", **BASE)
    want = first.run("shapes")
    (mine,) = tmp_path.glob("shapes-*.pkl")
    size = mine.stat().st_size
    old = tmp_path / "dense_correspondence-0.pkl"  # another rig pair's result, larger
    old.write_bytes(b"z" * (20 * size))
    os.utime(old, (1000, 1000))
    os.utime(mine, (500, 500))  # older than the other file ...
    again = Pipeline(cache=StageCache(disk=tmp_path, disk_max_bytes=1 << 30), method="bounded", **BASE)
    _same(again.run("shapes"), want, "shapes from disk")
    assert again.runs["shapes"] == 0 and mine.stat().st_mtime > old.stat().st_mtime  # ... until it is read
    # a bound below the three files (all the rig's shapes: ~3x the ARKit ones): the next write
    # evicts the least recently used one
    bound = 10 * size
    small = Pipeline(cache=StageCache(disk=tmp_path, disk_max_bytes=bound), method="bounded",
                     **{**BASE, "target_shapes": ""})
    small.run("shapes")
    assert small.runs["shapes"] == 1
    left = sorted(p.name for p in tmp_path.glob("*.pkl"))
    assert not old.exists() and len(left) == 2 and mine.name in left
    assert sum(p.stat().st_size for p in tmp_path.glob("*.pkl")) <= bound
    monkeypatch.setenv("FACE_RETARGET_CACHE_MAX_MB", "1.5")
    assert StageCache().disk_max_bytes == int(1.5 * (1 << 20))
    monkeypatch.setenv("FACE_RETARGET_CACHE_MAX_MB", "lots")
    with pytest.raises(ValueError, match="FACE_RETARGET_CACHE_MAX_MB"):
        StageCache()


def test_auto_pays_the_rig_pairs_registration_only_for_its_shape_map(hidden_rocketbox):
    """The rig pair's registration (tens of seconds the first time) runs under auto only when auto
    will map shapes over the face (no shared names): never for the sample's ARKit-named pair, with
    or without --target-shapes arkit (with example poses too: the map is their base). What a stage does not read is not in
    its key: auto's and bounded's marker stages share their keys (on the same motion map)."""
    curves = dict(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"))
    named = Pipeline(cache=StageCache(), target_rig=str(RIGS / "rocketbox_female_adult_02.glb"), **curves)
    assert "register" not in named._order("synthesize")
    named.configure(target_shapes="arkit")
    assert "register" not in named._order("synthesize")
    hidden = Pipeline(cache=StageCache(), target_rig=str(hidden_rocketbox), **curves)
    assert {"register", "dense_correspondence"} <= set(hidden._order("synthesize"))
    keys = {n: hidden.key(n) for n in ("correspond", "shapes", "calibrate")}
    hidden.configure(example_poses=[{"frame": 10, "weights": {"shape_000": 0.5}}])
    assert {"register", "dense_correspondence"} <= set(hidden._order("synthesize"))  # the map is the poses' base
    hidden.configure(example_poses=[], method="bounded", motion_scale="matched")
    assert "register" not in hidden._order("synthesize")
    assert {n: hidden.key(n) for n in keys} == keys
