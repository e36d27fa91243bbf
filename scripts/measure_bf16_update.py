"""How much of a GeCo update survives bf16 latents (the README's claim about stock CogVideoX).

The stock ``CogVideoXPipeline`` rounds its latents to the model dtype after every step. With the
pipeline hooks, the guided sample reaches the scheduler in fp32, but the scheduler's output is
rounded to bf16 again before the next step. This script measures, for a CogVideoX-5B latent
(``[1, 13, 16, 60, 90]``: 49 frames at 480x720) and the paper's normalised update (``eta = 3``,
``||u|| = 3``), what is left of the update ``u`` after that rounding:

- ``round trip``: ``d = bf16(z + u) - z`` for a bf16 latent ``z`` (the guided sample rounded);
- ``after a DDIM step``: ``d = bf16(A (z + u) + B x0) - bf16(A z + B x0)``, compared with
  ``A u`` (what fp32 latents keep), for the DDIM coefficients of a step of the guided phase.

For each: the kept norm ``||d|| / ||u||``, the angle between ``d`` and ``u``, and the part along
``u`` (``d.u / ||u||^2``: 1 = the whole update survives in its direction; the rest of ``d`` is
rounding noise). Two update
directions: Gaussian (every latent entry moved a little) and heavy-tailed (``g^3`` of a Gaussian
``g``: a few entries moved a lot, as a gradient concentrated on a few regions would). The numbers
are averages over ``--trials`` random draws (CPU, a few seconds)::

    python scripts/measure_bf16_update.py --json docs/benchmarks/bf16_update.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import torch

SHAPE = (1, 13, 16, 60, 90)


def _stats(d: torch.Tensor, u: torch.Tensor) -> tuple[float, float, float]:
    """``(||d|| / ||u||, angle(d, u) in degrees, d.u / ||u||^2)``: kept norm, angle, part along ``u``."""
    d, u = d.double().flatten(), u.double().flatten()
    kept = float(d.norm() / u.norm())
    cos = float(d @ u / (d.norm() * u.norm()).clamp_min(1e-300))
    return kept, math.degrees(math.acos(max(-1.0, min(1.0, cos)))), float(d @ u / (u @ u))


def ddim_coefficients(step: int, num_steps: int = 50) -> tuple[float, float]:
    """``A, B`` of ``z_prev = A z + B x0`` for step ``step`` of CogVideoX-5B's DDIM (v-prediction)."""
    from diffusers import CogVideoXDDIMScheduler

    sched = CogVideoXDDIMScheduler(
        beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", clip_sample=False,
        prediction_type="v_prediction", rescale_betas_zero_snr=True, set_alpha_to_one=True,
        snr_shift_scale=1.0, steps_offset=0, timestep_spacing="trailing",
    )
    sched.set_timesteps(num_steps)
    t = int(sched.timesteps[step])
    prev = t - sched.config.num_train_timesteps // num_steps
    a_t = float(sched.alphas_cumprod[t])
    a_prev = float(sched.alphas_cumprod[prev]) if prev >= 0 else float(sched.final_alpha_cumprod)
    A = math.sqrt((1 - a_prev) / (1 - a_t))
    return A, math.sqrt(a_prev) - math.sqrt(a_t) * A


def measure(trials: int = 5, eta: float = 3.0, step: int = 10, seed: int = 0) -> dict:
    gen = torch.Generator().manual_seed(seed)
    A, B = ddim_coefficients(step)
    results: dict[str, dict[str, list[float]]] = {}
    for _ in range(trials):
        z = torch.randn(SHAPE, generator=gen).bfloat16().float()  # the stock pipeline's bf16 latents
        x0 = torch.randn(SHAPE, generator=gen)
        g = torch.randn(SHAPE, generator=gen)
        for name, direction in (("gaussian", g), ("heavy_tailed", g**3)):
            u = -eta * direction / direction.norm()
            cases = {
                "round_trip": (_stats((z + u).bfloat16().float() - z, u)),
                "after_ddim_step": _stats(
                    (A * (z + u) + B * x0).bfloat16().float() - (A * z + B * x0).bfloat16().float(), A * u
                ),
            }
            for case, (kept, angle, along) in cases.items():
                entry = results.setdefault(f"{name}/{case}", {"kept_norm": [], "angle_deg": [], "along": []})
                entry["kept_norm"].append(kept)
                entry["angle_deg"].append(angle)
                entry["along"].append(along)
    summary = {
        key: {stat: sum(values) / len(values) for stat, values in entry.items()} for key, entry in results.items()
    }
    rms = eta / math.sqrt(math.prod(SHAPE))
    return {
        "shape": list(SHAPE),
        "eta": eta,
        "update_rms_per_entry": rms,
        "bf16_spacing_at_1": 2.0**-7,
        "ddim_step": step,
        "ddim_A_B": [A, B],
        "trials": trials,
        "results": summary,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=5)
    p.add_argument("--eta", type=float, default=3.0)
    p.add_argument("--step", type=int, default=10, help="DDIM step (of 50) for the step case")
    p.add_argument("--json", default=None, help="write the numbers to this file")
    args = p.parse_args(argv)
    out = measure(args.trials, args.eta, args.step)
    print(f"latent {out['shape']}, update eta={out['eta']}: {out['update_rms_per_entry']:.2e} per entry (rms), "
          f"bf16 spacing at 1.0 is {out['bf16_spacing_at_1']:.2e}")
    for key, entry in out["results"].items():
        print(f"{key:30s} kept norm {entry['kept_norm']:.3f}  angle {entry['angle_deg']:.1f} deg  "
              f"along u {entry['along']:.3f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
