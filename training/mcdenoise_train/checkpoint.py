"""Run files: the versioned checkpoints of the best networks (`best.pt`) and the resume
state (`state.pt`). The one module that writes and reads them (train.py, train_ms.py,
export.py, export_ms.py, ablation.py); every file is written atomically (temporary file
beside it, then `os.replace`), so an interrupted run keeps the previous complete file.

Checkpoints are dicts written with `torch.save` and read with `weights_only=True`:

Version 1, a contract-v1 pair (`save_checkpoint` / `load_checkpoint`):

    {
        "format": "mcdenoise.checkpoint",
        "version": 1,
        "variant": "full" | "nocov",
        "diffuse":  {"config": {...}, "state_dict": {...}},
        "specular": {"config": {...}, "state_dict": {...}},
        ...                # optional extra keys (step, metrics, optimizer state, ...)
    }

`config` is `DenoiserNet.config` (plain str/int values; `DenoiserNet(**config)` rebuilds
the network) and `state_dict` its `state_dict()`. Both components must have the variant's
feature count; they may differ in architecture. Extra keys are kept by `load_checkpoint`
and ignored by the exporter.

Version 2, one contract-v2 network (`save_msnet` / `load_msnet`):

    {"format": "mcdenoise.checkpoint", "version": 2,
     "config": MSNet.config, "state_dict": {...}, ...extra (step, val)}

Files that train_ms.py wrote before the format was versioned (`{"config", "state_dict",
"step", "val"}`, no "format" key) load as version 2.

The resume state (`save_state` / `load_state`) is `{"format": "mcdenoise.state",
"version": 1, ...}` plus the trainer's own keys: train.py keeps `models`, `opts` (per
component), `step`, `best`, `elapsed`; train_ms.py `model`, `opt`, `step`, `steps`,
`fitted`, `best`, `elapsed`. The data sampling is a function of the seed and the step, so
no generator state is stored. Files without the "format" key (written before) load as they
are.
"""

from __future__ import annotations

import os
from typing import Any, Mapping

import torch

from .contract import COMPONENTS, variant_for
from .files import atomic_path
from .model import DenoiserNet
from .msnet import MSNet

FORMAT = "mcdenoise.checkpoint"
VERSION = 1
MS_VERSION = 2
STATE_FORMAT = "mcdenoise.state"
STATE_VERSION = 1


def _cpu_state(net: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().cpu() for k, v in net.state_dict().items()}


def _save(obj: dict, path: str | os.PathLike) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def _check_extra(extra: Mapping[str, Any], reserved: set[str]) -> None:
    clash = reserved & extra.keys()
    if clash:
        raise ValueError(f"extra keys collide with the format: {sorted(clash)}")


def _check(d: Any, path, what: str, fmt: str, version: int) -> None:
    if not isinstance(d, dict) or d.get("format") != fmt:
        raise ValueError(f"{path}: not an mcdenoise {what} (format != {fmt!r})")
    if d.get("version") != version:
        raise ValueError(f"{path}: {what} version {d.get('version')}, expected {version}")


def _read(path: str | os.PathLike, version: int, legacy_ok: bool = False) -> dict[str, Any]:
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    legacy = isinstance(ckpt, dict) and "format" not in ckpt and {"config", "state_dict"} <= ckpt.keys()
    if not (legacy_ok and legacy):
        _check(ckpt, path, "checkpoint", FORMAT, version)
    return ckpt


def save_checkpoint(path: str | os.PathLike, models: Mapping[str, DenoiserNet], **extra: Any) -> None:
    """Write `models` ({'diffuse': net, 'specular': net}) and `extra` keys to `path`."""
    missing = [c for c in COMPONENTS if c not in models]
    if missing:
        raise ValueError(f"checkpoint needs both components; missing {missing}")
    variants = {variant_for(models[c].in_features) for c in COMPONENTS}
    if len(variants) != 1:
        raise ValueError(f"components disagree on the variant: {sorted(variants)}")
    _check_extra(extra, {"format", "version", "variant", *COMPONENTS})
    ckpt: dict[str, Any] = {"format": FORMAT, "version": VERSION, "variant": variants.pop()}
    for c in COMPONENTS:
        ckpt[c] = {"config": dict(models[c].config), "state_dict": _cpu_state(models[c])}
    ckpt.update(extra)
    _save(ckpt, path)


def load_checkpoint(path: str | os.PathLike) -> tuple[dict[str, DenoiserNet], dict[str, Any]]:
    """The networks ({'diffuse': net, 'specular': net}, on the CPU, eval mode) and the raw dict."""
    ckpt = _read(path, VERSION)
    models = {}
    for c in COMPONENTS:
        if c not in ckpt:
            raise ValueError(f"{path}: missing component {c!r}")
        net = DenoiserNet(**ckpt[c]["config"])
        net.load_state_dict(ckpt[c]["state_dict"])
        if net.variant != ckpt["variant"]:
            raise ValueError(
                f"{path}: {c} has {net.in_features} feature channels, "
                f"variant is {ckpt['variant']!r}"
            )
        models[c] = net.eval()
    return models, ckpt


def save_msnet(path: str | os.PathLike, net: MSNet, **extra: Any) -> None:
    """Write one contract-v2 network (its config and weights) and `extra` keys to `path`."""
    _check_extra(extra, {"format", "version", "config", "state_dict"})
    _save({"format": FORMAT, "version": MS_VERSION, "config": dict(net.config),
           "state_dict": _cpu_state(net), **extra}, path)


def load_msnet(path: str | os.PathLike) -> tuple[MSNet, dict[str, Any]]:
    """The network of a version-2 (or unversioned train_ms.py) checkpoint, on the CPU in
    eval mode, and the raw dict."""
    ckpt = _read(path, MS_VERSION, legacy_ok=True)
    cfg = dict(ckpt["config"])
    cfg.pop("arch", None)
    # Checkpoints written before the key existed were trained with the log pyramid.
    cfg.setdefault("specular_pyramid", "log")
    net = MSNet(**cfg)
    net.load_state_dict(ckpt["state_dict"])
    return net.eval(), ckpt


def save_state(path: str | os.PathLike, **state: Any) -> None:
    """Write a trainer's resume state (networks' and optimizers' state dicts, step, ...)."""
    _check_extra(state, {"format", "version"})
    _save({"format": STATE_FORMAT, "version": STATE_VERSION, **state}, path)


def load_state(path: str | os.PathLike, map_location: Any = "cpu") -> dict[str, Any]:
    """The resume state written by `save_state` (or by a trainer before it was versioned),
    tensors on `map_location`."""
    st = torch.load(path, map_location=map_location, weights_only=True)
    if not (isinstance(st, dict) and "format" not in st):  # else written before the format had a name
        _check(st, path, "resume state", STATE_FORMAT, STATE_VERSION)
    return st
