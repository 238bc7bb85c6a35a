"""The experiments/ scripts check what they will write before they run anything (an independent
tester's findings): a bad output path, report name or size is one line
``<script>.py: error: argument ...`` with exit 2 and no traceback, at once (they used to run for
a long time and fail at the end with a traceback, exit 1, or write outside reports/); a script
whose runs failed never exits 0, and never replaces a report with failed runs only.

* the argparse types of experiments/common.py: ``writable_dir``, ``writable_file`` (an existing
  folder is probed by creating a file there: as root, os.access says yes to /proc),
  ``report_name``, ``strand_count`` / ``strand_vertices``, and ``check_reports``, ``fail``;
* each script with the tester's bad arguments, as a subprocess;
* baselines, contact, paper_scenes and ablations with failed runs (their runs replaced by stubs).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from experiments import common

REPO = Path(__file__).resolve().parents[1]
PROC = pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")


# -- the helpers ---------------------------------------------------------------------------------
def test_writable_dir(tmp_path):
    assert common.writable_dir(str(tmp_path)) == tmp_path
    new = tmp_path / "a" / "b"
    assert common.writable_dir(str(new)) == new and not (tmp_path / "a").exists()   # checked, not made
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(argparse.ArgumentTypeError, match="exists and is not a directory"):
        common.writable_dir(str(afile))
    with pytest.raises(argparse.ArgumentTypeError, match="is a file, not a folder"):
        common.writable_dir(str(afile / "sub"))
    with pytest.raises(argparse.ArgumentTypeError, match="an empty path"):
        common.writable_dir("")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]   # the probes leave nothing behind


def test_writable_file(tmp_path):
    assert common.writable_file(str(tmp_path / "x.png")) == tmp_path / "x.png"
    assert common.writable_file(str(tmp_path / "new" / "x.json")) == tmp_path / "new" / "x.json"
    (tmp_path / "old.json").write_text("{}")
    assert common.writable_file(str(tmp_path / "old.json")) == tmp_path / "old.json"   # replaced
    for bad in (str(tmp_path), str(tmp_path) + "/", str(tmp_path / "d") + "/"):
        with pytest.raises(argparse.ArgumentTypeError, match="is a directory, not a file"):
            common.writable_file(bad)
    with pytest.raises(argparse.ArgumentTypeError, match="is a file, not a folder"):
        common.writable_file(str(tmp_path / "old.json" / "x.png"))
    with pytest.raises(argparse.ArgumentTypeError, match="an empty path"):
        common.writable_file("")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.json"]


@PROC
@pytest.mark.parametrize("path", ["/proc/x", "/proc/x/y/z.json", "/proc/self/x.png"])
def test_pseudo_filesystems_are_not_writable(path):
    """/proc passes os.access as root: the probe (create a file, remove it) tells."""
    with pytest.raises(argparse.ArgumentTypeError, match=r"cannot be written: /proc\S* is not writable"):
        common.writable_file(path)
    with pytest.raises(argparse.ArgumentTypeError, match="cannot be written"):
        common.writable_dir(path)


@pytest.mark.parametrize("name", ["bench_memory", "bench_memory_12000", "stress-bdf2", "a.b"])
def test_report_names(name):
    assert common.report_name(name) == name


@pytest.mark.parametrize("name, why", [
    ("", "an empty name"), ("   ", "an empty name"), ("../../../x", "path parts"), ("a/b", "path parts"),
    ("a..b", "path parts"), ("x\\y", "path parts"), (".hidden", "starts with '.'"), ("a\nb", "control characters"),
    ("x" * 201, "longer than 200 bytes"),
])
def test_bad_report_names(name, why):
    with pytest.raises(argparse.ArgumentTypeError, match="is not a report name") as err:
        common.report_name(name)
    assert why in str(err.value)


def test_size_arguments():
    assert common.strand_count("1") == 1 and common.strand_count("1000000") == 1_000_000
    for bad, msg in (("0", "is not a positive integer"), ("abc", "is not a positive integer"),
                     ("1000001", "more than 1,000,000 strands"), ("1e9", "is not a positive integer")):
        with pytest.raises(argparse.ArgumentTypeError, match=msg):
            common.strand_count(bad)
    assert common.strand_vertices("3") == 3
    with pytest.raises(argparse.ArgumentTypeError, match="is not an integer >= 3"):
        common.strand_vertices("2")
    with pytest.raises(argparse.ArgumentTypeError, match="more than 10,000 vertices in a strand"):
        common.strand_vertices("100000000")


def test_check_reports_and_fail(tmp_path, monkeypatch, capsys):
    ap = argparse.ArgumentParser(prog="x.py")
    monkeypatch.setattr(common, "ROOT", tmp_path)
    common.check_reports(ap, "r")                       # reports/ to be made: fine
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "r.json").mkdir()           # a folder where the report goes
    with pytest.raises(SystemExit) as exc:
        common.check_reports(ap, "r")
    assert exc.value.code == 2 and "x.py: error: the reports cannot be written" in capsys.readouterr().err
    (tmp_path / "reports" / "r.json").rmdir()
    (tmp_path / "reports").rmdir()
    (tmp_path / "reports").write_text("a file")
    with pytest.raises(SystemExit):
        common.check_reports(ap, "r")
    assert "reports is a file, not a folder" in capsys.readouterr().err
    monkeypatch.setattr(sys, "argv", ["/x/experiments/baselines.py"])
    assert common.fail("3 of 7 runs failed:\n  a, b") == 1
    assert capsys.readouterr().err == "baselines.py: error: 3 of 7 runs failed: a, b\n"


# -- the scripts, with the tester's bad arguments ------------------------------------------------
def script(module: str, *args, cwd: Path) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", f"experiments.{module}", *map(str, args)], cwd=cwd,
                          env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True, timeout=60)
    return proc, time.perf_counter() - t0


def assert_usage_error(proc, module: str, needle: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-3000:])
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if "error:" in ln]
    assert len(lines) == 1 and lines[0].startswith(f"{module}.py: error: "), proc.stderr
    assert needle in lines[0], lines[0]


@pytest.fixture
def run_folder(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "summary.json").write_text(json.dumps({"status": "completed"}))
    return folder


@PROC
@pytest.mark.parametrize("module, args, needle", [
    ("baselines", ["--out", "/proc/x"], "argument --out: '/proc/x': cannot be written"),
    ("contact", ["--work", "/proc/x", "--runs", "goaling_free"], "argument --work: '/proc/x': cannot be written"),
    ("contact", ["--out", "/proc/x/contact", "--runs", "goaling_free"], "argument --out: '/proc/x/contact.md'"),
    ("traced_run", ["/proc/out.json", "experiment=goaling_smoke"], "argument OUT.json: '/proc/out.json'"),
    ("scene_pictures", ["{run}", "/proc/x.png"], "argument png: '/proc/x.png': cannot be written"),
])
def test_unwritable_outputs_are_usage_errors(module, args, needle, run_folder, tmp_path):
    proc, _ = script(module, *(str(run_folder) if a == "{run}" else a for a in args), cwd=tmp_path)
    assert_usage_error(proc, module, needle)


@pytest.mark.parametrize("module, args, needle", [
    ("bench_memory", ["--report", "../../../x"], "argument --report: '../../../x' is not a report name"),
    ("bench_scale", ["--sizes", "100000000"], "argument --sizes: '100000000' is more than 1,000,000 strands"),
    ("scene_pictures", ["{run}", "{tmp}/x.xyz"], "matplotlib cannot write .xyz"),
    ("scene_pictures", ["{run}", "{run}"], "is a directory, not a file"),
    ("contact", ["--out", "{run}/summary.json/c", "--runs", "goaling_free"], "is a file, not a folder"),
    ("contact", ["--extra", "{tmp}/missing.json", "--runs", "goaling_free", "--work", "{tmp}/w", "--out", "{tmp}/c"],
     "argument --extra: "),
    ("fidelity_static", ["--vertices", "100000000"], "argument --vertices: '100000000' is more than 10,000"),
])
def test_bad_outputs_and_sizes_are_usage_errors(module, args, needle, run_folder, tmp_path):
    args = [a.replace("{run}", str(run_folder)).replace("{tmp}", str(tmp_path)) for a in args]
    proc, _ = script(module, *args, cwd=tmp_path)
    assert_usage_error(proc, module, needle)
    assert not (tmp_path / "w").exists() and not (tmp_path / "c.md").exists()


@PROC
def test_baselines_with_an_unwritable_out_runs_nothing(tmp_path):
    """Every run failed on the folder (140 tracebacks), exit 0, and the report was rewritten with
    "failed" in every cell: now exit 2 at once, nothing run, the report untouched."""
    before = {p: p.stat().st_mtime_ns for p in (REPO / "reports").glob("baselines.*")}
    proc, seconds = script("baselines", "--out", "/proc/x", cwd=tmp_path)
    assert_usage_error(proc, "baselines", "argument --out")
    assert proc.stdout == "" and seconds < 30
    assert {p: p.stat().st_mtime_ns for p in (REPO / "reports").glob("baselines.*")} == before


# -- in-process: sizes the guard refuses, failed runs --------------------------------------------
def test_bench_scale_refuses_a_size_the_guard_refuses_before_any_run(monkeypatch, capsys):
    from experiments import bench_scale

    monkeypatch.setattr("hairexp.app.guard.available_memory", lambda: 1e9)   # 10,000 x 26 vertices need 1.6 GB
    monkeypatch.setattr(bench_scale.subprocess, "run", lambda *a, **k: pytest.fail("a size ran"))
    with pytest.raises(SystemExit) as exc:
        bench_scale.main(["--sizes", "301", "10000"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "argument --sizes: 10000 strands" in err and "of memory" in err, err


def test_baselines_refuses_frames_the_guard_refuses(monkeypatch, capsys):
    from experiments import baselines

    monkeypatch.setattr(baselines, "run_scene", lambda *a, **k: pytest.fail("a scene ran"))
    with pytest.raises(SystemExit) as exc:
        baselines.main(["--experiments", "goaling", "--frames", "1000000000", "--no-report"])
    err = capsys.readouterr().err   # 1e9 steps: about 1 TB of memory and weeks of time, refused by the guard
    assert exc.value.code == 2 and "experiment goaling with --frames 1000000000" in err, err


def _scene(name: str, statuses: dict) -> dict:
    return {"experiment": name, "results": {c: {"status": s, "error": f"{c} broke"} for c, s in statuses.items()}}


@pytest.fixture
def baselines_stubbed(monkeypatch):
    from experiments import baselines

    written = []
    monkeypatch.setattr(baselines, "check_scenes", lambda *a: None)
    monkeypatch.setattr(baselines, "report", lambda scenes, wall: "md")
    monkeypatch.setattr(baselines, "write_report", lambda *a, **k: written.append(a[0]) or Path("reports/x.md"))
    monkeypatch.setattr(sys, "argv", ["/x/experiments/baselines.py"])
    return baselines, written


def test_baselines_with_every_run_failed_exits_1_and_keeps_the_report(baselines_stubbed, monkeypatch, tmp_path, capsys):
    baselines, written = baselines_stubbed
    monkeypatch.setattr(baselines, "run_scene", lambda e, f, root: _scene(e, {"free": "failed", "skinned": "not applicable"}))
    assert baselines.main(["--experiments", "goaling", "splitting", "--out", str(tmp_path)]) == 1
    assert written == []
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln]
    assert len(err) == 1 and err[0].startswith("baselines.py: error: no run completed (2 of 4 failed"), err
    assert "goaling/free: free broke" in err[0] and "left as they were" in err[0]


def test_baselines_with_some_runs_failed_writes_and_exits_1(baselines_stubbed, monkeypatch, tmp_path, capsys):
    baselines, written = baselines_stubbed
    monkeypatch.setattr(baselines, "run_scene",
                        lambda e, f, root: _scene(e, {"free": "completed", "tracking": "failed" if e == "goaling" else "completed"}))
    assert baselines.main(["--experiments", "goaling", "splitting", "--out", str(tmp_path)]) == 1
    assert written == ["baselines"]
    assert "baselines.py: error: 1 of 4 runs failed: goaling/tracking" in capsys.readouterr().err
    monkeypatch.setattr(baselines, "run_scene", lambda e, f, root: _scene(e, {"free": "completed", "skinned": "not applicable"}))
    assert baselines.main(["--experiments", "goaling", "--out", str(tmp_path)]) == 0


def test_baselines_a_bad_run_folder_is_a_failure_not_not_applicable(monkeypatch, tmp_path):
    """Only a controller that cannot drive the scene (an InputError of ``controller.*``) is "not
    applicable"; any other InputError (a run folder that is a file) fails the run."""
    from hairexp.errors import InputError

    from experiments import baselines

    def run(cfg, out):
        if baselines._name(cfg.controller.name) == "skinned":
            raise InputError("the skinned controller needs a keyframed body", "controller.name")
        raise InputError("is not a folder", str(out))

    monkeypatch.setattr(baselines, "run", run)
    res = baselines.run_scene("goaling", 6, tmp_path, only=["skinned"])["results"]
    assert res["free"]["status"] == "failed" and "is not a folder" in res["free"]["error"]
    assert res["skinned"]["status"] == "not applicable"


def test_contact_with_failed_runs(monkeypatch, tmp_path, capsys):
    from experiments import contact

    outcomes = {"stage": "completed", "barrier": "failed: RuntimeError: diverged"}
    monkeypatch.setattr(contact, "measure", lambda name, mode, *a: {"run": name, "mode": mode, "outcome": outcomes[mode]})
    monkeypatch.setattr(sys, "argv", ["/x/experiments/contact.py"])
    args = ["--runs", "goaling_free", "--work", str(tmp_path / "w"), "--out", str(tmp_path / "c")]
    assert contact.main(args) == 1
    assert "contact.py: error: 1 of 2 runs failed: goaling_free barrier" in capsys.readouterr().err
    assert len(json.loads((tmp_path / "c.json").read_text())) == 2
    outcomes["stage"] = "failed: RuntimeError: diverged"
    (tmp_path / "c.json").unlink()
    assert contact.main(args) == 3 and not (tmp_path / "c.json").exists()   # no run completed: nothing written
    outcomes.update(stage="completed", barrier="completed")
    assert contact.main(args) == 0


def test_paper_scenes_with_every_scene_failed_keeps_the_report(monkeypatch, capsys):
    from experiments import paper_scenes

    written = []
    monkeypatch.setattr(paper_scenes, "cached", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("boom")))
    monkeypatch.setattr(paper_scenes, "write_report", lambda *a, **k: written.append(a[0]))
    monkeypatch.setattr(sys, "argv", ["/x/experiments/paper_scenes.py"])
    assert paper_scenes.main(["goaling_smoke"]) == 1
    assert written == []
    assert "paper_scenes.py: error: every scene failed (goaling_smoke" in capsys.readouterr().err


def test_ablations_with_failed_runs(monkeypatch, capsys):
    from experiments import ablations

    written = []
    status = {"static": "failed", "sliding": "failed"}
    monkeypatch.setattr(ablations, "sweep", lambda scene, comp, launcher, out: [
        {"scene": scene, "comparison": comp, "value": v, "status": s, "error": "x"} for v, s in status.items()])
    monkeypatch.setattr("hairexp.app.report.write_report", lambda *a, **k: written.append(a[0]) or Path("r.md"))
    monkeypatch.setattr(sys, "argv", ["/x/experiments/ablations.py"])
    argv = ["--scenes", "goaling", "--comparisons", "targets"]
    assert ablations.main(argv) == 1 and written == []
    assert "ablations.py: error: no run completed" in capsys.readouterr().err
    status["sliding"] = "completed"
    assert ablations.main(argv) == 1 and written == ["ablations"]
    assert "ablations.py: error: 1 of 2 runs did not complete: goaling_smoke targets static (failed)" in capsys.readouterr().err
