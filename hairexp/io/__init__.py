"""Exchange with other tools.

* ``usd_layout``: the prim layout of hairexp's USD stages and the matrix conversions shared by
  the reader and the writer (README "USD scenes");
* ``usd_read``: a scene and its guide animation from a USD stage (``experiment=from_usd``);
* ``usd_write``: a scene in that input layout (``write_scene_usd``) and a run's
  ``result.usdc`` or ``result.usda`` (``write_result_usd``);
* ``export_scene``: the entry point ``python -m hairexp.io.export_scene <out.usda> [overrides]``,
  which writes a config's scene and guides as a USD stage (the export is hairexp/app/export_scene.py).

pxr (usd-core) is imported by these modules only; the rest of hairexp imports them lazily.
"""
