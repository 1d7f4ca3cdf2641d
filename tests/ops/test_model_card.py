"""The model card's checksum table names every shipped model file, and each digest is the
file's: a model exported again without the card following fails here."""

from __future__ import annotations

import hashlib
import re

from conftest import ROOT

MODELS = ROOT / "models"


def card_digests() -> dict[str, str]:
    text = (MODELS / "MODEL_CARD.md").read_text()
    return {m[1]: m[2] for m in re.finditer(r"^\| ([\w./-]+\.(?:onnx|pt)) \| ([0-9a-f]{64}) \|$", text, re.M)}


def test_every_shipped_file_has_its_digest_in_the_card():
    digests = card_digests()
    shipped = {p.relative_to(MODELS).as_posix() for p in MODELS.rglob("*.onnx")}
    assert shipped <= digests.keys(), f"not in the card: {sorted(shipped - digests.keys())}"
    for name, digest in digests.items():
        path = MODELS / name
        assert path.is_file(), f"the card names {name}, which is not there"
        assert hashlib.sha256(path.read_bytes()).hexdigest() == digest, f"{name}: the card's digest is not the file's"
