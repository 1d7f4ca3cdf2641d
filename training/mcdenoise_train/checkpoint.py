"""Training checkpoints: one file holds the diffuse and specular networks of one variant.

Format (a dict written with `torch.save`, readable with `weights_only=True`):

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
"""

from __future__ import annotations

import os
from typing import Any, Mapping

import torch

from .contract import COMPONENTS, variant_for
from .model import DenoiserNet

FORMAT = "mcdenoise.checkpoint"
VERSION = 1


def save_checkpoint(path: str | os.PathLike, models: Mapping[str, DenoiserNet], **extra: Any) -> None:
    """Write `models` ({'diffuse': net, 'specular': net}) and `extra` keys to `path`."""
    missing = [c for c in COMPONENTS if c not in models]
    if missing:
        raise ValueError(f"checkpoint needs both components; missing {missing}")
    variants = {variant_for(models[c].in_features) for c in COMPONENTS}
    if len(variants) != 1:
        raise ValueError(f"components disagree on the variant: {sorted(variants)}")
    reserved = {"format", "version", "variant", *COMPONENTS} & extra.keys()
    if reserved:
        raise ValueError(f"extra keys collide with the format: {sorted(reserved)}")
    ckpt: dict[str, Any] = {"format": FORMAT, "version": VERSION, "variant": variants.pop()}
    for c in COMPONENTS:
        ckpt[c] = {
            "config": dict(models[c].config),
            "state_dict": {k: v.detach().cpu() for k, v in models[c].state_dict().items()},
        }
    ckpt.update(extra)
    torch.save(ckpt, path)


def load_checkpoint(path: str | os.PathLike) -> tuple[dict[str, DenoiserNet], dict[str, Any]]:
    """The networks ({'diffuse': net, 'specular': net}, on the CPU, eval mode) and the raw dict."""
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise ValueError(f"{path}: not an mcdenoise checkpoint (format != {FORMAT!r})")
    if ckpt.get("version") != VERSION:
        raise ValueError(f"{path}: checkpoint version {ckpt.get('version')}, expected {VERSION}")
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
