"""torch, an optional dependency: the biological front end and TV depth need it, the camera pipeline does not.

The camera pipeline (footage readers, DIS/Farnebäck flow, receptive fields, readout, ratio and
parallax depth) runs on numpy, SciPy and OpenCV; the photoreceptor lattice, the EMDs, the
neurons, the compound eye, virtual electrophysiology and TV depth run on torch, installed by the
``bio`` extra (``pip install 'lobula[bio]'``).

Modules that compute with torch bind the name ``torch`` with ``from lobula._optional import torch``:
a stand-in that imports torch on its first attribute access, so importing such a module for
its configuration dataclasses or constants (``lobula.config`` needs the EMD front end's) costs
nothing and needs no torch; a module that touches torch while it loads (a default argument such
as ``dtype=torch.float32``) loads torch then. Without torch the first access raises
:class:`MissingExtraError`, whose one-line message names the extra; the command line prints it
without a traceback.
"""
from __future__ import annotations

import sys

__all__ = ["BIO_INSTALL", "MissingExtraError", "require_torch", "optional_torch", "is_tensor", "torch_device",
           "torch"]

#: how to install what the biological front end needs
BIO_INSTALL = "pip install 'lobula[bio]'"


class MissingExtraError(ImportError):
    """An optional dependency is not installed; the message says what needs it and how to install it."""


def require_torch(what: str = "this") -> object:
    """The torch module, imported now.

    what: what needs torch, for the message (e.g. "the EMD front end"). Raises
    :class:`MissingExtraError` (an ImportError, ``name == "torch"``) when torch is not
    installed; a torch that is installed but fails to load raises its own error.
    """
    try:
        import torch
    except ModuleNotFoundError as exc:
        if exc.name != "torch":
            raise
        raise MissingExtraError(f"{what} needs torch, which is not installed: {BIO_INSTALL}", name="torch") from None
    return torch


def torch_device(device: str, what: str = "--device") -> str:
    """``device`` (a torch device name) when this machine has it; else ValueError naming ``what``.

    Only cpu and cuda devices are taken: the TV solver and the biological front end run on those. Called
    before a run, so that a device a run cannot use is refused before its work, not after it.
    """
    torch = require_torch(f"{what} {device}")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"{what} {device!r} is not a torch device; use cpu or cuda") from None
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"{what} {device}: only cpu and cuda devices are supported")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"{what} {device}: torch {torch.__version__} sees no CUDA device on this machine; "
                         f"use {what} cpu")
    return device


def optional_torch():
    """The torch module when it is installed (imported now), else None: for settings such as thread
    counts that matter only where torch runs."""
    try:
        return require_torch()
    except MissingExtraError:
        return None


def is_tensor(a) -> bool:
    """Whether ``a`` is a torch tensor, without importing torch (only a caller that has torch can pass one)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(a, torch.Tensor)


class _LazyTorch:
    """Stands for the torch module and imports it on first attribute access (see the module docstring).

    Each attribute is looked up once and then kept on the instance, so later accesses
    (``torch.as_tensor`` in a per-frame loop) cost what a module attribute costs.
    """

    def __getattr__(self, name: str):
        # copy, pickle and inspect probe dunders (__deepcopy__, __wrapped__): they see the stand-in, not torch
        if name.startswith("__") and name.endswith("__") and name != "__version__":
            raise AttributeError(name)
        value = getattr(require_torch(), name)
        self.__dict__[name] = value
        return value

    def __repr__(self) -> str:
        loaded = "loaded" if "torch" in sys.modules else "not loaded yet"
        return f"<torch, imported on first use ({loaded})>"


#: torch, imported on first use (``from lobula._optional import torch``)
torch = _LazyTorch()
