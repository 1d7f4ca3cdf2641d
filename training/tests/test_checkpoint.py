"""Run files (checkpoint.py): the versioned best-network checkpoints and the resume state,
their round trips, and the files written before the formats were versioned."""

import pytest
import torch

from mcdenoise_train.checkpoint import (
    load_checkpoint,
    load_msnet,
    load_state,
    save_checkpoint,
    save_msnet,
    save_state,
)
from mcdenoise_train.model import DenoiserNet
from mcdenoise_train.msnet import MSNet

SMALL = dict(ext_width=4, ext_blocks=1, enc=[6, 6, 8, 8], dec=[6, 6, 8, 8], kernel_size=5, levels=5)


def _net(seed=0) -> MSNet:
    torch.manual_seed(seed)
    return MSNet(28, **SMALL).eval()


def _inputs(net: MSNet, seed=1):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(1, 10, 16, 16, generator=g), torch.randn(1, 10, 16, 16, generator=g),
            torch.rand(1, net.in_features, 16, 16, generator=g))


def _same_outputs(a: MSNet, b: MSNet) -> bool:
    x = _inputs(a)
    with torch.no_grad():
        return all(torch.equal(p, q) for p, q in zip(a(*x), b(*x)))


def _only(tmp_path, *names):
    return sorted(p.name for p in tmp_path.iterdir()) == sorted(names)


def test_msnet_checkpoint_round_trip(tmp_path):
    net = _net()
    save_msnet(tmp_path / "best.pt", net, step=7, val={"score": -1.5})
    raw = torch.load(tmp_path / "best.pt", map_location="cpu", weights_only=True)
    assert (raw["format"], raw["version"], raw["step"], raw["val"]) == ("mcdenoise.checkpoint", 2, 7, {"score": -1.5})
    back, meta = load_msnet(tmp_path / "best.pt")
    assert back.config == net.config and not back.training and meta["step"] == 7
    assert _same_outputs(net, back)
    assert _only(tmp_path, "best.pt")  # no temporary file left
    with pytest.raises(ValueError, match="collide"):
        save_msnet(tmp_path / "x.pt", net, config={})


def test_legacy_msnet_checkpoint_loads(tmp_path):
    """train_ms.py wrote best.pt without a format key before checkpoint.py versioned it."""
    net = _net(3)
    torch.save({"config": net.config, "state_dict": {k: t.detach().cpu() for k, t in net.state_dict().items()},
                "step": 250, "val": {"score": -2.0}}, tmp_path / "best.pt")
    back, meta = load_msnet(tmp_path / "best.pt")
    assert meta["step"] == 250 and _same_outputs(net, back)


def test_checkpoint_kinds_are_told_apart(tmp_path):
    save_msnet(tmp_path / "ms.pt", _net())
    pair = {c: DenoiserNet(in_features=28, arch="kpcn", width=4, layers=2, conv_kernel=3) for c in ("diffuse", "specular")}
    save_checkpoint(tmp_path / "pair.pt", pair, step=3)
    with pytest.raises(ValueError, match="version 2, expected 1"):
        load_checkpoint(tmp_path / "ms.pt")
    with pytest.raises(ValueError, match="version 1, expected 2"):
        load_msnet(tmp_path / "pair.pt")
    models, raw = load_checkpoint(tmp_path / "pair.pt")
    assert raw["step"] == 3 and set(models) == {"diffuse", "specular"}
    torch.save({"something": 1}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not an mcdenoise checkpoint"):
        load_msnet(tmp_path / "other.pt")


def _trained(seed=0):
    net = _net(seed).train()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    out = net(*_inputs(net))
    sum(o.square().mean() for o in out).backward()
    opt.step()
    return net, opt


def test_resume_state_round_trip(tmp_path):
    net, opt = _trained()
    save_state(tmp_path / "state.pt", model=net.state_dict(), opt=opt.state_dict(), fitted=True,
               step=20, steps=100, best=float("inf"), elapsed=1.5)
    st = load_state(tmp_path / "state.pt")
    assert (st["format"], st["version"]) == ("mcdenoise.state", 1)
    assert (st["step"], st["steps"], st["fitted"], st["best"], st["elapsed"]) == (20, 100, True, float("inf"), 1.5)
    net2, _ = _trained(5)
    opt2 = torch.optim.Adam(net2.parameters(), lr=1e-3)
    net2.load_state_dict(st["model"])
    opt2.load_state_dict(st["opt"])
    assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), net2.state_dict().values()))
    s1, s2 = opt.state_dict()["state"], opt2.state_dict()["state"]
    assert s1.keys() == s2.keys() and all(torch.equal(s1[k]["exp_avg"], s2[k]["exp_avg"]) for k in s1)
    assert _only(tmp_path, "state.pt")
    with pytest.raises(ValueError, match="collide"):
        save_state(tmp_path / "state.pt", version=3)


def test_legacy_resume_state_loads(tmp_path):
    """The dicts train.py and train_ms.py saved before checkpoint.py (no format key)."""
    net, opt = _trained()
    legacy = {"model": net.state_dict(), "opt": opt.state_dict(), "fitted": False, "step": 4500, "steps": 6000,
              "best": -10.6, "elapsed": 2646.0}
    torch.save(legacy, tmp_path / "state.pt")
    st = load_state(tmp_path / "state.pt")
    assert {k: st[k] for k in ("fitted", "step", "steps", "best", "elapsed")} == \
        {k: legacy[k] for k in ("fitted", "step", "steps", "best", "elapsed")}
    torch.optim.Adam(_net().parameters(), lr=1e-3).load_state_dict(st["opt"])
    torch.save({"format": "something.else"}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not an mcdenoise resume state"):
        load_state(tmp_path / "other.pt")
