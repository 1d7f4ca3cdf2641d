"""Regenerate the committed test frames (tests/fixtures/frames, see its README).

    python -m mcdenoise_train.datagen.fixtures --out ../tests/fixtures/frames

Writes, for the engine's and the daemon's tests:

- `cornell-spp8.exr`, `cornell-ref.exr`: Cornell-like box (scene `cornell(5)`: glossy
  sphere, box), 64x64, 8 spp and a 2048-spp reference, every channel with covariance;
- `cornell-nocov-spp8.exr`: the same 8-spp frame without the covariance pair (the
  `nocov` model path);
- `caustic-spp8.exr`, `caustic-ref.exr`: open scene with a glass sphere, a glossy gold
  torus and a small light (sharp shadows, highlights, caustics), 96x64 (not square);
- `shadow-spp8.exr`, `shadow-ref.exr`: the shadow-edge test scene, 64x64.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .backend import set_variant

FIXTURES = {
    # name: (scene factory name, width, height, noisy spp, reference spp, seed)
    "cornell": ("cornell5", 64, 64, 8, 2048, 11),
    "caustic": ("caustic_test", 96, 64, 8, 2048, 12),
    "shadow": ("shadow_test", 64, 64, 8, 1024, 13),
}


def _spec(kind):
    from . import scenes

    if kind == "cornell5":
        s = scenes.cornell(5)
        s["name"] = "cornell"
        return s
    return scenes.NAMED[kind]()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("../tests/fixtures/frames"))
    p.add_argument("--variant", default=None)
    args = p.parse_args(argv)
    set_variant(args.variant)
    from .. import exr
    from . import render, scenes
    from .integrator import Options

    opts = Options()
    for name, (kind, w, h, spp, ref_spp, seed) in FIXTURES.items():
        spec = _spec(kind)
        scene = scenes.build(spec, w, h)
        pa = scenes.camera_params(spec, w)["pixel_angle"]
        base = {"scene": spec["name"], "width": w, "height": h, "fixture": name}
        m = render.render(scene, w, h, spp, seed << 12, pa, opts)
        ch, meta = render.frame_channels(m)
        exr.write_frame(args.out / f"{name}-spp{spp}.exr", ch, {**meta, **base})
        if name == "cornell":
            nocov = {k: v for k, v in ch.items() if not k.startswith("covariance")}
            meta_nc = {k: v for k, v in meta.items() if k != "covariance_scale"}
            exr.write_frame(args.out / f"{name}-nocov-spp{spp}.exr", nocov, {**meta_nc, **base})
        r = render.render(scene, w, h, ref_spp, (seed << 12) + 2048, pa, opts)
        ch, meta = render.frame_channels(r)
        exr.write_frame(args.out / f"{name}-ref.exr", ch, {**meta, **base, "reference": True})
        print(f"{name}: {w}x{h}, {spp} spp + {ref_spp}-spp reference", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
