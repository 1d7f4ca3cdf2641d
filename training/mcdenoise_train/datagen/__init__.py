"""Training-data generator: procedural scenes rendered with Mitsuba 3 by our own path tracer,
and the same scenes with Blender Cycles.

The generator writes frames in the layout of docs/frame-layout.md: total colour, its
diffuse/specular split, albedo, normal, depth, the light transport covariance feature
and the variance of every buffer (written by `mcdenoise_train.exr`). docs/training-data.md
describes the method.

# Layout

- `backend`    -- picks the Mitsuba variant (`llvm_ad_rgb` by default, `cuda_ad_rgb` with a flag)
- `textures`   -- procedural textures (numpy) used as albedo and roughness maps
- `meshes`     -- generated triangle meshes (displaced spheres, tori) with curvature attributes
- `scenes`     -- the seedable scene families and the named scenes (Cornell box, shadow test, ...)
- `covariance` -- 4x4 light-field covariance operators (Belcour et al.) on 2x2 blocks
- `integrator` -- the path tracer: split radiance, features, per-vertex covariance records
- `render`     -- sample accumulation, variance of the mean, the spp ladder, frame assembly
- `dataset`    -- the N-scene driver (CLI, workers, manifest, resume, train/validation split, test set)
- `cycles`     -- Cycles frames: runs `cycles_worker` in bpy's environment, assembles buffers and variances
- `cycles_worker` -- builds a spec through bpy and renders it (runs inside the bpy environment)
- `fixtures`   -- regenerates the committed test frames under tests/fixtures/frames
- `figures`    -- the pictures of docs/training-data.md
"""
