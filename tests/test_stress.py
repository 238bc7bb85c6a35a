"""Numerical stress, reduced (validation issue, part 2; the full table: experiments/stress.py ->
reports/stress.md): a few of the extreme cases on the small goaling wisp for a few frames.  A run
that completes has every state and figure finite; a run that cannot go on stops with a clear
SimulationError / InputError (never NaN)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import experiments.stress as stress
import hairexp.physics.simulator as simulator_module


def assert_no_silent_nan(row: dict, out) -> None:
    if row["outcome"] == "failed":
        assert row["clear"], row.get("traceback")   # SimulationError / InputError, with a message
        assert row["error"] and "nan" not in row["error"].lower().split(":")[0]
        assert not (out / "result.npz").exists()
        s = json.loads((out / "summary.json").read_text())
        assert s["status"] == "failed" and s["error"]
    else:
        assert row["finite"] is True, row
        assert np.isfinite(np.load(out / "result.npz")["positions"]).all()
        for k in ("stretch_max", "iterations_mean", "converged_fraction"):
            assert math.isfinite(row[k]), (k, row)
    if row.get("steps"):  # the steps done, also before a failure, have finite metrics
        assert row["metrics_finite"], row


@pytest.mark.parametrize("case,controller,frames,extra", [
    ("dt_0.1", "free", 3, ()),
    ("stiff_both_x1000", "tracking", 4, ()),
    ("guide_teleport", "tracking", 4, ()),   # jumps at frames 1->2 and 3->4
    ("guide_jitter", "tracking", 3, ()),
    ("guide_stretch_2x_static", "tracking", 4, ()),
    ("collider_10ms", "free", 8, ()),   # the ball crosses the hair at t = 0.25 s
])
def test_stress_case_is_finite_or_fails_clearly(case, controller, frames, extra, tmp_path):
    row = stress.run_case(case, controller, tmp_path, frames, extra)
    assert_no_silent_nan(row, tmp_path / f"{case}_{controller}")
    assert row["outcome"] in ("completed", "recovered"), row.get("error")


def test_run_in_which_no_step_converged_fails_clearly(tmp_path):
    """The tip variance penalty far from its target from t = 0 takes hundreds of SQP iterations a
    step at full recovery; capped, the run's one step is kept finite but unconverged, and a run
    in which no step converged is failed (README "Run folder"), its metrics kept and finite."""
    row = stress.run_case("variance_20v0", "tracking", tmp_path, 1,
                          ("tracking.max_iterations=10", "solver.max_substep_levels=1"))
    assert row["outcome"] == "failed" and "no step converged" in row["error"], row
    assert_no_silent_nan(row, tmp_path / "variance_20v0_tracking")


def test_unconverged_step_with_on_failure_fail_is_a_clear_simulation_error(tmp_path):
    row = stress.run_case("guide_teleport", "tracking", tmp_path, 6,
                          extra=("solver.on_failure=fail", "tracking.max_iterations=3"))
    assert row["outcome"] == "failed" and row["error"].startswith("SimulationError"), row
    assert "did not converge" in row["error"]
    assert_no_silent_nan(row, tmp_path / "guide_teleport_tracking")


def test_warn_keeps_unconverged_steps_finite_and_flagged(tmp_path):
    row = stress.run_case("guide_teleport", "tracking", tmp_path, 6,
                          extra=("solver.on_failure=warn", "tracking.max_iterations=3"))
    assert_no_silent_nan(row, tmp_path / "guide_teleport_tracking")
    assert row["outcome"] == "completed" and row["unconverged_kept"] > 0 and row["converged_fraction"] < 1.0


def test_a_non_finite_collision_result_is_a_diverged_step_not_a_state(monkeypatch):
    """The finiteness check also covers the collision stage's output: a NaN it produced is
    retried by substepping and then raised as a SimulationError, never returned."""
    from experiments.common import compose
    from hairexp.app.assemble import assemble
    from hairexp.errors import SimulationError

    cfg = compose(stress.CASES["collider_10ms"][0] + ["solver.max_substep_levels=1"])
    sim = assemble(cfg).simulator
    real = simulator_module.collision_stage

    def poisoned(*a, **k):
        x, v, info = real(*a, **k)
        x = x.copy()
        x[-1, 0] = np.nan
        return x, v, info

    monkeypatch.setattr(simulator_module, "collision_stage", poisoned)
    with pytest.raises(SimulationError, match="diverged"):
        sim.step(sim.initial_state(), 0.04)


def test_stress_rows_reuse_the_report_cache(tmp_path, monkeypatch):
    """--cache: a row whose config, solver source and versions match is not run again; it keeps the
    original figures (and wall time) and says it is cached; another frame count is a new entry."""
    import hairexp.app.report_cache as rc

    monkeypatch.setattr(rc, "CACHE", tmp_path / "cache")
    fresh = stress.run_case("dt_0.1", "free", tmp_path / "a", 2, use_cache=True)
    assert fresh["cache"]["hit"] is False and fresh["config_hash"]
    again = stress.run_case("dt_0.1", "free", tmp_path / "b", 2, use_cache=True)
    assert again["cache"]["hit"] is True and again["cache"]["hash"] == fresh["cache"]["hash"]
    assert not (tmp_path / "b").exists()   # not run
    assert {k: again[k] for k in fresh if k != "cache"} == {k: fresh[k] for k in fresh if k != "cache"}
    other = stress.run_case("dt_0.1", "free", tmp_path / "c", 3, use_cache=True)
    assert other["cache"]["hit"] is False and other["config_hash"] != fresh["config_hash"]
