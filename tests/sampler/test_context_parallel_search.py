"""``run.context_parallel`` with a search and no guidance: the particles' anchor chunks are dealt
over the processes as guidance's are, and the search gives one process's video.

Two processes on the ``gloo`` backend (CPU) run the paper's pipeline (tiny CogVideoX) with an
unguided search of two particles, resampled once, scored on two anchors of two chunks: each
process decodes one chunk per scoring, gathers the other's anchor frames, and the particles'
scores, hence the resampling, are one process's. The video is compared with one process's at the
tolerance of ``test_context_parallel.py`` (the denoiser's split rounds differently).
"""

from __future__ import annotations

import os
import socket

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

import geco_guide.tiny as T
from geco_guide.estimators import tiny_estimators
from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline
from geco_guide.sampler.search.particle_search import SearchConfig

PROCESSES = 2
#: two anchors of a 9-frame video (3 latents), in latents 1 and 2: two chunks, one per process
ANCHORS = [4, 8]
FRAME_TOLERANCE = 5e-4  # absolute, frames in [0, 1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _search(processes: int) -> dict[str, torch.Tensor]:
    """The searched video and how many VAE decode calls this process made."""
    pipe = GeCoCogVideoXPipeline(**T.tiny_cogvideox_components(0))
    pipe.set_progress_bar_config(disable=True)
    calls = []
    decode = pipe.vae.decode

    def counted(*args, **kwargs):
        calls.append(1)
        return decode(*args, **kwargs)

    pipe.vae.decode = counted
    run = T.tiny_run_options(context_parallel=processes if processes > 1 else None)
    out = pipe("a marble bust", **{**T.TINY_CALL_KWARGS, "num_frames": 9, "output_type": "pt"},
               generator=[torch.Generator().manual_seed(s) for s in (0, 1)],
               guidance=T.tiny_guidance_config(anchors=ANCHORS, enabled=False), estimators=tiny_estimators(0),
               run_options=run, search=SearchConfig(particles=2, resample_steps=[2]),
               search_generator=torch.Generator().manual_seed(7))
    return {"frames": out.frames.float(), "decodes": torch.tensor(len(calls))}


def _worker(rank: int, port: int, folder: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), OMP_NUM_THREADS="1")
    torch.set_num_threads(1)
    dist.init_process_group("gloo", rank=rank, world_size=PROCESSES)
    try:
        torch.save(_search(PROCESSES), os.path.join(folder, f"rank{rank}.pt"))
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
def test_a_search_over_two_processes_deals_its_scoring_decode_and_gives_one_process_video(tmp_path):
    torch.set_num_threads(1)
    mp.spawn(_worker, args=(_free_port(), str(tmp_path)), nprocs=PROCESSES)
    one = _search(1)
    for rank in range(PROCESSES):
        split = torch.load(tmp_path / f"rank{rank}.pt")
        assert (split["frames"] - one["frames"]).abs().max() <= FRAME_TOLERANCE, rank
        # the scorings' decodes are half one process's (one chunk of two); the final decode is whole on each
        assert split["decodes"] < one["decodes"], (rank, int(split["decodes"]), int(one["decodes"]))
