"""The app layer: the only layer that reads the config.  The Python API of a run:

    from hairexp.app import assemble, compose_config

    run = assemble(compose_config(["experiment=goaling_smoke", "variants=[]", "controller=tracking"]))
    for step, frame, state, info in run.steps():
        ...

``compose_config`` composes conf/ as the command line does; ``assemble`` builds the scene,
guides, controller and simulator (hairexp/app/assemble.py); ``run_folder`` runs the whole
experiment into a run folder as ``python -m hairexp`` does (README "Run folder").
"""

from hairexp.app import startup

startup.install()   # python -m hairexp: a signal during the imports below is one line, exit 130 / 143

from hairexp.app.assemble import Run, assemble, assemble_scene  # noqa: E402
from hairexp.app.config import compose_config, to_plain  # noqa: E402
from hairexp.app.experiment import run_experiment as run_folder  # noqa: E402

__all__ = ["Run", "assemble", "assemble_scene", "compose_config", "run_folder", "to_plain"]
