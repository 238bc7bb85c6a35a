"""The spreading measure's apex window (``measure.apex_from`` / ``apex_until``): the apex is the
swing the scene is about, not a later one that undamped hair swings further."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from hairexp.app.config import compose_config
from hairexp.app.validate import validate_config
from hairexp.errors import InputError
from hairexp.evaluation.measures import RunData, tip_variance


def swinging_run(amplitudes, spreads):
    """Two strands of two vertices (root, tip); per frame the tips are ``amplitude`` ahead (+x)
    of the roots and ``spread`` apart along z."""
    offsets = np.array([0, 2, 4])
    frames = []
    for a, s in zip(amplitudes, spreads):
        x = np.zeros((4, 3))
        x[[0, 2], 2] = [-0.01, 0.01]
        x[1] = [a, -0.3, -s]
        x[3] = [a, -0.3, s]
        frames.append(x)
    scene = SimpleNamespace(strands=SimpleNamespace(offsets=offsets))
    return RunData(scene, np.arange(len(frames)) * 0.5, np.array(frames))


def test_apex_is_searched_in_the_window_only():
    # the first swing peaks at frame 2 (t 1.0 s); an undamped later swing goes further (frame 5)
    d = swinging_run([0.0, 0.1, 0.2, 0.0, -0.2, 0.3, 0.0], [0.01, 0.01, 0.02, 0.01, 0.01, 0.05, 0.01])
    everywhere = tip_variance(d, SimpleNamespace(axis=[1, 0, 0], apex_from=0.0, apex_until=-1.0))
    assert everywhere["apex_time"] == 2.5
    window = tip_variance(d, SimpleNamespace(axis=[1, 0, 0], apex_from=0.5, apex_until=1.5))
    assert window["apex_time"] == 1.0 and window["tip_variance_ratio"] == pytest.approx(4.0)


def test_an_empty_window_is_an_input_error():
    d = swinging_run([0.0, 0.1], [0.01, 0.01])
    with pytest.raises(InputError) as e:
        tip_variance(d, SimpleNamespace(axis=[1, 0, 0], apex_from=5.0, apex_until=-1.0))
    assert e.value.where == "measure.apex_from"


@pytest.mark.parametrize("over,key", [(["measure.apex_from=-1"], "measure.apex_from"),
                                      (["measure.apex_from=1.0", "measure.apex_until=0.5"], "measure.apex_until"),
                                      (["measure.apex_from=100", "measure.apex_until=-1"], "measure.apex_from"),
                                      (["measure.apex_until=nan"], "measure.apex_until")])
def test_bad_apex_window_is_refused_before_the_run(over, key):
    cfg = compose_config(["experiment=spreading"] + over)
    with pytest.raises(InputError) as e:
        validate_config(cfg)
    assert e.value.where == key
