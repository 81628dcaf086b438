"""The network, streaming and offline estimation, the classical box-fit row.

The public names below load their module on first use: most of them need torch, while
:mod:`seqshape.model.smooth` and :mod:`seqshape.model.heading` are numpy-only and used by
torch-free code (the labeller's modes without a network), which must not pay for torch.
"""

import importlib

_MODULE_OF = {
    "MODEL_PRESETS": "config", "ModelConfig": "config", "get_model_config": "config",
    "Estimate": "estimator", "Estimator": "estimator", "build_model": "estimator",
    "read_model_file": "estimator", "HeadingConfig": "heading", "PointEncoder": "network",
    "ShapePoseNet": "network", "OfflineConfig": "offline", "OfflineEstimator": "offline",
    "estimate_track": "offline",
}

__all__ = sorted(_MODULE_OF)


def __getattr__(name: str):  # lazy: torch (module docstring)
    if name not in _MODULE_OF:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_MODULE_OF[name]}"), name)


def __dir__() -> list[str]:
    return sorted({*globals(), *_MODULE_OF})
