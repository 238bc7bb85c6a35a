"""The paper's scenes as experiments (issue: scenes): smoke variants run in the default suite
(they complete, every variant writes its measure, the judge gives a verdict); the full runs
and their success are asserted in the ``slow`` suite (``make test-slow``)."""

from __future__ import annotations

import json

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from helpers import CONF_DIR
from hairexp.app.experiment import run_experiment

QUIET = ["logging.rerun=false", "logging.progress=false"]


def experiment_cfg(name: str, *overrides: str):
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return compose(config_name="config", overrides=[f"experiment={name}", *QUIET, *overrides])
    finally:
        GlobalHydra.instance().clear()


@pytest.mark.parametrize("name", ["goaling_smoke", "spreading_smoke", "celia_smoke", "stylization_smoke",
                                  "fanning_smoke"])
def test_smoke_experiment_runs_every_variant_and_judges(name, tmp_path):
    cfg = experiment_cfg(name)
    summary = run_experiment(cfg, tmp_path)
    assert summary["status"] == "completed" and isinstance(summary["success"], bool)
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["success"] == summary["success"]
    assert set(on_disk["variants"]) == {v.name for v in cfg.variants}
    for vname, v in on_disk["variants"].items():
        assert v["status"] == "completed" and v["measures"], vname
        assert (tmp_path / vname / "result.npz").is_file() and (tmp_path / vname / "summary.json").is_file()
        assert v["converged_fraction"] == 1.0, vname
    if name == "spreading_smoke":   # the penalty lands on its target even on the small scene
        errs = on_disk["verdict"]["relative_errors"]
        assert max(errs) < 0.05, errs
    if name == "fanning_smoke":     # Fig. 8: hard splits, soft fans out and tracks, even on the small scene
        assert on_disk["success"] is True, on_disk["verdict"]
        m = {k: v["measures"] for k, v in on_disk["variants"].items()}
        assert m["free"]["clumps"] == 1 and m["hard"]["clumps"] == 2
        assert m["soft"]["gap_ratio_max"] <= 2.0 < m["hard"]["gap_ratio_max"]
        assert m["soft"]["residual_rel_max"] <= 1e-6


def test_failing_variant_marks_the_experiment_failed(tmp_path, monkeypatch):
    """A variant that fails while it runs (its checks passed: a bad tracking.max_guide_distance is
    now refused before any variant runs, tests/test_run_folder.py) marks the experiment failed."""
    import hairexp.app.experiment as experiment

    real = experiment.run_checked   # a variant's run (checked with the others before the first ran)

    def run(vcfg, out, *a, **k):
        if out.name == "tracked":
            raise RuntimeError("the tracked variant failed")
        return real(vcfg, out, *a, **k)

    monkeypatch.setattr(experiment, "run_checked", run)
    cfg = experiment_cfg("goaling_smoke", "frames=2")
    with pytest.raises(RuntimeError):
        run_experiment(cfg, tmp_path)
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["status"] == "failed" and "tracked" in s["error"] and s["success"] is None
    assert (tmp_path / "free" / "summary.json").is_file()      # the free variant had run


def test_unknown_variant_key_is_an_input_error(tmp_path):
    from hairexp.errors import InputError

    cfg = experiment_cfg("goaling_smoke", "frames=2")
    cfg.variants[0].overrides = ["controller.nmae=free"]
    with pytest.raises(InputError, match=r"variants\[0\] \(free\).*controller.nmae"):
        run_experiment(cfg, tmp_path)


# -- full runs (slow) ---------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("name", ["goaling", "spreading", "stylization", "celia", "fanning"])  # splitting: tests/test_splitting.py
def test_full_experiment_meets_the_artistic_intent(name, tmp_path):
    summary = run_experiment(experiment_cfg(name), tmp_path)
    assert summary["status"] == "completed"
    assert summary["success"] is True, summary.get("verdict")


def test_ci_ablation_sliding_beats_static_on_goaling_smoke(tmp_path):
    """The paper's claim for sliding targets (3.2), on the goaling smoke experiment, tracked:
    no more SQP iterations and lower stretch than static targets (measured: 2.8 vs 8.6
    iterations a step, stretch 4.6e-4 vs 0.76)."""
    from hairexp.app.run import run

    out = {}
    for targets in ("static", "sliding"):
        cfg = experiment_cfg("goaling_smoke", "variants=[]", "controller.name=tracking", f"tracking.targets={targets}")
        out[targets] = run(cfg, tmp_path / targets)
    st, sl = out["static"], out["sliding"]
    assert sl["iterations_mean"] <= st["iterations_mean"]
    assert sl["stretch_max"] < st["stretch_max"]


@pytest.mark.slow
def test_celia_free_ponytail_misses_the_goblet_at_small_dt(tmp_path):
    """The celia contrast must not rest on implicit Euler's numerical damping: at dt = 0.0025 s
    (the accuracy report's reference step) the free ponytail still misses the goblet, and the
    tracked one still hits it.  (The goblet used to stand behind the head, where the free swing
    reached it at small dt.  The settle phase steps at scene.settle_dt whatever solver.dt is, so
    both dt start from the same settled ponytail.)"""
    from hairexp.app.run import run

    for controller, want in (("free", False), ("tracking", True)):
        cfg = experiment_cfg("celia", "variants=[]", f"controller.name={controller}", "solver.dt=0.0025", "frames=30")
        summary = run(cfg, tmp_path / controller)
        assert summary["status"] == "completed"
        assert summary["measures"]["hit"] is want, (controller, summary["measures"])


@pytest.mark.slow
@pytest.mark.parametrize("dt", [0.01, 0.0025])
def test_goaling_verdict_holds_at_small_dt(dt, tmp_path):
    """The goaling contrast must not rest on numerical damping (issue 13): with the default
    integrator the free wisp misses the wheel and the tracked one hits it at dt 0.01 and 0.0025 s
    too (dt 0.04 s: test_full_experiment_meets_the_artistic_intent).  With the C1 body keys the
    free wisp's distance to the wheel barely depends on dt (3.3 cm at 0.04 s, 3.4 cm at 0.01 and
    0.0025 s, 2026-12-03); with the former linear keys it was 7 mm at 0.0025 s."""
    summary = run_experiment(experiment_cfg("goaling", f"solver.dt={dt}"), tmp_path)
    assert summary["status"] == "completed"
    assert summary["success"] is True, summary.get("verdict")
    free = summary["variants"]["free"]["measures"]
    assert free["min_distance"] > 0.02, free
