"""plantdyn: step responses of industrial plants from normal operating data.

Layers (imports point down only): core numeric modules in ``pipeline`` (numpy/scipy
only, pure), adapters in ``pipeline.adapters`` (files, YAML, Rerun, storage),
composition in ``pipeline.jobs``, orchestration in the ``flows`` package.
"""

__version__ = "0.1.0"
