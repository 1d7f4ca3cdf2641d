"""Blender: denoise every frame Blender writes during an animation render with mcdenoise.

    MCDENOISE_SERVER=http://mcdenoise.farm:8080 MCDENOISE_TOKEN=... \
      blender -b shot.blend -P examples/blender/denoise_handler.py -a

A `render_write` handler (called after each frame file is written) hands the frame to
examples/farm/denoise_hook.py on a background thread, so Blender renders the next frame
meanwhile; `render_complete` waits for the outstanding frames and prints a summary. The
denoised frame is written next to the rendered one, named by the hook's default output
pattern (`shot_0001.exr` -> `shot_denoised_0001.exr`, `0001.exr` -> `denoised.0001.exr`;
see denoise_hook.py), and the hook's client follows each job through its events.

The output must be a multilayer OpenEXR that the daemon can read (docs/frame-layout.md):
either the canonical layout, or Cycles' own passes with the Diffuse Direct/Indirect/Color
passes and the denoising data passes enabled in the view layer (the daemon derives the
diffuse/specular split from them and takes the missing variances as 0). A render without
them is refused (422, missing channels named in Blender's console).
"""

import os
import sys
from concurrent.futures import ThreadPoolExecutor

import bpy

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "farm"))
import denoise_hook  # noqa: E402  (also puts clients/python on the path)

_client = denoise_hook.mc.Client(
    os.environ.get("MCDENOISE_SERVER", "http://127.0.0.1:8080"), token=os.environ.get("MCDENOISE_TOKEN")
)
_pool = ThreadPoolExecutor(max_workers=2)
_pending = []


def _on_write(scene, *_):
    path = bpy.path.abspath(scene.render.frame_path(frame=scene.frame_current))
    if path.lower().endswith(".exr"):
        _pending.append((path, _pool.submit(denoise_hook.denoise_frame, path, _client, label=scene.name)))


def _on_complete(*_):
    failed = 0
    for path, fut in _pending:
        try:
            fut.result()
        except Exception as e:  # report every frame, keep Blender's exit status
            failed += 1
            print(f"mcdenoise: {path}: {e}", file=sys.stderr)
    print(f"mcdenoise: {len(_pending) - failed} of {len(_pending)} frames denoised", file=sys.stderr)
    _pending.clear()


bpy.app.handlers.render_write.append(_on_write)
bpy.app.handlers.render_complete.append(_on_complete)
bpy.app.handlers.render_cancel.append(_on_complete)
