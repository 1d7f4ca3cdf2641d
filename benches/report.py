"""Writes docs/results.md from the measurements under docs/results/: `make bench` (speed.json,
oidn.json, paired.json) and `make eval` (val/ and test/: results.md, quality.png, crops/). Each target
reruns this script, so the page always shows the latest of both.

    python benches/report.py [--results docs/results] [--out docs/results.md]
"""

import argparse
import json
from pathlib import Path

SPEED_CMD = "make bench"
EVAL_CMD = "make eval"


def conditions(machine: dict) -> list[str]:
    """What else ran on the machine: the 1-minute load average before and after the run, and
    a note recorded with the measurements (`conditions` in speed.json) when there is one."""
    out = []
    if "loadavg_start" in machine:
        out.append(f"Load average (1 min) {machine['loadavg_start']:.1f} before and {machine['loadavg_end']:.1f} after "
                   f"the run, on {machine['threads']} threads.")
    if machine.get("conditions"):
        out.append(machine["conditions"])
    if out:
        out.append("")
    return out


def device_words(engine: dict) -> str:
    """Where the bench's networks ran (`device` of its engine section; older runs: the CPU
    provider)."""
    device = engine.get("device", "cpu")
    if device == "openvino" and engine.get("openvino_via") == "runtime":
        return ("the networks through OpenVINO's runtime, driven directly (`--device auto` on this CPU with "
                "AVX512-BF16, which OpenVINO's ONNX Runtime plugin does not serve: bfloat16); \"ONNX Runtime "
                "alone\" below is OpenVINO alone")
    if device == "openvino":
        return ("the networks through OpenVINO's execution provider (`--device auto` on this CPU with native "
                "bfloat16)")
    return f"the networks on `{device}` (ONNX Runtime's CPU provider, float32)" if device == "cpu" else \
        f"the networks on `{device}`"


def speed_section(speed: dict, oidn: dict | None) -> list[str]:
    m, g, e, d = speed["machine"], speed["gemm_ceiling"], speed["engine"], speed["daemon"]
    st = e["engine_stages_s"]
    total = e["engine_with_io_s"]
    out = [
        "## Speed",
        "",
        f"Machine: {m['cpu'] or 'unknown CPU'}, {m['threads']} threads, ONNX Runtime {m['ort_version']}; "
        f"{device_words(e)}. "
        f"Produced by `{SPEED_CMD}` (benches/speed.rs, benches/oidn_speed.py); every ratio below compares "
        "figures measured in the same run.",
        "",
        *conditions(m),
        "### Ceilings",
        "",
        "| measure | GFLOP/s |",
        "|---|---|",
        f"| FP32 GEMM ({g['n']}³ MatMul through ONNX Runtime), {g['threads']} threads | {g['gflops']:.1f} |",
        f"| FP32 GEMM, 1 thread | {g['gflops_1_thread']:.1f} |",
        f"| ONNX Runtime alone, shipped `{e['variant']}` models on the {e['width']}×{e['height']} frame's tiles "
        f"| {e['ort_alone_gflops']:.1f} ({100 * e['ort_alone_vs_gemm_ceiling']:.0f} % of GEMM) |",
        "",
        f"FLOPs are the models' own count (contract metadata `flops_per_pixel`) times the frame's pixels, "
        f"{e['flops_per_frame'] / 1e9:.2f} GFLOP per frame; the halo each tile computes beyond its core "
        "is work the count leaves out.",
        "",
        f"### Engine, {e['width']}×{e['height']}, tile {e['tile']}, {e['threads']} threads (median of {e['runs']})",
        "",
        "| stage | seconds | share |",
        "|---|---|---|",
    ]
    for k in ("decode", "preprocess", "inference", "reconstruction", "encode"):
        out.append(f"| {k} | {st[k]:.3f} | {100 * st[k] / total:.1f} % |")
    out += [
        f"| **engine** (preprocess, inference, reconstruction: `Engine::denoise`) | **{e['engine_s']:.3f}** | |",
        f"| **with EXR decode and encode** | **{total:.3f}** | |",
        "",
        f"- ONNX Runtime alone on the same tiles: {e['ort_alone_s']:.3f} s; the engine reaches "
        f"**{100 * e['engine_vs_ort_alone']:.0f} %** of its throughput, "
        f"{100 * e['engine_with_io_vs_ort_alone']:.0f} % counting the EXR decode and encode (which the daemon does "
        "outside the engine).",
        f"- Engine: {e['engine_gflops']:.1f} GFLOP/s, {100 * e['engine_vs_gemm_ceiling']:.0f} % of the GEMM ceiling.",
        "- Where the rest goes: " + ", ".join(
            f"{k} {st[k]:.2f} s" for k in sorted(("reconstruction", "encode", "preprocess", "decode"), key=lambda k: -st[k]))
        + ", run on the same cores between inferences. Running the reconstruction beside the next inference was "
        "tried and gained nothing: ONNX Runtime keeps both cores busy, so the overlap only moved the time into "
        "inference (see Speed work).",
        "",
        f"### Daemon end to end, {d['width']}×{d['height']} frames, 1 worker × {d['threads_per_worker']} threads",
        "",
        "Each client uploads a frame over HTTP, polls until it is done and downloads the result; "
        f"the engine alone does the same frame (decode, denoise, encode) in {d['engine_alone_s_per_frame']:.3f} s "
        f"({d['engine_alone_frames_per_hour']:.0f} frames/h).",
        "",
        "| clients | jobs | frames/h | vs engine alone | latency p50 (s) | latency p99 (s) | wall per frame (s) "
        "| worker per frame (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in d["clients"]:
        out.append(f"| {r['clients']} | {r['jobs']} | {r['frames_per_hour']:.0f} | {100 * r['vs_engine_alone']:.0f} % | "
                   f"{r['latency_p50_s']:.2f} | {r['latency_p99_s']:.2f} | {r.get('wall_per_frame_s', float('nan')):.3f} "
                   f"| {r.get('worker_per_frame_s', float('nan')):.3f} |")
    out += ["", "Worker per frame: the job's own timings (read, decode, denoise, encode, durable write of the "
            f"result); the engine alone takes {d['engine_alone_s_per_frame']:.3f} s for decode, denoise and encode. "
            "Wall minus worker time is time the worker had no frame (one client uploads only after its previous "
            "result) or lost to HTTP work on the same cores."]
    out += ["", "### Peak memory of `mcdenoise run`", "",
            "| frame | peak RSS (MB) | frame buffers (MB) | beyond the frame (MB) | time (s) |", "|---|---|---|---|---|"]
    for r in speed["memory"]:
        out.append(f"| {r['frame']} ({r['width']}×{r['height']}) | {r['peak_rss_mb']:.0f} | {r['frame_buffers_mb']:.0f} | "
                   f"{r['rss_beyond_frame_mb']:.0f} | {r['total_s']:.1f} |")
    out += ["", "Frame buffers: every decoded input plane and the output planes at 4 bytes per sample, which any "
            "denoiser holding the frame needs; what lies beyond them is the models, ONNX Runtime and the per-tile "
            "working set, bounded by the tile size."]
    out += precision_section(speed, e)
    if oidn:
        out += ["", f"### Intel Open Image Denoise on the same {oidn['width']}×{oidn['height']} frame and cores",
                "", "| denoiser | seconds | relative to ours |", "|---|---|---|",
                f"| mcdenoise engine with EXR decode and encode | {total:.2f} | 1.00 |"]
        for q, r in oidn["quality"].items():
            out.append(f"| OIDN {oidn.get('pyoidn', '')} quality {q} | {r['seconds']:.2f} | {r['seconds'] / total:.2f} |")
        files = {q: r["file_seconds"] for q, r in oidn["quality"].items() if "file_seconds" in r}
        if files:
            high = oidn["quality"].get("high", {})
            io = (f"here {high['file_read_seconds']:.2f} s to read and {high['file_write_seconds']:.2f} s to write"
                  if "file_read_seconds" in high else "read and write times not recorded")
            out += ["", "The same comparison in like terms: the denoising alone (our engine's stages against "
                    "OIDN's filter call, neither reading nor writing a file), and EXR file to EXR file "
                    "(`mcdenoise run` against OpenEXR's read, the filter call and a PIZ float RGB write). OpenEXR's "
                    f"Python binding reads and writes on one thread ({io}, where `mcdenoise` decodes in "
                    f"{st['decode']:.2f} s and encodes in {st['encode']:.2f} s on every core), so the second row "
                    "favours us by what a multi-threaded EXR library would save OIDN's side; the first row is the "
                    "like-for-like ratio of the two denoisers.", "",
                    "| measure | mcdenoise (s) | " + " | ".join(f"OIDN {q} (s) | ours / OIDN {q}" for q in files) + " |",
                    "|---|---|" + "---|---|" * len(files)]
            alone = " | ".join(f"{oidn['quality'][q]['seconds']:.2f} | {e['engine_s'] / oidn['quality'][q]['seconds']:.2f}"
                               for q in files)
            whole = " | ".join(f"{t:.2f} | {total / t:.2f}" for t in files.values())
            out += [f"| denoising alone | {e['engine_s']:.2f} | {alone} |",
                    f"| EXR file to EXR file | {total:.2f} | {whole} |"]
    return out


def precision_section(speed: dict, fp32: dict) -> list[str]:
    """Int8 against FP32 on the same frame (`--int8-models`), with both GEMM ceilings, and
    whether the CPU has bf16 instructions."""
    q = speed.get("int8")
    out = []
    if q:
        g, gi, e = speed["gemm_ceiling"], q["gemm_ceiling"], q["engine"]
        r = q["time_vs_fp32"]
        out += ["", f"### Int8 against FP32, {e['width']}×{e['height']}", "",
                *([f"Both models run through OpenVINO here: the \"FP32\" columns are the default model as served on "
                   "this CPU, in bfloat16.", ""] if fp32.get("device") == "openvino" else []),
                f"The int8 model is `{q['models']}` (`make bench` quantises the default `{e['variant']}` model "
                "with `mcdenoise_train.quantize --ops all`: u8 activations, s8 per-channel weights, every operator "
                "quantised, the kernel and blend heads in float). Int8 GEMM is u8 × s8 into int32 "
                "(MatMulInteger), a multiply and an add counted as two operations.", "",
                "| measure | FP32 | int8 | int8 / FP32 |", "|---|---|---|---|",
                f"| GEMM ceiling ({g['n']}³), {g['threads']} threads (G(FL)OP/s) | {g['gflops']:.1f} | {gi['gops']:.1f} "
                f"| {gi['gops'] / g['gflops']:.2f} |",
                f"| GEMM ceiling, 1 thread | {g['gflops_1_thread']:.1f} | {gi['gops_1_thread']:.1f} "
                f"| {gi['gops_1_thread'] / g['gflops_1_thread']:.2f} |",
                f"| ONNX Runtime alone (s) | {fp32['ort_alone_s']:.3f} | {e['ort_alone_s']:.3f} | {r['ort_alone']:.2f} |",
                f"| ONNX Runtime alone, share of its own ceiling | {100 * fp32['ort_alone_vs_gemm_ceiling']:.0f} % "
                f"| {100 * e['ort_alone_vs_gemm_ceiling']:.0f} % | |",
                f"| engine (s) | {fp32['engine_s']:.3f} | {e['engine_s']:.3f} | {r['engine']:.2f} |",
                f"| with EXR decode and encode (s) | {fp32['engine_with_io_s']:.3f} | {e['engine_with_io_s']:.3f} "
                f"| {r['engine_with_io']:.2f} |", "",
                "The share of the int8 ceiling counts every multiply-add of the model as int8, the float heads "
                "included. Int8 is not served: its quality loss on the validation scenes is above the 2 % the "
                "project allows (docs/training.md, Int8)."]
    flags = speed.get("bf16", {}).get("cpu_flags")
    if flags is not None:
        served = fp32.get("device") == "openvino"
        out += ["", "bf16: this CPU has " + (", ".join(flags) + (
            "; the figures above are its bfloat16 (OpenVINO)." if served else
            "; the figures above are ONNX Runtime's float32 CPU provider (`--device auto` takes OpenVINO's "
            "bfloat16 only where it was measured faster: AMX, or AVX512-BF16 on AMD; docs/results/speed-work.md).")
            if flags else
                "no bf16 instructions (no avx512_bf16 or amx_bf16 flag), so bf16 is not measured.")]
    return out


def speed_work(results: Path) -> list[str]:
    """The speed-work log (docs/results/speed-work.md, written by hand: each change with its
    predicted and measured effect), when there is one."""
    f = results / "speed-work.md"
    return ["", f.read_text().strip()] if f.exists() else []


def scale_out_section(report: dict) -> list[str]:
    """Shared mode against the embedded mode (docs/results/scale-out.json, `make bench-scale-out`)."""
    out = ["### Scale-out: shared mode (NATS JetStream) with 1, 2 and 3 replicas", "",
           f"Produced by `make bench-scale-out` (benches/scale_out.py): {report['results'][0]['jobs']} jobs of one "
           f"{report['frame_bytes'] / 1e6:.1f} MB frame ({Path(report['frame']).name}, the shipped models), submitted "
           f"round-robin at once; each replica one worker of {report['threads_per_replica']} thread on this "
           f"{report['cores']}-core machine, every configuration started fresh (nats-server with an empty store on "
           "loopback). Background renders and training were paused.", "",
           "| store | replicas | jobs/s | wall (s) | mean run (ms) | per-replica efficiency |", "|---|---|---|---|---|---|"]
    for r in report["results"]:
        eff = f"{r['efficiency']:.2f}" if "efficiency" in r else ""
        out.append(f"| {r['mode']} | {r['replicas']} | {r['jobs_per_s']:.2f} | {r['wall_s']:.2f} | {r['mean_run_ms']:.0f} | {eff} |")
    out += ["", f"The queue's own overhead (shared with 1 replica against embedded, per job): "
            f"{report['queue_overhead_ms_per_job']:.0f} ms, the frame stored in and fetched from the object store, "
            "the result stored, the record and message exchanges. Efficiency is throughput / (replicas × the "
            "one-replica shared throughput); past 2 replicas the 2 cores are the limit, not the queue."]
    return out


def gpu_section(gpu: dict, split: dict | None) -> list[str]:
    """The daemon on a GPU against OIDN's CUDA device (docs/results/gpu.json,
    benches/gpu_engine.py) and where the frame time goes (gpu-split.json, benches/gpu_split.py)."""
    oidn = {r["frame"]: r["ms_per_frame"] for r in gpu.get("oidn") or []}
    out = ["### GPU: the daemon against OIDN's CUDA device", "",
           f"Produced on a lent GPU ({gpu['machine']['gpu'].split(' (UUID')[0]}, {gpu['machine']['cpu_threads']} CPU "
           f"threads) by `{gpu['device_command']}` (benches/gpu_engine.py, docs/training.md \"The engine on the "
           f"GPU\"): synthetic frames with every channel; the daemon with {gpu['workers']} workers of "
           f"{gpu['threads_per_worker']} threads, whole frames, the shipped models; each client submits "
           f"{', '.join(f'{n} jobs of {s}' for s, n in gpu['jobs_per_client'].items())} in turn after a warm-up job. "
           "`inference` is the job's own stage: the inputs' copy to the device, the network and its reconstruction "
           "(in the graph), the outputs' copy back. OIDN: `oidnBenchmark -d cuda -r RT.hdr_alb_nrm.WxH` (HDR color, "
           "albedo, normal; quality high), its buffers already on the device.", "",
           "| frame | precision | I/O binding | clients | frames/s | latency p50 (s) | decode / preprocess / inference / "
           "encode (ms, median) | OIDN CUDA (ms) | inference / OIDN |", "|---|---|---|---|---|---|---|---|---|"]
    for r in gpu["daemon"] + gpu.get("variants", []):
        st = r["job_stages_ms_median"]
        o = oidn.get(r["frame"])
        what = r["precision"] if "variant" not in r else f"{r['variant']} ({r['precision']})"
        against = f"{o:.2f} | {st['inference'] / o:.0f}×" if o else " | "
        out.append(f"| {r['frame']} | {what} | {r['io_binding']} | {r['clients']} | {r['frames_per_s']:.2f} | "
                   f"{r['latency_p50_s']:.2f} | {st['decode']:.0f} / {st['preprocess']:.0f} / {st['inference']:.1f} / "
                   f"{st['encode']:.0f} | {against} |")
    for e in gpu.get("errors", []):
        first = next((ln for ln in e["error"].splitlines() if "CUDA failure" in ln or "failed" in ln),
                     e["error"].splitlines()[0])
        out.append(f"\nFailed: **{e['part']}**: `{first.strip()[:300]}`")
    for s in gpu.get("skipped", []):
        out.append(f"\nNot run (past the deadline): {s}")
    out += ["", "Parity: the same 320×192 frame through the GPU (reconstruction in the graph) and through the CPU "
            "engine (float32, its own reconstruction): the largest difference relative to the largest value.", "",
            "| precision | reconstruction | max abs difference | relative to the max |", "|---|---|---|---|"]
    for r in gpu["parity"]:
        out.append(f"| {r['precision']} | {r['reconstruction']} | {r['max_abs_diff']:.3g} | {r['relative_to_max']:.2g} |")
    if split:
        out += ["", "#### Where the frame time goes", "",
                f"Produced by `{split['device_command']}` (benches/gpu_split.py, PyTorch {split['torch']}): the "
                "shipped network and its reconstruction (the module `model-recon*.onnx` are exported from) on inputs "
                "already on the device, eager and replayed as one CUDA graph, and the copies across PCIe on their own "
                "(medians of CUDA-event timings). Frames padded to the network's multiple of 16.", "",
                "| frame | network + reconstruction fp32 / fp16 (ms) | as a CUDA graph fp32 / fp16 (ms) | OIDN CUDA (ms) | "
                "fp16 graph / OIDN | inputs to device, pageable / page-locked (ms) | outputs to host (ms) |",
                "|---|---|---|---|---|---|---|"]
        for r in split["rows"]:
            o = next((v for k, v in oidn.items() if k.split("x")[0] == r["frame"].split("x")[0]), None)
            ratio = f"{r['network_and_reconstruction_fp16_graph_ms'] / o:.1f}×" if o else ""
            out.append(f"| {r['frame']} | {r['network_and_reconstruction_fp32_ms']:.1f} / "
                       f"{r['network_and_reconstruction_fp16_ms']:.1f} | {r['network_and_reconstruction_fp32_graph_ms']:.1f}"
                       f" / {r['network_and_reconstruction_fp16_graph_ms']:.1f} | {f'{o:.2f}' if o else ''} | {ratio} | "
                       f"{r['inputs_to_device_pageable_ms']:.1f} / {r['inputs_to_device_pinned_ms']:.1f} "
                       f"({r['input_mb']:.0f} MB) | {r['outputs_to_host_ms']:.1f} ({r['output_mb']:.0f} MB) |")
        r = split["rows"][0]
        copies = r["inputs_to_device_pageable_ms"] + r["outputs_to_host_ms"]
        out += ["", f"At {r['frame']} the device's own work (fp16, {r['network_and_reconstruction_fp16_graph_ms']:.1f} ms) "
                f"is a small part of the job's inference stage; the copies through pageable memory "
                f"({r['inputs_to_device_pageable_ms']:.0f} ms in, {r['outputs_to_host_ms']:.0f} ms out, {copies:.0f} ms) "
                "are most of it. Page-locked inputs (the I/O binding) would take "
                f"{r['inputs_to_device_pinned_ms']:.1f} ms instead of {r['inputs_to_device_pageable_ms']:.0f}."]
    return out


def quality_time_section(report: dict) -> list[str]:
    out = ["", "### Quality against time", "",
           f"Produced by `{EVAL_CMD}` (benches/quality_time.py): mean RelMSE and DSSIM over the "
           f"{report['frames']} frames of `{report['results']}` on which every method ran, against the seconds per "
           f"{report['width']}×{report['height']} frame on this machine: `mcdenoise run` as a whole process "
           f"({report['threads']} threads; EXR decode, model load, denoise, EXR encode) and the OIDN call alone "
           f"(every core), the median of {report['runs']} runs after a warm-up.", "",
           "| method | seconds | RelMSE | DSSIM |", "|---|---|---|---|"]
    for p in report["points"]:
        out.append(f"| {p['method']} | {p['seconds']:.2f} | {p['relmse']:.4g} | {p['dssim']:.4g} |")
    return out + ["", "![quality against time](results/quality-time.png)"]


def quality_section(results: Path) -> list[str]:
    out = ["## Quality", "",
           f"Produced by `{EVAL_CMD}` (training/mcdenoise_train/evaluate.py): every frame denoised by `mcdenoise run` "
           "with the shipped models and by OIDN (pyoidn, HDR, albedo and normal, quality high); metrics computed by "
           "the engine against the reference."]
    # Each set's results.md opens with what it holds (frames, scenes, size, sample counts, renderers).
    for split, title in (("val", "Validation scenes (never trained on; they chose the checkpoints)"),
                         ("heldout-384", "Held-out scenes at 384² (never seen in training or selection)"),
                         ("heldout-384-cycles",
                          "Held-out Cycles scenes at 384² (never seen in training or selection)"),
                         ("test-both", "Test scenes, both renderers (never seen in training or selection)"),
                         ("test-256", "Test scenes at 256², rendered on a GPU (never seen in training or selection)"),
                         ("spp-range", "Sample counts outside the test sets, Mitsuba (a probe of 8 scenes, "
                                       "models/MODEL_CARD.md)"),
                         ("spp-range-cycles", "Sample counts outside the test sets, Cycles (a probe of 4 scenes)")):
        d = results / split
        if not (d / "results.md").exists():
            continue
        out += ["", f"### {title}", "", (d / "results.md").read_text().replace("## ", "#### ").strip(), ""]
        if (d / "quality.png").exists():
            out += [f"![quality against sample count, {split}](results/{split}/quality.png)", ""]
        crops = sorted((d / "crops").glob("*.png")) if (d / "crops").exists() else []
        if crops:
            out += ["Crops at each scene's lowest sample count (input, ours, OIDN, reference; clamped sRGB):", ""]
            out += [f"![{c.stem}](results/{split}/crops/{c.name})" for c in crops]
    if (results / "quality-time.json").exists():
        out += quality_time_section(json.loads((results / "quality-time.json").read_text()))
    return out


def paired_section(paired: dict) -> list[str]:
    """benches/paired_speed.py: `mcdenoise run` and OIDN timed in turns, round by round."""
    q, n = paired["oidn_quality"], len(paired["rounds"])
    out = ["", f"### `mcdenoise run` against OIDN {q}, in turns",
           "", f"Each of {n} rounds timed one `mcdenoise run` of the {paired['width']}×{paired['height']} frame as a "
           f"whole process (decode, model loading, the `{paired['variant']}` network, encode; {paired['threads']} "
           f"threads) and one OIDN {paired.get('pyoidn', '')} call at quality `{q}` (the call alone, its device made "
           "before), one after the other, so that the machine's drift from minute to minute weighs on both "
           "(benches/paired_speed.py).", "",
           f"| round | `mcdenoise run` (s) | OIDN {q} (s) | ours / OIDN |", "|---|---|---|---|"]
    for k, r in enumerate(paired["rounds"], 1):
        out.append(f"| {k} | {r['mcdenoise_run_s']:.2f} | {r['oidn_s']:.2f} | {r['ratio']:.2f} |")
    out.append(f"| **median** | {paired['mcdenoise_run_median_s']:.2f} | {paired['oidn_median_s']:.2f} | "
               f"**{paired['ratio_median']:.2f}** ({paired['ratio_min']:.2f}–{paired['ratio_max']:.2f}) |")
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--results", default="docs/results")
    p.add_argument("--out", default="docs/results.md")
    a = p.parse_args()
    results = Path(a.results)
    lines = ["# Results", "",
             "Speed against the machine's limits and quality against Intel Open Image Denoise, regenerated by "
             f"`{SPEED_CMD}` and `{EVAL_CMD}` (raw measurements in docs/results/). Do not edit by hand.", ""]
    speed = results / "speed.json"
    if speed.exists():
        oidn = results / "oidn.json"
        lines += speed_section(json.loads(speed.read_text()), json.loads(oidn.read_text()) if oidn.exists() else None)
        paired = results / "paired.json"
        if paired.exists():
            lines += paired_section(json.loads(paired.read_text()))
        lines += speed_work(results)
        lines.append("")
    scale_out = results / "scale-out.json"
    if scale_out.exists():
        lines += scale_out_section(json.loads(scale_out.read_text()))
        lines.append("")
    gpu = results / "gpu.json"
    if gpu.exists():
        split = results / "gpu-split.json"
        lines += gpu_section(json.loads(gpu.read_text()), json.loads(split.read_text()) if split.exists() else None)
        lines.append("")
    lines += quality_section(results)
    Path(a.out).write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
