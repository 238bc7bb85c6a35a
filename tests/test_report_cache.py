"""The report cache (hairexp/app/report_cache.py): keyed by the run config, the solver source and the
versions; a corrupt entry is recomputed with a warning; writes are atomic."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hairexp.app.report_cache import CacheWarning, cached, source_hash

CFG = {"experiment": "goaling", "frames": 30, "solver": {"dt": 0.04}}


class Counter:
    def __init__(self, value=1.5):
        self.calls = 0
        self.value = value

    def __call__(self):
        self.calls += 1
        return {"value": self.value, "calls": self.calls}


def test_hit_on_identical_key(tmp_path):
    f = Counter()
    r1, i1 = cached("k", {"config": CFG}, f, True, cache_dir=tmp_path, source="src")
    r2, i2 = cached("k", {"config": dict(CFG)}, f, True, cache_dir=tmp_path, source="src")
    assert f.calls == 1 and not i1["hit"] and i2["hit"]
    assert r1 == r2 == {"value": 1.5, "calls": 1}
    assert i2["hash"] == i1["hash"] and i2["date"] == i1["date"] and i2["config_hash"] == i1["config_hash"]
    entry = json.loads((tmp_path / "k" / f"{i1['hash']}.json").read_text())
    assert entry["key"]["key"]["config"] == CFG and entry["key"]["source_hash"] == "src"
    assert {"torch", "numpy", "scipy"} <= entry["key"]["versions"].keys() and entry["date"]


def test_without_use_cache_it_recomputes_and_refreshes(tmp_path):
    f = Counter()
    cached("k", {"config": CFG}, f, False, cache_dir=tmp_path, source="src")
    _, i = cached("k", {"config": CFG}, f, False, cache_dir=tmp_path, source="src")
    assert f.calls == 2 and not i["hit"]
    r, i = cached("k", {"config": CFG}, f, True, cache_dir=tmp_path, source="src")
    assert i["hit"] and r["calls"] == 2


def test_miss_when_the_config_changes(tmp_path):
    f = Counter()
    _, i1 = cached("k", {"config": CFG}, f, True, cache_dir=tmp_path, source="src")
    changed = {**CFG, "solver": {"dt": 0.02}}
    _, i2 = cached("k", {"config": changed}, f, True, cache_dir=tmp_path, source="src")
    assert f.calls == 2 and not i2["hit"] and i2["config_hash"] != i1["config_hash"] and i2["hash"] != i1["hash"]


def test_miss_when_a_source_file_changes(tmp_path):
    tree = tmp_path / "tree"
    (tree / "hairexp" / "physics").mkdir(parents=True)
    (tree / "conf").mkdir()
    solver = tree / "hairexp" / "physics" / "solver.py"
    solver.write_text("TOL = 1e-6\n")
    (tree / "conf" / "config.yaml").write_text("frames: 30\n")
    (tree / "notes.txt").write_text("not source")
    h1 = source_hash(tree, refresh=True)
    (tree / "notes.txt").write_text("still not source")
    assert source_hash(tree, refresh=True) == h1
    f = Counter()
    cached("k", {"config": CFG}, f, True, cache_dir=tmp_path / "c", source=h1)
    solver.write_text("TOL = 1e-7\n")
    h2 = source_hash(tree, refresh=True)
    assert h2 != h1
    _, i = cached("k", {"config": CFG}, f, True, cache_dir=tmp_path / "c", source=h2)
    assert f.calls == 2 and not i["hit"]
    (tree / "conf" / "config.yaml").write_text("frames: 31\n")
    assert source_hash(tree, refresh=True) not in (h1, h2)


@pytest.mark.parametrize("damage", ["truncate", "garbage", "wrong_key", "no_result", "missing_npz"])
def test_corrupt_entry_recomputes_with_a_warning(tmp_path, damage):
    f = Counter()
    compute = (lambda: {**f(), "x": np.arange(3.0)}) if damage == "missing_npz" else f
    _, i = cached("k", {"config": CFG}, compute, True, cache_dir=tmp_path, source="src")
    p = tmp_path / "k" / f"{i['hash']}.json"
    text = p.read_text()
    if damage == "truncate":
        p.write_text(text[: len(text) // 2])
    elif damage == "garbage":
        p.write_bytes(b"\x00\xff not json")
    elif damage == "wrong_key":
        e = json.loads(text)
        e["key"]["key"]["config"]["frames"] = 99
        p.write_text(json.dumps(e))
    elif damage == "no_result":
        e = json.loads(text)
        del e["result"]
        p.write_text(json.dumps(e))
    else:
        p.with_suffix(".npz").unlink()
    with pytest.warns(CacheWarning, match="unreadable entry"):
        r, i2 = cached("k", {"config": CFG}, compute, True, cache_dir=tmp_path, source="src")
    assert f.calls == 2 and not i2["hit"] and r["calls"] == 2
    r, i3 = cached("k", {"config": CFG}, compute, True, cache_dir=tmp_path, source="src")  # repaired
    assert i3["hit"] and r["calls"] == 2


def test_no_half_written_file_if_compute_raises(tmp_path):
    f = Counter()
    _, i = cached("k", {"config": CFG}, f, True, cache_dir=tmp_path, source="src")
    p = tmp_path / "k" / f"{i['hash']}.json"
    before = p.read_bytes()

    def boom():
        raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError, match="interrupted"):
        cached("k", {"config": CFG}, boom, False, cache_dir=tmp_path, source="src")
    with pytest.raises(RuntimeError, match="interrupted"):
        cached("k", {"config": {**CFG, "frames": 1}}, boom, True, cache_dir=tmp_path, source="src")
    assert p.read_bytes() == before
    assert sorted(x.name for x in (tmp_path / "k").iterdir()) == [p.name]


def test_no_half_written_file_if_the_write_fails(tmp_path):
    class Unserialisable:
        pass

    with pytest.raises(TypeError):
        cached("k", {"config": CFG}, lambda: {"bad": Unserialisable()}, True, cache_dir=tmp_path, source="src")
    assert not any((tmp_path / "k").iterdir()) if (tmp_path / "k").exists() else True


def test_arrays_round_trip_beside_the_json(tmp_path):
    pos = np.random.default_rng(0).normal(size=(4, 3, 3))
    r1, i1 = cached("k", {"config": CFG}, lambda: {"positions": pos, "n": 4}, True, cache_dir=tmp_path, source="s")
    r2, i2 = cached("k", {"config": CFG}, lambda: pytest.fail("recomputed"), True, cache_dir=tmp_path, source="s")
    assert i2["hit"] and (tmp_path / "k" / f"{i1['hash']}.npz").is_file()
    np.testing.assert_array_equal(r1["positions"], pos)
    np.testing.assert_array_equal(r2["positions"], pos)
    assert r2["n"] == 4


def test_store_false_keeps_nothing(tmp_path):
    f = Counter()
    _, i = cached("k", {"config": CFG}, f, True, cache_dir=tmp_path, source="s", store=lambda r: False)
    _, i = cached("k", {"config": CFG}, f, True, cache_dir=tmp_path, source="s", store=lambda r: False)
    assert f.calls == 2 and not i["hit"] and i["stored"] is False


def test_default_source_hash_covers_the_package_and_conf():
    from hairexp.app.report_cache import ROOT

    h = source_hash(ROOT, refresh=True)
    assert len(h) == 16 and source_hash(ROOT) == h
    assert source_hash(ROOT, ("hairexp/**/*.py",), refresh=True) != h


def test_an_interrupted_write_leaves_the_old_entry_and_no_temporary_file(tmp_path, monkeypatch):
    """Interrupted after the new content is written but before it is in place (os.fsync raises):
    the entry on disk is still the complete old one."""
    f = Counter()
    _, i = cached("k", {"config": CFG}, f, False, cache_dir=tmp_path, source="src")
    p = tmp_path / "k" / f"{i['hash']}.json"
    before = p.read_bytes()

    def interrupted(fd):
        raise KeyboardInterrupt

    monkeypatch.setattr("os.fsync", interrupted)
    with pytest.raises(KeyboardInterrupt):
        cached("k", {"config": CFG}, Counter(value=2.5), False, cache_dir=tmp_path, source="src")
    monkeypatch.undo()
    assert p.read_bytes() == before
    assert sorted(x.name for x in (tmp_path / "k").iterdir()) == [p.name]
    r, i = cached("k", {"config": CFG}, lambda: pytest.fail("recomputed"), True, cache_dir=tmp_path, source="src")
    assert i["hit"] and r["value"] == 1.5
