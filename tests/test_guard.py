"""The resource guard (hairexp/app/guard.py): the estimate is a pure function of the run's size;
a run that cannot fit in the available memory is refused at start naming the keys (unless
guard.allow_large), a long one is announced with its steps and a rough time."""

from __future__ import annotations

import logging

import pytest

from hairexp.app import assemble, compose_config
from hairexp.app import guard
from hairexp.app.guard import (BYTES_PER_FRAME, BYTES_PER_VERTEX, DISK_BYTES_PER_STEP, DISK_BYTES_PER_VERTEX_FRAME,
                               Estimate, check, estimate, guard_run)
from hairexp.errors import InputError


def test_estimate_is_the_documented_sum():
    e = estimate(1000, 10, 4, settle_steps=5)
    assert e.steps == 40 and e.settle_steps == 5 and e.total_steps == 45
    assert e.memory == 1000 * BYTES_PER_VERTEX + 11 * BYTES_PER_FRAME
    assert e.disk == 11 * 1000 * DISK_BYTES_PER_VERTEX_FRAME + 40 * DISK_BYTES_PER_STEP
    assert e.seconds == pytest.approx(45 * (guard.SECONDS_PER_STEP + 1000 * guard.SECONDS_PER_VERTEX_STEP))
    g = estimate(1000, 10, 4, guide_vertices=30, guide_steps=40)
    assert g.memory == e.memory + 30 * BYTES_PER_VERTEX and g.total_steps == 80
    # linear in the vertices; frames and steps cost disk, memory only the crate index's bytes a frame
    assert estimate(2000, 10, 4).memory - estimate(1000, 10, 4).memory == pytest.approx(1000 * BYTES_PER_VERTEX)
    assert estimate(1000, 3000, 1).memory - estimate(1000, 200, 1).memory == pytest.approx(2800 * BYTES_PER_FRAME)


def test_long_runs_cost_disk_not_memory(tmp_path):
    """Frames and metrics rows are streamed to the run folder (issue 12): 5 x 10^6 frames of a small
    scene fit in memory (the crate index's bytes a frame); they are refused for the disk they would
    fill, naming the folder."""
    long_ = estimate(60, 5 * 10 ** 6, 1)
    assert long_.memory < 6e9 and long_.disk > 2e10
    check(long_, "frames", allow_large=False, available=1e10)      # no disk known: memory fits
    with pytest.raises(InputError, match=r"about [\d.]+ GB of disk .* 1 GB is free where /runs/x is; .*allow_large"):
        check(long_, "frames", allow_large=False, available=1e10, disk_free=1e9, folder="/runs/x")
    check(estimate(60, 200, 1), "frames", allow_large=False, available=1e10, disk_free=1e9)
    assert guard.available_disk(tmp_path / "not" / "yet") > 0      # the nearest existing ancestor's disk


def test_small_runs_pass_and_big_ones_are_refused():
    check(estimate(60, 30, 1), "k", allow_large=False, available=1e9)
    with pytest.raises(InputError, match=r"about [\d.]+ TB of memory .* guard\.allow_large=true") as err:
        check(estimate(2 * 10 ** 8, 30, 1), "scene.n_strands x scene.n_vertices", allow_large=False, available=1e9)
    assert err.value.where == "scene.n_strands x scene.n_vertices"
    check(estimate(60, 30, 1), "k", allow_large=False, available=None)   # unknown memory: no refusal


def test_allow_large_runs_with_a_warning(caplog, monkeypatch):
    monkeypatch.setattr(guard, "_ANNOUNCED", set())   # said once a process: another test may have said it
    with caplog.at_level(logging.WARNING, logger="hairexp.app.guard"):
        check(estimate(10 ** 7, 30, 1), "k", allow_large=True, available=1e6)
    assert "running anyway" in caplog.text


def test_long_runs_are_announced(caplog):
    with caplog.at_level(logging.WARNING, logger="hairexp.app.guard"):
        check(Estimate(1e6, 1e6, 10, 0, 1.0), "k", allow_large=False, available=1e9)
        assert "long run" not in caplog.text
        check(estimate(60, 30, 1, settle_steps=25_000_000), "k", allow_large=False, available=1e9)
    assert "long run: about 2.5e+07 steps" in caplog.text and "days" in caplog.text


def test_available_memory_is_known_here():
    assert guard.available_memory() > 0


@pytest.fixture(scope="module")
def base():
    return compose_config(["experiment=goaling_smoke", "variants=[]", "frames=2", "logging.rerun=false"])


@pytest.mark.parametrize("override,keys", [
    ("scene.n_strands=100000000", "scene.n_strands x scene.n_vertices"),   # 1e9 vertices
    ("solver.dt=1e-9", "solver.dt"),                                       # 8e7 steps: 16 GB of metrics rows
])
def test_assemble_refuses_before_building(override, keys, monkeypatch, tmp_path):
    monkeypatch.setattr(guard, "run_folder", lambda: str(tmp_path))       # as in a Hydra job
    monkeypatch.setattr(guard, "available_disk", lambda folder: 1e9)
    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "logging.rerun=false", override])
    with pytest.raises(InputError) as err:
        assemble(cfg)
    assert keys in err.value.where and ("available" in str(err.value) or "is free" in str(err.value))


def test_settle_steps_are_counted(base, caplog):
    from omegaconf import OmegaConf

    cfg = OmegaConf.merge(base, {"scene": {"settle": 1e6}})   # 2.5e7 settle steps of 0.04 s
    with caplog.at_level(logging.WARNING, logger="hairexp.app.guard"):
        est = guard_run(cfg, 60, 1)
    assert est.settle_steps >= 25_000_000 and "long run" in caplog.text and "scene.settle" in caplog.text


def test_runs_longer_than_a_week_are_refused(caplog):
    """scene.settle=1e9 (about 5e10 steps, thousands of days) stops at start; allow_large runs it."""
    huge = estimate(60, 30, 1, settle_steps=5 * 10 ** 10)
    assert huge.seconds > guard.MAX_RUN_SECONDS
    with pytest.raises(InputError, match=r"roughly [\d.e+]+ days .*, more than 7 days; .*guard\.allow_large=true"):
        check(huge, "scene.settle", allow_large=False, available=1e12)
    with caplog.at_level(logging.WARNING, logger="hairexp.app.guard"):
        check(huge, "scene.settle", allow_large=True, available=1e12)
    assert "running anyway" in caplog.text
    check(estimate(60, 30, 1, settle_steps=25_000_000), "k", allow_large=False, available=1e12)   # days: warned only
