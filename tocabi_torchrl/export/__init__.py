"""Export a trained policy: ONNX (optionally TorchScript) plus the JSON I/O contract (``docs/deploying.md``).

    python -m tocabi_torchrl.export --checkpoint RUN_DIR_OR_PT --out policy.onnx [--torchscript] [--overwrite]

Needs the ``export`` extra (``onnx``); the runtime that runs the result is :mod:`tocabi_torchrl.runtime`.
"""

from .onnx_export import ExportError, ExportResult, LoadedPolicy, export_policy, load_policy

__all__ = ["ExportError", "ExportResult", "LoadedPolicy", "export_policy", "load_policy"]
