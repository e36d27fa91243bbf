"""``geco bench cost`` prints no time for a card the run's peak does not fit: it says so."""

from __future__ import annotations

from geco_guide.perf import cost
from geco_guide.perf.cards import GPU_SPECS, card_memory_gib


def _report(peak_gb: float, unguided_gb: float) -> dict:
    """A cost report as :func:`cost.cost_report` makes it, of the fields the table reads."""
    times = {gpu: 10.0 for gpu in GPU_SPECS}
    return {"per_stage": {"denoiser": {"count": 4, "flops_forward": 1e12, "flops_backward": 0.0, "flops": 1e12,
                                       "time_s": times}},
            "flops_ratio_guided_over_unguided": 2.0, "flops_unguided": 1e15, "flops_guided": 2e15, "mode": "faithful",
            "roofline": {"wall_time_s": {gpu: {"unguided": 100.0, "guided": 300.0} for gpu in GPU_SPECS},
                         "efficiency": 0.5},
            "settings": {"decoder": "vae", "preset": "cogvideox-5b"}, "peak_memory_gb": peak_gb, "peak_at": "decode",
            "weights_gb": {"denoiser": 10.0}, "peak_memory_gb_unguided": unguided_gb, "ops_ratio_guided_over_unguided": None}


def test_a_card_the_peak_does_not_fit_gets_no_time():
    small = min(GPU_SPECS, key=card_memory_gib)
    large = max(GPU_SPECS, key=card_memory_gib)
    peak = (card_memory_gib(small) + card_memory_gib(large)) / 2  # the guided run fits the large card only
    lines = cost.cost_table(_report(peak, unguided_gb=1.0)).splitlines()

    assert f"{large}: unguided 100 s, guided 300 s (efficiency 0.50)" in lines
    assert (f"{small}: unguided 100 s, guided does not fit ({peak:.1f} GiB peak > {card_memory_gib(small):.1f} GiB) "
            "(efficiency 0.50)") in lines
    assert f"| {large} (s) |" in lines[0] and f"| {small} (s; the peak does not fit) |" in lines[0]
