"""Synthetic ground truth: analytic volumes, a reference volume renderer and the capture protocol.

``catalog.scene_catalog()`` lists the scenes; ``writer.write_scene`` renders one into a dataset
(``visnerf make-scene``). Modules: ``fields`` (analytic scalar fields), ``transfer_function`` (TFs
and the TF-1 / TF-2 schemes), ``raymarch`` and ``reference_renderer`` (DVR and IR),
``protocol`` (icosphere views, test path), ``contact_sheet``.
"""
