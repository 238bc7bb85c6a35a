"""Bad input fails early with an InputError naming the place at fault; on the command line,
with exit code 2, one line on stderr naming the key, and no result file."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from helpers import scene_cfg
from hairexp.errors import InputError
from hairexp.app.builders import build_scene
from hairexp.model.rigid import RigidMotion
from hairexp.model.strands import Strands, validate_polylines

DENSITY = 2e-4


def three_curves(counts=(4, 5, 3)) -> tuple[np.ndarray, np.ndarray]:
    """Packed straight curves with 2 cm edges, one per row of ``counts``."""
    pts = []
    for s, n in enumerate(counts):
        pts.append(np.c_[np.full(n, 0.01 * s), -0.02 * np.arange(n), np.zeros(n)])
    return np.concatenate(pts), np.asarray(counts)


def test_valid_polylines_build_strands():
    pts, counts = three_curves()
    s = Strands.from_polylines(pts, counts, DENSITY)
    assert s.n_strands == 3 and s.n_vertices == 12
    assert list(s.offsets) == [0, 4, 9, 12]
    assert s.kinematic.sum() == 6  # two root vertices per strand
    np.testing.assert_allclose(s.masses.sum(), DENSITY * s.rest_lengths.sum(), rtol=1e-14)
    assert len(s.edges) == 12 - 3 and len(s.bends) == 12 - 6


@pytest.mark.parametrize("curve", [0, 1, 2])
def test_nan_point_names_the_curve(curve):
    pts, counts = three_curves()
    offsets = np.r_[0, np.cumsum(counts)]
    pts[offsets[curve] + 2, 1] = np.nan
    for call in (lambda: Strands.from_polylines(pts, counts, DENSITY, where="hair.usd"),
                 lambda: validate_polylines(pts, counts, "hair.usd")):
        with pytest.raises(InputError, match=rf"hair\.usd: curve {curve} vertex 2 is not finite"):
            call()


def test_inf_point_is_rejected():
    pts, counts = three_curves()
    pts[5, 0] = np.inf
    with pytest.raises(InputError, match="curve 1"):
        Strands.from_polylines(pts, counts, DENSITY)


@pytest.mark.parametrize("counts,match", [((4, 5, 4), "add up to"), ((4, 5), "add up to"),
                                          # a curve's own count is named first (a negative one said only the sum)
                                          ((4, 5, 1), "curve 2 has 1 vertex"), ((4, -5, 4), "curve 1 has -5 vertices")])
def test_counts_not_matching_points(counts, match):
    pts, _ = three_curves()
    with pytest.raises(InputError, match=match):
        validate_polylines(pts, np.asarray(counts), "where")
    with pytest.raises(InputError, match=match):
        Strands.from_polylines(pts, np.asarray(counts), DENSITY)


@pytest.mark.parametrize("curve", [0, 1, 2])
def test_zero_length_edge_names_the_curve(curve):
    pts, counts = three_curves()
    offsets = np.r_[0, np.cumsum(counts)]
    v = offsets[curve] + 1
    pts[v + 1] = pts[v]  # edge (1, 2) of this curve has zero length
    for call in (lambda: Strands.from_polylines(pts, counts, DENSITY), lambda: validate_polylines(pts, counts, "w")):
        with pytest.raises(InputError, match=rf"curve {curve} has a zero-length edge between vertices 1 and 2"):
            call()


def test_touching_curves_are_not_a_zero_length_edge():
    """The last vertex of one curve may coincide with the first of the next (no edge there)."""
    pts, counts = three_curves((3, 3))
    pts[3:] += pts[2] - pts[3]
    Strands.from_polylines(pts, counts, DENSITY)


@pytest.mark.parametrize("curve", [0, 1, 2])
def test_too_few_vertices_names_the_curve(curve):
    counts = [4, 5, 3]
    counts[curve] = 2
    pts, counts = three_curves(counts)
    with pytest.raises(InputError, match=rf"curve {curve} has 2 vertices, needs at least 3"):
        Strands.from_polylines(pts, counts, DENSITY)


@pytest.mark.parametrize("bad", [
    lambda p, c: (p[:, :2], c),                     # wrong shape
    lambda p, c: (p, np.zeros(0, dtype=int)),       # no curves
])
def test_malformed_arrays(bad):
    pts, counts = three_curves()
    with pytest.raises(InputError):
        validate_polylines(*bad(pts, counts), "w")


@pytest.mark.parametrize("density", [0.0, -1.0, np.nan])
def test_bad_linear_density(density):
    pts, counts = three_curves()
    with pytest.raises(InputError, match="linear density"):
        Strands.from_polylines(pts, counts, density)


@pytest.mark.parametrize("times", [[0.0, 1.0, 1.0], [0.0, 2.0, 1.0], [1.0, 0.0]])
def test_rigid_motion_times_must_increase(times):
    K = len(times)
    with pytest.raises(InputError, match="motion.times"):
        RigidMotion(np.asarray(times), np.zeros((K, 3)), np.zeros((K, 3)), "linear")


def test_rigid_motion_rejects_nan_and_bad_interpolation():
    with pytest.raises(InputError, match="motion"):
        RigidMotion(np.array([0.0, 1.0]), np.array([[0, 0, 0], [np.nan, 0, 0]]), np.zeros((2, 3)))
    with pytest.raises(InputError, match="motion.interpolation"):
        RigidMotion(np.array([0.0, 1.0]), np.zeros((2, 3)), np.zeros((2, 3)), "quadratic")


@pytest.mark.parametrize("kw,key", [
    ({"length": -1.0}, "scene.length"),
    ({"n_vertices": 2}, "scene.n_vertices"),
    ({"n_strands": 0}, "scene.n_strands"),
    ({"direction": [0.0, 0.0, 0.0]}, "scene.direction"),
    ({"gravity": [0.0, float("nan"), 0.0]}, "scene.gravity"),
    ({"hair": {"stretch_stiffness": 0.0}}, "scene.hair.stretch_stiffness"),
    ({"hair": {"air_drag": -1.0}}, "scene.hair.air_drag"),
])
def test_scene_config_errors_name_the_key(kw, key):
    with pytest.raises(InputError) as info:
        build_scene(scene_cfg(**kw))
    assert info.value.where == key
    assert str(info.value).startswith(key + ":")


# --------------------------------------------------------------------------------------------
# the command line
# --------------------------------------------------------------------------------------------

def run_cli(args, out):
    return subprocess.run([sys.executable, "-m", "hairexp", "experiment=goaling", "variants=[]", "frames=2", "scene.n_strands=2",
                           "scene.n_vertices=5", f"hydra.run.dir={out}", *args], cwd=out.parent,
                          env=dict(os.environ, CI="1"), capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("override,key", [("scene.length=-1", "scene.length"), ("solver.dt=0", "solver.dt")])
def test_cli_bad_value_exits_2_with_one_line(tmp_path, override, key):
    out = tmp_path / "run"
    proc = run_cli([override], out)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = [l for l in proc.stderr.splitlines() if l.strip()]
    assert len(lines) == 1, proc.stderr
    assert key in lines[0]
    assert "Traceback" not in proc.stderr + proc.stdout
    assert not (out / "result.npz").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed" and key in summary["error"]


def test_cli_unknown_key_exits_nonzero(tmp_path):
    out = tmp_path / "run"
    proc = run_cli(["scene.n_strandz=3"], out)
    assert proc.returncode != 0
    assert "scene.n_strandz" in proc.stderr
    assert not (out / "result.npz").exists()
