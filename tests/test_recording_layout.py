"""The recording's default layout (issue 17): the camera framed on the bounds of every frame,
the plots that apply to the run, the key moment taken from the scene's measure, and
``comparison.rrd``'s contents read back from the file."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from hairexp.evaluation.measures import experiment_key_moment, key_moment
from hairexp.outputs import layout

SMALL = ["experiment=goaling_smoke", "frames=4", "scene.n_strands=6", "scene.n_vertices=10", "guides.source=rigid",
         "logging.progress=false", "logging.rerun=true"]


# -- bounds and camera ------------------------------------------------------------------------
def test_bounds_grow_frame_by_frame_to_those_of_all_frames():
    rng = np.random.default_rng(0)
    frames = [rng.normal(size=(50, 3)) * (1 + f) + f for f in range(20)]
    b = layout.Bounds()
    assert b.empty
    for x in frames:
        b.add(x)
    b.add(np.full((2, 3), np.nan))                       # a non-finite point frames nothing
    allx = np.concatenate(frames)
    np.testing.assert_array_equal(b.lo, allx.min(0))
    np.testing.assert_array_equal(b.hi, allx.max(0))
    b.add_sphere([100.0, 0.0, 0.0], 2.0)                 # a collider's ball
    assert b.hi[0] == 102.0 and b.lo[0] == allx.min(0)[0]
    assert layout.Bounds.from_json(json.loads(json.dumps(b.to_json()))).to_json() == b.to_json()


@pytest.mark.parametrize("lo, hi, aspect", [
    ((-0.03, -0.30, -0.06), (0.83, 0.03, 0.06), 2.6),   # goaling: wide along x, thin along z
    ((-0.2, -0.5, -0.1), (0.1, 0.1, 0.4), 1.2),         # a scene spread along z: seen along x
    ((0.0, 0.0, 0.0), (1e-3, 2.0, 1e-3), 0.5),          # a tall, thin view
])
def test_camera_sees_every_corner_of_the_bounds(lo, hi, aspect):
    b = layout.Bounds(np.array(lo, float), np.array(hi, float))
    eye, target, up = layout.frame_camera(b, aspect=aspect)
    np.testing.assert_allclose(target, b.center)
    assert layout.in_view(b.corners(), eye, target, up, aspect).all()
    # the margin is small: halfway to the target some corner is out of view (the check can fail)
    closer = target + 0.5 * (eye - target)
    assert not layout.in_view(b.corners(), closer, target, up, aspect).all()
    # the eye looks across the largest horizontal extent: along the thinnest horizontal axis
    thin = int(np.argmin([b.size[0], np.inf, b.size[2]]))
    d = (eye - target) / np.linalg.norm(eye - target)
    assert abs(d[thin]) > abs(d[2 - thin])


def test_frame_camera_refuses_empty_bounds():
    with pytest.raises(ValueError, match="nothing was drawn"):
        layout.frame_camera(layout.Bounds())


@pytest.mark.parametrize("size, spacing", [(0.86, 0.1), (0.3, 0.05), (4.0, 0.5), (0.012, 0.002)])
def test_grid_spacing_is_round_and_at_the_scenes_scale(size, spacing):
    b = layout.Bounds(np.zeros(3), np.array([size, 0.1, size / 3]))
    assert layout.grid_spacing(b) == pytest.approx(spacing)


# -- plots ------------------------------------------------------------------------------------
def with_data(df: pd.DataFrame) -> set[str]:
    return {c for c in df.columns if pd.api.types.is_numeric_dtype(df[c]) and np.isfinite(df[c].astype(float)).any()}


def test_plots_of_a_free_and_a_tracked_run():
    free = pd.DataFrame({"kinetic_energy": [0.1, 0.2], "potential_energy": [-1.0, -0.9], "contacts": [0, 3],
                         "iterations": [3, 4], "residual_rel_max": [np.nan, np.nan],
                         "variance_ratio_mean": [np.nan, np.nan], "constraint_force_rel": [np.nan, np.nan]})
    titles = [p.title for p in layout.choose_plots(with_data(free))]
    assert titles == ["energy (J)", "contacts", "iterations"]
    tracked = free.assign(residual_rel_max=[1e-10, 2e-10], constraint_force_rel=[0.5, 74.8],
                          variance_ratio_mean=[1.0, 1.1])
    plots = layout.choose_plots(with_data(tracked))
    assert [p.title for p in plots] == ["energy (J)", "contacts", "iterations", "tracking residual / hair length",
                                        "control force / hair weight"]
    assert plots[-1].columns == ("constraint_force_rel",)   # control_force_rel (baselines) has no data here


@pytest.mark.parametrize("lo, hi, want", [(0.0, 74.8, (0.0, 74.8 * 1.08)), (3.0, 3.0, (0.0, 3.0 + 0.08 * 3.0)),
                                          (-2.0, 2.0, (-2.32, 2.32)), (0.0, 0.0, (0.0, 0.5))])
def test_axis_range_shows_the_data_from_zero(lo, hi, want):
    a, b = layout.axis_range(lo, hi)
    assert a <= min(lo, 0.0) and b > hi and b > a
    assert (a, b) == pytest.approx(want)


# -- key moment -------------------------------------------------------------------------------
def test_key_moment_from_each_measure():
    hit = {"hit": True, "first_hit_time": 0.92, "min_distance_time": 0.92, "min_distance": 0.0}
    miss = {"hit": False, "first_hit_time": None, "min_distance_time": 1.04, "min_distance": 0.107}
    assert key_moment("collider_contact", hit) == (0.92, "first hit")
    assert key_moment("collider_contact", miss) == (1.04, "closest approach")
    assert key_moment("tip_variance", {"apex_time": 0.96}) == (0.96, "apex")
    assert key_moment("clumps", {"time": 2.4, "clumps": 3}) == (2.4, "clump time")
    assert key_moment("block_rail", {"left_rail_time": 4.88}) == (4.88, "leaves the rail")
    assert key_moment("block_rail", {"left_rail_time": None}) is None
    assert key_moment("none", {}) is None
    # an experiment: the tracked run's hit wins over the free run's closest approach
    assert experiment_key_moment("collider_contact", {"free": miss, "tracked": hit}) == (0.92, "first hit")
    assert experiment_key_moment("collider_contact", {"free": miss}) == (1.04, "closest approach")
    assert experiment_key_moment("block_rail", {"free": {"left_rail_time": None},
                                                "tracked": {"left_rail_time": 4.88}}) == (4.88, "leaves the rail")


def test_key_window_stays_in_the_run():
    assert layout.key_window(0.92, 2.24) == pytest.approx((0.62, 1.22))
    assert layout.key_window(0.1, 2.24) == pytest.approx((0.0, 0.4))
    assert layout.key_window(2.2, 2.24) == pytest.approx((1.9, 2.24))


# -- the recordings, read back ----------------------------------------------------------------
def blueprint_rows(rrd, column: str) -> list:
    """Every value of a blueprint component column (e.g. 'ViewBlueprint:display_name')."""
    from rerun.chunk import RrdReader

    r = RrdReader(rrd)
    out = []
    for store in r.blueprints():
        for c in r.stream(store=store):
            rb = c.to_record_batch()
            if column in rb.schema.names:
                out += [x for v in rb.column(column).to_pylist() if v is not None for x in v]   # rows of batches
    return out


def key_ranges_hold(rrd, key: float, views: int) -> bool:
    """``views`` 3D views show the one frame at ``key`` s on sim_time, and no other frame."""
    ranges = blueprint_rows(rrd, "VisibleTimeRanges:ranges")
    frame = 0.04e9   # 25 fps: the next frame must lie outside
    return len(ranges) == views and all(
        r["timeline"] == "sim_time" and r["range"]["start"] <= key * 1e9 <= r["range"]["end"]
        and r["range"]["end"] - r["range"]["start"] < frame for r in ranges)


def entity_rows(rrd, path: str) -> int:
    from rerun.chunk import RrdReader

    return sum(c.num_rows for c in RrdReader(rrd).stream().filter(content=path, is_static=False))


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    """goaling_smoke (free and tracked), tiny, with recordings."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from helpers import CONF_DIR
    from hairexp.app.experiment import run_experiment

    out = tmp_path_factory.mktemp("exp")
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=SMALL)
    GlobalHydra.instance().clear()
    return out, run_experiment(cfg, out)


def test_each_recording_has_one_layout_framed_on_its_run(experiment):
    from rerun.chunk import RrdReader

    out, summary = experiment
    for v in ("free", "tracked"):
        rrd = out / v / "recording.rrd"
        assert len(RrdReader(rrd).blueprints()) == 1           # one layout per file, sent at the end
        view = json.loads((out / v / "summary.json").read_text())["view"]
        b = layout.Bounds.from_json(view["bounds"])
        x = np.load(out / v / "result.npz")["positions"]
        assert (b.lo <= x.min((0, 1))).all() and (b.hi >= x.max((0, 1))).all()   # every frame's hair
        eyes = blueprint_rows(rrd, "EyeControls3D:position")
        assert eyes and all(np.allclose(e, eyes[0]) for e in eyes)
        names = set(blueprint_rows(rrd, "ViewBlueprint:display_name"))
        assert {"hair", "energy (J)", "contacts", "iterations"} <= names
        tracked_only = {"tracking residual / hair length", "control force / hair weight"}
        assert (tracked_only <= names) == (v == "tracked") and (not tracked_only & names) == (v == "free")
        assert blueprint_rows(rrd, "PanelBlueprint:state")   # the selection panel's state is set
        sel = blueprint_rows(rrd, "TimePanelBlueprint:time_selection")
        key = view["key"]["time"]
        assert len(sel) == 1 and sel[0]["min"] <= key * 1e9 <= sel[0]["max"]
        assert any(n.startswith("key moment: ") for n in names)   # a 3D view fixed at the key frame
        assert key_ranges_hold(rrd, key, 1)


def test_metrics_are_one_chunk_each_whatever_the_run_length(experiment):
    """rerun's file writer keeps an index row per chunk until the footer: the metrics go to the
    recording at the end, one chunk per metric holding every step, and the per-cluster variance
    ratios are one entity (a series per cluster), not one entity per cluster."""
    from rerun.chunk import RrdReader

    out, _ = experiment
    for v in ("free", "tracked"):
        rrd = out / v / "recording.rrd"
        df = pd.read_parquet(out / v / "metrics.parquet")
        chunks = [c for c in RrdReader(rrd).stream().filter(content="/metrics/**", is_static=False)]
        entities = {c.entity_path for c in chunks}
        numeric = {f"/metrics/{k}" for k in df.columns if k not in ("step", "frame", "time")
                   and (pd.api.types.is_numeric_dtype(df[k]) or pd.api.types.is_bool_dtype(df[k]))}
        assert entities == numeric and len(chunks) == len(entities)
        assert all(c.num_rows == len(df) for c in chunks)
        ratios = [c for c in RrdReader(rrd).stream().filter(content="/clusters/**", is_static=False)]
        if v == "free":
            assert ratios == []
        else:
            assert {c.entity_path for c in ratios} == {"/clusters/variance_ratio"}
            assert sum(c.num_rows for c in ratios) == len(np.load(out / v / "result.npz")["times"])   # a row per frame


def test_comparison_holds_every_variant_side_by_side(experiment):
    import pyarrow.parquet as pq
    from rerun.chunk import RrdReader

    out, summary = experiment
    rrd = out / "comparison.rrd"
    assert summary["comparison"]["file"] == "comparison.rrd"
    names = blueprint_rows(rrd, "ViewBlueprint:display_name")
    assert {"free", "tracked", "iterations"} <= set(names)
    origins = blueprint_rows(rrd, "ViewBlueprint:space_origin")
    assert {"/runs/free/world", "/runs/tracked/world"} <= set(origins)
    for v in ("free", "tracked"):
        frames = len(np.load(out / v / "result.npz")["times"])
        assert entity_rows(rrd, f"/runs/{v}/world/hair") == frames
        steps = pq.read_metadata(out / v / "metrics.parquet").num_rows
        assert entity_rows(rrd, f"/metrics/iterations/{v}") == steps
    assert entity_rows(rrd, "/world/hair") == 0            # nothing left at a variant's own paths
    assert entity_rows(out / "tracked" / "recording.rrd", "/world/com") > 0
    assert entity_rows(rrd, "/runs/tracked/world/com") == 0   # the overlays stay in the variant's recording
    key = summary["comparison"]["key"]["time"]
    sel = blueprint_rows(rrd, "TimePanelBlueprint:time_selection")
    assert len(sel) == 1 and sel[0]["min"] <= key * 1e9 <= sel[0]["max"]
    assert len(RrdReader(rrd).recordings()) == 1
    assert key_ranges_hold(rrd, key, 2)                       # both variants at the key moment
    assert f"key moment: {summary['comparison']['key']['what']}" in blueprint_rows(
        rrd, "ContainerBlueprint:display_name")


def test_frame_columns_count_each_entitys_own_rows(tmp_path):
    """An entity is sent when its own pending rows reach ``max_bytes`` or ``max_frames``: a
    large entity (the hair) filling its bytes does not end a chunk of a small one (the body),
    so a long run writes fewer chunks (rerun keeps an index row per chunk until the footer);
    ``send()`` ends a chunk of every entity."""
    import rerun as rr
    from rerun.chunk import RrdReader

    from hairexp.outputs.rerun_sink import FrameColumns

    rec = rr.RecordingStream("hairexp-test", recording_id="frame-columns-own")
    rec.save(str(tmp_path / "f.rrd"))
    cols = FrameColumns(rec, max_bytes=10 * (100 * 12 + 24), max_frames=25)   # the big one: 10 frames
    for f in range(60):
        cols.frame(f, 0.04 * f)
        cols.add("/big", rr.Points3D, None, positions=np.full((100, 3), f, np.float32))
        cols.add("/small", rr.Points3D, None, positions=np.full((1, 3), f, np.float32))
        cols.send_if_due()
        if f == 29:
            assert cols.bytes == 5 * (12 + 24)   # /small: 5 rows since frame 25, /big: none (sent at 29)
    cols.send()
    rec.flush()
    rec.disconnect()
    r = RrdReader(str(tmp_path / "f.rrd"))
    rows = {p: [c.num_rows for c in r.stream().filter(content=p, is_static=False)] for p in ("/big", "/small")}
    assert rows["/big"] == [10] * 6
    assert rows["/small"] == [25, 25, 10]


@pytest.mark.parametrize("form", ["list", "joined"])
@pytest.mark.parametrize("lengths", ["varying", "equal"])
def test_frame_columns_send_every_frame_as_logged_in_a_few_chunks(tmp_path, lengths, form):
    """The frames' columns (``FrameColumns``): rows sent in chunks of at most ``max_frames``
    read back equal to what was logged, strips of varying counts and lengths included (equal
    lengths take the SDK's array path: one (strips, points, 3) array a chunk), given as a list of
    arrays or joined (``Strips``: one array and the lengths), and a buffer once sent is not
    written again (rerun may still hold it)."""
    import rerun as rr
    from rerun.chunk import RrdReader

    from hairexp.outputs.rerun_sink import FrameColumns, Strips, _Rows

    rows = _Rows()
    rows.append(np.ones((3, 2)))
    sent = rows.take()
    rows.append(np.zeros((5, 2)))          # a new buffer: the one sent keeps its rows
    assert sent.shape == (3, 2) and (sent == 1).all()
    with pytest.raises(ValueError):
        rows.append(np.zeros((1, 3)))

    rng = np.random.default_rng(3)
    rec = rr.RecordingStream("hairexp-test", recording_id="frame-columns")
    rec.save(str(tmp_path / "f.rrd"))
    cols = FrameColumns(rec, max_frames=7)
    logged = {}
    for f in range(20):
        cols.frame(f, 0.04 * f)
        n = (lambda: 4) if lengths == "equal" else (lambda: int(rng.integers(2, 6)))
        strips = [rng.random((n(), 3)).astype(np.float32) for _ in range(int(rng.integers(1, 4)))]
        pts = rng.random((4, 3)).astype(np.float32)
        given = strips if form == "list" else Strips(np.concatenate(strips), np.array([len(a) for a in strips]))
        cols.add("/s", rr.LineStrips3D, dict(radii=0.01), strips=given)
        cols.add("/p", rr.Points3D, None, positions=pts)
        logged[f] = (strips, pts)
        cols.send_if_due()
    cols.send()
    rec.flush()
    rec.disconnect()
    r = RrdReader(str(tmp_path / "f.rrd"))
    for path, field in (("/s", "LineStrips3D:strips"), ("/p", "Points3D:positions")):
        chunks = list(r.stream().filter(content=path, is_static=False))
        assert len(chunks) == 3 and max(c.num_rows for c in chunks) == 7   # 7 + 7 + 6 frames
        got = {}
        for c in chunks:
            rb = c.to_record_batch()
            for f, v in zip(rb.column("frame").to_pylist(), rb.column(field).to_pylist()):
                got[f] = v
        assert sorted(got) == list(range(20))
        for f, (strips, pts) in logged.items():
            if path == "/s":
                assert len(got[f]) == len(strips)
                for a, b in zip(got[f], strips):
                    np.testing.assert_array_equal(np.array(a, np.float32), b)
            else:
                np.testing.assert_array_equal(np.array(got[f], np.float32), pts)


def test_bounds_add_is_the_points_range_without_the_non_finite_ones():
    """``Bounds.add`` reduces the points as contiguous columns (fast path); the same box as the
    plain per-axis min and max, with non-finite points ignored and no points a no-op."""
    from hairexp.outputs.layout import Bounds

    rng = np.random.default_rng(3)
    for n in (1, 2, 7, 7826):
        p = rng.normal(size=(n, 3)) * [1.0, 10.0, 0.1]
        b = Bounds()
        b.add(p)
        np.testing.assert_array_equal(b.lo, p.min(axis=0))
        np.testing.assert_array_equal(b.hi, p.max(axis=0))
        q = p.copy()
        q[0] = [np.nan, 1e9, -np.inf]
        b2 = Bounds()
        b2.add(q)
        rest = q[1:]
        if len(rest):
            np.testing.assert_array_equal(b2.lo, rest.min(axis=0))
            np.testing.assert_array_equal(b2.hi, rest.max(axis=0))
        else:
            assert b2.empty
    b3 = Bounds()
    b3.add(np.zeros((0, 3)))
    assert b3.empty
    b3.add(np.array([[np.inf, 0.0, 0.0]]))
    assert b3.empty


def test_usd_extent_is_the_points_range_widened():
    from hairexp.io.usd_write import _extent

    p = np.random.default_rng(4).normal(size=(500, 3))
    e = _extent(p, 0.01)
    np.testing.assert_array_equal(e, np.stack([p.min(axis=0) - 0.01, p.max(axis=0) + 0.01]).astype(np.float32))
