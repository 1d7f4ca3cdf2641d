"""Mitsuba variant selection.

Everything in `datagen` runs on `llvm_ad_rgb` (CPU, vectorised through LLVM) unless told
otherwise; `cuda_ad_rgb` runs the same code on a GPU. The LLVM backend needs LLVM >= 16:
Debian's default LLVM 15 aborts inside Dr.Jit, so when the library is not found by
itself we point Dr.Jit at libLLVM 19 (installed by scripts/setup).
"""

from __future__ import annotations

import glob
import os

DEFAULT_VARIANT = "llvm_ad_rgb"
_LLVM_CANDIDATES = (
    "/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/llvm-19/lib/libLLVM.so.1",
    "/usr/lib/llvm-19/lib/libLLVM-19.so",
)


def _point_drjit_at_llvm19() -> None:
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    for path in _LLVM_CANDIDATES + tuple(sorted(glob.glob("/usr/lib/*/libLLVM*.so.19*"))):
        if os.path.exists(path):
            os.environ["DRJIT_LIBLLVM_PATH"] = path
            return


def set_variant(variant: str | None = None):
    """Select the Mitsuba variant (default `llvm_ad_rgb`, or $MCDENOISE_MI_VARIANT) and return `mitsuba`."""
    variant = variant or os.environ.get("MCDENOISE_MI_VARIANT") or DEFAULT_VARIANT
    if variant.startswith("llvm"):
        _point_drjit_at_llvm19()
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi
