"""Check ``run.context_parallel`` on GPUs: a faithful guided call split over N GPUs against one GPU.

Run it twice with the same ``--out`` (``scripts/check_context_parallel.sh`` does both): first on
one GPU (the reference), then under ``torchrun --nproc-per-node N`` (the split run, compared)::

    python scripts/check_context_parallel.py --model cogvideox-5b --out /tmp/geco-cp
    torchrun --nproc-per-node 2 scripts/check_context_parallel.py --model cogvideox-5b --out /tmp/geco-cp

The call is the model's own (its registry preset: size, steps, dtype, faithful guidance with the
memory plan that fits), with guidance at the first ``--steps`` step only (``--updates`` updates,
no time travel): a guided update is normalised, so its direction carries rounding into the
latents, and a whole schedule would amplify the rounding of the split attention beyond what a
comparison of frames can read. Each process prints its sampling seconds and peak GPU memory;
the split run's rank 0 then prints, against the reference:

- the relative difference of every update's gradient norm (the gradient through the GeCo loss,
  the anchor decode and the split denoiser);
- the largest difference of the frames (in ``[0, 1]``);
- the time and peak memory of both runs,

and PASS where the norms agree to ``--norm-tolerance`` (default 2 %) and the frames to
``--frame-tolerance`` (default 0.03). These bounds are set for bf16 weights before any GPU run:
the split changes only the order of the attention's sums (bf16 rounding, ~0.4 %), and a wrong
split (a shard lost or counted twice, a gradient not summed over the processes) moves the norms
by tens of percent. The numbers printed are what to judge by.

Extra arguments are config overrides (``key=value``); ``--preset tiny`` (and no GPU) runs the same
check on the tiny models and the CPU, which shows that the script works, not that the GPUs do.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch
import torch.distributed as dist


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="registry model (default cogvideox-5b unless --preset)")
    parser.add_argument("--preset", default=None, help="a config preset instead of --model (e.g. tiny)")
    parser.add_argument("--out", required=True, help="folder of the reference and the comparison")
    parser.add_argument("--steps", type=int, default=8, help="denoising steps (default 8)")
    parser.add_argument("--updates", type=int, default=2, help="guided updates at the first step (default 2)")
    parser.add_argument("--prompt", default="a marble bust on a turntable, the camera circling it")
    parser.add_argument("--norm-tolerance", type=float, default=0.02)
    parser.add_argument("--frame-tolerance", type=float, default=0.03)
    parser.add_argument("overrides", nargs="*", metavar="key=value")
    return parser.parse_args(argv)


def _config(args: argparse.Namespace, processes: int):
    from geco_guide.config import load_config, model_preset

    model = args.model or (None if args.preset else "cogvideox-5b")
    overrides = [f"sampling.num_inference_steps={args.steps}", f"guidance.repeats={args.updates}x1,0x{args.steps - 1}",
                 "guidance.time_travel=null", "guidance.denoiser_grad=true", *args.overrides]
    if processes > 1:
        overrides.append(f"run.context_parallel={processes}")
    changes = {"model.name": model} if model else None
    return load_config(None, args.preset, overrides, changes=changes,
                       model_preset=model_preset(model) if model else None)


def _peak_gb() -> float | None:
    return torch.cuda.max_memory_allocated() / 2**30 if torch.cuda.is_available() else None


def main(argv: list[str]) -> int:
    from geco_guide.generation import check_generation, load_models, sample

    args = _parse(argv)
    processes = int(os.environ.get("WORLD_SIZE", "1"))
    # the generation path's checks, which also put each process on the GPU of its LOCAL_RANK
    cfg = check_generation(_config(args, processes), args.prompt)
    models = load_models(cfg)
    rank = dist.get_rank() if dist.is_initialized() else 0
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    made = sample(models, cfg, args.prompt, progress=rank == 0)
    seconds = time.perf_counter() - start
    peak = _peak_gb()
    peaks = [peak]
    if dist.is_initialized():
        peaks = [None] * processes
        dist.all_gather_object(peaks, peak)
    shown = ", ".join("n/a (CPU)" if p is None else f"{p:.1f} GiB" for p in peaks)
    print(f"rank {rank}/{processes}: sampling {seconds:.1f} s, peak GPU memory per rank: {shown}", flush=True)
    if rank != 0:
        return 0
    result = {"frames": made.frames, "norms": torch.tensor([r["grad_norm"] for r in made.report.log]),
              "seconds": seconds, "peaks": peaks}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.save(result, out / f"processes{processes}.pt")
    if processes == 1:
        print(f"reference written: {out / 'processes1.pt'}; now run the split run with the same --out")
        return 0
    return _compare(torch.load(out / "processes1.pt"), result, processes, args)


def _compare(one: dict, split: dict, processes: int, args: argparse.Namespace) -> int:
    if one["norms"].shape != split["norms"].shape or one["frames"].shape != split["frames"].shape:
        print("FAIL: the reference is of another call (run both with the same arguments)")
        return 1
    norms = ((split["norms"] - one["norms"]).abs() / one["norms"]).tolist()
    frames = float((split["frames"] - one["frames"]).abs().max())
    print(f"updates' gradient norms, 1 vs {processes} processes: {one['norms'].tolist()} vs {split['norms'].tolist()} "
          f"(relative differences {[f'{d:.2e}' for d in norms]})")
    print(f"largest frame difference: {frames:.2e} (frames in [0, 1])")
    print(f"time: {one['seconds']:.1f} s on one process, {split['seconds']:.1f} s on {processes} "
          f"({one['seconds'] / split['seconds']:.2f}x)")
    if one["peaks"][0] is not None:
        print(f"peak GPU memory: {one['peaks'][0]:.1f} GiB on one GPU, per rank {[round(p, 1) for p in split['peaks']]}")
    passed = max(norms, default=0.0) <= args.norm_tolerance and frames <= args.frame_tolerance
    print(f"{'PASS' if passed else 'FAIL'}: norms within {args.norm_tolerance:.0%}, frames within {args.frame_tolerance}")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
