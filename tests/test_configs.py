"""Configs: every experiment and every group option composes against the schema, and the
schema rejects unknown keys, wrong types and bad choices at composition, naming the key."""

from __future__ import annotations

import dataclasses
import shutil
import typing
from enum import Enum

import pytest
from hydra.errors import HydraException
from omegaconf import OmegaConf

import hairexp.app.config  # noqa: F401  (registers the schema)
from helpers import CONF_DIR
from hairexp.app.config import Config, OnFailure, to_plain
from hairexp.app.builders import build_scene

EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))
GROUP_OPTIONS = sorted((d.name, p.stem) for d in CONF_DIR.iterdir() if d.is_dir() and d.name != "experiment"
                       for p in d.glob("*.yaml"))


def full_message(exc: BaseException) -> str:
    """The exception's text with its causes (Hydra puts the key in the chained error)."""
    parts = []
    while exc is not None:
        parts.append(str(exc))
        exc = exc.__cause__ or exc.__context__
    return "\n".join(parts)


def yaml_leaves(path, package: str = ""):
    """(dotted key, value) of every leaf a config file sets (Hydra's ``defaults`` list excluded);
    ``package`` is the node a group file lands in (none for ``# @package _global_`` files)."""
    data = OmegaConf.to_container(OmegaConf.load(path))
    data.pop("defaults", None)

    def walk(node, prefix):
        for k, v in node.items():
            if isinstance(v, dict):
                yield from walk(v, f"{prefix}{k}.")
            elif isinstance(v, list) and v and all(isinstance(e, dict) for e in v):
                for i, e in enumerate(v):   # lists of records (colliders, edits, variants)
                    yield from walk(e, f"{prefix}{k}[{i}].")
            else:
                yield f"{prefix}{k}", v

    return list(walk(data, f"{package}." if package else ""))


def assert_file_applied(cfg, path, package=""):
    plain = OmegaConf.create(to_plain(cfg))
    leaves = yaml_leaves(path, package)
    assert leaves, path
    for key, value in leaves:
        assert OmegaConf.select(plain, key) == value, f"{path.name}: {key}"


def test_there_are_experiments():
    assert {"goaling", "celia"} <= set(EXPERIMENTS)


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_composes_and_builds(hydra_conf, name, tmp_path):
    cfg = hydra_conf([f"experiment={name}"])
    assert cfg.experiment == name
    assert_file_applied(cfg, CONF_DIR / "experiment" / f"{name}.yaml")  # experiments are applied last
    strands, vertices = cfg.scene.n_strands, cfg.scene.n_vertices
    if name == "from_usd":  # needs a stage (scene.usd): a small scene in the input layout
        from usd_helpers import N_STRANDS, N_VERTICES, source_cfg, write_stage

        from hairexp.io.usd_read import stage_timing

        write_stage(tmp_path / "scene.usda", source_cfg())
        cfg.scene.usd = str(tmp_path / "scene.usda")
        cfg = stage_timing(cfg)  # frames, fps: null -> from the stage
        strands, vertices = N_STRANDS, N_VERTICES
    assert OmegaConf.is_missing(cfg, "frames") is False and cfg.frames >= 1
    plain = to_plain(cfg)  # resolves every interpolation; enums become strings
    assert plain["experiment"] == name and isinstance(plain["solver"]["on_failure"], str)
    scene = build_scene(cfg.scene)  # the experiment's scene is valid input
    assert scene.strands.n_strands == strands
    assert scene.strands.n_vertices == strands * vertices


@pytest.mark.parametrize("group,option", GROUP_OPTIONS, ids=[f"{g}={o}" for g, o in GROUP_OPTIONS])
def test_group_option_composes(hydra_conf, group, option):
    cfg = hydra_conf([f"{group}={option}"])
    assert_file_applied(cfg, CONF_DIR / group / f"{option}.yaml", package=group)


def test_overrides_are_typed(hydra_conf):
    cfg = hydra_conf(["experiment=goaling", "scene.n_strands=7", "solver.on_failure=warn", "solver.dt=0.01"])
    assert cfg.scene.n_strands == 7 and isinstance(cfg.scene.n_strands, int)
    assert cfg.solver.on_failure == OnFailure.warn
    assert cfg.solver.dt == 0.01


def enum_fields(cls=Config, prefix=""):
    """(dotted key, Enum type) of every Enum-typed field of the schema."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        if dataclasses.is_dataclass(t):
            yield from enum_fields(t, f"{prefix}{f.name}.")
        elif isinstance(t, type) and issubclass(t, Enum):
            yield f"{prefix}{f.name}", t


ENUM_CHOICES = [(key, m) for key, t in enum_fields() for m in t]


def test_schema_has_enum_choices():
    keys = {k for k, _ in ENUM_CHOICES}
    assert {"solver.on_failure", "solver.derivatives", "scene.builder", "scene.motion.interpolation"} <= keys


@pytest.mark.parametrize("key,member", ENUM_CHOICES, ids=[f"{k}={m.value}" for k, m in ENUM_CHOICES])
def test_every_enum_choice_is_accepted_by_its_documented_value(hydra_conf, key, member):
    """The value (what the YAML files, the docs and the code compare against) must be what the
    command line accepts; OmegaConf converts strings by member *name*, so they must agree."""
    cfg = hydra_conf([f"{key}={member.value}"])
    assert OmegaConf.select(cfg, key) == member
    node = to_plain(cfg)
    for part in key.split("."):
        node = node[part]
    assert node == member.value


@pytest.mark.parametrize("override,key", [
    ("scene.n_strandz=3", "scene.n_strandz"),
    ("scene.hair.air_drg=1.0", "scene.hair.air_drg"),
    ("scene.n_strands=abc", "scene.n_strands"),
    ("solver.dt=fast", "solver.dt"),
    ("solver.on_failure=bogus", "solver.on_failure"),
    ("scene.motion.interpolation=quadratic", "scene.motion.interpolation"),
    ("logging.rerun=maybe", "logging.rerun"),
])
def test_bad_override_fails_at_compose_naming_the_key(hydra_conf, override, key):
    with pytest.raises(HydraException) as info:
        hydra_conf(["experiment=goaling", override])
    assert key in full_message(info.value)


def test_unknown_experiment_fails(hydra_conf):
    with pytest.raises(HydraException, match="experiment/nope"):
        hydra_conf(["experiment=nope"])


def test_typo_inside_an_experiment_file_fails(tmp_path):
    """The schema checks the YAML files too, not only the command line."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    conf = tmp_path / "conf"
    shutil.copytree(CONF_DIR, conf)
    text = (conf / "experiment" / "goaling.yaml").read_text()
    assert "  n_vertices: 20\n" in text
    (conf / "experiment" / "typo.yaml").write_text(text.replace("  n_vertices: 20\n", "  n_vertice: 20\n"))
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
            compose(config_name="config", overrides=["experiment=goaling"])  # the copy itself is fine
            with pytest.raises(HydraException) as info:
                compose(config_name="config", overrides=["experiment=typo"])
    finally:
        GlobalHydra.instance().clear()
    assert "n_vertice" in full_message(info.value)


@pytest.mark.parametrize("launcher,key,value", [(None, "n_jobs", 2), ("submitit_local", "timeout_min", None),
                                                ("submitit_slurm", "partition", "cpu")])
def test_sweep_launchers_compose(launcher, key, value):
    """The default -m launcher is joblib with 2 jobs; submitit_local and submitit_slurm replace
    it whole (a launcher-specific key in the primary config broke them before)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    over = ["experiment=goaling"]
    if launcher:
        over.append(f"hydra/launcher={launcher}")
    if launcher == "submitit_slurm":
        over.append("hydra.launcher.partition=cpu")
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="config", overrides=over, return_hydra_config=True)
    finally:
        GlobalHydra.instance().clear()
    assert key in cfg.hydra.launcher
    if value is not None:
        assert cfg.hydra.launcher[key] == value


def test_compositions_share_the_config_store_without_changing_it():
    """Hydra's repository copies share the ConfigStore (``config._share_config_store``: --help
    listed the groups through 80 deep copies of the schema).  Sharing is safe only if composing
    never writes into the store: its schema nodes are the same after compositions with overrides,
    a refused one included, and a composition after them equals one made before."""
    import copy

    from hydra.core.config_store import ConfigStore

    from hairexp.app.config import compose_config

    cs = ConfigStore.instance()
    assert copy.deepcopy(cs) is cs

    def snapshot(node):
        return {k: snapshot(v) if isinstance(v, dict) else OmegaConf.to_yaml(v.node) for k, v in node.items()}

    before = snapshot(cs.repo)
    first = OmegaConf.to_yaml(compose_config(["experiment=goaling_smoke"]))
    compose_config(["experiment=splitting_smoke", "solver.dt=0.02", "scene.n_strands=7", "controller=free"])
    with pytest.raises(Exception):
        compose_config(["experiment=goaling_smoke", "solver.dt=fast"])
    assert snapshot(cs.repo) == before
    assert OmegaConf.to_yaml(compose_config(["experiment=goaling_smoke"])) == first


@pytest.mark.parametrize("name", [n for n in EXPERIMENTS if n != "from_usd"])
def test_every_variant_of_an_experiment_passes_the_run_checks(hydra_conf, name):
    """What ``python -m hairexp experiment=<name>`` checks before its first step, for every
    variant (``_checked_variants``: ``check_config`` and the judge): a check made stricter (the
    roots' path through the colliders, session of 2026-12-07) must not refuse a shipped scene.
    ``from_usd`` needs a stage (``test_experiment_composes_and_builds`` builds one)."""
    from hairexp.app.experiment import _checked_variants

    cfg = hydra_conf([f"experiment={name}"])
    if not cfg.variants:
        from hairexp.app.assemble import check_config

        check_config(cfg)
        return
    names, vcfgs = _checked_variants(cfg)
    assert len(names) == len(cfg.variants) == len(vcfgs) >= 1
