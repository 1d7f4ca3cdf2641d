"""The pictures of docs/training-data.md.

    python -m mcdenoise_train.datagen.figures --out ../docs/img [--spp 512]

- `datagen-covariance.png`: colour next to the covariance buffer for scenes with sharp
  shadows, glossy highlights and a caustic;
- `datagen-shadow-edge.png`: the shadow-edge test scene, its covariance, and a profile
  across the edge;
- `datagen-split.png`: colour = diffuse + specular, with albedo, normal and depth;
- `datagen-scenes.png`: a sample of generated scenes (seeds 0-11);
- `datagen-families.png`: a contact sheet of every scene family (`--only families`):
  noisy input, reference, albedo, normal and covariance of one scene each.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from .backend import set_variant


def tonemap(rgb):
    rgb = np.maximum(rgb, 0.0)
    return np.clip(rgb / (1.0 + rgb), 0.0, 1.0) ** (1.0 / 2.2)


def _rgb(ch, prefix=""):
    if prefix:
        return np.stack([ch[f"{prefix}.R"], ch[f"{prefix}.G"], ch[f"{prefix}.B"]], -1)
    return np.stack([ch["R"], ch["G"], ch["B"]], -1)


def _render(spec, w, h, spp, seed=1):
    from . import render, scenes
    from .integrator import Options

    scene = scenes.build(spec, w, h)
    pa = scenes.camera_params(spec, w)["pixel_angle"]
    m = render.render(scene, w, h, spp, seed, pa, Options())
    return render.frame_channels(m)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("../docs/img"))
    p.add_argument("--spp", type=int, default=512)
    p.add_argument("--size", type=int, default=192)
    p.add_argument("--only", choices=("all", "families"), default="all")
    p.add_argument("--families", default=None, help="families of the contact sheet (default: all)")
    p.add_argument("--seed", type=int, default=1, help="seed of each family's scene on the contact sheet")
    p.add_argument("--renderer", choices=("mitsuba", "cycles"), default="mitsuba", help="renderer of the contact sheet")
    args = p.parse_args(argv)
    set_variant()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from . import scenes

    args.out.mkdir(parents=True, exist_ok=True)
    S = args.size
    if args.only == "families":
        families = args.families.split(",") if args.families else list(scenes.KINDS)
        name = "datagen-families.png" if args.renderer == "mitsuba" else "datagen-families-cycles.png"
        contact_sheet(plt, families, args.seed, 128, 16, args.spp, args.out / name, args.renderer)
        return 0

    # colour next to covariance
    specs = [("caustic_test", scenes.caustic_test()), ("cornell(5)", scenes.cornell(5)),
             ("open(4)", scenes.generate(4, "open")), ("room(3)", scenes.generate(3, "room"))]
    fig, ax = plt.subplots(len(specs), 2, figsize=(6.4, 3.2 * len(specs)))
    for i, (label, spec) in enumerate(specs):
        ch, meta = _render(spec, S, S, args.spp)
        ax[i, 0].imshow(tonemap(_rgb(ch)))
        ax[i, 0].set_title(f"{label}: colour, {args.spp} spp", fontsize=9)
        im = ax[i, 1].imshow(ch["covariance"], cmap="inferno", vmin=0, vmax=1)
        ax[i, 1].set_title(f"covariance (scale {meta['covariance_scale']:.2f})", fontsize=9)
        for a in ax[i]:
            a.axis("off")
    fig.colorbar(im, ax=ax[:, 1], shrink=0.3)
    fig.savefig(args.out / "datagen-covariance.png", dpi=80, bbox_inches="tight")
    plt.close(fig)
    print("datagen-covariance.png", file=sys.stderr)

    # shadow edge
    ch, meta = _render(scenes.shadow_test(), 128, 128, args.spp)
    fig, ax = plt.subplots(1, 3, figsize=(11, 3.4))
    ax[0].imshow(tonemap(_rgb(ch)))
    ax[0].set_title("shadow_test: colour", fontsize=9)
    ax[1].imshow(ch["covariance"], cmap="inferno", vmin=0, vmax=1)
    ax[1].set_title("covariance", fontsize=9)
    for a in ax[:2]:
        a.axis("off")
    rows = slice(16, 112)
    x = np.arange(128) + 0.5
    ax[2].plot(x, ch["G"][rows].mean(0) / ch["G"][rows].max(), label="radiance (normalised)")
    ax[2].plot(x, ch["covariance"][rows].mean(0), label="covariance")
    ax[2].axvline(scenes.shadow_test_edge_column(128), color="gray", ls=":", label="shadow edge (geometry)")
    ax[2].set_xlabel("image column")
    ax[2].set_title("mean over rows 16-111", fontsize=9)
    ax[2].legend(fontsize=7)
    fig.savefig(args.out / "datagen-shadow-edge.png", dpi=80, bbox_inches="tight")
    plt.close(fig)
    print("datagen-shadow-edge.png", file=sys.stderr)

    # split and features
    ch, _ = _render(scenes.caustic_test(), S, S, args.spp // 2)
    panels = [("colour", tonemap(_rgb(ch))), ("diffuse", tonemap(_rgb(ch, "diffuse"))),
              ("specular", tonemap(_rgb(ch, "specular"))), ("albedo", np.clip(_rgb(ch, "albedo"), 0, 1)),
              ("normal", np.clip(_rgb(ch, "normal") * 0.5 + 0.5, 0, 1)),
              ("depth", ch["depth.Z"] / max(ch["depth.Z"].max(), 1e-6))]
    fig, ax = plt.subplots(2, 3, figsize=(9, 6))
    for a, (t, img) in zip(ax.ravel(), panels):
        a.imshow(img, cmap="gray" if img.ndim == 2 else None)
        a.set_title(t, fontsize=9)
        a.axis("off")
    fig.savefig(args.out / "datagen-split.png", dpi=80, bbox_inches="tight")
    plt.close(fig)
    print("datagen-split.png", file=sys.stderr)

    # a sample of generated scenes
    fig, ax = plt.subplots(3, 4, figsize=(10, 7.8))
    for s, a in enumerate(ax.ravel()):
        spec = scenes.generate(s)
        ch, _ = _render(spec, 128, 128, 64)
        a.imshow(tonemap(_rgb(ch)))
        a.set_title(spec["name"], fontsize=8)
        a.axis("off")
    fig.savefig(args.out / "datagen-scenes.png", dpi=72, bbox_inches="tight")
    plt.close(fig)
    print("datagen-scenes.png", file=sys.stderr)
    return 0


def contact_sheet(plt, families, seed, size, spp, ref_spp, path, renderer="mitsuba"):
    """One row per family: noisy input, reference (both exposed by the same factor, from
    the reference), albedo, normal, covariance (of the noisy frame; Mitsuba only)."""
    from . import cycles, scenes

    cols = ("noisy", "reference", "albedo", "normal") + (("covariance",) if renderer == "mitsuba" else ())
    fig, ax = plt.subplots(len(families), len(cols), figsize=(2.0 * len(cols), 2.1 * len(families)), squeeze=False)
    for r, fam in enumerate(families):
        spec = scenes.generate(seed, fam)
        if renderer == "cycles":
            res, _ = cycles.render_frames(spec, size, size, [spp], ref_spp, seed)
            noisy, ref = res[spp][0], res["ref"][0]
        else:
            noisy, _ = _render(spec, size, size, spp, seed=1)
            ref, _ = _render(spec, size, size, ref_spp, seed=1 << 20)
        lum = 0.2126 * ref["R"] + 0.7152 * ref["G"] + 0.0722 * ref["B"]
        k = 0.5 / max(float(np.percentile(lum, 90)), 1e-6)
        panels = [tonemap(k * _rgb(noisy)), tonemap(k * _rgb(ref)), np.clip(_rgb(noisy, "albedo"), 0, 1),
                  np.clip(_rgb(noisy, "normal") * 0.5 + 0.5, 0, 1)] + ([noisy["covariance"]] if "covariance" in noisy else [])
        for c, img in enumerate(panels):
            ax[r, c].imshow(img, cmap="inferno" if img.ndim == 2 else None, vmin=0, vmax=1)
            ax[r, c].set_xticks([])
            ax[r, c].set_yticks([])
            if r == 0:
                ax[r, c].set_title(f"{cols[c]}" + (f" {spp} spp" if c == 0 else f" {ref_spp} spp" if c == 1 else ""),
                                   fontsize=8)
        ax[r, 0].set_ylabel(f"{spec['name']}\n(exposure x{k:.2g})", fontsize=7)
        print(spec["name"], file=sys.stderr, flush=True)
    fig.savefig(path, dpi=72, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
